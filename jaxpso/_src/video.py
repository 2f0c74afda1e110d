"""Video and image-folder input, overlays, and the tracker's result files.

Everything here runs on the host in NumPy.  OpenCV and matplotlib are
imported inside the functions that use them, so `import jaxpso` (and
`import jaxpso.io`) stays free of both.  Frames are RGB throughout: colour
frames are (H, W, 3) uint8 in R, G, B order; the BGR order of OpenCV stays
inside this module.
"""

from __future__ import annotations

import csv
import json
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

STATUS_NAMES = ("TRACKED", "RECOVERED", "LOST")
"""Names of the tracker's status codes 0, 1, 2 (`jaxpso.TrackStatus`)."""

STATUS_COLORS = ((0, 200, 0), (255, 140, 0), (230, 0, 0))
"""RGB colour of the overlay for status 0 (green), 1 (orange) and 2 (red)."""

WITHIN_PX = 5.0
"""Corner error (px) under which `write_results` counts a frame as within tolerance."""

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


def _image_files(folder: str) -> list[str]:
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
    paths = _image_files(path)
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
  (RECOVERED) and red for 2 (LOST) (`STATUS_COLORS`, RGB); a filled disc
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
    ValueError: on a bad shape, a status outside {0, 1, 2} or thickness < 1.
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
    raise ValueError(f"status must be 0, 1 or 2, got {status!r}") from None
  if code != status or code not in (0, 1, 2):
    raise ValueError(f"status must be 0, 1 or 2, got {status!r}")
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


def _field(result, name: str, trailing=(), dtype=np.float64) -> np.ndarray:
  try:
    value = getattr(result, name)
  except AttributeError:
    raise TypeError(f"result must be a TrackResult (it has no field {name!r})") from None
  array = np.asarray(value, dtype)
  if array.ndim != 1 + len(trailing) or array.shape[1:] != tuple(trailing):
    layout = "(T" + "".join(f", {n}" for n in trailing) + ")"
    raise ValueError(f"result.{name} must have shape {layout}, got shape {array.shape}")
  return array


def _table(result, truth_corners):
  """Per-frame columns of a track result, checked for consistent lengths."""
  columns = {
      "corners": _field(result, "corners", (4, 2)),
      "scores": _field(result, "scores"),
      "quality": _field(result, "quality"),
      "status": _field(result, "status", dtype=np.int64),
      "num_iterations": _field(result, "num_iterations", dtype=np.int64),
      "num_evaluations": _field(result, "num_evaluations", dtype=np.int64),
  }
  length = len(columns["corners"])
  for name, column in columns.items():
    if len(column) != length:
      raise ValueError(f"result.{name} has {len(column)} frames, result.corners {length}")
  if np.any((columns["status"] < 0) | (columns["status"] >= len(STATUS_NAMES))):
    raise ValueError(f"result.status must hold codes 0, 1 or 2, got {np.unique(columns['status'])}")
  errors = None
  if truth_corners is not None:
    truth = np.asarray(truth_corners, np.float64)
    if truth.shape != (length, 4, 2):
      raise ValueError(f"truth_corners must have shape ({length}, 4, 2) like result.corners,"
                       f" got shape {truth.shape}")
    errors = corner_errors(columns["corners"], truth)
  return columns, errors


def corner_errors(corners, truth_corners) -> np.ndarray:
  """Root-mean-square distance between tracked and true corners, per frame.

  e_t = sqrt(1/4 Σ_i |c_ti − c*_ti|²), the Baker–Matthews alignment error
  (the same as `jaxpso.warp.corner_error` on the homographies); +inf where
  a corner is not finite.

  Args:
    corners: (T, 4, 2) tracked corners.
    truth_corners: (T, 4, 2) true corners.

  Returns:
    (T,) float64 errors in pixels.

  Examples:
    >>> import numpy as np
    >>> square = np.array([[[0.0, 0.0], [9.0, 0.0], [9.0, 9.0], [0.0, 9.0]]])
    >>> corner_errors(square + [3.0, 4.0], square).tolist()
    [5.0]
  """
  corners = np.asarray(corners, np.float64)
  truth = np.asarray(truth_corners, np.float64)
  if corners.ndim != 3 or corners.shape[1:] != (4, 2) or truth.shape != corners.shape:
    raise ValueError(f"corners and truth_corners must both have shape (T, 4, 2), got"
                     f" {corners.shape} and {truth.shape}")
  with np.errstate(invalid="ignore", over="ignore"):
    errors = np.sqrt(np.mean(np.sum((corners - truth) ** 2, axis=-1), axis=-1))
  return np.where(np.isfinite(errors), errors, np.inf)


def _number(value: float):
  """A float for JSON: None where not finite (JSON has no inf or NaN)."""
  value = float(value)
  return value if math.isfinite(value) else None


def summarize(result, *, truth_corners=None) -> dict:
  """Summary of a track result: frames, status counts, and errors if truth is given.

  Args:
    result: a `jaxpso.TrackResult` (any object with its per-frame fields).
    truth_corners: optional (T, 4, 2) true corners.

  Returns:
    dict with "frames" (T), "status_counts" ({"TRACKED": n, "RECOVERED": n,
    "LOST": n}) and "median_score"; with truth also "within_5px" (fraction of
    frames whose corner error is <= `WITHIN_PX`), "median_error_px",
    "mean_error_px" and "max_error_px" (None where not finite).
  """
  columns, errors = _table(result, truth_corners)
  return _summary(columns, errors)


def _summary(columns, errors) -> dict:
  status = columns["status"]
  scores = columns["scores"]
  finite_scores = scores[np.isfinite(scores)]
  summary = {
      "frames": len(status),
      "status_counts": {name: int(np.sum(status == code))
                        for code, name in enumerate(STATUS_NAMES)},
      "median_score": _number(np.median(finite_scores)) if finite_scores.size else None,
  }
  if errors is not None:
    summary.update({
        "within_5px": float(np.mean(errors <= WITHIN_PX)) if errors.size else 0.0,
        "median_error_px": _number(np.median(errors)) if errors.size else None,
        "mean_error_px": _number(np.mean(errors)) if errors.size else None,
        "max_error_px": _number(np.max(errors)) if errors.size else None,
    })
  return summary


def _short(value) -> str:
  """The shortest text that reads back as the same float32 ("inf", "nan" where not finite)."""
  return str(np.float32(value))


_CORNER_COLUMNS = tuple(f"{corner}_{axis}" for corner in ("tl", "tr", "br", "bl") for axis in "xy")


def write_results(out_dir, result, *, truth_corners=None) -> dict:
  """Writes results.csv and results.json for a track result; returns the summary.

  results.csv has one row per frame with the columns frame, status (name),
  score, quality, tl_x, tl_y, tr_x, tr_y, br_x, br_y, bl_x, bl_y, error_px
  (only with truth: RMS corner error, `corner_errors`), iterations and
  evaluations.  results.json holds {"summary": `summarize(...)`, "frames":
  [one object per frame with the same values, corners as [[x, y] × 4]]};
  non-finite numbers are written as null.

  Args:
    out_dir: folder to write into (created if missing).
    result: a `jaxpso.TrackResult` (any object with fields corners (T, 4, 2),
      scores, quality, status, num_iterations, num_evaluations (T,)).
    truth_corners: optional (T, 4, 2) true corners.

  Returns:
    The summary dict (see `summarize`).

  Raises:
    TypeError: if `result` lacks a field.
    ValueError: on inconsistent shapes or status codes outside {0, 1, 2}.
  """
  columns, errors = _table(result, truth_corners)
  summary = _summary(columns, errors)
  out_dir = os.fspath(out_dir)
  os.makedirs(out_dir, exist_ok=True)
  header = ["frame", "status", "score", "quality", *_CORNER_COLUMNS]
  if errors is not None:
    header.append("error_px")
  header += ["iterations", "evaluations"]
  rows = []
  with open(os.path.join(out_dir, "results.csv"), "w", newline="") as f:
    writer = csv.writer(f)
    writer.writerow(header)
    for t in range(summary["frames"]):
      corners = columns["corners"][t]
      row = {"frame": t, "status": STATUS_NAMES[columns["status"][t]],
             "score": _number(columns["scores"][t]), "quality": _number(columns["quality"][t]),
             "corners": [[_number(x), _number(y)] for x, y in corners]}
      if errors is not None:
        row["error_px"] = _number(errors[t])
      row["iterations"] = int(columns["num_iterations"][t])
      row["evaluations"] = int(columns["num_evaluations"][t])
      rows.append(row)
      values = [t, row["status"], _short(columns["scores"][t]), _short(columns["quality"][t]),
                *(_short(v) for v in corners.ravel())]
      if errors is not None:
        values.append(_short(errors[t]))
      writer.writerow(values + [row["iterations"], row["evaluations"]])
  with open(os.path.join(out_dir, "results.json"), "w") as f:
    json.dump({"summary": summary, "frames": rows}, f, indent=1, allow_nan=False)
  return summary


def _centres(corners: np.ndarray) -> np.ndarray:
  """(T, 2) images of the template centre: where the quadrilateral's diagonals cross.

  A homography maps the rectangle's centre (its diagonals' crossing) to the
  crossing of the mapped diagonals; the corners' mean is the fallback where
  the diagonals are (nearly) parallel.
  """
  tl, tr, br, bl = (corners[:, i] for i in range(4))
  d1, d2 = br - tl, bl - tr
  denominator = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
  offset = tr - tl
  safe = np.abs(denominator) > 1e-9
  s = np.where(safe, (offset[:, 0] * d2[:, 1] - offset[:, 1] * d2[:, 0])
               / np.where(safe, denominator, 1.0), 0.5)
  crossing = tl + s[:, None] * d1
  return np.where(safe[:, None], crossing, corners.mean(axis=1))


def plot_results(path, result, *, truth_corners=None) -> None:
  """Writes a PNG: the error (or score) per frame and the template centre's path.

  Left: the RMS corner error per frame with the `WITHIN_PX` line if truth is
  given, else the score per frame; points coloured by status.  Right: the
  trajectory of the template centre in image coordinates, tracked and (if
  given) true.  Uses matplotlib's Agg canvas directly (no pyplot, the global
  backend is left alone).

  Args:
    path: the PNG file to write (str or `os.PathLike`); its folder must exist.
    result: a `jaxpso.TrackResult` (fields as in `write_results`).
    truth_corners: optional (T, 4, 2) true corners.

  Raises:
    ImportError: if matplotlib is not installed (pip install jaxpso[plots]).
    TypeError, ValueError: as `write_results`.
  """
  columns, errors = _table(result, truth_corners)
  try:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
  except ImportError as error:
    raise ImportError("plot_results needs matplotlib: pip install 'jaxpso[plots]'") from error

  status = columns["status"]
  frames = np.arange(len(status))
  colors = np.array([np.array(c) / 255.0 for c in STATUS_COLORS])[status]
  figure = Figure(figsize=(10, 4))
  FigureCanvasAgg(figure)
  left, right = figure.subplots(1, 2)
  if errors is not None:
    shown = np.where(np.isfinite(errors), errors, np.nan)
    left.plot(frames, shown, color="0.6", linewidth=1, zorder=1)
    left.scatter(frames, shown, c=colors, s=12, zorder=2)
    left.axhline(WITHIN_PX, color="k", linestyle="--", linewidth=1, label=f"{WITHIN_PX:g} px")
    left.set_ylabel("RMS corner error (px)")
    if np.nanmax(np.append(shown, 0.0)) > 20 * WITHIN_PX:
      left.set_yscale("log")
    left.set_title("corner error per frame")
  else:
    shown = np.where(np.isfinite(columns["scores"]), columns["scores"], np.nan)
    left.plot(frames, shown, color="0.6", linewidth=1, zorder=1)
    left.scatter(frames, shown, c=colors, s=12, zorder=2)
    left.set_ylabel("score")
    left.set_title("score per frame")
  left.set_xlabel("frame")
  for code, name in enumerate(STATUS_NAMES):  # legend entries for the status colours
    left.scatter([], [], color=np.array(STATUS_COLORS[code]) / 255.0, s=12, label=name)
  left.legend(loc="best", fontsize="small")

  tracked = _centres(columns["corners"])
  if truth_corners is not None:
    truth = _centres(np.asarray(truth_corners, np.float64))
    right.plot(truth[:, 0], truth[:, 1], color="k", linewidth=1.5, label="truth")
  right.plot(tracked[:, 0], tracked[:, 1], color="tab:green", linewidth=1, marker=".",
             markersize=3, label="tracked")
  right.invert_yaxis()
  right.set_aspect("equal", adjustable="datalim")
  right.set_xlabel("x (px)")
  right.set_ylabel("y (px)")
  right.set_title("template centre")
  right.legend(loc="best", fontsize="small")
  figure.tight_layout()
  figure.savefig(os.fspath(path), dpi=80, format="png")

