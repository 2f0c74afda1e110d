"""A template as a few point sets of fixed capacity: the registration's shape-independent input.

Why: a compiled registration that took the template and its pyramid as
arrays of the template's shape compiled once per template size.  Here the
template is prepared on the host (NumPy and OpenCV, no compilation) into
point sets in flat arrays of one fixed capacity, with each set's offset and
size as data, and the registration scores a set chunk by chunk
(`measures.over_chunks`), so one program serves templates of every size and
costs what their points cost.  The sets, in template pixel coordinates of
their pyramid level:

* level l < `levels`: the pixels of the template's Gaussian pyramid level l
  (OpenCV's pyrDown).  At level 0 only the `pixels` fraction of largest
  gradient magnitude (at least `MIN_PIXELS`) feeds the refinement; a level
  of more than `resolution` pixels keeps that many of largest gradient, so
  a large template costs no more than one of `resolution` pixels.
* `FULL`: the full-resolution pixels of the final loss and `quality`: all
  of them up to `resolution`, over that one pixel of every s×s cell (every
  s-th row and column, or a pseudo-random place in the cell where that grid
  aliases a texture; with the default `RESOLUTION` a 100×100 template keeps
  one of every 3×3), scored in one chunk.

`resolution` (`TrackConfig.resolution`, static: it sets the arrays'
capacity) is the budget of points per set; the default's trade-off is
measured in benchmarks/README.md (resolution).

The constants of the similarities (the template's MI binning range and its
loss against itself, `quality`'s scale) are computed here too, once.
"""

from __future__ import annotations

import collections
import hashlib
import math
import threading
from typing import NamedTuple

import jax
import numpy as np

from jaxpso._src import atlas

RESOLUTION = 1280
"""Points per set at most by default (more pixels: those of largest gradient, or a subsample)."""
MIN_RESOLUTION = 64
"""The smallest budget (an 8×8 template's pixels)."""
MIN_PIXELS = 256
"""The level-0 selection keeps at least this many pixels."""
FULL = atlas.MAX_LEVELS
"""Index of the full-resolution set in `Template.sets`."""
LEVEL_CONTRAST = 0.15
"""A pyramid level keeping under this share of the finer level's standard deviation has lost the
template's texture (`textured_levels`).

Photographs keep 0.39–0.96 per level (3 087 levels of random 24–300 px crops
of the CC0 images), white noise 0.27; a 1 px checkerboard 0, a texture of
period 3 px 0.007, of period 4 px 0.07.
"""
CHUNK = 640
"""Every set's slot is a multiple of this (the registration's chunks, 640 and 160 points, divide it)."""
REMAP_RIDGE = 0.01
"""Weight of MI's remap's pull toward the mean intensity (`Template.remap`, `refine.adapted_coefficients`).

At 1 (a pixel's worth per bin) the remap's fixed point sat off the
alignment: Baker–Matthews median errors 0.0019–0.0032 px on unchanged
images and 0.032–0.043 px under gamma 0.5; at 0.01, 0.0010–0.0017 and
0.0022–0.0043 px, success equal in all 36 cells (benchmarks/convergence.py,
commit c5000b9).  Only 0.01 was tried.
"""


def slot(resolution: int = RESOLUTION) -> int:
  """Points reserved for each set: `resolution` rounded up to a multiple of `CHUNK`."""
  return -(-resolution // CHUNK) * CHUNK


def capacity(resolution: int = RESOLUTION) -> int:
  """Points of a `Template`'s arrays: a `slot` per set."""
  return (atlas.MAX_LEVELS + 1) * slot(resolution)


class Template(NamedTuple):
  """A prepared template (a pytree of arrays; leading batch axes allowed).

  Attributes:
    points: (capacity(resolution), 2) float32 (x, y) of every set's points, in pixels of
      the set's pyramid level; set i at offset i·`slot(resolution)`, zero-padded.
    values: (capacity(resolution),) float32 their intensities.
    sets: (MAX_LEVELS + 1, 2) int32 offset and size of the level sets
      ((0, 0) beyond `levels`), then of the `FULL` set.
    levels: () int32 pyramid levels in use.
    size: (2,) float32 the template's (h, w) in pixels.
    value_range: (2,) float32 MI's binning range of the template (`value_range`).
    self_loss: (3,) float32 the template's loss against itself under "mi"
      (binned over `value_range` with `bins` bins), "ncc" and "ssd" (its
      variance): `quality`'s scale.
    remap: (bins, bins) float32 (XᵀX + REMAP_RIDGE·I)⁻¹ of level 0's set's MI bin
      weights X: at level 0, MI's Gauss–Newton ends fitting the adapted
      template T̃ = X·c by least squares (`refine.adapted_coefficients`).
  """
  points: jax.Array
  values: jax.Array
  sets: jax.Array
  levels: jax.Array
  size: jax.Array
  value_range: jax.Array
  self_loss: jax.Array
  remap: jax.Array


SIMILARITIES = ("mi", "ncc", "ssd")
"""The order of `Template.self_loss`."""


def _gradient_magnitude(image: np.ndarray) -> np.ndarray:
  """(h·w,) squared gradient magnitude of an (h, w) image (h, w ≥ 2), `np.gradient`'s differences in 0.6× its time."""

  def along_rows(f, out):  # central differences along the last axis, one-sided at its ends
    np.subtract(f[:, 2:], f[:, :-2], out=out[:, 1:-1])
    out[:, 1:-1] *= 0.5
    np.subtract(f[:, 1], f[:, 0], out=out[:, 0])
    np.subtract(f[:, -1], f[:, -2], out=out[:, -1])

  gx, gy = np.empty_like(image), np.empty_like(image)
  along_rows(image, gx)
  along_rows(image.T, gy.T)
  gx *= gx
  gy *= gy
  gx += gy
  return gx.reshape(-1)


def _largest_gradient(image: np.ndarray, count: int) -> np.ndarray:
  """Flat indices of the `count` pixels of largest gradient magnitude, ascending.

  Ties at the threshold go to the first pixels (the selection is a function
  of the image alone).  A partition of the values and two comparisons took
  half the time of an `argpartition`.
  """
  if count >= image.size:
    return np.arange(image.size)
  magnitude = _gradient_magnitude(image)
  threshold = np.partition(magnitude, magnitude.size - count)[magnitude.size - count]
  chosen = magnitude > threshold
  ties = np.flatnonzero(magnitude == threshold)
  chosen[ties[:count - np.count_nonzero(chosen)]] = True
  return np.flatnonzero(chosen)


def _subsample(image: np.ndarray, resolution: int) -> np.ndarray:
  """Flat indices of one pixel per s×s cell of `image` (h, w); s the smallest keeping at most
  `resolution` pixels.

  The pixel is the cell's first (every s-th row and column) unless that grid
  keeps under half of the template's contrast, as it does a texture of
  period s (a 1 px checkerboard at s = 2 is constant on it); then it is at a
  place in the cell drawn once from a fixed seed.
  """
  rows, cols = image.shape
  step = 1
  while math.ceil(rows / step) * math.ceil(cols / step) > resolution:
    step += 1
  top, left = np.arange(0, rows, step), np.arange(0, cols, step)
  grid = (top[:, None] * cols + left[None, :]).reshape(-1)
  values = image.reshape(-1)
  if values[grid].std() >= 0.5 * values.std():
    return grid
  place = np.random.default_rng(0).random((2, top.size, left.size))
  row = top[:, None] + (place[0] * np.minimum(step, rows - top)[:, None]).astype(np.int64)
  col = left[None, :] + (place[1] * np.minimum(step, cols - left)[None, :]).astype(np.int64)
  return (row * cols + col).reshape(-1)


# MI bins intensities over the range between these quantiles, widened by
# _RANGE_MARGIN of its span each way and at least _MIN_SPAN wide, so that a
# low-contrast template fills the bins instead of two or three of them.  The
# quantiles are read off a histogram of _RANGE_HISTOGRAM bins between the
# extremes.
_RANGE_QUANTILES, _RANGE_MARGIN, _MIN_SPAN = (0.01, 0.99), 0.1, 0.05
_RANGE_HISTOGRAM = 1024


def textured_levels(template: np.ndarray, levels: int) -> int:
  """How many of the first `levels` pyramid levels of `template` (h, w) show its texture.

  A level counts while it keeps at least `LEVEL_CONTRAST` of the finer
  level's standard deviation; a texture of period 2–4 px (a checkerboard,
  fine stripes) is flat on the next level.
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  level = np.ascontiguousarray(template, np.float32)
  spread = cv2.meanStdDev(level)[1][0, 0]  # np.std costs 15 µs a call, this 2
  for count in range(1, levels):
    level = cv2.pyrDown(level)
    coarser = cv2.meanStdDev(level)[1][0, 0]
    if coarser < LEVEL_CONTRAST * spread:
      return count
    spread = coarser
  return levels


def value_range(values: np.ndarray) -> np.ndarray:
  """(2,) float32 MI's binning range of intensities (n,) (`measures.intensity_range` on the host)."""
  least, span = values.min(), values.max() - values.min()
  span = span if span > 0 else 1.0
  index = np.clip(((values - least) / span * _RANGE_HISTOGRAM).astype(np.int64), 0,
                  _RANGE_HISTOGRAM - 1)
  cumulative = np.cumsum(np.bincount(index, minlength=_RANGE_HISTOGRAM))
  found = np.searchsorted(cumulative, np.asarray(_RANGE_QUANTILES) * cumulative[-1])
  lo, hi = least + (found + 0.5) * (span / _RANGE_HISTOGRAM)
  half = max(hi - lo, _MIN_SPAN) * (0.5 + _RANGE_MARGIN)
  return np.array([(lo + hi) / 2 - half, (lo + hi) / 2 + half], np.float32)


# The cubic B-spline's four pieces at t in [0, 1): piece i is Σ_k t^k · _CUBIC_PIECES[k, i].
_CUBIC_PIECES = np.array([[1, 4, 1, 0], [-3, 0, 3, 0], [3, -6, 3, 0], [-1, 3, -3, 1]]) / 6.0


def _gram(values: np.ndarray, bins: int, value_range_: np.ndarray) -> np.ndarray:
  """(bins + 3, bins + 3) float64 XᵀX of the cubic B-spline bin weights X (n, bins + 3) of
  intensities (n,) (`measures.bin_weights` on the host).

  Each intensity weighs bins ⌊s⌋ − 1 … ⌊s⌋ + 2 (the pieces at t = s − ⌊s⌋);
  the columns past `bins` only ever get weight 0 (at s = bins − 2).  The 16
  products per intensity are summed by `np.bincount`, with no BLAS call: a
  dense n × 19 X and XᵀX by BLAS (0.05 ms alone) woke OpenBLAS's threads
  beside the compiled call's, and `align` (MI, 100×100 templates) took 10.6
  ms a call against 7.1–8.3 with OPENBLAS_NUM_THREADS=1; runtime.py's cases:
  align's medians 7–36 % lower in one run (benchmarks/results/runtime_cases_gram.md).
  """
  lo, hi = (float(v) for v in value_range_)
  s = 1.0 + (np.clip(values, lo, hi) - lo) * ((bins - 3) / (hi - lo))
  whole = np.floor(s)
  t = s - whole
  powers = (np.ones_like(t), t, t * t, t * t * t)
  pieces = np.stack([sum(p * c for p, c in zip(powers, column)) for column in _CUBIC_PIECES.T])
  weighed = whole.astype(np.int64) - 1 + np.arange(4)[:, None]  # (4, n) the bins each weighs
  width = bins + 3
  index = weighed[:, None] * width + weighed[None]  # (4, 4, n)
  weight = pieces[:, None] * pieces[None]
  return np.bincount(index.reshape(-1), weight.reshape(-1),
                     minlength=width * width).reshape(width, width)


def self_losses(values: np.ndarray, bins: int, value_range_: np.ndarray) -> np.ndarray:
  """(3,) float32 the loss of intensities (n,) against themselves: −MI, −NCC, SSD's scale (variance)."""
  joint = _gram(values, bins, value_range_)[:bins, :bins]
  p = joint / joint.sum()

  def entropy(q):
    q = q[q > 0]
    return -np.sum(q * np.log(q))

  mi = entropy(p.sum(0)) + entropy(p.sum(1)) - entropy(p)
  variance = values.var()
  textured = variance > (1e-6 * (1.0 + abs(values.mean()))) ** 2
  return np.array([-mi, -1.0 if textured else 0.0, variance], np.float32)


def remap(values: np.ndarray, bins: int, value_range_: np.ndarray) -> np.ndarray:
  """(bins, bins) float32 `Template.remap` of a set's intensities (n,)."""
  gram = _gram(values, bins, value_range_)[:bins, :bins]
  return np.linalg.inv(gram + REMAP_RIDGE * np.eye(bins)).astype(np.float32)


def prepare(template: np.ndarray, levels: int, pixels: float, bins: int,
            resolution: int = RESOLUTION) -> Template:
  """(h, w) float32 template → its `Template` (NumPy arrays).

  Args:
    template: (h, w) grey template; `levels` levels must stay at least 2×2.
    levels: pyramid levels, 1 to MAX_LEVELS.
    pixels: fraction of level 0's pixels (largest gradient) the refinement uses.
    bins: MI's histogram bins (for `Template.self_loss` and `Template.remap`).
    resolution: points per set at most.
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  pyramid = [np.ascontiguousarray(template, np.float32)]
  for _ in range(levels - 1):
    pyramid.append(cv2.pyrDown(pyramid[-1]))
  chosen = []
  for index, level in enumerate(pyramid):
    wanted = max(MIN_PIXELS, math.ceil(pixels * level.size)) if index == 0 else level.size
    chosen.append((level, _largest_gradient(level, min(wanted, resolution))))
  chosen += [None] * (atlas.MAX_LEVELS - levels)
  chosen.append((pyramid[0], _subsample(pyramid[0], resolution)))
  points = atlas.empty((capacity(resolution), 2))  # aligned: the program reads them uncopied
  values = atlas.empty(capacity(resolution))
  points[:], values[:] = 0.0, 0.0
  sets = np.zeros((atlas.MAX_LEVELS + 1, 2), np.int32)
  for index, entry in enumerate(chosen):
    if entry is None:
      continue
    image, flat = entry
    rows, cols = np.divmod(flat, image.shape[1])
    offset = index * slot(resolution)
    points[offset:offset + flat.size] = np.stack([cols, rows], axis=-1)
    values[offset:offset + flat.size] = image.reshape(-1)[flat]
    sets[index] = offset, flat.size
  full = chosen[FULL][0].reshape(-1)[chosen[FULL][1]].astype(np.float64)
  value_range_ = value_range(full)
  finest = values[sets[0, 0]:sets[0, 0] + sets[0, 1]].astype(np.float64)
  return Template(points, values, sets, np.int32(levels), np.asarray(template.shape, np.float32),
                  value_range_, self_losses(full, bins, value_range_),
                  remap(finest, bins, value_range_))


# `prepared` keeps the last few prepared templates: aligning one template
# against many images (or from many starts) prepares it once.
_CACHE_SIZE = 16
_cache: collections.OrderedDict = collections.OrderedDict()
_lock = threading.Lock()


def prepared(template: np.ndarray, levels: int, pixels: float, bins: int,
             resolution: int = RESOLUTION) -> Template:
  """`prepare`, or the same template's earlier preparation (keyed by its content; read-only arrays)."""
  array = np.ascontiguousarray(template, np.float32)
  key = (array.shape, hashlib.blake2b(array.data, digest_size=16).digest(), levels, pixels, bins,
         resolution)
  with _lock:
    if key in _cache:
      _cache.move_to_end(key)
      return _cache[key]
  result = prepare(array, levels, pixels, bins, resolution)
  for leaf in result:
    if isinstance(leaf, np.ndarray):
      leaf.setflags(write=False)
  with _lock:
    _cache[key] = result
    while len(_cache) > _CACHE_SIZE:
      _cache.popitem(last=False)
  return result
