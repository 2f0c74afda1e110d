"""A region's registration under motion blur: the template smeared along the region's motion.

Why: a camera moving fast blurs the region along its motion during the
exposure, and a fine texture then no longer matches the sharp template:
on challenges.py's brick poster (seed 1, out of view), 5-6 px of blur took
the right match's quality to MI 0.43-0.52 and NCC 0.77-0.84, under
`TrackConfig.lost_threshold`, and the region was LOST in full view.  The
same template convolved with a line of half the region's motion between
frames scored MI 0.79-0.81 and NCC 0.96-0.97 at the truth (2026-11-27).
The exposure is not known, so the smear is tried at `EXPOSURES` of that
motion.  On the host, only for frames the tracker would report LOST while
the region moves fast.
"""

from __future__ import annotations

import numpy as np

from jaxpso._src import align as aligning

MIN_MOTION_PX = 2.0
"""The region's motion between frames (RMS over its corners) from which a lost frame is tried blurred."""
MIN_INSIDE = 0.5
"""The share of the region inside the frame that a blurred registration counts from."""
EXPOSURES = (0.5, 1.0)
"""Exposures tried, as fractions of the time between frames."""


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
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  rows, cols = template.shape
  centre = np.array([(cols - 1) / 2, (rows - 1) / 2, 1.0])
  here = h @ centre
  moved = step @ here
  back = np.linalg.inv(h) @ np.array([moved[0] / moved[2], moved[1] / moved[2], 1.0])
  vector = exposure * (back[:2] / back[2] - centre[:2])
  return cv2.filter2D(template, -1, line_kernel(vector), borderType=cv2.BORDER_REFLECT)


def register_blurred(frame: np.ndarray, template: np.ndarray, h: np.ndarray, step: np.ndarray,
                     config, key):
  """`AlignResult` of the best of `EXPOSURES` (highest quality): `align` of the template smeared
  along `step` (`smear`), from h.

  frame (H, W), template (h, w) float32 grey; h (3, 3) the start; step (3, 3)
  the region's last motion between frames.
  """
  best = None
  for exposure in EXPOSURES:
    found = aligning.align(frame, smear(template, h, step, exposure), h, config=config, key=key)
    if best is None or float(found.quality) > float(best.quality):
      best = found
  return best
