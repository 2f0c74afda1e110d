"""Which part of a region is visible, and its registration from that part alone.

Why: a region half covered (an occluder) or half outside the frame still
shows enough to track, but the whole template's quality drops under
`TrackConfig.lost_threshold`, and `track` would freeze its estimate while
the target moves on.  Here the region is split into `GRID` × `GRID` blocks;
at the estimate each block is judged visible where it lies inside the
frame and the frame, mapped back onto the template, correlates closely with
the template's block (both smoothed, so that the estimate may be a pixel
off; a block partly covered correlates at 0.5–0.87 against 0.93–1 for a
clear one, challenges.py's occlusion).  The largest rectangle of blocks
nearly all visible is a template of its own, registered by `align` from
the estimate; its homography, moved back to the whole template's pixels,
is the region's.  On the host, only for frames the tracker would report
LOST or matched mostly outside the frame.  Under a quarter inside, too
little is left to register: `followed` moves the estimate with the part
inside (a shift), the region still LOST.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from jaxpso._src import align as aligning
from jaxpso._src import checks

GRID = 8
"""Blocks per side of the region."""
# A block is visible where this share of it lies in the frame and its
# smoothed correlation with the template's block reaches _BLOCK_NCC.  With
# 4×4 blocks and 0.5, blocks half covered entered the visible part, whose
# registration then lay 6–52 px off (challenges.py, occlusion).
_IN_FRAME, _BLOCK_NCC, _SMOOTHING_PX = 0.95, 0.9, 2.0
# The visible part: a rectangle of blocks with at least this share visible.
_FILLED = 0.9
MIN_VISIBLE = 0.25
"""The smallest share of the region registered from its visible part."""
# The registered rectangle's share of the region at least: where the visible
# part is not a rectangle (an occluder's corner), its largest one is smaller.
_MIN_PART = 0.15
# The visible part's shorter side at least (a template of 3 pyramid levels).
_MIN_SIDE = 16
# Blocks are judged visible where the estimate is within about 2 px; a
# start this far off is first moved by the shift of best correlation
# (`recentred`): coasting on through a pan that stopped put a brick poster
# half out of the frame 3 px off, where no block matched (challenges.py,
# seed 1, out of view, MI).
_SHIFT_PX = 8

# `followed`: template shifts within FOLLOW_PX pixels, leaving at least
# FOLLOW_SHARE of it inside the frame (both less the smoothing's rim); the
# shift counts where the smoothed part inside correlates at FOLLOW_NCC.
# challenges.py, out of view, seeds 0 and 1, from the truth moved 12-40 px:
# the truth at 23-50 % inside under 5-7 px of motion blur correlated at
# 0.987-0.999 and was found to 0.1 px; with less inside the best shift lay
# 1-6 px off at 0.978-0.992, or 17-75 px off at 0.59-0.94.  Tracked, from
# the shape the region left with, 1.4-1.7 px off at 0.973-0.986.  A region
# coming back lay 28-54 px from where it left.
FOLLOW_PX, FOLLOW_SHARE, FOLLOW_NCC = 48, 0.15, 0.97


def blocks(frame: np.ndarray, template: np.ndarray, h: np.ndarray,
           either_sign: bool) -> np.ndarray:
  """(GRID, GRID) bool: the template's blocks visible in `frame` at `h` (template → frame).

  frame (H, W), template (h, w): float32 grey.  `either_sign`: an
  anticorrelated block counts (mutual information matches an inverted image).
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  rows, cols = template.shape
  back, inside = mapped_back(frame, h, (cols, rows))
  smooth = [cv2.GaussianBlur(a, (0, 0), _SMOOTHING_PX) for a in (back, template)]
  visible = np.zeros((GRID, GRID), bool)
  for i, j in itertools.product(range(GRID), repeat=2):
    window = _window(i, j, rows, cols)
    ncc = correlation(smooth[0][window], smooth[1][window], either_sign)
    visible[i, j] = inside[window].mean() >= _IN_FRAME and ncc >= _BLOCK_NCC
  return visible


def mapped_back(frame: np.ndarray, h: np.ndarray, size,
                border: int = 0) -> tuple[np.ndarray, np.ndarray]:
  """((rows, cols) the frame mapped onto template pixels by h (3, 3, template → frame), (rows,
  cols) how much of each of them lies inside the frame less a rim of `border` pixels, 0 to
  1); size (cols, rows).

  frame (H, W): float32 grey.
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
  h = np.asarray(h, np.float64)
  inside = np.zeros_like(frame)
  inside[border:frame.shape[0] - border, border:frame.shape[1] - border] = 1.0
  return (cv2.warpPerspective(frame, h, size, flags=flags),
          cv2.warpPerspective(inside, h, size, flags=flags))


def correlation(a: np.ndarray, b: np.ndarray, either_sign: bool) -> float:
  """The normalised cross-correlation of two arrays of one shape, 0 where either is flat; its
  magnitude where `either_sign` (an anticorrelation counts, as mutual information's)."""
  a, b = a - a.mean(), b - b.mean()
  spread = np.sqrt(np.sum(a * a) * np.sum(b * b))
  score = float(np.sum(a * b) / spread) if spread > 1e-12 else 0.0
  return abs(score) if either_sign else score


def masked_correlation(image: np.ndarray, inside: np.ndarray, patch: np.ndarray,
                       least: float, either_sign: bool = False) -> np.ndarray:
  """(H − h + 1, W − w + 1) the normalised cross-correlation of an (h, w) `patch` placed at
  every offset of an (H, W) `image` whose pixels count where `inside` (H, W) is 1 (0
  elsewhere), over those pixels alone, its magnitude where `either_sign`; -1 where fewer than
  `least` of the patch's are, or either side is flat there."""
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  inside = np.asarray(inside, np.float32)
  # Centred first: the sums below subtract products of large terms.
  image = (image - np.sum(image * inside) / max(float(inside.sum()), 1.0)) * inside
  patch = patch - patch.mean()

  def sums(a, b):
    return cv2.matchTemplate(np.ascontiguousarray(a, np.float32),
                             np.ascontiguousarray(b, np.float32), cv2.TM_CCORR)

  ones = np.ones_like(patch)
  count, s_i, s_ii = sums(inside, ones), sums(image, ones), sums(image * image, ones)
  s_p, s_pp, s_ip = sums(inside, patch), sums(inside, patch * patch), sums(image, patch)
  n = np.maximum(count, 1.0)
  covariance = s_ip - s_i * s_p / n
  spread = np.maximum(s_ii - s_i * s_i / n, 0.0) * np.maximum(s_pp - s_p * s_p / n, 0.0)
  enough = (count >= least * patch.size - 0.5) & (spread > 1e-12 * n * n)
  scores = covariance / np.sqrt(np.maximum(spread, 1e-30))
  return np.where(enough, np.abs(scores) if either_sign else scores, -1.0)


def followed(frame: np.ndarray, template: np.ndarray, h: np.ndarray,
             either_sign: bool) -> tuple[np.ndarray, float]:
  """((3, 3) h moved by the template shift, within `FOLLOW_PX`, at which the template's part
  inside the frame correlates best with the frame, both smoothed; that correlation), over
  shifts that leave at least `FOLLOW_SHARE` of the template inside; (h, -1) where none does.

  A region mostly outside the frame has too little inside for its
  homography; this moves the estimate with the part still inside (a
  translation).  frame (H, W), template (h, w): float32 grey; h (3, 3)
  template → frame.
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  rows, cols = template.shape
  reach = FOLLOW_PX
  rim = math.ceil(2 * _SMOOTHING_PX)  # smoothing reflects an image at its edges: left out
  # The template less its rim, shifted by up to `reach` either way.
  pad = reach - rim
  around = np.array([[1.0, 0, -pad], [0, 1, -pad], [0, 0, 1]])
  back, inside = mapped_back(cv2.GaussianBlur(frame, (0, 0), _SMOOTHING_PX), h @ around,
                             (cols + 2 * pad, rows + 2 * pad), rim)
  patch = cv2.GaussianBlur(template, (0, 0), _SMOOTHING_PX)[rim:rows - rim, rim:cols - rim]
  scores = masked_correlation(back, inside > 0.999, patch, FOLLOW_SHARE, either_sign)
  dy, dx = np.unravel_index(int(np.argmax(scores)), scores.shape)
  if scores[dy, dx] <= -1.0:
    return h, -1.0
  return (h @ np.array([[1.0, 0, dx - reach], [0, 1, dy - reach], [0, 0, 1]]),
          float(scores[dy, dx]))


def _window(i: int, j: int, rows: int, cols: int) -> tuple[slice, slice]:
  """Block (i, j)'s rows and columns in a template of (rows, cols) pixels."""
  return (slice(i * rows // GRID, (i + 1) * rows // GRID),
          slice(j * cols // GRID, (j + 1) * cols // GRID))


def _bounds(rectangle, rows: int, cols: int) -> tuple[int, int, int, int]:
  """(y0, y1, x0, x1) template pixels of a (row0, row1, col0, col1) rectangle of blocks."""
  r0, r1, c0, c1 = rectangle
  return r0 * rows // GRID, r1 * rows // GRID, c0 * cols // GRID, c1 * cols // GRID


def largest_rectangle(visible: np.ndarray) -> tuple[int, int, int, int] | None:
  """(row0, row1, col0, col1) block bounds of the largest rectangle with at least `_FILLED` of its
  blocks visible; None if no block is.

  A hole is allowed because a block of little texture correlates with its
  own noise; an occluder's edge hides whole rows or columns of blocks.
  """
  best, area = None, 0
  n_rows, n_cols = visible.shape
  total = np.pad(np.cumsum(np.cumsum(visible, 0), 1), ((1, 0), (1, 0)))
  for r0, c0 in itertools.product(range(n_rows), range(n_cols)):
    for r1, c1 in itertools.product(range(r0 + 1, n_rows + 1), range(c0 + 1, n_cols + 1)):
      size = (r1 - r0) * (c1 - c0)
      count = total[r1, c1] - total[r0, c1] - total[r1, c0] + total[r0, c0]
      if size > area and count >= _FILLED * size:
        best, area = (r0, r1, c0, c1), size
  return best


def recentred(frame: np.ndarray, template: np.ndarray, h: np.ndarray,
              either_sign: bool) -> np.ndarray:
  """(3, 3) h moved by the template shift, within `_SHIFT_PX`, at which the template's part
  inside the frame correlates best with the frame (h itself where too little is inside).

  frame (H, W), template (h, w): float32 grey; h (3, 3) template → frame.
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  rows, cols = template.shape
  pad = _SHIFT_PX
  around = np.array([[1.0, 0, -pad], [0, 1, -pad], [0, 0, 1]])
  back, inside = mapped_back(frame, h @ around, (cols + 2 * pad, rows + 2 * pad))
  # Template pixels whose every shifted copy stays inside the frame.
  ok = cv2.erode((inside > 0.999).astype(np.uint8), np.ones((2 * pad + 1, 2 * pad + 1), np.uint8))
  ok = ok[pad:pad + rows, pad:pad + cols].astype(bool)
  grid = np.array([[ok[_window(i, j, rows, cols)].all() for j in range(GRID)]
                   for i in range(GRID)])
  rectangle = largest_rectangle(grid)
  if rectangle is None:
    return h
  y0, y1, x0, x1 = _bounds(rectangle, rows, cols)
  if min(y1 - y0, x1 - x0) < _MIN_SIDE:
    return h
  part = template[y0:y1, x0:x1]
  window = back[y0:y1 + 2 * pad, x0:x1 + 2 * pad]
  scores = cv2.matchTemplate(window, part, cv2.TM_CCOEFF_NORMED)
  scores = np.nan_to_num(np.abs(scores) if either_sign else scores, nan=-1.0)
  dy, dx = np.unravel_index(int(np.argmax(scores)), scores.shape)
  return h @ np.array([[1.0, 0, dx - pad], [0, 1, dy - pad], [0, 0, 1]])


def register_part(frame: np.ndarray, template: np.ndarray, h: np.ndarray, config, key,
                  either_sign: bool):
  """(`AlignResult` of the whole template's homography, visible share) from the visible part,
  or (None, visible share) where less than `MIN_VISIBLE` of the region is visible (or its
  largest visible rectangle is less than `_MIN_PART` of it).

  frame (H, W), template (h, w) float32 grey; h (3, 3) the estimate.  The
  blocks are judged at h or at h `recentred`, whichever shows more of them.
  (None, 0) where h folds the template (`checks.is_start`), (None, visible share) where the
  part's match does.
  """
  h = np.asarray(h, np.float64)
  if not checks.is_start(h, template.shape):
    return None, 0.0
  visible = blocks(frame, template, h, either_sign)
  moved = recentred(frame, template, h, either_sign)
  if not np.array_equal(moved, h):
    seen = blocks(frame, template, moved, either_sign)
    if seen.sum() > visible.sum():
      h, visible = moved, seen
  share = float(visible.mean())
  rectangle = largest_rectangle(visible)
  if rectangle is None or share < MIN_VISIBLE:
    return None, share
  rows, cols = template.shape
  y0, y1, x0, x1 = _bounds(rectangle, rows, cols)
  if (y1 - y0) * (x1 - x0) < _MIN_PART * rows * cols or min(y1 - y0, x1 - x0) < _MIN_SIDE:
    return None, share
  shift = np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1]], np.float64)
  part = np.ascontiguousarray(template[y0:y1, x0:x1])
  if np.std(part) < checks.MIN_TEXTURE:
    return None, share
  found = aligning.align(frame, part, np.asarray(h, np.float64) @ shift, config=config, key=key)
  whole = np.asarray(found.homography, np.float64) @ np.linalg.inv(shift)
  if not checks.is_start(whole, template.shape):  # the part's match folds the rest
    return None, share
  return found._replace(homography=(whole / whole[2, 2]).astype(np.float32)), share
