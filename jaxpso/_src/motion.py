"""Motion models: search parameters u → template → frame homographies.

Both models take parameters u in pixel-like units around a base motion, so
that one search box (±`search_radius` px in every dimension) and one damping
serve every model:

* "homography": u (…, 8) are the offsets in frame pixels of the template's
  4 corners (TL, TR, BR, BL; x then y) from where the start homography puts
  them; H maps the template's corners onto the moved ones.  Offsets in the
  frame, not in the template, keep the box the same for every start: with a
  strongly projective start, template-side offsets of the same image motion
  reached 120 px where frame-side ones stayed within 3σ (Baker–Matthews
  trials at σ = 16).
* "plane": u (…, dof) are the paper's pose parameters of eq. (1) restricted to
  `dof` (2: tx, ty; 4: tx, ty, tz, wz; 6: all), each divided by the pose
  change that moves the template by about one pixel; the camera's incremental
  motion T(u) is applied after the base pose, T̂ = T(u) · T_base, and
  H = K (R̂ + t̂ nᵀ) K⁻¹ · H₀ with H₀ the template → frame-0 homography
  (the plane distance d is 1).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import homography
from jaxpso._src import plane


class Plane(NamedTuple):
  """The fixed geometry of plane-induced motion (a pytree).

  Attributes:
    camera: (3, 3) intrinsics K.
    normal: (3,) unit plane normal in frame-0 camera coordinates.
    template_to_frame0: (3, 3) homography H₀.
    unit: (dof,) pose change per unit of u (plane-distance units or radians).
  """
  camera: jax.Array
  normal: jax.Array
  template_to_frame0: jax.Array
  unit: jax.Array


def corners(shape) -> jax.Array:
  """(4, 2) corners TL, TR, BR, BL of a template of `shape` (h, w), static or a traced (2,) array."""
  h, w = shape[0], shape[1]
  zero = jnp.zeros_like(jnp.asarray(w, jnp.float32))
  right, bottom = jnp.asarray(w, jnp.float32) - 1, jnp.asarray(h, jnp.float32) - 1
  return jnp.stack([jnp.stack([zero, zero]), jnp.stack([right, zero]),
                    jnp.stack([right, bottom]), jnp.stack([zero, bottom])])


def corner_gap(first, second, size) -> jax.Array:
  """() the largest distance between the template corners two (3, 3) homographies map."""
  rect = corners(size)
  gap = homography.apply_to_points(first, rect)[0] - homography.apply_to_points(second, rect)[0]
  return jnp.max(jnp.linalg.norm(gap, axis=-1))


def dimension(motion: str, dof: int) -> int:
  """Number of search parameters of a motion model."""
  return 8 if motion == "homography" else dof


def plane_geometry(camera, normal, template_to_frame0, shape, dof: int) -> Plane:
  """`Plane` with units that move the template's corners by about one pixel.

  A translation tx (ty) of δ moves the image by f·δ px, and so does a
  rotation about y (x); tz and a rotation about z move a point at distance ρ
  from the principal point by ρ·δ, with ρ the mean distance of the
  template's corners in frame 0.

  Args:
    camera: (3, 3) K.  normal: (3,) unit normal.
    template_to_frame0: (3, 3) H₀.  shape: template (h, w).  dof: 2, 4 or 6.
  """
  corners, _ = homography.apply_to_points(template_to_frame0, homography.rect_corners(shape))
  rho = jnp.maximum(jnp.mean(jnp.linalg.norm(corners - camera[:2, 2], axis=-1)), 1.0)
  f = camera[0, 0]
  per_axis = jnp.stack([1 / f, 1 / f, 1 / rho, 1 / f, 1 / f, 1 / rho])
  return Plane(camera, normal, template_to_frame0, per_axis[np.asarray(plane.DOF_AXES[dof])])


def checked_plane_geometry(camera, plane_normal, frame_shape, h0, shape, dof):
  """Validated `Plane` from the user's camera and normal (None: the defaults).

  Args:
    camera: (3, 3) K or None (`plane.default_camera` of `frame_shape`).
    plane_normal: (3,) normal in frame-0 camera coordinates or None (0, 0, 1).
    frame_shape: (H, W) of the frame the template was cut from.
    h0: (3, 3) template → that frame.  shape: template (h, w).  dof: 2, 4 or 6.
  """
  k = plane.checked_camera(camera, frame_shape)
  n = plane.checked_normal((0.0, 0.0, 1.0) if plane_normal is None else plane_normal,
                           "plane_normal")
  centre = np.asarray(h0, np.float64) @ np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2, 1.0])
  ray = np.linalg.solve(k, centre / centre[2])
  if not n @ ray > 1e-6:
    raise ValueError(
        f"plane_normal {plane_normal!r} puts the template's plane behind the camera: n·X = d > 0"
        " must hold for the points X seen in the template")
  return plane_geometry(jnp.asarray(k, jnp.float32), jnp.asarray(n, jnp.float32), h0, shape, dof)


def checked_plane_geometries(camera, plane_normal, frame_shape, starts, shapes, dof):
  """`checked_plane_geometry` of each start in `starts` (R, 3, 3), stacked (NumPy).

  `shapes`: the R templates' (h, w).
  """
  return jax.tree.map(lambda *leaves: np.stack(leaves), *[
      jax.tree.map(np.asarray, checked_plane_geometry(camera, plane_normal, frame_shape,
                                                      np.asarray(h, np.float32), shape, dof))
      for h, shape in zip(starts, shapes)])


def plane_pose(u, base_pose, geometry: Plane, dof: int) -> jax.Array:
  """T(u) · T_base: (…, dof) parameters → (…, 4, 4) frame-0 → frame poses."""
  step = plane.pose_from_params(plane.expand_dof(u * geometry.unit, dof))
  return jnp.matmul(step, base_pose)


def pose_to_homography(pose, geometry: Plane) -> jax.Array:
  """(…, 4, 4) poses → (…, 3, 3) template → frame homographies."""
  frame0_to_frame = plane.plane_homography(pose, geometry.camera, geometry.normal)
  return jnp.matmul(frame0_to_frame, geometry.template_to_frame0)


def to_homography(u, base, geometry: Plane | None, shape, motion: str, dof: int) -> jax.Array:
  """Search parameters → template → frame homographies.

  Args:
    u: (…, D) parameters (`dimension(motion, dof)`).
    base: (3, 3) start homography ("homography") or (4, 4) base pose ("plane").
    geometry: `Plane` for "plane", else None.
    shape: template (h, w), static or a traced (2,) array.
    motion: "homography" or "plane".
    dof: pose parameters of "plane".

  Returns:
    (…, 3, 3) homographies, h[2, 2] not normalised.
  """
  if motion == "homography":
    return rect_to_quad(moved_corners(u, base, shape), shape)
  return pose_to_homography(plane_pose(u, base, geometry, dof), geometry)


def moved_corners(u, base, shape) -> jax.Array:
  """(…, 4, 2) corners of motion "homography": where `base` (3, 3) puts the template's, plus u (…, 8)."""
  quad, _ = homography.apply_to_points(base, corners(shape))
  return quad + u.reshape(u.shape[:-1] + (4, 2))


def rect_to_quad(quad, shape) -> jax.Array:
  """(…, 3, 3) homography from the template's rectangle (h, w) = `shape` onto `quad` (…, 4, 2).

  `homography.homography_from_corners` for a source that is the template's
  own rectangle: the rectangle maps onto the unit square by a scaling, so
  no inverse is needed.  The quad is centred and scaled to unit spread
  first, to keep float32 in range.  Scale: w > 0 over the template for a
  convex quad in the template's corner order.
  """
  centre, spread, unit = homography._normalize_quad(quad)
  core = homography._square_to_quad(unit)
  width, height = jnp.asarray(shape[1], quad.dtype) - 1, jnp.asarray(shape[0], quad.dtype) - 1
  core = core * jnp.stack([1 / width, 1 / height, jnp.ones_like(width)])
  top = spread[..., None, None] * core[..., :2, :] + centre[..., :, None] * core[..., 2:, :]
  return jnp.concatenate([top, core[..., 2:, :]], axis=-2)


# A candidate whose template area changes by more than this factor either way
# is rejected (a swarm far from the target can otherwise collapse the quad
# onto a few pixels whose statistics happen to match).
MAX_AREA_RATIO = 16.0


def corner_turns(quad) -> jax.Array:
  """(…, 4, 2) corners TL, TR, BR, BL → (…, 4) cross products of successive edges.

  All positive for a convex quad with the template's own orientation (x
  right, y down); a folded quad mixes signs, a mirrored one is all negative.
  """
  edges = jnp.roll(quad, -1, axis=-2) - quad
  following = jnp.roll(edges, -1, axis=-2)
  return edges[..., 0] * following[..., 1] - edges[..., 1] * following[..., 0]


def admissible(h, shape) -> jax.Array:
  """Whether homographies keep the template a convex quad of sensible size.

  True where all 4 corners map with w > 0, the mapped quad is convex with the
  template's orientation and its area is within `MAX_AREA_RATIO` of the
  template's either way.

  Args:
    h: (…, 3, 3) template → frame homographies.  shape: template (h, w),
      static or a traced (2,) array.

  Returns:
    (…) bool.
  """
  quad, w = homography.apply_to_points(h, corners(shape))
  return jnp.all(w > 0, axis=-1) & admissible_quad(quad, shape)


def admissible_quad(quad, shape) -> jax.Array:
  """`admissible` for quads (…, 4, 2) known to have w > 0 (motion "homography" builds them so)."""
  turns = corner_turns(quad)
  # The shoelace area is half the sum of the cross products about one corner.
  area = 0.5 * (turns[..., 0] + turns[..., 2])
  ratio = area / ((shape[0] - 1.0) * (shape[1] - 1.0))
  return jnp.all(turns > 0, axis=-1) & (ratio > 1 / MAX_AREA_RATIO) & (ratio < MAX_AREA_RATIO)
