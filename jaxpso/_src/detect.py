"""`detect`: a template found anywhere in an image, with no start.

Why it works this way: a swarm over the whole frame's position, rotation and
scale has too small a basin to find (at 160×120 positions, 24 rotations and
a 4× scale range the right one is about one cell in 10⁴), so the search is
split where each part is cheap.  The coarse stage is exhaustive over the
translation: for a grid of rotations and scales the template's inner disc,
rotated and scaled onto a pyramid level where it spans about `_PATCH_PX`
pixels, is correlated with that level of the whole image (OpenCV's
normalised cross-correlation, on the host: no compilation, a fraction of a
millisecond per map).  A template whose inner square is flat at that level
(its telling edges lie near its rim) is correlated whole instead, over its
rotated footprint.  The best peaks, one per rotation and scale, merged
where they name one place and ranked again on the next finer level, are the
candidate basins; a place's peak at another rotation that scores nearly as
well (a template that looks alike turned) is a candidate of its own.  An
elongated template's inner disc places it but tells its rotation and scale
poorly: around each candidate a grid of rotations and scales is scored by
correlating the whole template, smoothed; the candidate's own start and the
best of them are refined on a deeper pyramid than the template's default.
Each candidate is then a start of a bounded `align` (Gauss–Newton from the
coarsest level, then from level 1, one quick swarm where those fall short),
best first, until one reaches `TrackConfig.accept_quality` or is clearly ahead
of another (`_CLEAR_AHEAD`: evidence that does not rest on the quality's
level, which differs from one image to the next); the best, where it falls
short of the first, is aligned again with the caller's config (retries, the
full search).  Where no place reached the first nor was clearly ahead, the
whole search runs again with the disc spanning twice the pixels, on the next
finer level (`_SECOND_LOOK_PX`; not for an elongated template), and the better
of the two bests stands.  So `detect` adds no compiled program: it runs
`align`'s.  With `partial`, places where the inner square lies partly outside
the image are correlated too, over the pixels inside (`_masked_correlation`),
and the best of them are tried after the others: a region coming back into the
frame.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from jaxpso._src import blur
from jaxpso._src import checks
from jaxpso._src import visible as visibility
from jaxpso._src.align import AlignResult
from jaxpso._src.align import align
from jaxpso._src.align import counted
from jaxpso._src.config import TrackConfig

# The template's inner disc spans about this many pixels of the level it is
# matched on: small enough that a frame's coarse level is cheap to scan,
# large enough that the correlation peak stands out of a textured background.
_PATCH_PX = 12.0
# A template whose inner square, low-passed for its level, varies under this
# share of the whole template's spread (a flat middle, the telling edges near
# the rim) is correlated whole, over its rotated footprint (OpenCV's masked
# correlation, about 5× the cost of a map).
_FLAT_MIDDLE = 0.5
# The inner disc of a template whose long side exceeds _ELONGATED times its
# short one places it but tells its rotation and scale poorly: at 6:1
# (benchmarks/detection.py --aspect 6, seed 0) the first candidate lay at the
# right place in 26 of 30 trials, its rotation up to 22° and its scale up to
# 1.6× off, and `align` (`bounded`) from it succeeded in 19 of 60.  Each
# candidate of such a template is therefore also aligned from the variant,
# within _VARIANT_STEPS steps either way of scale (ratio) and rotation
# (degrees), at which the image, mapped back onto the template, correlates
# best with it, both smoothed by _VARIANT_SIGMA template pixels (scoring the
# 48 costs about 15 ms).  Detection at 6:1 went from 39 to 57 % (MI) and at
# 3:1 from 88 to 91 %; the best two variants instead of the candidate and
# the best, 57 and 88 %; the best two of a 3 × 3 grid of 8° and 2^(1/4),
# 51 and 93 %, at 6:1 from the first candidate 29 of 60 against 31 for all
# nine, whose `align`s cost 4× the time.
_ELONGATED = 2.0
_VARIANT_STEPS, _VARIANT_RATIO, _VARIANT_DEG, _VARIANT_SIGMA = 3, 2.0 ** (1 / 8), 4.0, 4.0
# `align` refines an elongated template's starts on as many pyramid levels as
# keep its short side at least this many pixels (by default
# `config.COARSEST_PX`, 12, and 1-2 levels for most of them): from the first
# candidate's two starts at 6:1, 34 of 60 succeeded against 32, in 33 ms
# against 51 (the swarm searches a coarser level); at 3:1 50 and 50, 23 ms
# against 32.  Detection: 6:1 57 → 61 % (MI), 58 → 61 % (NCC); 3:1 91 and
# 91 → 89 %.
_ELONGATED_COARSEST_PX = 6.0
# Grid steps: 15° of rotation and a factor 2^(1/3) of scale move the patch's
# rim by about 1.6 px of its level, inside the correlation peak.
_ANGLE_STEP, _SCALE_RATIO = 15.0, 2.0 ** (1 / 3)
# Two peaks name the same place when their centres are closer than this
# fraction of the template's matched size.
_SAME_PLACE = 0.5
# A template that looks alike turned (bricks, tiles: half a turn) peaks at
# its place at two rotations, and the one merged away may be the right one:
# detection.py's seed 1 lost four brick trials, three of them where the right
# rotation scored 0.91-1.00 of the half turn's at its place.  So each place also
# keeps its best peak turned more than _TURNED degrees from its own, where
# that scores at least _TWIN times the place's, and, refined like it and
# still at _TWIN times it, tries it as a place of its own right after it.
# detection.py, 100 trials each (2026-12-08): MI at seeds 1, 2, 4, 5 96 →
# 99, 94 → 97, 95 → 96, 94 → 96 %; NCC 96 → 99, 92 → 95, 96 → 97, 95 → 97 %;
# seeds 0 and 3 as they were, no trial lost; MI at 3:1 (60 trials) 91.7 →
# 93.3 %, at 6:1 68.3 → 66.7 % (a miss whose polish now starts from another
# wrong place).
_TWIN, _TURNED = 0.8, 60.0
# Only a template that looks alike turned keeps twins: its inner square,
# shrunk to span about _ALIKE_PX pixels and turned by a quarter, a half or
# three quarters, correlates with the template somewhere at least _ALIKE.
# detection.py's templates (seeds 0-2, 300): brick crops 0.24-0.95 (median
# 0.71), the other photographs' 0.04-0.59; the six trials the twins fixed there
# scored 0.71-0.92.  Elsewhere twins of wrong places only cost alignments.
_ALIKE_PX, _ALIKE = 24.0, 0.6
# Each candidate is refined on this many finer levels, within this many
# pixels of each level around its place.
_REFINE_LEVELS, _REFINE_PX = 2, 3
# This many times the candidates asked for are refined on the next finer
# level and ranked there: a coarse peak of the background can outscore the
# target's, whose larger patch on the finer level tells them apart
# (benchmarks/results/detection.md: 96 % within 2 px with the coarse ranking,
# 98 % with this one).  Ranking 8× instead of 16× (2026-12-07, detection.py,
# MI and NCC at seeds 0 and 1, MI at 3:1 and 6:1, 460 trials) left every
# trial's error as it was, and halved the stage's ~580 small correlations;
# 4× lost MI's trial 47 at seed 0.
_RERANK = 8
# The places wholly inside are aligned, best first, until the best one's
# quality is _CLEAR_AHEAD times every other aligned place's (at least two,
# the best at least 1/_CLEAR_AHEAD of the lost threshold): the coarse ranking
# put the target first, and the next place confirmed it is not a tie.  MI's
# right places score 0.59–0.97 in detection.py's scenes, wrong ones
# 0.01–0.46.  Replayed on every place's recorded `bounded` alignment
# (2026-12-07; detection.py's scenes, seeds 0 and 1, 100 trials each, MI
# and NCC; 60 trials at 3:1 and 6:1, MI): no trial lost, MI's alignments
# per detection 3.5-3.6 → 2.0 (squares), 7.0 → 4.2 (3:1), 7.8 → 5.6 (6:1),
# NCC's 1.6-1.7 → 1.3-1.4.  Places partly outside are aligned whatever.
_CLEAR_AHEAD = 2.0
# `detect` looks again where its best place is neither accepted nor clear ahead
# (`_best_of`): candidates from maps where the inner disc spans this many
# pixels, one pyramid level finer, aligned alike, the better best standing.
# Where the disc spans _PATCH_PX, smaller scales' peaks on finer maps can
# outscore the right place's (detection.py's seed 2, trials 6 and 66, seed 4,
# trial 44: every candidate at a scale of 0.42-0.75, the truth's 1.2-1.5).
# At 24 px instead of 12, detection.py (seeds 0-5, 100 trials each,
# 2026-12-08) found 571 of 600 (MI) and 572 (NCC) against 585 and 583, but not
# the same ones: the coarser maps find what the finer ones miss too.  Looking
# again (the same seeds, db7b05e beside): 585 → 589 (MI), 583 → 587 (NCC),
# none lost, medians as before, the 90th percentile up to 2.3×
# (detection_look*.md).  Not for an elongated template (`_ELONGATED`), whose
# inner disc is a small part of it: at 3:1 no trial gained and at 6:1 one of
# 60, at 1.8-1.9× the 90th percentile's time (detection_look_aspect3.md,
# detection_look_aspect6.md).
_SECOND_LOOK_PX = 24.0
# `detect(partial=True)` correlates the template's inner square where at
# least this share of it lies inside the image (a template about half
# inside), over that share alone.
_PARTIAL_SHARE = 0.5
# ... and refines this many candidates of places partly outside the image
# after the `count` best wholly inside.
_PARTIAL_CANDIDATES = 2
# Places partly outside correlate on half a patch, and one corner of the
# frame can top every map: each map gives this many places.
_PARTIAL_PLACES = 4
SCALES, ANGLES, CANDIDATES = (0.5, 2.0), (-180.0, 180.0), 4
"""`detect`'s default scale range, rotation range (degrees) and candidate places refined."""
# With mutual information the image may be inverted (MI matches it):
# peaks of negative correlation count too.  NCC and SSD cannot match it.
_EITHER_SIGN = {"mi": True, "ncc": False, "ssd": False}


def _checked_range(value, name: str, positive: bool) -> tuple[float, float]:
  try:
    low, high = (float(v) for v in value)
  except (TypeError, ValueError):
    raise ValueError(f"{name} must be two numbers (low, high), got {value!r}") from None
  if not (math.isfinite(low) and math.isfinite(high)) or low > high:
    raise ValueError(f"{name} must be finite with low <= high, got {value!r}")
  if positive and low <= 0:
    raise ValueError(f"{name} must be > 0, got {value!r}")
  return low, high


def _grid(low: float, high: float, step: float, geometric: bool) -> np.ndarray:
  """Values from low to high (both included) at most `step` apart (a ratio when `geometric`)."""
  if geometric:
    count = 1 + math.ceil(math.log(high / low) / math.log(step) - 1e-9) if high > low else 1
    return np.geomspace(low, high, count)
  count = 1 + math.ceil((high - low) / step - 1e-9) if high > low else 1
  return np.linspace(low, high, count)


def _similarity(centre, scale: float, angle_deg: float, template_shape) -> np.ndarray:
  """(3, 3) template pixel → image pixel: rotate by the angle and scale about the template's
  centre, which lands on `centre` (x, y)."""
  rows, cols = template_shape
  a = math.radians(angle_deg)
  c, s = scale * math.cos(a), scale * math.sin(a)
  x, y = (cols - 1) / 2, (rows - 1) / 2
  # In Python floats: called for every map and refinement try, NumPy's small
  # arrays cost ten times as much.
  return np.array([[c, -s, centre[0] - (c * x - s * y)], [s, c, centre[1] - (s * x + c * y)],
                   [0.0, 0.0, 1.0]])


def _masked_correlation(picture: np.ndarray, patch: np.ndarray, first, last,
                        least: float) -> np.ndarray:
  """(rows, cols) the normalised cross-correlation of a (side, side) `patch` whose top-left
  corner lies at every (x, y) from `first` to `last` (level pixels, both included; the patch
  may reach outside `picture`), over its pixels inside; -1 where fewer than `least` of them
  are, or either is flat there."""
  side = patch.shape[0]
  rows, cols = picture.shape
  x0, y0 = first
  x1, y1 = np.asarray(last) + side  # one past the window's last pixel
  inside = np.zeros((y1 - y0, x1 - x0), np.float32)
  image = np.zeros_like(inside)
  ys, xs = slice(max(y0, 0), min(y1, rows)), slice(max(x0, 0), min(x1, cols))
  window = picture[ys, xs]
  inside[ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0] = 1.0
  image[ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0] = window
  return visibility.masked_correlation(image, inside, patch, least)


def candidates(image: np.ndarray, template: np.ndarray, scales, angles, count: int,
               either_sign: bool, partial=None, patch_px: float = _PATCH_PX):
  """(places wholly inside, places partly outside): lists of places, best first, each a list
  of (3, 3) float64 starts from the coarse correlation stage, up to `count` places inside,
  each followed by its turned twin where it has one (`_TWIN`); a place's one start, or for an
  elongated template (`_ELONGATED`) two, its own and a variant (`likeliest`).

  image (H, W), template (h, w): float32 grey.  `scales`, `angles` (low,
  high): the ranges searched (angles in degrees); `either_sign`: anticorrelation
  counts as a match too; `partial` (scales, angles) ranges: up to
  `_PARTIAL_CANDIDATES` places partly outside within them, where up to
  `1 - _PARTIAL_SHARE` of the template's inner square lies outside the image
  (None: none); `patch_px`: the pixels the inner disc spans on the level it is correlated on
  (`_PATCH_PX`, `_SECOND_LOOK_PX`).
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  rows, cols = template.shape
  disc = min(rows, cols) / math.sqrt(2.0)  # the side of the square inside the inscribed disc
  elongated = _elongated(template.shape)
  top, left = (int((n - disc) / 2) for n in (rows, cols))  # the inner square's corner
  levels = [np.ascontiguousarray(image, np.float32)]
  lowpassed = {}  # sigma → (low-passed template, flat middle), shared by its rotations

  def smoothed(factor):
    """(the template low-passed before shrinking by `factor` (a Gaussian of about half the new
    pixel) or itself; whether its inner square varies under `_FLAT_MIDDLE` of its spread)."""
    sigma = _antialias_sigma(factor)
    sigma = sigma if sigma > 0.3 else 0.0
    if sigma not in lowpassed:
      blurred = cv2.GaussianBlur(template, (0, 0), sigma) if sigma else template
      middle = blurred[top:rows - top, left:cols - left]
      lowpassed[sigma] = blurred, float(np.std(middle)) < _FLAT_MIDDLE * float(np.std(blurred))
    return lowpassed[sigma]

  def match(scale, angle, level, around=None, border=False, places=1):
    """[(score, (x, y) full-resolution centre)] of the best `places` places of the patch at
    `level`, best first, at least half the patch apart; within a few level pixels of `around`
    when given; [] where the patch does not fit.  `border`: places partly outside the picture
    (`_PARTIAL_SHARE`), alone where `around` is None."""
    picture = levels[level]
    factor = scale / 2 ** level  # template pixel → level pixel
    blurred, flat_middle = smoothed(factor)
    whole = flat_middle and not border
    side = max(4, int(math.ceil(math.hypot(rows, cols) * factor)) if whole
               else int(round(disc * factor)))
    if side + 2 > min(picture.shape):
      return []
    # level patch pixel q ← template pixel p: q = factor·R·(p − centre) + patch centre
    to_patch = _similarity(((side - 1) / 2,) * 2, factor, angle, template.shape)[:2]
    patch = cv2.warpAffine(blurred, to_patch, (side, side), flags=cv2.INTER_LINEAR)
    mask = None
    if whole:  # the template's footprint, less its interpolated rim
      mask = (cv2.warpAffine(np.ones_like(blurred), to_patch, (side, side),
                             flags=cv2.INTER_LINEAR) > 0.999).astype(np.float32)
    spread = cv2.meanStdDev(patch, mask=None if mask is None else (mask > 0).astype(np.uint8))[1]
    if float(spread[0, 0]) < checks.MIN_TEXTURE / 4:  # np.std: 15 µs a call, this 2
      return []
    pad = int(side * (1 - _PARTIAL_SHARE)) if border else 0  # the patch's reach outside
    # The patch's top-left places tried (level pixels), in Python ints: NumPy's
    # small arrays cost more than the small maps of a refinement.
    corner = [-pad, -pad]
    last = [picture.shape[1] - side + pad, picture.shape[0] - side + pad]
    if around is not None:  # a window of ±_REFINE_PX level pixels around the centre
      for k in range(2):
        low = round(float(around[k]) / 2 ** level - (side - 1) / 2) - _REFINE_PX
        corner[k] = min(max(low, corner[k]), last[k])
        last[k] = min(corner[k] + 2 * _REFINE_PX, last[k])
    corner, last = np.array(corner), np.array(last)
    if pad:
      scores = _masked_correlation(picture, patch, corner, last, _PARTIAL_SHARE)
      if around is None:  # the places wholly inside are the other search's
        ys, xs = np.indices(scores.shape) + corner[::-1, None, None]
        inner = np.array(picture.shape)[:, None, None] - side
        scores[(ys >= 0) & (xs >= 0) & (ys <= inner[0]) & (xs <= inner[1])] = -1.0
    else:
      window = picture[corner[1]:last[1] + side, corner[0]:last[0] + side]
      scores = cv2.matchTemplate(window, patch, cv2.TM_CCOEFF_NORMED, mask=mask)
    # At the edge, half patches anticorrelated with the frame outscored an MI
    # target coming back (challenges.py, seed 1, out of view): not counted.
    if either_sign and not border:
      np.abs(scores, out=scores)  # both maps are this call's own
    scores[~np.isfinite(scores)] = -1.0
    found = []
    for _ in range(places):
      y, x = divmod(int(np.argmax(scores)), scores.shape[1])
      found.append((float(scores[y, x]), (corner + [x, y] + (side - 1) / 2) * 2 ** level))
      reach = side // 2
      scores[max(y - reach, 0):y + reach + 1, max(x - reach, 0):x + reach + 1] = -np.inf
    return found

  def level_of(scale):
    level = max(0, int(round(math.log2(disc * scale / patch_px))))
    while len(levels) <= level and min(levels[-1].shape) >= 2 * patch_px:
      levels.append(cv2.pyrDown(levels[-1]))
    return min(level, len(levels) - 1)

  def starts(wanted: int, border: bool, scales, angles):
    """The `wanted` best candidates' (3, 3) homographies within the (low, high) ranges `scales`
    and `angles`; `border`: of places partly outside."""
    angle_grid = _grid(angles[0], angles[1], _ANGLE_STEP, False)
    if angles[1] - angles[0] >= 360.0 - 1e-6:  # a full turn: -180 and 180 are one angle
      angle_grid = angle_grid[:-1]
    peaks = []  # (score, centre, scale, angle, level)
    for scale in _grid(scales[0], scales[1], _SCALE_RATIO, True):
      level = level_of(scale)
      for angle in angle_grid:
        for found in match(scale, angle, level, border=border,
                           places=_PARTIAL_PLACES if border else 1):
          peaks.append(found + (scale, angle, level))
    peaks.sort(key=lambda p: -p[0])
    alike = not border and _looks_alike_turned(template)  # twins: places wholly inside only
    # spots: the chosen places as Python floats (math.dist's fast path); twins: each place's
    # best peak turned more than `_TURNED` from its own that scores `_TWIN` times it, or None.
    chosen, spots, twins = [], [], []
    for peak in peaks:
      spot = (float(peak[1][0]), float(peak[1][1]))
      near = next((k for k, (there, other) in enumerate(zip(spots, chosen))
                   if math.dist(spot, there) <= _SAME_PLACE * disc * min(peak[2], other[2])),
                  None)
      if near is None:
        chosen.append(peak)
        spots.append(spot)
        twins.append(None)
      elif (alike and twins[near] is None and _turned(peak[3], chosen[near][3])
            and peak[0] >= _TWIN * chosen[near][0]):
        twins[near] = peak
      if len(chosen) == _RERANK * wanted:
        break

    def refine(candidate, levels: int):
      """The candidate (score, place, scale, angle, level, angle step, scale step) refined on
      the next `levels` finer levels, halving the grid's steps each level."""
      score, place, scale, angle, level, step_angle, step_scale = candidate
      for finer in range(level - 1, max(level - 1 - levels, -1), -1):
        tries = [(s_, a_) for s_ in (scale / step_scale, scale, scale * step_scale)
                 for a_ in (angle - step_angle, angle, angle + step_angle)]
        results = [(found[0], s_, a_) for s_, a_ in tries
                   for found in [match(s_, a_, finer, place, border)] if found]
        if not results:
          break
        (score, place), scale, angle = max(results, key=lambda r: r[0][0])
        level, step_angle, step_scale = finer, step_angle / 2, step_scale ** 0.5
      return score, place, scale, angle, level, step_angle, step_scale

    # Every candidate refined on the next finer level and ranked there; the best
    # `wanted` refined on the finer levels left, each followed by its twin where
    # that, refined alike, still scores `_TWIN` times it.
    grid = (_ANGLE_STEP / 2, _SCALE_RATIO ** 0.5)  # the coarse grid's half steps
    ranked = sorted(((refine(peak + grid, 1), twin) for peak, twin in zip(chosen, twins)),
                    key=lambda c: -c[0][0])
    finished = []
    for own, twin in ranked[:wanted]:
      finished.append(refine(own, _REFINE_LEVELS - 1))
      twin = None if twin is None else refine(twin + grid, _REFINE_LEVELS)
      if twin is not None and twin[0] >= _TWIN * finished[-1][0]:
        finished.append(twin)
    if not elongated or border:
      return [[_similarity(c[1], c[2], c[3], template.shape)] for c in finished]
    steps = range(-_VARIANT_STEPS, _VARIANT_STEPS + 1)
    return [[_similarity(c[1], c[2], c[3], template.shape),
             likeliest([_similarity(c[1], c[2] * _VARIANT_RATIO ** i, c[3] + _VARIANT_DEG * j,
                                    template.shape) for i in steps for j in steps if i or j])]
            for c in finished]

  def likeliest(starts):
    """The one of `starts` ((3, 3) each) at which the image, mapped back onto the template,
    correlates best with it, both smoothed by `_VARIANT_SIGMA` template pixels."""
    smooth = cv2.GaussianBlur(template, (0, 0), _VARIANT_SIGMA)
    scores = []
    for h in starts:
      back, inside = visibility.mapped_back(levels[0], h, (cols, rows))
      inside = inside > 0.999
      back = cv2.GaussianBlur(back, (0, 0), _VARIANT_SIGMA)
      scores.append(visibility.correlation(smooth[inside], back[inside], either_sign)
                    if inside.sum() >= 0.25 * rows * cols else -1.0)
    return starts[int(np.argmax(scores))]

  return (starts(count, False, scales, angles),
          starts(_PARTIAL_CANDIDATES, True, *partial) if partial is not None else [])


def _antialias_sigma(factor: float) -> float:
  """The Gaussian sigma (pixels) that low-passes an image before it is shrunk by `factor`: about
  half the new pixel; 0 for `factor` >= 1."""
  return 0.5 * math.sqrt(1 / factor ** 2 - 1) if factor < 1 else 0.0


def _looks_alike_turned(template: np.ndarray) -> bool:
  """Whether `template` (h, w) float32 looks alike turned by a quarter, a half or three quarters
  of a turn (`_ALIKE`); a template whose inner square is flat does not."""
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  factor = min(1.0, _ALIKE_PX / (min(template.shape) / math.sqrt(2.0)))
  small = template
  if factor < 1.0:
    small = cv2.resize(cv2.GaussianBlur(template, (0, 0), _antialias_sigma(factor)), None,
                       fx=factor, fy=factor, interpolation=cv2.INTER_AREA)
  side = int(round(min(small.shape) / math.sqrt(2.0)))
  top, left = ((n - side) // 2 for n in small.shape)
  square = small[top:top + side, left:left + side]
  if float(cv2.meanStdDev(square)[1][0, 0]) < checks.MIN_TEXTURE / 4:  # flat: matchTemplate says 1
    return False
  return any(float(np.nanmax(cv2.matchTemplate(small, np.ascontiguousarray(np.rot90(square, k)),
                                                cv2.TM_CCOEFF_NORMED))) >= _ALIKE
             for k in (1, 2, 3))


def _turned(a: float, b: float) -> bool:
  """Whether rotations `a` and `b` (degrees) differ by more than `_TURNED` degrees."""
  return abs((a - b + 180.0) % 360.0 - 180.0) > _TURNED


def _elongated(shape) -> bool:
  """Whether a template of `shape` (h, w) is longer than `_ELONGATED` times its width."""
  return max(shape) > _ELONGATED * min(shape)


def bounded(config: TrackConfig) -> TrackConfig:
  """`config` whose `align` runs Gauss–Newton from the start (from the coarsest level, then from
  level 1), then one quick swarm whose result stands whatever its quality.

  Only knobs change (no other program): a wrong place costs no retries, and
  where no search finds a valid warp every later stage is as short as the
  quick one.
  """
  return dataclasses.replace(config, retry_quality=-1.0, retries=0, retry_scale=1,
                             max_iterations=max(1, config.quick_iterations))


def detect(image, template, *, config: TrackConfig = TrackConfig(), key=0,
           scales=SCALES, angles=ANGLES, candidates_tried: int = CANDIDATES,
           motion_blur: bool = False, partial: bool = False) -> AlignResult:
  """Finds `template` anywhere in `image`, with no start.

  The template may appear at any position, rotated in-plane within
  `angles`, scaled within `scales` and somewhat tilted (the refinement
  is a full homography).  A coarse correlation over the whole image picks
  candidate places (module docstring); each is refined by `align`, best
  first, until one reaches `TrackConfig.accept_quality` or is twice every
  other's quality (`_CLEAR_AHEAD`); a best short of the first
  is aligned again from there with `config` (retries, the full search).
  Where neither held, a second look correlates one pyramid level finer
  (`_SECOND_LOOK_PX`; not for a template over 2:1) and refines its own
  candidates alike, and the better of the two bests is returned.

  Args:
    image: (H, W) grey or (H, W, 3) colour, uint8 or float in [0, 1].
    template: (h, w) grey or colour, same conventions; no larger than the image.
    config: `TrackConfig` of the refinement (`align`'s).
    key: the swarm's seed (`align`'s).
    scales: (low, high) > 0: the template's size in the image relative to its own.
    angles: (low, high) in-plane rotation in degrees (at most a full turn).
    candidates_tried: how many candidate places `align` refines at most per look (each
      from two starts, of rotation and scale fitted there, where the
      template's long side is over twice its short one), besides a place's
      turned twin where the template looks alike turned there.
    motion_blur: a candidate short of `accept_quality` is aligned again with
      the template smeared by the line of motion blur fitted to the image
      there (`blur.register_fitted`), and the better of the two counts.
    partial: the template may lie partly outside the image: places where
      at least half of its inner square is inside are correlated over that
      part (positive correlation only; each map costs about 5× OpenCV's),
      and `align` refines the template over its pixels inside (at least
      `TrackConfig.min_valid`).

  Returns:
    `AlignResult` of the best candidate (highest quality); its status is
    `AlignStatus.NO_VALID_WARP` when no candidate could be scored, and
    `AlignStatus.NO_MATCH` when its quality stays under
    `TrackConfig.hopeless_quality`; its `num_iterations` and
    `num_evaluations` count every alignment `detect` ran, not the best's alone.

  Raises:
    ValueError: a template larger than the image, a flat template, an empty
      or non-finite range, `candidates_tried` < 1.
  """
  if not isinstance(config, TrackConfig):
    raise TypeError(f"config must be a TrackConfig, got {type(config).__name__}")
  picture = np.asarray(checks.to_gray(image, "image"))
  patch = np.asarray(checks.to_gray(template, "template"))
  if patch.shape[0] > picture.shape[0] or patch.shape[1] > picture.shape[1]:
    raise ValueError(f"template of shape {patch.shape} is larger than image of shape"
                     f" {picture.shape}")
  checks.check_texture(np.array([np.std(patch)]), lambda _: "template")
  scales = _checked_range(scales, "scales", positive=True)
  angles = _checked_range(angles, "angles", positive=False)
  if angles[1] - angles[0] > 360.0:
    raise ValueError(f"angles must span at most 360 degrees, got {angles!r}")
  checks.check_int(candidates_tried, "candidates_tried", 1)
  for name, flag in (("motion_blur", motion_blur), ("partial", partial)):
    if not isinstance(flag, bool):
      raise ValueError(f"{name} must be a bool, got {flag!r}")
  found = search(picture, patch, config, key, scales, angles, candidates_tried,
                 -math.inf if motion_blur else None, (scales, angles) if partial else None,
                 polish=True)
  if found is None:
    raise ValueError(f"template of shape {patch.shape} has no place to be matched in image of"
                     f" shape {picture.shape} at scales {scales}: it does not fit, or what is"
                     f" correlated of it is flat at every scale")
  return found


def search(picture: np.ndarray, patch: np.ndarray, config: TrackConfig, key, scales, angles,
           candidates_tried: int, blurred_from: float | None,
           partial=None, polish: bool = False) -> AlignResult | None:
  """`detect` on checked input: picture (H, W) and patch (h, w) float32 grey; `blurred_from`:
  a candidate's smeared alignment (`blur.register_fitted`) counts where its quality reaches
  this, None: none is tried; `partial`: the (scales, angles) ranges of the places partly
  outside the image also searched (`candidates`), None: none; `polish`: a best short of
  `accept_quality` is aligned again from itself with `config` (`_polished`), and where it
  was not sure (`_best_of`) the places of a second look (`_SECOND_LOOK_PX`) too.
  Its counts (`num_iterations`, `num_evaluations`) sum every alignment run.  None where no
  place could be correlated (the template does not fit, or is flat at every scale)."""
  either_sign = _EITHER_SIGN[config.similarity]
  places = candidates(picture, patch, scales, angles, candidates_tried, either_sign, partial)
  elongated = _elongated(patch.shape)
  if elongated:  # automatic levels go deeper (`_ELONGATED_COARSEST_PX`)
    config = config.for_template(patch.shape, patch, coarsest=_ELONGATED_COARSEST_PX)
  quick = bounded(config)
  accept = math.inf if config.accept_quality is None else config.accept_quality
  with counted() as spent:
    best, sure = _best_of(picture, patch, *places, quick, key, blurred_from, accept, either_sign)
    if polish:
      best = _polished(best, picture, patch, config, key, accept)
      if best is not None and not sure and float(best.quality) < accept and not elongated:
        closer, _ = candidates(picture, patch, scales, angles, candidates_tried, either_sign,
                               patch_px=_SECOND_LOOK_PX)
        other, _ = _best_of(picture, patch, closer, [], quick, key, blurred_from, accept,
                            either_sign)
        other = _polished(other, picture, patch, config, key, accept)
        if other is not None and float(other.quality) > float(best.quality):
          best = other
  if best is None:
    return None
  return best._replace(num_iterations=jnp.asarray(spent.iterations, jnp.int32),
                       num_evaluations=jnp.asarray(spent.evaluations, jnp.int32))


def _polished(found: AlignResult | None, picture, patch, config: TrackConfig, key,
              accept: float) -> AlignResult | None:
  """`found`, or where its quality is short of `accept`, its alignment again with `config`
  (retries, the full search) if that is better.

  detection.py, 2026-11-29 (--trials 100, seed 0): NCC's trial 81 went from 5.8 px off at NCC
  0.28 to 0.11 px at 0.88; trial 42 from 1.7 to 2.9 px, to NCC's own optimum (`align` from
  the truth ends 3.0 px off); success 99 % (MI) and 98 % (NCC) as before, medians within the
  host's noise.  Not in `track`'s re-detection (`search`'s `polish` False), where a region
  often is not in the frame at all."""
  if found is None or not -math.inf < float(found.quality) < accept:
    return found
  again = align(picture, patch, found.homography, config=config, key=key)
  return again if float(again.quality) > float(found.quality) else found


def _best_of(picture, patch, inside, outside, quick: TrackConfig, key, blurred_from,
             accept: float, either_sign: bool) -> tuple[AlignResult | None, bool]:
  """(the highest-quality `search` candidate, whether it is sure): the starts of the places
  `inside`, then `outside` (`candidates`), each aligned with `quick`, a smeared alignment of it
  counting from the quality `blurred_from` (None: none tried), up to the first that reaches
  `accept`; the places inside left once the best is clear ahead of another (`_clear_ahead`).
  Sure: it reached `accept` or is clear ahead.  None where there is no start."""
  best, tops = None, []  # tops: each place's best quality
  for index, place in enumerate(inside + outside):
    if index < len(inside) and _clear_ahead(tops, quick):
      continue
    tops.append(-math.inf)
    for start in place:
      found = align(picture, patch, start, config=quick, key=key)
      if blurred_from is not None and float(found.quality) < accept:
        smeared = blur.register_fitted(picture, patch, np.asarray(found.homography), quick, key,
                                       either_sign)
        if (smeared is not None and float(smeared.quality) > float(found.quality)
            and float(smeared.quality) >= blurred_from):
          found = smeared
      tops[-1] = max(tops[-1], float(found.quality))
      if best is None or float(found.quality) > float(best.quality):
        best = found
      if float(found.quality) >= accept:
        return best, True
  return best, _clear_ahead(tops, quick)


def _clear_ahead(tops: list, config: TrackConfig) -> bool:
  """Whether the best of the places' qualities `tops` (at least two) is `_CLEAR_AHEAD` times
  every other's and at least 1/`_CLEAR_AHEAD` of the lost threshold."""
  if len(tops) < 2:
    return False
  runner_up, top = sorted(tops)[-2:]
  return top >= config.lost_threshold / _CLEAR_AHEAD and top >= _CLEAR_AHEAD * max(runner_up, 0.0)
