"""Planar homographies (8 degrees of freedom) as batched 3x3 matrices.

Conventions: a homography `h` maps template pixel coordinates (x, y) to image
pixel coordinates, OpenCV style, with pixel centres at integer coordinates and
homogeneous column vectors, `p' ~ h p`.  Every function broadcasts over leading
`...` axes and works under `jit` and `vmap`.  Homographies are defined up to a
non-zero scale; functions that build one document the scale they return.

The swarm searches homographies through **corner offsets**: `x` (..., 8) holds
the displacements (dx, dy) of the template's four corners (TL, TR, BR, BL,
flattened as dx_TL, dy_TL, dx_TR, ...) in template pixels, and `C(x)` is the
homography taking the template rectangle onto the displaced corners, with
`C(0) = I`.  It is used instead of the exponential map of sl(3) because

* box bounds are interpretable: a PSO search box of +-r px per corner
  coordinate says directly how far any template corner may move, and the
  bound means the same thing in all 8 dimensions (they are isotropic), whereas
  the sl(3) generators mix translations, rotations, scalings and perspective
  terms with incomparable units;
* it matches the Baker-Matthews corner-perturbation protocol used to generate
  and score test warps (`corner_error` is the matching error metric);
* conditioning does not depend on the template size: the offsets are divided by
  the template size before the projective map is built, so a 30 px and a
  600 px template give equally well conditioned problems;
* it composes with the current estimate as `H = H_prev @ C(x)`, so the search
  box is always centred on the previous estimate.
"""

from __future__ import annotations

import operator

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src.checks import as_checked
from jaxpso._src.checks import as_float_array
from jaxpso._src.checks import check_finite_if_concrete
from jaxpso._src.checks import check_min_rank
from jaxpso._src.checks import check_shape2d
from jaxpso._src.checks import check_trailing



def _matrix(value, name: str) -> jax.Array:
  return as_checked(value, (3, 3), name, "(..., 3, 3)")


def _quad(value, name: str) -> jax.Array:
  return as_checked(value, (4, 2), name, "(..., 4, 2)")


def _template_shape(shape) -> tuple[int, int]:
  """Checks a template shape with at least two pixels along each axis."""
  h, w = check_shape2d(shape, "shape")
  if h < 2 or w < 2:
    raise ValueError(
        f"shape must be at least (2, 2) so that the corners are distinct, got {shape!r}")
  return h, w


def _adjugate_and_det(h: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Adjugate (..., 3, 3) and determinant (...) of `h`.

  With rows r0, r1, r2 of `h`, the columns of adj(h) are r1 x r2, r2 x r0 and
  r0 x r1, so that h adj(h) = det(h) I with det(h) = r0 . (r1 x r2).
  """
  r0, r1, r2 = h[..., 0, :], h[..., 1, :], h[..., 2, :]
  c0 = jnp.cross(r1, r2)
  adj = jnp.stack([c0, jnp.cross(r2, r0), jnp.cross(r0, r1)], axis=-1)
  return adj, jnp.sum(r0 * c0, axis=-1)


def _invertible(h: jax.Array, det: jax.Array) -> jax.Array:
  """True where |det h| > eps^2 max|h_ij|^3, i.e. `h` is numerically non-singular.

  The test is scale invariant, as befits a matrix defined up to scale.
  """
  eps = jnp.finfo(h.dtype).eps
  scale = jnp.max(jnp.abs(h), axis=(-2, -1))
  return jnp.abs(det) > eps * eps * scale**3


def compose(a, b) -> jax.Array:
  """Composes two homographies, `a` after `b`.

  c = a b, so that c p ~ a (b p).

  Args:
    a: (..., 3, 3) homography applied second.
    b: (..., 3, 3) homography applied first; leading axes broadcast with `a`.

  Returns:
    (..., 3, 3) product `a @ b`.
  """
  return jnp.matmul(_matrix(a, "a"), _matrix(b, "b"))


def inverse(h) -> jax.Array:
  """Inverts homographies through the adjugate (no LU factorisation).

  h^-1 = adj(h) / det(h).  Where `h` is numerically singular
  (|det h| <= eps^2 max|h_ij|^3) the adjugate itself is returned: it is still
  finite, equals the inverse up to scale whenever the inverse exists, and
  satisfies h adj(h) = det(h) I ~ 0 otherwise.  The double `where` keeps the
  values and gradients finite in both cases.

  Args:
    h: (..., 3, 3) homographies.

  Returns:
    (..., 3, 3) inverses.
  """
  return _inverse(_matrix(h, "h"))


def _inverse(h: jax.Array) -> jax.Array:
  """`inverse` without input validation."""
  adj, det = _adjugate_and_det(h)
  ok = _invertible(h, det)
  safe_det = jnp.where(ok, det, 1.0)
  # × the reciprocal, not ÷: one rounding in every program (batching.each)
  return jnp.where(ok[..., None, None], adj * (1.0 / safe_det)[..., None, None], adj)


def normalize(h) -> jax.Array:
  """Rescales homographies to unit determinant.

  h / cbrt(det h) has determinant +1 (the cube root keeps the sign of det h),
  so it is the SL(3) representative of the projective map and maps every point
  to the same place as `h`.  Numerically singular matrices
  (|det h| <= eps^2 max|h_ij|^3) are returned unchanged.

  Args:
    h: (..., 3, 3) homographies.

  Returns:
    (..., 3, 3) homographies with determinant 1.
  """
  h = _matrix(h, "h")
  _, det = _adjugate_and_det(h)
  ok = _invertible(h, det)
  scale = jnp.where(ok, jnp.cbrt(jnp.where(ok, det, 1.0)), 1.0)
  return h / scale[..., None, None]


def _similarity(s: jax.Array, tx: jax.Array, ty: jax.Array) -> jax.Array:
  """[[s, 0, tx], [0, s, ty], [0, 0, 1]] broadcast over the leading axes."""
  s, tx, ty = jnp.broadcast_arrays(s, tx, ty)
  one, zero = jnp.ones_like(s), jnp.zeros_like(s)
  rows = [s, zero, tx, zero, s, ty, zero, zero, one]
  return jnp.stack(rows, axis=-1).reshape(s.shape + (3, 3))


def translation(tx, ty) -> jax.Array:
  """Builds pure translations.

  T = [[1, 0, tx], [0, 1, ty], [0, 0, 1]].

  Args:
    tx: (...) shift along x in pixels.
    ty: (...) shift along y in pixels; broadcasts with `tx`.

  Returns:
    (..., 3, 3) translation homographies.
  """
  tx = as_checked(tx, (), "tx", "(...)")
  ty = as_checked(ty, (), "ty", "(...)")
  return _similarity(jnp.ones((), jnp.result_type(tx, ty)), tx, ty)


def scaling(s) -> jax.Array:
  """Builds isotropic scalings about the origin.

  S = diag(s, s, 1).

  Args:
    s: (...) scale factors.

  Returns:
    (..., 3, 3) scaling homographies.
  """
  s = as_checked(s, (), "s", "(...)")
  zero = jnp.zeros((), s.dtype)
  return _similarity(s, zero, zero)


def rect_corners(shape) -> jax.Array:
  """Corners of a template in template pixel coordinates.

  For shape (h, w): TL (0, 0), TR (w-1, 0), BR (w-1, h-1), BL (0, h-1).

  Args:
    shape: (h, w) template size in pixels.

  Returns:
    (4, 2) corner coordinates (x, y), default float dtype.
  """
  return jnp.asarray(host_rect_corners(check_shape2d(shape, "shape")), dtype=float)


def host_rect_corners(shape) -> np.ndarray:
  """`rect_corners` of an (h, w) template as (4, 2) float64 NumPy, unchecked (host-side set-up)."""
  rows, cols = shape
  return np.array([[0, 0], [cols - 1, 0], [cols - 1, rows - 1], [0, rows - 1]], np.float64)


def apply_to_points(h, points) -> tuple[jax.Array, jax.Array]:
  """Maps points through homographies.

  (x_h, y_h, w) = h (x, y, 1) and p' = (x_h, y_h) / w.  Points with w > 0 lie
  in front of the projective map's line at infinity and are the valid ones
  for a homography whose sign makes template points positive (as built by
  this module).  The division is safe: where |w| <= eps (|x_h| + |y_h|) the
  denominator is replaced by sign(w) eps (|x_h| + |y_h|) (sign(0) = +1), so
  the coordinates are clamped to magnitude at most 1/eps (about 8.4e6 in
  float32) along the true direction and stay continuous; a point mapped to
  the zero vector returns (0, 0).  Values and gradients stay finite.

  Args:
    h: (..., 3, 3) homographies.
    points: (..., N, 2) points (x, y); leading axes broadcast with `h`.

  Returns:
    A pair `(mapped, w)`: (..., N, 2) projected points and (..., N) the
    homogeneous coordinate w, returned unclamped for validity tests.
  """
  h = _matrix(h, "h")
  points = as_float_array(points, "points")
  check_min_rank(points, 2, "points", "(..., N, 2)")
  check_trailing(points, (2,), "points", "(..., N, 2)")
  check_finite_if_concrete(points, "points")
  return _apply(h, points)


def _apply(h: jax.Array, points: jax.Array) -> tuple[jax.Array, jax.Array]:
  """`apply_to_points` without input validation."""
  # Multiply-adds, not a (N, 3) × (3, 3) matmul: batched, XLA's CPU backend
  # ran the matmul as a slow library call (benchmarks/README.md,
  # implementation choices).
  x, y = points[..., 0], points[..., 1]

  def row(i):
    return h[..., i, 0, None] * x + h[..., i, 1, None] * y + h[..., i, 2, None]

  numerator_x, numerator_y, w = row(0), row(1), row(2)
  magnitude = jnp.abs(numerator_x) + jnp.abs(numerator_y)
  floor = jnp.finfo(w.dtype).eps * magnitude
  clamped = jnp.where(magnitude > 0, jnp.where(w >= 0, floor, -floor), 1.0)
  denominator = jnp.where(jnp.abs(w) > floor, w, clamped)
  return jnp.stack([numerator_x / denominator, numerator_y / denominator], axis=-1), w


def square_to_quad(quad) -> jax.Array:
  """Closed-form projective map from the unit square onto a quadrilateral.

  Maps (0, 0), (1, 0), (1, 1), (0, 1) to the corners p0..p3 of `quad` (TL, TR,
  BR, BL).  Writing x = (a u + b v + c) / (g u + h v + 1) and likewise y with
  (d, e, f), the corners (0, 0), (1, 0), (0, 1) give c = x0,
  a = x1 - x0 + g x1, b = x3 - x0 + h x3 (same for y), and the corner (1, 1)
  leaves the 2x2 system

    g dx1 + h dx2 = sx,   g dy1 + h dy2 = sy,

  with dx1 = x1 - x2, dx2 = x3 - x2, sx = x0 - x1 + x2 - x3 (same for y).
  Cramer's rule divides by dx1 dy2 - dx2 dy1; instead the whole matrix is
  multiplied by s = dx2 dy1 - dx1 dy2 (the cross product (p3 - p2) x
  (p1 - p2), 1 for the unit square), so no division is performed:

    g' = dx2 sy - sx dy2,  h' = sx dy1 - dx1 sy,
    [[s (x1 - x0) + g' x1, s (x3 - x0) + h' x3, s x0],
     [s (y1 - y0) + g' y1, s (y3 - y0) + h' y3, s y0],
     [g',                  h',                  s   ]].

  For a convex quad listed in the same rotational order as the square
  (clockwise on screen, y down) w = g' u + h' v + s > 0 on the whole square.
  A non-convex or reflected quad gives w <= 0 at some corner, and a degenerate
  one (three collinear corners) a singular matrix, e.g. w = s = 0 at TL when
  TR, BR and BL are collinear.  Everything stays finite, gradients included.

  Args:
    quad: (..., 4, 2) corners (x, y) in TL, TR, BR, BL order.

  Returns:
    (..., 3, 3) homographies, scaled by s.
  """
  return _square_to_quad(_quad(quad, "quad"))


def _square_to_quad(quad: jax.Array) -> jax.Array:
  """`square_to_quad` without input validation."""
  x0, x1, x2, x3 = (quad[..., i, 0] for i in range(4))
  y0, y1, y2, y3 = (quad[..., i, 1] for i in range(4))
  sx, sy = x0 - x1 + x2 - x3, y0 - y1 + y2 - y3
  dx1, dx2, dy1, dy2 = x1 - x2, x3 - x2, y1 - y2, y3 - y2
  s = dx2 * dy1 - dx1 * dy2
  g = dx2 * sy - sx * dy2
  h = sx * dy1 - dx1 * sy
  rows = [
      s * (x1 - x0) + g * x1, s * (x3 - x0) + h * x3, s * x0,
      s * (y1 - y0) + g * y1, s * (y3 - y0) + h * y3, s * y0,
      g, h, s,
  ]
  return jnp.stack(rows, axis=-1).reshape(s.shape + (3, 3))


def _normalize_quad(quad: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Centre (..., 2) and spread (...) of a quad, and the quad mapped by them.

  The normalised quad (quad - centre) / spread has mean absolute coordinate 1;
  a quad collapsed to a point keeps spread 1.
  """
  centre = jnp.mean(quad, axis=-2)
  offsets = quad - centre[..., None, :]
  spread = jnp.mean(jnp.abs(offsets), axis=(-2, -1))
  spread = jnp.where(spread > 0, spread, 1.0)
  # × the reciprocal, not ÷: one rounding in every program (batching.each)
  return centre, spread, offsets * (1.0 / spread)[..., None, None]


def homography_from_corners(src, dst) -> jax.Array:
  """Homography mapping four source corners onto four destination corners.

  H = Q(dst) Q(src)^-1 with Q = `square_to_quad` and the inverse of
  `inverse`.  To keep float32 in range for large coordinates, both quads are
  first centred and scaled to unit mean absolute coordinate by similarities
  N_src, N_dst (q' = N q), and H = N_dst^-1 Q(dst') Q(src')^-1 N_src.
  The scale of H is arbitrary; for convex quads in TL, TR, BR, BL order it is
  positive on the source quad (w > 0).  Degenerate quads give finite,
  possibly singular, matrices (see `square_to_quad` and `inverse`).

  Args:
    src: (..., 4, 2) source corners (x, y), TL, TR, BR, BL.
    dst: (..., 4, 2) destination corners; leading axes broadcast with `src`.

  Returns:
    (..., 3, 3) homographies with dst_i ~ H src_i.
  """
  src = _quad(src, "src")
  dst = _quad(dst, "dst")
  src_centre, src_spread, src_n = _normalize_quad(src)
  dst_centre, dst_spread, dst_n = _normalize_quad(dst)
  core = jnp.matmul(_square_to_quad(dst_n), _inverse(_square_to_quad(src_n)))
  denormalize_dst = _similarity(dst_spread, dst_centre[..., 0], dst_centre[..., 1])
  normalize_src = _similarity(1.0 / src_spread, -src_centre[..., 0] / src_spread,
                              -src_centre[..., 1] / src_spread)
  return jnp.matmul(jnp.matmul(denormalize_dst, core), normalize_src)


def host_homography_from_corners(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
  """`homography_from_corners` in NumPy float64, scaled to h[2, 2] = 1 (no JAX dispatch).

  Solves the 8 × 8 linear system of the four correspondences.  For host-side
  set-up, where eager JAX operations would compile a program each.

  Args:
    src: (N, 4, 2) source corners, TL, TR, BR, BL.
    dst: (N, 4, 2) destination corners.

  Returns:
    (N, 3, 3) float64 homographies with dst_i ~ H src_i.
  """
  x, y = src[..., 0], src[..., 1]
  u, v = dst[..., 0], dst[..., 1]
  one, zero = np.ones_like(x), np.zeros_like(x)
  rows_u = np.stack([x, y, one, zero, zero, zero, -u * x, -u * y], -1)  # (N, 4, 8)
  rows_v = np.stack([zero, zero, zero, x, y, one, -v * x, -v * y], -1)
  system = np.concatenate([rows_u, rows_v], -2)  # (N, 8, 8)
  h = np.linalg.solve(system, np.concatenate([u, v], -1)[..., None])[..., 0]
  return np.concatenate([h, np.ones(h.shape[:-1] + (1,))], -1).reshape(h.shape[:-1] + (3, 3))


def corner_offsets_to_homography(x, shape) -> jax.Array:
  """Homography C(x) moving the template corners by the offsets `x`.

  C maps the template corners c_i (`rect_corners(shape)`) to c_i + x_i.  With
  D = diag(w - 1, h - 1, 1) taking the unit square onto the template,
  C(x) = D Q(q) D^-1 where Q = `square_to_quad` and q_i = D^-1 (c_i + x_i) is
  the unit square displaced by the offsets in units of the template size, so
  the construction is equally well conditioned for every template size.  No
  inverse is needed and C(0) = I exactly.  The scale is that of Q (1 at
  x = 0); w > 0 over the template whenever the displaced corners form a convex
  quad in the template's corner order.

  Args:
    x: (..., 8) corner displacements in template pixels, ordered dx_TL, dy_TL,
      dx_TR, dy_TR, dx_BR, dy_BR, dx_BL, dy_BL.
    shape: (h, w) template size in pixels, at least (2, 2).

  Returns:
    (..., 3, 3) homographies from template pixels to displaced pixels.
  """
  x = as_checked(x, (8,), "x", "(..., 8)")
  h, w = _template_shape(shape)
  size = np.array([w - 1.0, h - 1.0])
  unit = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
  offsets = x.reshape(x.shape[:-1] + (4, 2)) / jnp.asarray(size, x.dtype)
  quad = jnp.asarray(unit, x.dtype) + offsets
  d = np.array([w - 1.0, h - 1.0, 1.0])
  return _square_to_quad(quad) * jnp.asarray(d[:, None] / d[None, :], x.dtype)


def homography_to_corner_offsets(h, shape) -> jax.Array:
  """Corner offsets x with C(x) ~ h, the inverse of `corner_offsets_to_homography`.

  x_i = h(c_i) - c_i for the template corners c_i (TL, TR, BR, BL), with the
  projection of `apply_to_points` (corners sent to or beyond infinity get its
  clamped, finite coordinates).

  Args:
    h: (..., 3, 3) homographies from template pixels.
    shape: (h, w) template size in pixels.

  Returns:
    (..., 8) offsets dx_TL, dy_TL, dx_TR, ..., dy_BL in pixels.
  """
  h = _matrix(h, "h")
  corners = rect_corners(shape).astype(h.dtype)
  mapped, _ = _apply(h, corners)
  return (mapped - corners).reshape(mapped.shape[:-2] + (8,))


# `inside_share` counts the centres of this many × this many cells of the template.
_INSIDE_GRID = 16


def inside_share(h, size, image_size, xp=jnp) -> jax.Array:
  """() float32 the share of a template of `size` (h, w) that the homography h (3, 3) maps inside
  an image of `image_size` (w, h): of the centres of `_INSIDE_GRID`² cells over it (unchecked,
  for compiled programs; `xp=np` on the host, where eager JAX compiled each operation in every
  process: 0.6 s on a first call)."""
  cells = (xp.arange(_INSIDE_GRID, dtype=xp.float32) + 0.5) * (1.0 / _INSIDE_GRID)
  ys, xs = xp.meshgrid(cells * (size[0] - 1), cells * (size[1] - 1), indexing="ij")
  mapped = xp.asarray(h, xp.float32) @ xp.stack([xs.ravel(), ys.ravel(),
                                                 xp.ones(xs.size, xp.float32)])
  ahead = mapped[2] > 0
  xy = mapped[:2] / xp.where(ahead, mapped[2], 1.0)
  inside = ahead & xp.all((xy >= 0) & (xy <= xp.asarray(image_size)[:, None] - 1), axis=0)
  return xp.mean(inside.astype(xp.float32))


def corner_error(h_est, h_true, shape) -> jax.Array:
  """Root-mean-square corner displacement between two homographies.

  e = sqrt(1/4 sum_i |h_est(c_i) - h_true(c_i)|^2) over the template corners
  c_i, the Baker-Matthews / POT alignment error.  The square root is guarded
  so that e = 0 has a finite (zero) gradient.

  Args:
    h_est: (..., 3, 3) estimated homographies.
    h_true: (..., 3, 3) reference homographies; leading axes broadcast.
    shape: (h, w) template size in pixels.

  Returns:
    (...) errors in pixels.
  """
  h_est = _matrix(h_est, "h_est")
  h_true = _matrix(h_true, "h_true")
  corners = rect_corners(shape).astype(jnp.result_type(h_est, h_true))
  est, _ = _apply(h_est, corners)
  true, _ = _apply(h_true, corners)
  mean_square = jnp.mean(jnp.sum((est - true)**2, axis=-1), axis=-1)
  positive = mean_square > 0
  return jnp.where(positive, jnp.sqrt(jnp.where(positive, mean_square, 1.0)), 0.0)


def _level_ratios(level) -> np.ndarray:
  """Entries s_i / s_j of S M S^-1 for S = diag(2^-level, 2^-level, 1)."""
  try:
    level = operator.index(level)
  except TypeError:
    raise TypeError(f"level must be an int, got {level!r}") from None
  f = 2.0**-level
  return np.array([[1.0, 1.0, f], [1.0, 1.0, f], [1.0 / f, 1.0 / f, 1.0]])


def homography_to_level(h, level) -> jax.Array:
  """Expresses a full-resolution homography in pyramid-level coordinates.

  Level-l pixel coordinates are p_l = S p_0 with S = diag(2^-l, 2^-l, 1)
  (OpenCV `pyrDown`: level-1 pixel i sits at level-0 pixel 2i), so
  H_l = S H_0 S^-1.  The scaling by powers of two is exact.

  Args:
    h: (..., 3, 3) homographies between level-0 pixel coordinates.
    level: int pyramid level (static; negative levels upsample).

  Returns:
    (..., 3, 3) homographies between level-`level` pixel coordinates.
  """
  h = _matrix(h, "h")
  return h * jnp.asarray(_level_ratios(level), h.dtype)


def homography_from_level(h, level) -> jax.Array:
  """Expresses a pyramid-level homography in full-resolution coordinates.

  H_0 = S^-1 H_l S with S = diag(2^-l, 2^-l, 1), the inverse of
  `homography_to_level`.

  Args:
    h: (..., 3, 3) homographies between level-`level` pixel coordinates.
    level: int pyramid level (static).

  Returns:
    (..., 3, 3) homographies between level-0 pixel coordinates.
  """
  h = _matrix(h, "h")
  return h / jnp.asarray(_level_ratios(level), h.dtype)
