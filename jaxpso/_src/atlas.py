"""An image's Gaussian pyramid in one flat buffer, sampled at any level.

Why: a compiled program is specialised to the shapes of its arguments, so a
registration that took the image (or a window of it) as a 2-D array compiled
once per image or window size, about a minute each.  Here the pyramid's
levels lie one after another, row-major, in one float32 buffer of a fixed
capacity (powers of 4 from 2¹⁶ values, `capacity`), and each level's
offset, width and height are data.  One program then serves every image
size up to the capacity, and the level to sample is a runtime value, so one
copy of the Gauss–Newton loop serves every level.

The pyramid is built on the host with OpenCV's `pyrDown` (`build`; equal to
`sampling.pyr_down`), which costs no compilation and a fraction of a
millisecond for a 640×480 frame.  `sample` reads bilinear values with four
scalar gathers per point; on the CPU those ran faster than the single gather
of packed 4-pixel rows they replace (88 vs 265 µs for 43 000 points).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

MAX_LEVELS = 6
"""Pyramid levels an atlas (and a registration) holds at most."""

# Capacities are powers of 4 from this one: few distinct programs, at most 4×
# the pyramid's size in the buffer.
_SMALLEST_CAPACITY = 2**16
# Homogeneous coordinate w below which a projected point is invalid.
_MIN_W = 1e-8


class Atlas(NamedTuple):
  """A pyramid in one buffer (a pytree; leading batch axes allowed).

  Attributes:
    pixels: (C,) float32 values of every level, row-major, level after level;
      zero after the last level.
    levels: (MAX_LEVELS, 3) int32 offset, width and height of each level
      (levels beyond the pyramid's repeat its coarsest).
  """
  pixels: jax.Array
  levels: jax.Array


# XLA's CPU client hands a program a host buffer without copying it only where
# the data starts on this boundary (bytes); else it copies the buffer on every
# call (0.3 ms for a 4 MiB atlas: benchmarks/README.md, implementation choices).
_ALIGNMENT = 64


def empty(shape, dtype=np.float32) -> np.ndarray:
  """An uninitialised NumPy array whose data starts on a 64-byte boundary (`_ALIGNMENT`)."""
  dtype, shape = np.dtype(dtype), (int(shape),) if np.ndim(shape) == 0 else tuple(shape)
  count = math.prod(shape)
  spare = np.empty(count * dtype.itemsize + _ALIGNMENT, np.uint8)
  start = -spare.ctypes.data % _ALIGNMENT
  return spare[start:start + count * dtype.itemsize].view(dtype).reshape(shape)


def capacity(values: int) -> int:
  """The buffer size holding `values` values: a power of 4, at least 2¹⁶."""
  size = _SMALLEST_CAPACITY
  while size < values:
    size *= 4
  return size


def level_shapes(shape, levels: int) -> list[tuple[int, int]]:
  """(H_l, W_l) of `levels` pyramid levels of an image of `shape` (what pyrDown gives)."""
  shapes = [tuple(int(s) for s in shape)]
  for _ in range(levels - 1):
    shapes.append(tuple((s + 1) // 2 for s in shapes[-1]))
  return shapes


def build(image: np.ndarray, levels: int, size: int | None = None) -> Atlas:
  """The `levels`-level Gaussian pyramid of an (H, W) float32 image as a NumPy `Atlas`.

  Args:
    image: (H, W) float32 grey image; every level must stay at least 2×2.
    levels: 1 to MAX_LEVELS.
    size: the buffer's capacity; default `capacity` of the pyramid.
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  pyramid = [np.ascontiguousarray(image, np.float32)]
  for _ in range(levels - 1):
    pyramid.append(cv2.pyrDown(pyramid[-1]))
  total = sum(level.size for level in pyramid)
  size = capacity(total) if size is None else size
  if total > size:
    raise ValueError(f"a pyramid of {total} values does not fit an atlas of {size}")
  pixels = empty(size)
  pixels[total:] = 0.0
  table = np.zeros((MAX_LEVELS, 3), np.int32)
  offset = 0
  for index, level in enumerate(pyramid):
    pixels[offset:offset + level.size] = level.reshape(-1)
    table[index] = offset, level.shape[1], level.shape[0]
    offset += level.size
  table[len(pyramid):] = table[len(pyramid) - 1]
  # Aligned (`empty`) and read-only: the CPU client then hands the buffer to
  # a program without copying it.
  pixels.setflags(write=False)
  table.setflags(write=False)
  return Atlas(pixels, table)


def _project(h, points):
  """(x', y', w) of (k, 2) points through (..., 3, 3) homographies, each (..., k); w unclamped.

  Multiply-adds, not a matmul: batched, XLA's CPU backend ran the small
  matmul as a slow library call.
  """
  x, y = points[:, 0], points[:, 1]
  m = h.reshape(h.shape[:-2] + (9, 1))
  num_x, num_y, w = (m[..., i, :] * x + m[..., i + 1, :] * y + m[..., i + 2, :] for i in (0, 3, 6))
  safe = jnp.where(w > _MIN_W, w, 1.0)
  return num_x / safe, num_y / safe, w


class Level(NamedTuple):
  """One level of an atlas: its buffer and geometry (see `Atlas.level`)."""
  pixels: jax.Array
  offset: jax.Array
  width: jax.Array
  height: jax.Array

  def interpolate(self, x, y):
    """Bilinear values at level coordinates x, y (any shape, equal), clamped into the level.

    One gather of the four neighbours of every point (…, 4): one kernel
    where four gathers were four.
    """
    right, bottom = (self.width - 1).astype(x.dtype), (self.height - 1).astype(x.dtype)
    x = jnp.clip(x, 0.0, right)
    y = jnp.clip(y, 0.0, bottom)
    x0 = jnp.minimum(jnp.floor(x), right - 1.0)
    y0 = jnp.minimum(jnp.floor(y), bottom - 1.0)
    index = self.offset + y0.astype(jnp.int32) * self.width + x0.astype(jnp.int32)
    shifts = jnp.stack([0, 1, self.width, self.width + 1])
    q = jnp.take(self.pixels, index[..., None] + shifts, mode="clip")
    fx, fy = x - x0, y - y0
    top = q[..., 0] + fx * (q[..., 1] - q[..., 0])
    below = q[..., 2] + fx * (q[..., 3] - q[..., 2])
    return top + fy * (below - top)

  def project(self, h, points):
    """(x', y', w, valid) of (k, 2) points mapped by (..., 3, 3) h; x', y' are 0 where invalid.

    Valid: w > 0 and inside [0, W−1] × [0, H−1], where all four bilinear
    neighbours exist.
    """
    x, y, w = _project(h, points)
    valid = ((w > _MIN_W) & (x >= 0) & (x <= (self.width - 1).astype(x.dtype)) & (y >= 0)
             & (y <= (self.height - 1).astype(y.dtype)))
    return jnp.where(valid, x, 0.0), jnp.where(valid, y, 0.0), w, valid

  def sample(self, h, points):
    """Values (..., k) at (k, 2) template points mapped by (..., 3, 3) h, 0 where invalid, and the mask."""
    x, y, _, valid = self.project(h, points)
    return jnp.where(valid, self.interpolate(x, y), 0.0), valid

  def sample_with_gradient(self, h, points):
    """`sample` plus the central-difference gradient and the projection.

    The gradient is the difference of the interpolated image one pixel
    either side (one-sided where that leaves the level), which equals the
    bilinear interpolation of the central-difference gradient image.  Five
    gathers of (k, 4): one of (k, 5, 4) took twice as long.

    Returns:
      (values, gx, gy, valid, (x', y', w)), each (..., k); zeros where invalid.
    """
    x, y, w, valid = self.project(h, points)
    right, bottom = (self.width - 1).astype(x.dtype), (self.height - 1).astype(x.dtype)
    step_x = jnp.minimum(x + 1.0, right) - jnp.maximum(x - 1.0, 0.0)
    step_y = jnp.minimum(y + 1.0, bottom) - jnp.maximum(y - 1.0, 0.0)
    gx = (self.interpolate(x + 1.0, y) - self.interpolate(x - 1.0, y)) / step_x
    gy = (self.interpolate(x, y + 1.0) - self.interpolate(x, y - 1.0)) / step_y

    def zero(v):
      return jnp.where(valid, v, 0.0)

    return zero(self.interpolate(x, y)), zero(gx), zero(gy), valid, (x, y, w)


def level(atlas: Atlas, index) -> Level:
  """Level `index` (a traced int allowed) of an unbatched atlas."""
  offset, width, height = atlas.levels[index]
  return Level(atlas.pixels, offset, width, height)


def to_level(h, index):
  """(…, 3, 3) full-resolution homography → level `index` (traced) coordinates, S H S⁻¹.

  Level-l pixel p_l = p_0 / 2^l (pyrDown: level-1 pixel i sits at level-0
  pixel 2i); the scaling by powers of two is exact.
  """
  f = jnp.exp2(-jnp.asarray(index, h.dtype))
  ratios = jnp.stack([jnp.stack([1.0, 1.0, f]), jnp.stack([1.0, 1.0, f]),
                      jnp.stack([1 / f, 1 / f, 1.0])]).astype(h.dtype)
  return h * ratios


def dense(atlas: Atlas, index: int, shape) -> jax.Array:
  """Level `index` of an unbatched atlas as an (H_l, W_l) array of the given static `shape`."""
  offset = atlas.levels[index, 0]
  return jax.lax.dynamic_slice(atlas.pixels, (offset,), (math.prod(shape),)).reshape(shape)
