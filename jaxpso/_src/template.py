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
  of more than `LEVEL_POINTS` pixels keeps that many of largest gradient, so
  a large template costs no more than a 128×128 one.
* `FULL`: every full-resolution pixel, the final loss and `quality`'s; over
  `FULL_POINTS`, a regular subsample (every s-th row and column).
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

LEVEL_POINTS = 2560
"""A pyramid level's points at most (more: those of largest gradient)."""
FULL_POINTS = 10240
"""Points of the full-resolution loss and quality at most (more: a regular subsample)."""
MIN_PIXELS = 256
"""The level-0 selection keeps at least this many pixels."""
FULL = atlas.MAX_LEVELS
"""Index of the full-resolution set in `Template.sets`."""
CHUNK = 512
"""Every set is padded to a multiple of this."""
CAPACITY = atlas.MAX_LEVELS * LEVEL_POINTS + FULL_POINTS
"""Points of a `Template`'s arrays: every set at its largest (a level's `LEVEL_POINTS` read
from its offset, or the `FULL` set's `FULL_POINTS`, stay inside)."""


class Template(NamedTuple):
  """A prepared template (a pytree of arrays; leading batch axes allowed).

  Attributes:
    points: (CAPACITY, 2) float32 (x, y) of every set's points, in pixels of
      the set's pyramid level; each set zero-padded to a multiple of `CHUNK`.
    values: (CAPACITY,) float32 their intensities.
    sets: (MAX_LEVELS + 1, 2) int32 offset and size of the level sets
      ((0, 0) beyond `levels`), then of the `FULL` set.
    levels: () int32 pyramid levels in use.
    size: (2,) float32 the template's (h, w) in pixels.
  """
  points: jax.Array
  values: jax.Array
  sets: jax.Array
  levels: jax.Array
  size: jax.Array


def _largest_gradient(image: np.ndarray, count: int) -> np.ndarray:
  """Flat indices of the `count` pixels of largest gradient magnitude, ascending."""
  if count >= image.size:
    return np.arange(image.size)
  gy, gx = np.gradient(image)
  magnitude = (gx * gx + gy * gy).reshape(-1)
  return np.sort(np.argpartition(-magnitude, count - 1)[:count])


def _subsample(shape) -> np.ndarray:
  """Flat indices of every s-th row and column, s the smallest keeping at most FULL_POINTS."""
  rows, cols = shape
  step = 1
  while math.ceil(rows / step) * math.ceil(cols / step) > FULL_POINTS:
    step += 1
  grid = np.arange(0, rows, step)[:, None] * cols + np.arange(0, cols, step)[None, :]
  return grid.reshape(-1)


def prepare(template: np.ndarray, levels: int, pixels: float) -> Template:
  """(h, w) float32 template → its `Template` (NumPy arrays).

  Args:
    template: (h, w) grey template; `levels` levels must stay at least 2×2.
    levels: pyramid levels, 1 to MAX_LEVELS.
    pixels: fraction of level 0's pixels (largest gradient) the refinement uses.
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  pyramid = [np.ascontiguousarray(template, np.float32)]
  for _ in range(levels - 1):
    pyramid.append(cv2.pyrDown(pyramid[-1]))
  chosen = []
  for index, level in enumerate(pyramid):
    wanted = max(MIN_PIXELS, math.ceil(pixels * level.size)) if index == 0 else level.size
    chosen.append((level, _largest_gradient(level, min(wanted, LEVEL_POINTS))))
  chosen += [None] * (atlas.MAX_LEVELS - levels) + [(pyramid[0], _subsample(pyramid[0].shape))]
  points = np.zeros((CAPACITY, 2), np.float32)
  values = np.zeros(CAPACITY, np.float32)
  sets = np.zeros((atlas.MAX_LEVELS + 1, 2), np.int32)
  offset = 0
  for index, entry in enumerate(chosen):
    if entry is None:
      continue
    image, flat = entry
    rows, cols = np.divmod(flat, image.shape[1])
    points[offset:offset + flat.size] = np.stack([cols, rows], axis=-1)
    values[offset:offset + flat.size] = image.reshape(-1)[flat]
    sets[index] = offset, flat.size
    offset += -(-flat.size // CHUNK) * CHUNK
  return Template(points, values, sets, np.int32(levels),
                  np.asarray(template.shape, np.float32))


# `prepared` keeps the last few prepared templates: aligning one template
# against many images (or from many starts) prepares it once.
_CACHE_SIZE = 16
_cache: collections.OrderedDict = collections.OrderedDict()
_lock = threading.Lock()


def prepared(template: np.ndarray, levels: int, pixels: float) -> Template:
  """`prepare`, or the same template's earlier preparation (keyed by its content; read-only arrays)."""
  array = np.ascontiguousarray(template, np.float32)
  key = (array.shape, hashlib.blake2b(array.data, digest_size=16).digest(), levels, pixels)
  with _lock:
    if key in _cache:
      _cache.move_to_end(key)
      return _cache[key]
  result = prepare(array, levels, pixels)
  for leaf in result:
    if isinstance(leaf, np.ndarray):
      leaf.setflags(write=False)
  with _lock:
    _cache[key] = result
    while len(_cache) > _CACHE_SIZE:
      _cache.popitem(last=False)
  return result
