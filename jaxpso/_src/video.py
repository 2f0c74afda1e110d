"""Frames in and out: video and image-folder input, overlays, video files.

Everything here runs on the host in NumPy.  OpenCV is imported inside the
functions that use it (and matplotlib, for the plots, only inside
`results.py`), so `import jaxpso` (and `import jaxpso.io`) stays free of
both.  Frames are RGB throughout: colour frames are (H, W, 3) uint8 in R, G,
B order; the BGR order of OpenCV stays inside this module.

The tracker's result files, summaries and plots live in `results.py`, which
imports the status colours from here; this module imports nothing from it,
so frame input/output does not depend on the result formats.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable, Iterator

import numpy as np

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm",
                    ".ppm", ".pbm", ".pnm")
"""File name endings (lower case) that `read_frames` reads from a folder."""

VIDEO_CODECS = {".mp4": "mp4v", ".avi": "MJPG"}
"""FourCC that `write_video` uses for each file name ending."""

STATUS_COLORS = ((0, 200, 0), (255, 140, 0), (230, 0, 0), (210, 0, 210))
"""RGB colour of the overlay for status 0 (green), 1 (orange), 2 (red) and 3 (magenta)."""

_TRUTH_COLOR = (0, 120, 255)  # RGB: a thin blue outline for the true corners


def _natural_key(name: str):
  """Sort key comparing runs of digits as numbers: frame2 < frame10."""
  return [(0, int(part), "") if part.isdigit() else (1, 0, part)
          for part in re.split(r"(\d+)", name) if part]


def _cv2():
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  return cv2


def _convert(image: np.ndarray, gray: bool) -> np.ndarray:
  """BGR (H, W, 3) uint8 from OpenCV → RGB (H, W, 3) or grey (H, W), contiguous."""
  cv2 = _cv2()
  code = cv2.COLOR_BGR2GRAY if gray else cv2.COLOR_BGR2RGB
  return cv2.cvtColor(image, code)


def image_files(folder: str) -> list[str]:
  """The paths of the images (`IMAGE_EXTENSIONS`) in folder, in natural name order."""
  names = [name for name in os.listdir(folder)
           if name.lower().endswith(IMAGE_EXTENSIONS)
           and os.path.isfile(os.path.join(folder, name))]
  return [os.path.join(folder, name) for name in sorted(names, key=_natural_key)]


def _read_image(path: str, gray: bool, shape) -> np.ndarray:
  cv2 = _cv2()
  try:
    image = cv2.imread(path, cv2.IMREAD_COLOR)
  except cv2.error as error:
    raise ValueError(f"cannot decode image {path!r}: {error}") from None
  if image is None:
    raise ValueError(f"cannot decode image {path!r}")
  if shape is not None and image.shape[:2] != shape:
    raise ValueError(f"image {path!r} is {image.shape[1]}×{image.shape[0]} px, but the"
                     f" folder's first image is {shape[1]}×{shape[0]} px")
  return _convert(image, gray)


def _folder_frames(paths: list[str], first: np.ndarray, gray: bool) -> Iterator[np.ndarray]:
  yield first
  shape = first.shape[:2]
  for path in paths[1:]:
    yield _read_image(path, gray, shape)


def _video_frames(capture, first: np.ndarray, gray: bool) -> Iterator[np.ndarray]:
  try:
    yield _convert(first, gray)
    while True:
      ok, image = capture.read()
      if not ok or image is None:
        return
      yield _convert(image, gray)
  finally:
    capture.release()


def read_frames(source, *, gray: bool = False) -> Iterator[np.ndarray]:
  """Frames of a video file or of a folder of images, one at a time.

  A folder yields its images (`IMAGE_EXTENSIONS`, other files are ignored)
  in name order, runs of digits compared as numbers (frame2 before frame10);
  all must have the size of the first.  A file is decoded by OpenCV's video
  reader (any container and codec the installed OpenCV reads).  The path is
  checked and the first frame decoded before this returns, so a bad source
  fails here, not at the first `next`.

  Args:
    source: path (str or `os.PathLike`) of a video file or of a folder.
    gray: yield grey frames instead of colour.

  Returns:
    An iterator of uint8 frames: (H, W, 3) in RGB order (OpenCV's BGR is
    converted; grey images come out with three equal channels), or (H, W)
    if `gray`.  Every frame has the same shape.

  Raises:
    FileNotFoundError: if `source` does not exist.
    ValueError: if OpenCV cannot read it, a folder holds no images, an image
      in it cannot be decoded or differs in size (raised when reached), or a
      video yields no frame.
  """
  path = os.fspath(source)
  if not os.path.exists(path):
    raise FileNotFoundError(f"no such video file or image folder: {path!r}")
  if os.path.isdir(path):
    paths = image_files(path)
    if not paths:
      raise ValueError(f"folder {path!r} holds no images"
                       f" (looked for {', '.join(IMAGE_EXTENSIONS)})")
    first = _read_image(paths[0], gray, None)
    return _folder_frames(paths, first, gray)
  cv2 = _cv2()
  try:
    capture = cv2.VideoCapture(path)
    opened = capture.isOpened()
    ok, first = capture.read() if opened else (False, None)
  except cv2.error as error:
    raise ValueError(f"OpenCV cannot read the video {path!r}: {error}") from None
  if not opened:
    raise ValueError(f"OpenCV cannot open {path!r} as a video")
  if not ok or first is None:
    capture.release()
    raise ValueError(f"the video {path!r} yields no frames")
  return _video_frames(capture, first, gray)


def to_rgb_uint8(frame, name: str = "frame") -> np.ndarray:
  """A new (H, W, 3) uint8 RGB array from a grey or colour, uint8 or float frame.

  Args:
    frame: (H, W), (H, W, 1) or (H, W, 3) array, uint8 or floating point in
      [0, 1] (clipped; NaN becomes 0).
    name: the argument's name in error messages.

  Returns:
    (H, W, 3) uint8 array (never a view of `frame`).

  Raises:
    ValueError: on any other shape.
    TypeError: on any other dtype.
  """
  array = np.asarray(frame)
  if array.ndim == 3 and array.shape[2] == 1:
    array = array[:, :, 0]
  if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] != 3) or array.size == 0:
    raise ValueError(f"{name} must have shape (H, W) or (H, W, 3), got shape {array.shape}")
  if array.dtype == np.uint8:
    out = array.copy()
  elif np.issubdtype(array.dtype, np.floating):
    scaled = np.nan_to_num(array.astype(np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    out = np.round(np.clip(scaled, 0.0, 1.0) * 255.0).astype(np.uint8)
  else:
    raise TypeError(f"{name} must be uint8 or floating point in [0, 1], got dtype {array.dtype}")
  if out.ndim == 2:
    out = np.repeat(out[:, :, None], 3, axis=2)
  return np.ascontiguousarray(out)


def _quad(corners, name: str) -> np.ndarray:
  quad = np.asarray(corners, np.float64)
  if quad.shape != (4, 2):
    raise ValueError(f"{name} must have shape (4, 2) (TL, TR, BR, BL), got shape {quad.shape}")
  return quad


def _fixed_point(quad: np.ndarray, shape) -> np.ndarray:
  """Corners as int32 with 4 fractional bits (cv2's `shift=4`), kept in a safe range."""
  limit = 4.0 * max(shape[0], shape[1]) + 64.0
  return np.round(np.clip(quad, -limit, limit) * 16.0).astype(np.int32).reshape(-1, 1, 2)


def draw_overlay(frame, corners, status, *, truth_corners=None, thickness: int = 2) -> np.ndarray:
  """A colour copy of `frame` with the tracked quadrilateral drawn on it.

  The quadrilateral is green for status 0 (TRACKED), orange for 1
  (RECOVERED), red for 2 (LOST) and magenta for 3 (DOUBTFUL)
  (`STATUS_COLORS`, RGB); a filled disc
  marks its top-left corner (the template's first corner).  Non-finite
  corners draw nothing.

  Args:
    frame: (H, W) or (H, W, 3) frame, uint8 or float in [0, 1]; colour
      frames are taken as RGB.  Not modified.
    corners: (4, 2) tracked corners (x, y) in the order TL, TR, BR, BL.
    status: the frame's status code, 0, 1 or 2.
    truth_corners: optional (4, 2) true corners, drawn as a thin blue outline
      under the tracked one.
    thickness: line width in pixels (>= 1).

  Returns:
    (H, W, 3) uint8 RGB image.

  Raises:
    ValueError: on a bad shape, a status outside {0, 1, 2, 3} or thickness < 1.
    TypeError: on a frame dtype other than uint8 or float.

  Examples:
    >>> import numpy as np
    >>> square = [[10, 10], [40, 10], [40, 30], [10, 30]]
    >>> image = draw_overlay(np.zeros((48, 64), np.float32), square, 0)
    >>> image.shape, image.dtype.name, image[10, 25].tolist()
    ((48, 64, 3), 'uint8', [0, 200, 0])
  """
  cv2 = _cv2()
  image = to_rgb_uint8(frame)
  quad = _quad(corners, "corners")
  try:
    code = int(status)
  except (TypeError, ValueError):
    raise ValueError(f"status must be 0, 1, 2 or 3, got {status!r}") from None
  if code != status or not 0 <= code < len(STATUS_COLORS):
    raise ValueError(f"status must be 0, 1, 2 or 3, got {status!r}")
  if isinstance(thickness, bool) or not isinstance(thickness, int) or thickness < 1:
    raise ValueError(f"thickness must be an int >= 1, got {thickness!r}")
  if truth_corners is not None:
    truth = _quad(truth_corners, "truth_corners")
    if np.all(np.isfinite(truth)):
      cv2.polylines(image, [_fixed_point(truth, image.shape)], True, _TRUTH_COLOR, 1,
                    cv2.LINE_AA, 4)
  if np.all(np.isfinite(quad)):
    color = STATUS_COLORS[code]
    points = _fixed_point(quad, image.shape)
    cv2.polylines(image, [points], True, color, thickness, cv2.LINE_AA, 4)
    cv2.circle(image, tuple(int(v) for v in points[0, 0]), 16 * (thickness + 2), color, -1,
               cv2.LINE_AA, 4)
  return image


def write_video(path, frames: Iterable, *, fps: float = 25.0) -> int:
  """Writes frames to a video file with OpenCV's `VideoWriter`.

  The codec follows the file name: MPEG-4 part 2 ("mp4v") for .mp4, Motion
  JPEG ("MJPG") for .avi (`VIDEO_CODECS`).  The writer opens at the first
  frame, whose size every later frame must have.

  Args:
    path: the file to write (str or `os.PathLike`), ending in .mp4 or .avi;
      its folder must exist.
    frames: iterable of (H, W, 3) RGB or (H, W) grey frames, uint8 or float
      in [0, 1].
    fps: frames per second stored in the file (> 0).

  Returns:
    The number of frames written.

  Raises:
    ValueError: on another file name ending, fps <= 0, no frames, or a frame
      whose size differs from the first.
    OSError: if the writer cannot be opened or writes nothing (the codec is
      missing from the installed OpenCV, or the folder is not writable).
  """
  path = os.fspath(path)
  extension = os.path.splitext(path)[1].lower()
  if extension not in VIDEO_CODECS:
    raise ValueError(f"video path must end in one of {tuple(VIDEO_CODECS)}, got {path!r}")
  if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0):
    raise ValueError(f"fps must be > 0, got {fps!r}")
  cv2 = _cv2()
  codec = VIDEO_CODECS[extension]
  writer = None
  count = 0
  try:
    for index, frame in enumerate(frames):
      image = to_rgb_uint8(frame, f"frames[{index}]")
      if writer is None:
        size = (image.shape[1], image.shape[0])
        writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*codec), float(fps), size)
        if not writer.isOpened():
          raise OSError(f"cannot open a video writer for {path!r} (codec {codec},"
                        f" {size[0]}×{size[1]} px); is the folder writable and the codec"
                        " available in this OpenCV build?")
      elif (image.shape[1], image.shape[0]) != size:
        raise ValueError(f"frames[{index}] is {image.shape[1]}×{image.shape[0]} px, but the"
                         f" first frame is {size[0]}×{size[1]} px")
      writer.write(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
      count += 1
  finally:
    if writer is not None:
      writer.release()
  if count == 0:
    raise ValueError(f"no frames to write to {path!r}")
  if not os.path.isfile(path) or os.path.getsize(path) == 0:
    raise OSError(f"the video writer wrote nothing to {path!r} (codec {codec})")
  return count
