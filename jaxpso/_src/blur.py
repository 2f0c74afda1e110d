"""A region's registration under motion blur: the template smeared along the region's motion.

Why: a camera moving fast blurs the region along its motion during the
exposure, and a fine texture then no longer matches the sharp template:
on challenges.py's brick poster (seed 1, out of view), 5-6 px of blur took
the right match's quality to MI 0.43-0.52 and NCC 0.77-0.84, under
`TrackConfig.lost_threshold`, and the region was LOST in full view.  The
same template convolved with a line of half the region's motion between
frames scored MI 0.79-0.81 and NCC 0.96-0.97 at the truth (2026-11-27).
The exposure is not known, so the smear is tried at `EXPOSURES` of that
motion.  Where the region's motion is not known (a re-detection after a
loss), the line is fitted to the frame at a candidate place instead
(`fit_line`): at the truth of that sequence the best line correlated at
0.97-0.98 and took the quality to MI 0.76-0.85 and NCC 0.95-0.98, where a
brick 79 px off reached MI 0.39-0.54 and NCC 0.79-0.86 (2026-11-27).  On
the host, only for frames the tracker would report LOST.
"""

from __future__ import annotations

import numpy as np

from jaxpso._src import align as aligning
from jaxpso._src import checks
from jaxpso._src import visible

MIN_MOTION_PX = 2.0
"""The region's motion between frames (RMS over its corners) from which a lost frame is tried blurred."""
MIN_INSIDE = 0.5
"""The share of the region inside the frame that a blurred registration counts from."""
MAX_GAP = 2
"""The most LOST frames since the motion was seen for its smear to be tried: after a long loss
the motion is stale, and a poster smeared along it matched 49 px off at NCC 0.89 after 25 lost
frames (challenges.py, seed 0, out of view); `detect` fits the blur instead."""
EXPOSURES = (0.5, 1.0)
"""Exposures tried, as fractions of the time between frames."""
LINE_LENGTHS_PX = (2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0)
"""Lengths of the lines `fit_line` tries (template pixels), at every `LINE_ANGLE_STEP`."""
LINE_ANGLE_STEP = 15.0
# The template's rim this many pixels wide is left out of the fit: the
# smear there reads the reflected border.
_FIT_MARGIN = 8
# A place whose frame, both smoothed by _COARSE_SIGMA px, correlates with
# the template under _MIN_COARSE is not fitted; one whose best line
# correlates under _MIN_FIT is not aligned smeared.  challenges.py,
# 2026-11-27: at the truth under 6-13 px of blur the smoothed correlation
# was 0.91-1.0 and the best line 0.95-1.0 (0.77 where a shake turned within
# the exposure); a brick 79 px off 0.84-0.94 (seed 1); detect's candidates
# in frames without the target, smoothed 0.1-0.8, best line up to 0.78
# (lines at full resolution; at half resolution, as fitted here, the truth
# 0.99-1.0).
_COARSE_SIGMA, _MIN_COARSE, _MIN_FIT = 4.0, 0.85, 0.9


def line_kernel(vector) -> np.ndarray:
  """(n, n) float32 kernel summing to 1: a line segment along `vector` (x, y) pixels, centred."""
  vector = np.asarray(vector, np.float64)
  length = float(np.hypot(*vector))
  size = 2 * int(np.ceil(length / 2)) + 3
  kernel = np.zeros((size, size), np.float64)
  centre = (size - 1) / 2
  for t in np.linspace(-0.5, 0.5, max(2, int(np.ceil(2 * length)) + 1)):
    x, y = centre + t * vector
    x0, y0 = int(np.floor(x)), int(np.floor(y))
    fx, fy = x - x0, y - y0  # bilinear splat of each sample
    kernel[y0:y0 + 2, x0:x0 + 2] += np.outer([1 - fy, fy], [1 - fx, fx])
  return (kernel / kernel.sum()).astype(np.float32)


def smear(template: np.ndarray, h: np.ndarray, step: np.ndarray, exposure: float) -> np.ndarray:
  """(h, w) float32 `template` blurred as the frame sees it when the region moves by `step`.

  h (3, 3): template → frame; step (3, 3): the region's motion from one
  frame to the next (frame → frame).  The blur is the template centre's
  motion over `exposure` of it, brought back into template pixels.
  """
  rows, cols = template.shape
  centre = np.array([(cols - 1) / 2, (rows - 1) / 2, 1.0])
  here = h @ centre
  moved = step @ here
  back = np.linalg.inv(h) @ np.array([moved[0] / moved[2], moved[1] / moved[2], 1.0])
  return smeared_along(template, exposure * (back[:2] / back[2] - centre[:2]))


def smeared_along(template: np.ndarray, line) -> np.ndarray:
  """(h, w) float32 `template` convolved with `line_kernel(line)` (x, y template pixels)."""
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  return cv2.filter2D(template, -1, line_kernel(line), borderType=cv2.BORDER_REFLECT)


def register_blurred(frame: np.ndarray, template: np.ndarray, h: np.ndarray, step: np.ndarray,
                     config, key):
  """`AlignResult` of the best of `EXPOSURES` (highest quality): `align` of the template smeared
  along `step` (`smear`), from h; None where h folds the template (`checks.is_start`) or
  every smear is textureless (`checks.MIN_TEXTURE`: a periodic texture smeared along its
  period).

  frame (H, W), template (h, w) float32 grey; h (3, 3) the start; step (3, 3)
  the region's last motion between frames.
  """
  if not checks.is_start(h, template.shape):
    return None
  best = None
  for exposure in EXPOSURES:
    smeared = smear(template, h, step, exposure)
    if np.std(smeared) < checks.MIN_TEXTURE:
      continue
    found = aligning.align(frame, smeared, h, config=config, key=key)
    if best is None or float(found.quality) > float(best.quality):
      best = found
  return best


def fit_line(frame: np.ndarray, template: np.ndarray, h: np.ndarray, either_sign: bool):
  """((2,) line (x, y) in template pixels, its correlation): the line kernel whose smear of the
  template correlates best with the frame mapped back onto the template at h (zero: none
  better than the sharp template).

  frame (H, W), template (h, w) float32 grey; h (3, 3) template → frame.
  `either_sign`: an anticorrelation counts (mutual information).  The
  correlation is over the template's pixels inside the frame, `_FIT_MARGIN`
  from its rim; -1 where fewer than a quarter of them are; the smoothed
  correlation where that is under `_MIN_COARSE` (no line is fitted).
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  rows, cols = template.shape
  back, inside = visible.mapped_back(frame, h, (cols, rows))
  inside = inside > 0.999
  rim = _FIT_MARGIN
  inside[:rim], inside[-rim:], inside[:, :rim], inside[:, -rim:] = False, False, False, False
  if inside.sum() < 0.25 * rows * cols:
    return np.zeros(2), -1.0

  def correlation(a, b, mask):
    return visible.correlation(a[mask], b[mask], either_sign)

  # The smoothed correlation away from the frame's edge, whose zeros the smoothing spreads.
  reach = 2 * int(np.ceil(2 * _COARSE_SIGMA)) + 1
  away = cv2.erode(inside.astype(np.uint8), np.ones((reach, reach), np.uint8)).astype(bool)
  coarse = correlation(*(cv2.GaussianBlur(a, (0, 0), _COARSE_SIGMA) for a in (template, back)),
                       away if away.sum() >= 0.1 * rows * cols else inside)
  if coarse < _MIN_COARSE:
    return np.zeros(2), coarse
  # Fitted at half resolution (a quarter of the cost), both halved alike.
  template, back = cv2.pyrDown(template), cv2.pyrDown(back)
  # A halved pixel is inside where its even and odd source pixels are; an odd side's last one
  # has no odd partner and counts as outside.
  even, odd = inside[::2, ::2], inside[1::2, 1::2]
  inside = np.zeros(template.shape, bool)
  inside[:odd.shape[0], :odd.shape[1]] = even[:odd.shape[0], :odd.shape[1]] & odd
  lines = [np.zeros(2)] + [length * np.array([np.cos(a), np.sin(a)])
                           for length in LINE_LENGTHS_PX
                           for a in np.radians(np.arange(0.0, 180.0, LINE_ANGLE_STEP))]
  best, best_score = lines[0], -np.inf
  for line in lines:
    score = correlation(smeared_along(template, line / 2), back, inside)
    if score > best_score:
      best, best_score = line, score
  return best, best_score


def register_fitted(frame: np.ndarray, template: np.ndarray, h: np.ndarray, config, key,
                    either_sign: bool):
  """`AlignResult` of the template smeared by `fit_line`'s line at h, aligned from h; None where
  the sharp template fits best, the line fits under `_MIN_FIT`, too little of the template
  is inside the frame, h folds it (`checks.is_start`) or the smear is textureless.

  frame (H, W), template (h, w) float32 grey; h (3, 3) the start.
  """
  if not checks.is_start(h, template.shape):
    return None
  line, score = fit_line(frame, template, h, either_sign)
  if score < _MIN_FIT or not np.any(line):
    return None
  smeared = smeared_along(template, line)
  if np.std(smeared) < checks.MIN_TEXTURE:
    return None
  return aligning.align(frame, smeared, h, config=config, key=key)
