"""Templates that match themselves shifted (periodic textures), and the best shift around a match.

Why: a periodic texture (stripes, a checkerboard, tiles) matches itself
moved by its period, and straight stripes match themselves anywhere along
the stripes: only the template's border, where texture meets background,
tells those places from the truth.  `track`'s searches stop in the nearest
of these basins.  Moving periodic textures (2-6 px periods, 24-120 px
templates pasted on a photograph; benchmarks/periodic.py, 2026-11-28) had
101 of 1 598 frames TRACKED or RECOVERED more than 5 px off: the estimate
slid along the stripes by the target's motion each frame, at a quality
that fell from 1 to 0.7 while the truth, 2-10 px away, scored 1.  So for
such a template `track` looks at every template shift within `REACH_PX`
of each match (`best_shift`), moves to a better one, and calls a match
that another shift equals DOUBTFUL.  On the host, only for templates
`aliased` flags.
"""

from __future__ import annotations

import functools

import numpy as np

from jaxpso._src import visible

REACH_PX = 16
"""The largest template shift (either axis, pixels) looked at, at most a quarter of a side."""
# A template is aliased where a shift correlates with it (over their
# overlap) at _ALIAS_NCC or more, and some shift on the way there at
# _VALLEY less: a second peak, not the slope of the first.  Of 8 000
# random 16-300 px crops of the four CC0 photographs (brick, camera, grass,
# gravel) one reached 0.82 (sky over one curved edge), the others 0.69 at
# most; checkerboards and mixed periodic textures 1, stripes of period 2-4
# at any angle 0.84-1 (99 % of them over 0.85; 2026-11-28).
_ALIAS_NCC, _VALLEY = 0.85, 0.3
# Frame pixels of a shifted template that must lie inside the frame for the
# shift to count.
_LEAST_INSIDE = 0.9


@functools.lru_cache(maxsize=None)
def _paths(reach: int) -> tuple[np.ndarray, np.ndarray]:
  """((S,) flat indices of the shifts (dx, dy) ≠ 0 with dx ≥ 0 in a (2 reach + 1)² map, (S, L)
  flat indices of the shifts on the straight path from 0 to each, itself where shorter)."""
  side, ends, paths = 2 * reach + 1, [], []
  length = 2 * reach
  for dy in range(-reach, reach + 1):
    for dx in range(0, reach + 1):
      if dx == 0 and dy <= 0:
        continue
      steps = 2 * max(abs(dx), abs(dy))
      t = np.arange(1, steps) / steps
      path = (np.round(reach + t * dy).astype(int) * side + np.round(reach + t * dx).astype(int))
      end = (reach + dy) * side + reach + dx
      ends.append(end)
      paths.append(np.concatenate([path, np.full(length - path.size, end)]))
  return np.array(ends), np.stack(paths)


def reach(shape) -> int:
  """The shift reach for a template of (rows, cols): `REACH_PX`, at most a quarter of a side."""
  return min(REACH_PX, min(shape) // 4)


def aliased(template: np.ndarray) -> bool:
  """Whether the template matches itself shifted by some s, 0 < |s| ≤ `reach`, nearly as well as
  unshifted (its self-correlation has a second peak of at least `_ALIAS_NCC`).

  template (h, w): float32 grey.
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  d = reach(template.shape)
  if d < 2:
    return False
  rows, cols = template.shape
  template = np.asarray(template, np.float32)
  scores = cv2.matchTemplate(template, template[d:rows - d, d:cols - d], cv2.TM_CCOEFF_NORMED)
  scores = np.nan_to_num(scores, nan=0.0).ravel()
  ends, paths = _paths(d)
  peak = scores[ends]
  return bool(np.any((peak >= _ALIAS_NCC) & (scores[paths].min(axis=1) <= peak - _VALLEY)))


def best_shift(frame: np.ndarray, template: np.ndarray, h: np.ndarray,
               either_sign: bool) -> tuple[np.ndarray, np.ndarray]:
  """((2,) the template shift (x, y) within `reach` at which the frame, mapped back by h,
  correlates best with the template, 0 where none can be scored; ((2 reach + 1)² scores) the
  correlation at every shift, the centre unshifted, -1 where under `_LEAST_INSIDE` of the
  template lies inside the frame).

  frame (H, W), template (h, w): float32 grey; h (3, 3) template → frame.
  `either_sign`: an anticorrelation counts (mutual information).
  """
  rows, cols = template.shape
  d = reach(template.shape)
  around = np.array([[1.0, 0, -d], [0, 1, -d], [0, 0, 1]])
  back, inside = visible.mapped_back(frame, np.asarray(h, np.float64) @ around,
                                     (cols + 2 * d, rows + 2 * d))
  scores = visible.masked_correlation(back, inside > 0.999, template, _LEAST_INSIDE, either_sign)
  dy, dx = np.unravel_index(int(np.argmax(scores)), scores.shape)
  if scores[dy, dx] <= -1.0:
    return np.zeros(2, int), scores
  return np.array([dx - d, dy - d]), scores
