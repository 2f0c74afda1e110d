"""`track`'s inputs on the host: frames as iterators, regions as corners, templates cut from frame 0.

Everything here is NumPy (and OpenCV, imported where used) and runs before
anything is compiled: it turns what the caller passed (an array or an
iterable of frames, R sequences in lockstep, rois as (x, y, w, h) boxes or
(4, 2) corner quads) into what `track` needs, and names the argument in
every error.
"""

from __future__ import annotations

import itertools

import jax
import numpy as np

from jaxpso._src import homography
from jaxpso._src import motion


def frame_iterator(frames):
  """An iterator over the frames, and their number if known."""
  if isinstance(frames, (np.ndarray, jax.Array)):
    if frames.ndim not in (3, 4):
      raise ValueError(
          f"frames must be (T, H, W) or (T, H, W, 3), or an iterable of frames;"
          f" got an array of shape {frames.shape}")
    return iter(frames), frames.shape[0]
  if isinstance(frames, (str, bytes)) or not hasattr(frames, "__iter__"):
    raise TypeError(f"frames must be an array or an iterable of frames, got {type(frames).__name__}")
  return iter(frames), (len(frames) if hasattr(frames, "__len__") else None)


_END = object()


def lockstep(sequences, count: int):
  """An iterator over lists holding frame t of each of `count` sequences, and their length if known."""
  if isinstance(sequences, (np.ndarray, jax.Array)):
    if sequences.ndim not in (4, 5):
      raise ValueError(f"with sequences=True, frames must be (R, T, H, W) or (R, T, H, W, 3), or R"
                       f" iterables of frames; got an array of shape {sequences.shape}")
  elif isinstance(sequences, (str, bytes)) or not hasattr(sequences, "__len__"):
    raise TypeError("with sequences=True, frames must be an array or a sequence of R sequences,"
                    f" got {type(sequences).__name__}")
  if len(sequences) != count:
    raise ValueError(f"with sequences=True, frames must hold one sequence per region: {count}"
                     f" regions, {len(sequences)} sequences")
  iterators, lengths = zip(*(frame_iterator(s) for s in sequences))
  if None not in lengths and len(set(lengths)) > 1:  # refused before anything is compiled
    raise ValueError(f"the sequences must have one length: their lengths are {list(lengths)}")

  def steps():
    for index, step in enumerate(itertools.zip_longest(*iterators, fillvalue=_END)):
      if any(f is _END for f in step):
        raise ValueError(f"the sequences must have one length: some end after {index} frames,"
                         " some do not")
      yield list(step)

  known = None if None in lengths else lengths[0]
  return steps(), known


def template_geometry(roi, frame_shape, name: str = "roi"):
  """roi → (its (4, 2) corners TL, TR, BR, BL in frame 0, template shape (h, w))."""
  array = np.asarray(roi, np.float64) if not isinstance(roi, (str, bytes)) else None
  if array is None or array.shape not in ((4,), (4, 2)):
    raise ValueError(f"{name} must be (x, y, w, h) or (4, 2) corners TL, TR, BR, BL; got {roi!r}")
  if not np.all(np.isfinite(array)):
    raise ValueError(f"{name} must be finite, got {roi!r}")
  height, width = frame_shape
  if array.shape == (4,):
    x, y, w, h = array
    if w < 1 or h < 1 or w != int(w) or h != int(h):
      raise ValueError(f"{name} width and height must be positive integers, got {roi!r}")
    corners = np.array([[x, y], [x + w - 1, y], [x + w - 1, y + h - 1], [x, y + h - 1]])
    shape = (int(h), int(w))
  else:
    corners = array
    w = 0.5 * (np.linalg.norm(corners[1] - corners[0]) + np.linalg.norm(corners[2] - corners[3]))
    h = 0.5 * (np.linalg.norm(corners[3] - corners[0]) + np.linalg.norm(corners[2] - corners[1]))
    shape = (int(round(h)) + 1, int(round(w)) + 1)
    if not np.all(np.asarray(motion.corner_turns(corners)) > 0) or min(shape) < 2:
      raise ValueError(
          f"{name} corners must form a convex, non-degenerate quadrilateral in the order TL, TR,"
          f" BR, BL (clockwise on the image), got {roi!r}")
  if (corners.min(axis=0) < 0).any() or corners[:, 0].max() > width - 1 or corners[:, 1].max() > height - 1:
    raise ValueError(f"{name} {roi!r} must lie inside frame 0 of shape {frame_shape}")
  return corners, shape


def regions(roi):
  """roi → (list of single rois, whether it was a batch)."""
  if isinstance(roi, (str, bytes)):
    raise ValueError(f"roi must be (x, y, w, h) or (4, 2) corners, or a batch of them; got {roi!r}")
  ndim = np.ndim(roi)
  batched = ndim == 3 or (ndim == 2 and np.shape(roi)[-1] == 4)
  if batched and len(roi) == 0:
    raise ValueError("roi must hold at least one region, got an empty batch")
  return (list(roi) if batched else [roi]), batched


def template(frame: np.ndarray, corners: np.ndarray, shape) -> np.ndarray:
  """The (h, w) template of a region of frame 0: its pixels, or its quad warped onto the rectangle."""
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  rows, cols = shape
  rect = homography.host_rect_corners(shape)
  if np.array_equal(corners - corners[0], rect) and np.all(corners[0] == np.round(corners[0])):
    x, y = int(corners[0, 0]), int(corners[0, 1])
    return np.ascontiguousarray(frame[y:y + rows, x:x + cols])
  h = cv2.getPerspectiveTransform(rect.astype(np.float32), corners.astype(np.float32))
  return cv2.warpPerspective(frame, h, (cols, rows), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
