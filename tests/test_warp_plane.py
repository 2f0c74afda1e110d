"""Tests for `jaxpso.warp` (2 of 3): the plane-induced model and poses, `jaxpso._src.plane`.

Compilation dominates the runtime, so the tests share a few jitted functions
and reuse the same input shapes.
"""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpso._src import homography as hm
from jaxpso._src import plane as pl

FRAME = (240, 320)
CAMERA = pl.default_camera(FRAME)
NORMAL = np.array([0.2, -0.1, 1.0], np.float32) / np.linalg.norm([0.2, -0.1, 1.0])

_rodrigues = jax.jit(pl.rodrigues)
_rotation_log = jax.jit(pl.rotation_log)
_pose_from_params = jax.jit(pl.pose_from_params)
_plane_homography = jax.jit(pl.plane_homography)
_pose_from_homography = jax.jit(pl.pose_from_homography)


def _rotation_vectors(seed, n, max_angle):
  rng = np.random.default_rng(seed)
  axes = rng.normal(size=(n, 3))
  axes /= np.linalg.norm(axes, axis=1, keepdims=True)
  return axes * rng.uniform(0, max_angle, size=(n, 1))


def _moderate_params(seed, n=8):
  """Poses (n, 6): translations up to 0.3 plane distances, rotations up to 0.4 rad."""
  t = np.random.default_rng(seed).uniform(-0.3, 0.3, size=(n, 3))
  return np.c_[t, _rotation_vectors(seed + 1, n, 0.4)].astype(np.float32)


def test_rodrigues_matches_opencv():
  omega = np.r_[np.zeros((1, 3)), [[1e-6, 0, 0]], _rotation_vectors(0, 14, np.pi - 1e-3)]
  rotations = _rodrigues(omega.astype(np.float32))
  for r, w in zip(rotations, omega):
    np.testing.assert_allclose(r, cv2.Rodrigues(w)[0], atol=2e-6)


def test_rotation_log_round_trip():
  omega = np.r_[np.zeros((1, 3)), [[0, 0, 1e-5]], _rotation_vectors(1, 13, np.pi - 1e-3)]
  half_turn = np.diag([1.0, -1.0, -1.0])
  rotations = np.r_[np.asarray(_rodrigues(omega.astype(np.float32))), half_turn[None]]
  logs = _rotation_log(rotations.astype(np.float32))
  np.testing.assert_allclose(logs[:-1], omega, atol=2e-6)
  np.testing.assert_allclose(np.abs(logs[-1]), [np.pi, 0.0, 0.0], atol=1e-6)
  with jax.enable_x64(True):
    logs = jax.jit(lambda w: pl.rotation_log(pl.rodrigues(w)))(omega)
    assert logs.dtype == jnp.float64
    np.testing.assert_allclose(logs, omega, atol=1e-11)


def test_gradients_at_identity_are_finite():
  jac_exp, jac_log = jax.jit(lambda w, r: (jax.jacfwd(pl.rodrigues)(w),
                                           jax.jacrev(pl.rotation_log)(r)))(
                                               jnp.zeros(3), jnp.eye(3))
  generators = np.stack([np.cross(e, -np.eye(3)) for e in np.eye(3)], axis=-1)
  np.testing.assert_allclose(jac_exp, generators, atol=1e-7)
  assert np.all(np.isfinite(jac_log))
  np.testing.assert_allclose(np.einsum("kij,ijl->kl", jac_log, generators), np.eye(3), atol=1e-6)


def test_pose_params_round_trip_and_inverse():
  x = _moderate_params(2)
  poses = _pose_from_params(x)
  np.testing.assert_allclose(poses[:, :3, 3], x[:, :3])
  np.testing.assert_allclose(poses[:, 3], np.broadcast_to([0, 0, 0, 1], (8, 4)))
  np.testing.assert_allclose(jax.jit(pl.params_from_pose)(poses), x, atol=2e-6)
  eye = np.broadcast_to(np.eye(4), poses.shape)
  np.testing.assert_allclose(pl.compose_poses(poses, pl.invert_pose(poses)), eye, atol=1e-6)
  np.testing.assert_allclose(pl.compose_poses(pl.invert_pose(poses), poses), eye, atol=1e-6)


def test_expand_dof():
  np.testing.assert_array_equal(pl.expand_dof(jnp.asarray([1.0, 2.0]), 2), [1, 2, 0, 0, 0, 0])
  np.testing.assert_array_equal(pl.expand_dof(jnp.asarray([[1.0, 2.0, 3.0, 4.0]]), 4),
                                [[1, 2, 3, 0, 0, 4]])
  x = jnp.arange(6.0)
  np.testing.assert_array_equal(pl.expand_dof(x, 6), x)
  for dof in (3, 2.0, True, "6"):
    with pytest.raises(ValueError, match=r"dof.*\(2, 4, 6\)"):
      pl.expand_dof(x, dof)
  with pytest.raises(ValueError, match=r"x.*dof=4"):
    pl.expand_dof(x, 4)


def test_default_camera():
  np.testing.assert_array_equal(pl.default_camera((480, 640)),
                                [[640, 0, 319.5], [0, 640, 239.5], [0, 0, 1]])
  np.testing.assert_array_equal(pl.camera_matrix(jnp.asarray(640.0), jnp.asarray(319.5),
                                                 jnp.asarray(239.5)),
                                pl.default_camera((480, 640)))


def test_plane_homography_matches_numpy():
  poses = _pose_from_params(_moderate_params(3))
  h = _plane_homography(poses, CAMERA, NORMAL, 2.0)
  k = np.asarray(CAMERA, np.float64)
  for h_ours, pose in zip(h, np.asarray(poses, np.float64)):
    expected = k @ (pose[:3, :3] + np.outer(pose[:3, 3], NORMAL) / 2.0) @ np.linalg.inv(k)
    np.testing.assert_allclose(h_ours, expected, rtol=1e-5, atol=1e-5 * np.abs(expected).max())
  # A non-unit normal is normalised.
  np.testing.assert_allclose(_plane_homography(poses, CAMERA, 3.0 * NORMAL, 2.0), h,
                             rtol=1e-5, atol=1e-5)


def test_plane_homography_maps_projected_plane_points():
  poses = np.asarray(_pose_from_params(_moderate_params(4)), np.float64)
  distance = 2.0
  h = np.asarray(_plane_homography(poses, CAMERA, NORMAL, distance), np.float64)
  # Points on n . X = d, spread around the point where the optical axis meets the plane.
  u1 = np.cross([1.0, 0.0, 0.0], NORMAL)
  u1 /= np.linalg.norm(u1)
  u2 = np.cross(NORMAL, u1)
  ab = np.random.default_rng(5).uniform(-0.5, 0.5, size=(10, 2))
  points = distance / NORMAL[2] * np.array([0.0, 0.0, 1.0]) + ab[:, :1] * u1 + ab[:, 1:] * u2
  np.testing.assert_allclose(points @ NORMAL, distance, rtol=1e-6)
  k = np.asarray(CAMERA, np.float64)
  pixels_0 = points @ k.T
  pixels_0 = pixels_0[:, :2] / pixels_0[:, 2:]
  for h_ours, pose in zip(h, poses):
    moved = points @ pose[:3, :3].T + pose[:3, 3]
    assert np.all(moved[:, 2] > 0)
    pixels = moved @ k.T
    pixels = pixels[:, :2] / pixels[:, 2:]
    mapped, w = hm.apply_to_points(h_ours.astype(np.float32), pixels_0.astype(np.float32))
    assert np.all(w > 0)
    np.testing.assert_allclose(mapped, pixels, atol=1e-2)


def test_matches_opencv_decomposition():
  poses = np.asarray(_pose_from_params(_moderate_params(6)), np.float64)
  distance = 2.0
  h = np.asarray(_plane_homography(poses, CAMERA, NORMAL, distance), np.float64)
  for h_ours, pose in zip(h, poses):
    _, rotations, translations, normals = cv2.decomposeHomographyMat(
        h_ours, np.asarray(CAMERA, np.float64))
    match = [np.allclose(r, pose[:3, :3], atol=1e-4)
             and np.allclose(t[:, 0], pose[:3, 3] / distance, atol=1e-4)
             and np.allclose(n[:, 0], NORMAL, atol=1e-4)
             for r, t, n in zip(rotations, translations, normals)]
    assert any(match)


def test_pose_from_homography_round_trip():
  x = _moderate_params(7)
  poses = _pose_from_params(x)
  h = _plane_homography(poses, CAMERA, NORMAL, 2.0)
  scale = np.array([1.0, -1.0, 1e-3, -250.0, 3.0, 1.0, -1.0, 0.5], np.float32)[:, None, None]
  recovered = _pose_from_homography(h * scale, CAMERA, NORMAL, 2.0)
  np.testing.assert_allclose(recovered, poses, atol=1e-5)
  # Pure rotation: coincident singular values, gradients must stay finite.
  grad = jax.jit(jax.grad(lambda r: jnp.sum(pl.pose_from_homography(
      pl.plane_homography(pl.pose_from_params(r), CAMERA, NORMAL), CAMERA, NORMAL))))(
          jnp.asarray([0.0, 0.0, 0.0, 0.1, 0.0, 0.0]))
  assert np.all(np.isfinite(grad))


def test_jit_and_vmap_match_loop():
  poses = _pose_from_params(_moderate_params(8))
  loop = np.stack([_plane_homography(p, CAMERA, NORMAL, 2.0) for p in poses])
  vmapped = jax.jit(jax.vmap(pl.plane_homography, in_axes=(0, None, None, None)))(
      poses, CAMERA, NORMAL, 2.0)
  np.testing.assert_allclose(vmapped, loop, rtol=1e-6, atol=1e-6)
  np.testing.assert_allclose(_plane_homography(poses, CAMERA, NORMAL, 2.0), loop, rtol=1e-6,
                             atol=1e-6)


def test_template_to_frame():
  h = hm.translation(jnp.asarray(5.0), jnp.asarray(-2.0)) @ hm.scaling(jnp.asarray(2.0))
  for offset in (jnp.asarray([10.0, 20.0]), np.array([10, 20])):
    composed = pl.template_to_frame(h, offset)
    np.testing.assert_allclose(composed, [[2, 0, 25], [0, 2, 38], [0, 0, 1]])


@pytest.mark.parametrize("call, name", [
    (lambda: pl.plane_homography(jnp.eye(4), CAMERA, jnp.zeros(3)), "normal"),
    (lambda: pl.plane_homography(jnp.eye(4), CAMERA, NORMAL, 0.0), "distance"),
    (lambda: pl.plane_homography(jnp.eye(4), CAMERA, NORMAL, -1.0), "distance"),
    (lambda: pl.plane_homography(jnp.eye(3), CAMERA, NORMAL), "pose"),
    (lambda: pl.plane_homography(jnp.eye(4), jnp.eye(3, dtype=jnp.int32), NORMAL), "camera"),
    (lambda: pl.pose_from_homography(jnp.eye(3), CAMERA, jnp.zeros(3)), "normal"),
    (lambda: pl.pose_from_homography(jnp.eye(3), CAMERA, NORMAL, -2.0), "distance"),
    (lambda: pl.rodrigues(jnp.zeros(4)), "omega"),
    (lambda: pl.rotation_log(jnp.full((3, 3), jnp.inf)), "rotation"),
    (lambda: pl.pose_from_params(jnp.zeros(6, jnp.int32)), "x"),
    (lambda: pl.template_to_frame(jnp.eye(3), jnp.zeros(3)), "roi_offset"),
])
def test_bad_input_names_argument(call, name):
  with pytest.raises((ValueError, TypeError), match=rf"\b{name}\b"):
    call()
