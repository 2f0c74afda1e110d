"""Pull-sampling of images at warped template grids, and the Gaussian pyramid.

A homography maps template pixel (x, y) to image pixel (x, y) with pixel
centres at integer coordinates (the OpenCV convention).  `warp_image` samples
the image bilinearly at the template grid mapped by a whole batch of
homographies in one call, so a swarm of candidate motions is evaluated at once.

Speed: the four bilinear neighbours of every image pixel are packed into one
(H-1)·(W-1) × 4 table, so each sample is a single 4-wide gather instead of four
scalar gathers, faster for the full swarm evaluation on the CPU
(benchmarks/README.md, implementation choices).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxpso._src import checks
from jaxpso._src import homography

# Homogeneous coordinate w below which a projected point is declared invalid.
_MIN_W = 1e-8


def template_grid(shape) -> jax.Array:
  """Pixel centres of a template of `shape = (h, w)`.

  Returns:
    (h, w, 2) array of (x, y) template pixel coordinates, x = column, y = row.
  """
  h, w = checks.check_shape2d(shape, "shape")
  y, x = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32),
                      jnp.arange(w, dtype=jnp.float32), indexing="ij")
  return jnp.stack([x, y], axis=-1)


def _project(homographies, x, y, frame_shape):
  """Maps coordinates `x, y` through `homographies` (…, 3, 3), broadcasting.

  Returns projected (x', y') set to 0 where invalid, the homogeneous w (1
  where w is not positive) and the validity mask: w > 0, finite, and inside
  [0, W-1] × [0, H-1] so that all four bilinear neighbours exist.
  """
  height, width = frame_shape
  h = homographies[..., None, None, :, :]
  den = h[..., 2, 0] * x + h[..., 2, 1] * y + h[..., 2, 2]
  num_x = h[..., 0, 0] * x + h[..., 0, 1] * y + h[..., 0, 2]
  num_y = h[..., 1, 0] * x + h[..., 1, 1] * y + h[..., 1, 2]
  ok = den > _MIN_W
  den = jnp.where(ok, den, 1.0)
  px = num_x / den
  py = num_y / den
  valid = (ok & (px >= 0) & (px <= width - 1) & (py >= 0) & (py <= height - 1))
  return jnp.where(valid, px, 0.0), jnp.where(valid, py, 0.0), den, valid


def warp_points(homographies, points, frame_shape):
  """Maps points through homographies and reports which land inside the frame.

  Args:
    homographies: (..., 3, 3) template → frame homographies.
    points: (..., n, 2) template coordinates (x, y); leading axes broadcast.
    frame_shape: (H, W) of the frame the points land in.

  Returns:
    `(mapped, valid)`: (..., n, 2) frame coordinates and a (..., n) bool mask,
    true where w > 0, the result is finite and the point lies in
    [0, W-1] × [0, H-1] (where all four bilinear neighbours exist).
  """
  height, width = checks.check_shape2d(frame_shape, "frame_shape")
  mapped, w = homography.apply_to_points(homographies, points)
  x, y = mapped[..., 0], mapped[..., 1]
  valid = ((w > _MIN_W) & jnp.isfinite(x) & jnp.isfinite(y) & (x >= 0)
           & (x <= width - 1) & (y >= 0) & (y <= height - 1))
  return mapped, valid


def pack_quads(image) -> jax.Array:
  """Packs the 2×2 bilinear neighbourhood of every pixel into one row.

  Args:
    image: (H, W) float image, H, W >= 2.

  Returns:
    ((H-1)·(W-1), 4) rows (I[y,x], I[y,x+1], I[y+1,x], I[y+1,x+1]).
  """
  return jnp.stack([image[:-1, :-1], image[:-1, 1:], image[1:, :-1],
                    image[1:, 1:]], axis=-1).reshape(-1, 4)


def _interpolate(quads, frame_shape, x, y):
  """Bilinear values at frame coordinates x, y (any shape), clamped into the frame."""
  height, width = frame_shape
  x = jnp.clip(x, 0.0, width - 1.0)
  y = jnp.clip(y, 0.0, height - 1.0)
  x0 = jnp.minimum(jnp.floor(x), width - 2)
  y0 = jnp.minimum(jnp.floor(y), height - 2)
  q = jnp.take(quads, y0.astype(jnp.int32) * (width - 1) + x0.astype(jnp.int32), axis=0,
               mode="clip")
  fx, fy = x - x0, y - y0
  top = q[..., 0] + fx * (q[..., 1] - q[..., 0])
  bottom = q[..., 2] + fx * (q[..., 3] - q[..., 2])
  return top + fy * (bottom - top)


def sample_quads(quads, frame_shape, homographies, shape):
  """`warp_image` on an image already packed by `pack_quads` (no checks).

  The tracker packs a frame once and samples it at every PSO iteration.
  """
  return sample_points(quads, frame_shape, homographies, template_grid(shape))


def sample_points(quads, frame_shape, homographies, grid):
  """`sample_quads` at any (h, w, 2) array of template points (x, y).

  Returns:
    (patches, mask), each (..., h, w); patches are 0 where invalid.
  """
  x, y, _, valid = _project(homographies, grid[..., 0], grid[..., 1], frame_shape)
  return jnp.where(valid, _interpolate(quads, frame_shape, x, y), 0.0), valid


def sample_with_gradient(quads, frame_shape, homographies, grid, *, projection: bool = False):
  """`sample_points` plus the central-difference image gradient at the samples.

  The gradient image's bilinear interpolation at p equals the central
  difference of the interpolated image, (I(p + e) − I(p − e)) / 2 with unit
  steps e, which four more gathers of the same packed table give; no
  gradient image is built or packed.  (Where p ± e leaves the frame the
  difference is one-sided.)

  Args:
    grid: (h, w, 2) template points, e.g. `template_grid(shape)`.
    projection: also return where the points land, as a fifth item
      (x', y', w), each (..., h, w): the frame coordinates (0 where invalid)
      and the homogeneous w (1 where w <= 0).  Gauss–Newton's Jacobian
      needs them, and projecting once more would cost a second pass.

  Returns:
    (patches, grad_x, grad_y, mask), each (..., h, w); zeros where invalid.
  """
  height, width = frame_shape
  x, y, w, valid = _project(homographies, grid[..., 0], grid[..., 1], frame_shape)

  def at(px, py):
    return _interpolate(quads, frame_shape, px, py)

  step_x = jnp.minimum(x + 1.0, width - 1.0) - jnp.maximum(x - 1.0, 0.0)
  step_y = jnp.minimum(y + 1.0, height - 1.0) - jnp.maximum(y - 1.0, 0.0)
  grad_x = (at(x + 1.0, y) - at(x - 1.0, y)) / step_x
  grad_y = (at(x, y + 1.0) - at(x, y - 1.0)) / step_y
  zero = lambda v: jnp.where(valid, v, 0.0)
  sampled = zero(at(x, y)), zero(grad_x), zero(grad_y), valid
  return sampled + ((x, y, w),) if projection else sampled


def warp_image(image, homographies, shape):
  """Samples `image` at the template grid mapped by each homography.

  Bilinear pull sampling: patch[..., v, u] = image(H · (u, v, 1)); equal to
  `cv2.warpPerspective(image, H, (w, h), flags=INTER_LINEAR | WARP_INVERSE_MAP)`
  wherever the mapped point lies inside the frame.

  Args:
    image: (H, W) float image (H, W >= 2).
    homographies: (..., 3, 3) template → image homographies, e.g. (n, 3, 3)
      for a swarm of n candidates.
    shape: template shape (h, w).

  Returns:
    `(patches, mask)` of shape (..., h, w): the sampled values (0 where
    invalid) and a bool mask, true where the mapped point has w > 0, is finite
    and lies inside [0, W-1] × [0, H-1].

  Raises:
    TypeError: non-float image or homographies.
    ValueError: wrong ranks or shapes, an image smaller than 2×2, a non-finite
      concrete image or homographies.

  Examples:
    >>> import jax.numpy as jnp
    >>> from jaxpso import warp
    >>> image = jnp.arange(16.0).reshape(4, 4) / 16
    >>> shift = jnp.array([[1.0, 0, 1], [0, 1, 0], [0, 0, 1]])
    >>> patches, mask = warp.warp_image(image, shift, (2, 2))
    >>> patches.tolist(), bool(mask.all())
    ([[0.0625, 0.125], [0.3125, 0.375]], True)
  """
  image = check_image(image)
  homographies = checks.as_checked(homographies, (3, 3), "homographies", "(..., 3, 3)")
  shape = checks.check_shape2d(shape, "shape")
  return sample_quads(pack_quads(image), image.shape, homographies, shape)


def check_image(image, name: str = "image") -> jax.Array:
  """Validates a 2-D finite float image of at least 2×2 pixels and returns it."""
  image = checks.as_float_array(image, name)
  if image.ndim != 2:
    raise ValueError(f"{name} must be a 2-D (H, W) grey image, got shape {image.shape}")
  if min(image.shape) < 2:
    raise ValueError(f"{name} must be at least 2×2 pixels, got shape {image.shape}")
  checks.check_finite_if_concrete(image, name)
  return image


_PYRAMID_TAPS = (1 / 16, 4 / 16, 6 / 16, 4 / 16, 1 / 16)


def _blur_decimate(image, axis: int):
  """The 5-tap binomial filter along `axis`, evaluated at the even positions only.

  Strided slices of the padded image: filtering every position and then
  dropping the odd ones, with a transpose for the columns, was several times
  slower on the CPU (benchmarks/README.md, implementation choices).
  """
  pad = [(0, 0), (0, 0)]
  pad[axis] = (2, 2)
  padded = jnp.pad(image, pad, mode="reflect")  # OpenCV REFLECT_101
  count = (image.shape[axis] + 1) // 2
  return sum(t * jax.lax.slice_in_dim(padded, i, i + 2 * count - 1, 2, axis)
             for i, t in enumerate(_PYRAMID_TAPS))


def pyr_down(image) -> jax.Array:
  """One Gaussian pyramid level, equal to `cv2.pyrDown` (default border).

  Args:
    image: (H, W) float image.

  Returns:
    ((H + 1) // 2, (W + 1) // 2) image; level-1 pixel i sits at level-0 pixel 2i.
  """
  image = check_image(image)
  return _blur_decimate(_blur_decimate(image, 0), 1)


def gaussian_pyramid(image, levels: int) -> list[jax.Array]:
  """Returns `[image, pyr_down(image), ...]` with `levels` images in all.

  Args:
    image: (H, W) float image.
    levels: number of levels, >= 1; every level must stay at least 2×2.
  """
  image = check_image(image)
  checks.check_int(levels, "levels", 1)
  smallest = min(image.shape)
  for _ in range(levels - 1):
    smallest = (smallest + 1) // 2  # the size pyr_down gives
  if smallest < 2:
    raise ValueError(
        f"levels={levels} is too many for an image of shape {image.shape}:"
        " the coarsest level would be smaller than 2×2")
  pyramid = [image]
  for _ in range(levels - 1):
    pyramid.append(pyr_down(pyramid[-1]))
  return pyramid
