"""Plane-induced homographies from camera poses (the paper's motion model).

A camera pose T = (R, t), a (..., 4, 4) rigid transform, maps frame-0 camera
coordinates to current camera coordinates, X_cur = R X_0 + t.  The target is
the plane n . X = d of frame-0 camera coordinates, with `normal` n the unit
normal oriented so that d > 0 (the plane lies in front of the camera; d
defaults to 1, so translations are in units of the plane distance).  This is
the convention of `cv2.decomposeHomographyMat`.  Points of the plane satisfy
n^T X / d = 1, hence X_cur = (R + t n^T / d) X_0 and with the intrinsics K

  H = K (R + t n^T / d) K^-1

maps frame-0 pixels to current-frame pixels (OpenCV pixel convention, as in
`jaxpso._src.homography`).

Every function broadcasts over leading `...` axes and works under `jit` and
`vmap`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import homography
from jaxpso._src.checks import as_checked
from jaxpso._src.checks import check_shape2d

DOF_AXES = {2: (0, 1), 4: (0, 1, 2, 5), 6: (0, 1, 2, 3, 4, 5)}
"""Indices into the pose parameters (tx, ty, tz, wx, wy, wz) searched for each
number of degrees of freedom: 2 = (tx, ty), 4 = (tx, ty, tz, rotation about
the optical axis z), 6 = all."""



def _pose(value, name: str) -> jax.Array:
  return as_checked(value, (4, 4), name, "(..., 4, 4)")


def _camera(value) -> jax.Array:
  """Validates intrinsics K (..., 3, 3), invertible where concrete."""
  camera = as_checked(value, (3, 3), "camera", "(..., 3, 3)")
  if not isinstance(camera, jax.core.Tracer):
    k = np.asarray(camera, np.float64)
    if not np.all(np.abs(np.linalg.det(k)) > 1e-12 * np.max(np.abs(k), axis=(-2, -1)) ** 3):
      raise ValueError(f"camera must be invertible, got {k.tolist()!r}")
  return camera


def _skew(v: jax.Array) -> jax.Array:
  """[v]_x (..., 3, 3), the matrix with [v]_x u = v x u."""
  x, y, z = v[..., 0], v[..., 1], v[..., 2]
  zero = jnp.zeros_like(x)
  rows = [zero, -z, y, z, zero, -x, -y, x, zero]
  return jnp.stack(rows, axis=-1).reshape(v.shape[:-1] + (3, 3))


def _assemble(rotation: jax.Array, t: jax.Array) -> jax.Array:
  """[[R, t], [0, 1]] (..., 4, 4) from R (..., 3, 3) and t (..., 3)."""
  batch = jnp.broadcast_shapes(rotation.shape[:-2], t.shape[:-1])
  rotation = jnp.broadcast_to(rotation, batch + (3, 3))
  t = jnp.broadcast_to(t, batch + (3,))
  top = jnp.concatenate([rotation, t[..., None]], axis=-1)
  bottom = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 0.0, 1.0], top.dtype),
                            top.shape[:-2] + (1, 4))
  return jnp.concatenate([top, bottom], axis=-2)


def rodrigues(omega) -> jax.Array:
  """Rotation matrices from rotation vectors (the exponential map of so(3)).

  With theta = |omega| and K = [omega]_x,

    R = exp(K) = cos(theta) I + A K + B omega omega^T,
    A = sin(theta) / theta,  B = (1 - cos(theta)) / theta^2
      = (sin(theta / 2) / (theta / 2))^2 / 2.

  For theta^2 < eps the Taylor expansions A = 1 - theta^2 / 6,
  B = 1/2 - theta^2 / 24, cos(theta) = 1 - theta^2 / 2 are used; the
  double `where` keeps the gradient finite (and exact) at omega = 0.

  Args:
    omega: (..., 3) rotation vectors (axis times angle in radians).

  Returns:
    (..., 3, 3) rotation matrices.
  """
  omega = as_checked(omega, (3,), "omega", "(..., 3)")
  return _rodrigues(omega)


def _rodrigues(omega: jax.Array) -> jax.Array:
  theta2 = jnp.sum(omega * omega, axis=-1)
  small = theta2 < jnp.finfo(omega.dtype).eps
  theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
  half_sinc = jnp.sin(0.5 * theta) / (0.5 * theta)
  a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
  b = jnp.where(small, 0.5 - theta2 / 24.0, 0.5 * half_sinc * half_sinc)
  c = jnp.where(small, 1.0 - 0.5 * theta2, jnp.cos(theta))
  eye = jnp.eye(3, dtype=omega.dtype)
  outer = omega[..., :, None] * omega[..., None, :]
  return (c[..., None, None] * eye + a[..., None, None] * _skew(omega)
          + b[..., None, None] * outer)


def rotation_log(rotation) -> jax.Array:
  """Rotation vectors of rotation matrices (the logarithm of SO(3)).

  With v = vee(R - R^T) / 2 = sin(theta) a and cos(theta) = (tr R - 1) / 2,
  theta = atan2(|v|, cos(theta)) is accurate over [0, pi].  For
  cos(theta) >= 0, omega = (theta / sin(theta)) v, with theta / sin(theta) =
  1 + |v|^2 / 6 once |v|^2 < eps (finite gradient at R = I).  For
  cos(theta) < 0, where v loses precision, the axis is read from the symmetric
  part (R + R^T) / 2 - cos(theta) I = (1 - cos(theta)) a a^T (its column with
  the largest diagonal entry, normalised) and its sign from v.  At
  theta = pi exactly, omega and -omega describe the same rotation and the sign
  returned is decided by rounding in v; results are accurate for theta in
  [0, pi) and up to that sign at pi.

  Args:
    rotation: (..., 3, 3) rotation matrices.

  Returns:
    (..., 3) rotation vectors with |omega| in [0, pi].
  """
  rotation = as_checked(rotation, (3, 3), "rotation", "(..., 3, 3)")
  return _rotation_log(rotation)


def _rotation_log(rotation: jax.Array) -> jax.Array:
  r = rotation
  v = 0.5 * jnp.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
                       r[..., 1, 0] - r[..., 0, 1]], axis=-1)
  cos = 0.5 * (jnp.trace(r, axis1=-2, axis2=-1) - 1.0)
  sin2 = jnp.sum(v * v, axis=-1)
  positive = sin2 > 0
  sin = jnp.where(positive, jnp.sqrt(jnp.where(positive, sin2, 1.0)), 0.0)
  theta = jnp.arctan2(sin, cos)
  # Near theta = 0 (and generally for cos >= 0): omega = theta / sin * v.
  small = sin2 < jnp.finfo(r.dtype).eps
  factor = jnp.where(small, 1.0 + sin2 / 6.0, theta / jnp.where(small, 1.0, sin))
  # For cos < 0: the axis from the symmetric part, its sign from v.
  obtuse = cos < 0
  symmetric = 0.5 * (r + jnp.swapaxes(r, -1, -2)) - cos[..., None, None] * jnp.eye(3, dtype=r.dtype)
  k = jnp.argmax(jnp.diagonal(symmetric, axis1=-2, axis2=-1), axis=-1)
  column = jnp.take_along_axis(symmetric, k[..., None, None], axis=-1)[..., 0]
  norm2 = jnp.where(obtuse, jnp.sum(column * column, axis=-1), 1.0)
  axis = column / jnp.sqrt(norm2)[..., None]
  axis = jnp.where((jnp.sum(axis * v, axis=-1) < 0)[..., None], -axis, axis)
  return jnp.where(obtuse[..., None], theta[..., None] * axis, factor[..., None] * v)


def pose_from_params(x) -> jax.Array:
  """Rigid transforms from the 6 pose parameters of the paper's eq. (1).

  x = (tx, ty, tz, wx, wy, wz): the translation t is taken as is and the
  rotation through the exponential map, R = `rodrigues`(w), so
  T = [[R, t], [0, 1]].

  Args:
    x: (..., 6) parameters (t, w), t in plane-distance units, w in radians.

  Returns:
    (..., 4, 4) poses mapping frame-0 to current camera coordinates.
  """
  x = as_checked(x, (6,), "x", "(..., 6)")
  return _assemble(_rodrigues(x[..., 3:]), x[..., :3])


def params_from_pose(pose) -> jax.Array:
  """Pose parameters (t, w) of rigid transforms, the inverse of `pose_from_params`.

  t is the translation column and w = `rotation_log`(R) (|w| in [0, pi]).

  Args:
    pose: (..., 4, 4) rigid transforms.

  Returns:
    (..., 6) parameters (tx, ty, tz, wx, wy, wz).
  """
  pose = _pose(pose, "pose")
  return jnp.concatenate([pose[..., :3, 3], _rotation_log(pose[..., :3, :3])], axis=-1)


def expand_dof(x, dof: int) -> jax.Array:
  """Embeds reduced pose parameters into the full 6-vector.

  Entry j of `x` goes to index DOF_AXES[dof][j] of (tx, ty, tz, wx, wy, wz);
  the other parameters are zero.

  Args:
    x: (..., dof) reduced parameters.
    dof: 2 (tx, ty), 4 (tx, ty, tz, wz) or 6 (all).

  Returns:
    (..., 6) full parameters.
  """
  if isinstance(dof, bool) or not isinstance(dof, (int, np.integer)) or dof not in DOF_AXES:
    raise ValueError(f"dof must be one of {tuple(DOF_AXES)}, got {dof!r}")
  x = as_checked(x, (dof,), "x", f"(..., {dof}) for dof={dof}")
  full = jnp.zeros(x.shape[:-1] + (6,), x.dtype)
  return full.at[..., list(DOF_AXES[int(dof)])].set(x)


def camera_matrix(focal, cx, cy) -> jax.Array:
  """Pinhole intrinsics with square pixels and no skew.

  K = [[f, 0, cx], [0, f, cy], [0, 0, 1]].

  Args:
    focal: (...) focal length in pixels, > 0.
    cx: (...) principal point x in pixels.
    cy: (...) principal point y in pixels.

  Returns:
    (..., 3, 3) camera matrices (leading axes broadcast).
  """
  focal = as_checked(focal, (), "focal", "(...)")
  if not isinstance(focal, jax.core.Tracer) and not np.all(np.asarray(focal) > 0):
    raise ValueError(f"focal must be positive, got {np.asarray(focal)!r}")
  cx = as_checked(cx, (), "cx", "(...)")
  cy = as_checked(cy, (), "cy", "(...)")
  focal, cx, cy = jnp.broadcast_arrays(focal, cx, cy)
  one, zero = jnp.ones_like(focal), jnp.zeros_like(focal)
  rows = [focal, zero, cx, zero, focal, cy, zero, zero, one]
  return jnp.stack(rows, axis=-1).reshape(focal.shape + (3, 3))


def default_camera(shape) -> jax.Array:
  """Default intrinsics for a frame of shape (H, W).

  f = max(H, W), cx = (W - 1) / 2, cy = (H - 1) / 2, so the field of view along
  the longer side is 2 atan(1/2), about 53.1 degrees (horizontal for landscape
  frames).

  Args:
    shape: (H, W) frame size in pixels.

  Returns:
    (3, 3) camera matrix, default float dtype.
  """
  return jnp.asarray(_default_camera(shape), dtype=float)


def _default_camera(shape) -> np.ndarray:
  """`default_camera` as float64 NumPy."""
  h, w = check_shape2d(shape, "shape")
  f = float(max(h, w))
  return np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])


def checked_camera(camera, frame_shape) -> np.ndarray:
  """(3, 3) float64 intrinsics given by the user, `default_camera(frame_shape)` for None.

  Raises ValueError unless finite and invertible (host-side, for the entry
  points' arguments).
  """
  k = (_default_camera(frame_shape) if camera is None
       else np.asarray(camera, np.float64))
  if k.shape != (3, 3) or not np.all(np.isfinite(k)) or abs(np.linalg.det(k)) < 1e-12:
    raise ValueError(f"camera must be a finite, invertible 3×3 matrix, got {camera!r}")
  return k


def checked_normal(normal, name: str) -> np.ndarray:
  """(3,) float64 unit normal from the user's argument `name`; ValueError unless finite and non-zero."""
  n = np.asarray(normal, np.float64)
  if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9:
    raise ValueError(f"{name} must be a finite non-zero 3-vector, got {normal!r}")
  return n / np.linalg.norm(n)


def _unit_normal(normal) -> jax.Array:
  """Validates a non-zero normal (..., 3) and scales it to unit length."""
  normal = as_checked(normal, (3,), "normal", "(..., 3)")
  norm2 = jnp.sum(normal * normal, axis=-1)
  if not isinstance(norm2, jax.core.Tracer):
    tiny = np.finfo(normal.dtype).tiny
    if not np.all(np.asarray(norm2) > tiny):
      raise ValueError(
          f"normal must be a non-zero vector, got {np.asarray(normal)!r}"
          f" with shape {normal.shape}")
  return normal / jnp.sqrt(norm2)[..., None]


def _distance(distance) -> jax.Array:
  """Validates a positive plane distance (...)."""
  distance = as_checked(distance, (), "distance", "(...)")
  if not isinstance(distance, jax.core.Tracer) and not np.all(np.asarray(distance) > 0):
    raise ValueError(f"distance must be positive, got {np.asarray(distance)!r}")
  return distance


def plane_homography(pose, camera, normal, distance=1.0) -> jax.Array:
  """Homography induced by the plane n . X = d between frame 0 and the current frame.

  H = K (R + t n^T / d) K^-1 with n normalised to unit length.  Under `jit`
  the checks on `normal` and `distance` cannot run; a zero normal or
  non-positive distance then gives non-finite output.

  Args:
    pose: (..., 4, 4) poses (R, t) from frame-0 to current camera coordinates.
    camera: (..., 3, 3) intrinsics K, invertible.
    normal: (..., 3) plane normal in frame-0 camera coordinates, non-zero.
    distance: (...) plane distance d > 0 (1 by default).

  Returns:
    (..., 3, 3) homographies from frame-0 pixels to current-frame pixels.
  """
  pose = _pose(pose, "pose")
  camera = _camera(camera)
  n = _unit_normal(normal)
  d = _distance(distance)
  # × the reciprocal, not ÷: one rounding in every program (batching.each)
  t_over_d = pose[..., :3, 3] * (1.0 / d)[..., None]
  euclidean = pose[..., :3, :3] + t_over_d[..., :, None] * n[..., None, :]
  return jnp.matmul(jnp.matmul(camera, euclidean), homography.inverse(camera))


def _plane_basis(n: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Orthonormal u1, u2 (..., 3) with u1 x u2 = n for unit vectors n (..., 3).

  u1 is built from the coordinate axis least aligned with n, so |e x n| >=
  sqrt(2/3) and no guard is needed.
  """
  e = jax.nn.one_hot(jnp.argmin(jnp.abs(n), axis=-1), 3, dtype=n.dtype)
  u1 = jnp.cross(e, n)
  # × the reciprocal, not ÷: one rounding in every program (batching.each)
  u1 = u1 * (1.0 / jnp.linalg.norm(u1, axis=-1, keepdims=True))
  return u1, jnp.cross(n, u1)


def pose_from_homography(h, camera, normal, distance=1.0) -> jax.Array:
  """Recovers the pose from a plane-induced homography with a known plane.

  M = K^-1 H K ~ lambda (R + t n^T / d) for an unknown scale lambda.  For
  u1, u2 orthonormal and perpendicular to n, M [u1, u2] = lambda R [u1, u2]:
  the sign of lambda is that of det M (det(R + t n^T / d) = 1 + n^T R^T t / d
  > 0 while the camera stays on its side of the plane) and, with
  A = sign(det M) M [u1, u2] and S = A^T A, the orthogonal Procrustes fit is
  Q = A S^(-1/2) (the 3x2 matrix with orthonormal columns closest to A) with
  |lambda| = tr(S^(1/2)) / 2, the mean of the two in-plane singular values of
  M (the middle singular value of M for an exact plane homography).  S^(1/2)
  of the 2x2 matrix is closed-form: with delta = sqrt(det S) and
  tau = sqrt(tr S + 2 delta), S^(1/2) = (S + delta I) / tau.  The determinant
  fix takes R n = q1 x q2, so R = [q1, q2, q1 x q2] [u1, u2, n]^T is a proper
  rotation, and t = d (M n / lambda - R n).  No SVD is used, so gradients stay
  finite when singular values coincide (e.g. a pure rotation).  Where M is
  rank deficient on the plane (det S <= (eps tr S)^2) R = I and lambda = 1 are
  returned.  The overall scale and sign of `h` do not matter.

  Args:
    h: (..., 3, 3) homographies from frame-0 to current-frame pixels.
    camera: (..., 3, 3) intrinsics K, invertible.
    normal: (..., 3) plane normal in frame-0 camera coordinates, non-zero.
    distance: (...) plane distance d > 0 (1 by default).

  Returns:
    (..., 4, 4) poses (R, t) from frame-0 to current camera coordinates.
  """
  h = as_checked(h, (3, 3), "h", "(..., 3, 3)")
  camera = _camera(camera)
  n = _unit_normal(normal)
  d = _distance(distance)
  m = jnp.matmul(jnp.matmul(homography.inverse(camera), h), camera)
  det = jnp.sum(m[..., 0, :] * jnp.cross(m[..., 1, :], m[..., 2, :]), axis=-1)
  sign = jnp.where(det < 0, -1.0, 1.0)
  u1, u2 = _plane_basis(n)
  basis = jnp.stack([u1, u2], axis=-1)
  a = sign[..., None, None] * jnp.matmul(m, basis)
  p = jnp.sum(a[..., 0] * a[..., 0], axis=-1)
  q = jnp.sum(a[..., 0] * a[..., 1], axis=-1)
  r = jnp.sum(a[..., 1] * a[..., 1], axis=-1)
  det_s = p * r - q * q
  eps = jnp.finfo(m.dtype).eps
  ok = det_s > (eps * (p + r))**2
  delta = jnp.sqrt(jnp.where(ok, det_s, 1.0))
  tau = jnp.sqrt(jnp.where(ok, p + r, 2.0) + 2.0 * delta)
  # S^(-1/2) = tau (S + delta I)^-1 = adj(S + delta I) / (delta tau).
  inv_sqrt = jnp.stack([r + delta, -q, -q, p + delta], axis=-1).reshape(p.shape + (2, 2))
  # × the reciprocal, not ÷: one rounding in every program (batching.each)
  q_in = jnp.matmul(a, inv_sqrt * (1.0 / (delta * tau))[..., None, None])
  q_in = jnp.where(ok[..., None, None], q_in, basis)
  scale = sign * jnp.where(ok, 0.5 * tau, 1.0)
  q1, q2 = q_in[..., 0], q_in[..., 1]
  image = jnp.stack([q1, q2, jnp.cross(q1, q2)], axis=-1)
  frame = jnp.stack([u1, u2, n], axis=-1)
  rotation = jnp.matmul(image, jnp.swapaxes(frame, -1, -2))
  # × the reciprocal, not ÷: one rounding in every program (batching.each)
  m_n = jnp.sum(m * n[..., None, :], axis=-1) * (1.0 / scale)[..., None]
  rn = jnp.sum(rotation * n[..., None, :], axis=-1)
  return _assemble(rotation, d[..., None] * (m_n - rn))


def template_to_frame(h_frame0_to_frame, roi_offset) -> jax.Array:
  """Homography from template pixels to current-frame pixels.

  H_template = H @ translation(x0, y0): a template pixel p sits at frame-0
  pixel p + (x0, y0), the ROI's top-left corner.

  Args:
    h_frame0_to_frame: (..., 3, 3) homographies from frame-0 pixels.
    roi_offset: (..., 2) top-left corner (x0, y0) of the ROI in frame-0
      pixels; integer offsets are accepted and converted.

  Returns:
    (..., 3, 3) homographies from template pixels to current-frame pixels.
  """
  h = as_checked(h_frame0_to_frame, (3, 3), "h_frame0_to_frame", "(..., 3, 3)")
  offset = jnp.asarray(roi_offset)
  if jnp.issubdtype(offset.dtype, jnp.integer):
    offset = offset.astype(h.dtype)
  offset = as_checked(offset, (2,), "roi_offset", "(..., 2)")
  return jnp.matmul(h, homography.translation(offset[..., 0], offset[..., 1]))


def compose_poses(a, b) -> jax.Array:
  """Composes rigid transforms, `a` after `b`.

  T = a b (the tracker accumulates T_hat <- T(x) T_hat).

  Args:
    a: (..., 4, 4) pose applied second.
    b: (..., 4, 4) pose applied first; leading axes broadcast with `a`.

  Returns:
    (..., 4, 4) composed poses.
  """
  return jnp.matmul(_pose(a, "a"), _pose(b, "b"))


def invert_pose(pose) -> jax.Array:
  """Inverts rigid transforms.

  [[R, t], [0, 1]]^-1 = [[R^T, -R^T t], [0, 1]].

  Args:
    pose: (..., 4, 4) rigid transforms.

  Returns:
    (..., 4, 4) inverse transforms.
  """
  pose = _pose(pose, "pose")
  r_t = jnp.swapaxes(pose[..., :3, :3], -1, -2)
  t = pose[..., :3, 3]
  return _assemble(r_t, -jnp.sum(r_t * t[..., None, :], axis=-1))
