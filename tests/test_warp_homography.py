"""Tests for `jaxpso.warp` (1 of 3): the homography algebra, `jaxpso._src.homography`.

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

SHAPE = (48, 64)
UNIT_SQUARE = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)

_inverse = jax.jit(hm.inverse)
_compose = jax.jit(hm.compose)
_apply = jax.jit(hm.apply_to_points)
_square_to_quad = jax.jit(hm.square_to_quad)
_from_corners = jax.jit(hm.homography_from_corners)
_to_h = jax.jit(hm.corner_offsets_to_homography, static_argnums=1)
_to_x = jax.jit(hm.homography_to_corner_offsets, static_argnums=1)
_corner_error = jax.jit(hm.corner_error, static_argnums=2)


def _random_homographies(seed, n=4):
  """Well-conditioned homographies with perspective terms, (n, 3, 3) float32."""
  rng = np.random.default_rng(seed)
  h = np.eye(3) + rng.normal(scale=0.1, size=(n, 3, 3))
  h[:, :2, 2] = rng.uniform(-20, 20, size=(n, 2))
  h[:, 2, :2] = rng.normal(scale=1e-3, size=(n, 2))
  return h.astype(np.float32)


def _random_points(seed, n=5):
  return np.random.default_rng(seed).uniform(0, 60, size=(n, 2)).astype(np.float32)


def _random_quads(rng, n, size):
  """Convex quads in TL, TR, BR, BL order: a jittered, shifted square, (n, 4, 2)."""
  quads = (UNIT_SQUARE + rng.uniform(-0.2, 0.2, size=(n, 4, 2))) * size
  return (quads + rng.uniform(-size, size, size=(n, 1, 2))).astype(np.float32)


def test_compose_inverse_round_trip():
  h = _random_homographies(0)
  inv = _inverse(h)
  eye = np.broadcast_to(np.eye(3), h.shape)
  np.testing.assert_allclose(_compose(h, inv), eye, atol=1e-5)
  np.testing.assert_allclose(_compose(inv, h), eye, atol=1e-5)
  np.testing.assert_allclose(_inverse(inv), h, rtol=1e-4, atol=1e-5)
  np.testing.assert_allclose(inv, np.linalg.inv(h), rtol=1e-4, atol=1e-5)


def test_compose_broadcasts():
  h = _random_homographies(1)
  out = _compose(h[:2, None], h)
  assert out.shape == (2, 4, 3, 3)
  np.testing.assert_allclose(out, np.matmul(h[:2, None], h), rtol=1e-5, atol=1e-5)


def test_jit_and_vmap_match_loop():
  h = _random_homographies(2)
  loop_inv = np.stack([hm.inverse(m) for m in h])
  loop_cmp = np.stack([hm.compose(m, m) for m in h])
  np.testing.assert_allclose(_inverse(h), loop_inv, rtol=1e-6, atol=1e-6)
  vmapped_inv, vmapped_cmp = jax.jit(
      lambda m: (jax.vmap(hm.inverse)(m), jax.vmap(hm.compose)(m, m)))(h)
  np.testing.assert_allclose(vmapped_inv, loop_inv, rtol=1e-6, atol=1e-6)
  np.testing.assert_allclose(vmapped_cmp, loop_cmp, rtol=1e-6, atol=1e-6)


def test_inverse_of_singular_is_finite_adjugate():
  singular = jnp.asarray([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 1.0, 1.0]])
  inv, grad = jax.jit(lambda m: (hm.inverse(m), jax.grad(lambda a: jnp.sum(hm.inverse(a)))(m)))(
      singular)
  assert np.all(np.isfinite(inv)) and np.all(np.isfinite(grad))
  np.testing.assert_allclose(singular @ inv, np.zeros((3, 3)), atol=1e-5)


def test_normalize_unit_determinant_same_points():
  h = _random_homographies(3) * np.array([2.0, -0.5, 7.0, -30.0], np.float32)[:, None, None]
  n = jax.jit(hm.normalize)(h)
  np.testing.assert_allclose(np.linalg.det(np.asarray(n, np.float64)), 1.0, rtol=1e-5)
  points = _random_points(4)
  np.testing.assert_allclose(_apply(n, points)[0], _apply(h, points)[0], rtol=1e-5, atol=1e-4)


def test_translation_scaling_and_rect_corners():
  t = hm.translation(jnp.asarray([1.0, 2.0]), jnp.asarray(3.0))
  assert t.shape == (2, 3, 3)
  np.testing.assert_array_equal(t[1], [[1, 0, 2], [0, 1, 3], [0, 0, 1]])
  np.testing.assert_array_equal(hm.scaling(jnp.asarray(2.0)), np.diag([2.0, 2.0, 1.0]))
  corners = hm.rect_corners(SHAPE)
  assert corners.dtype == jnp.float32
  np.testing.assert_array_equal(corners, [[0, 0], [63, 0], [63, 47], [0, 47]])


def test_apply_to_points_matches_numpy():
  h, points = _random_homographies(5), _random_points(6)
  mapped, w = _apply(h, points)
  assert mapped.shape == (4, 5, 2) and w.shape == (4, 5)
  homogeneous = np.einsum("bij,nj->bni", h.astype(np.float64), np.c_[points, np.ones(5)])
  np.testing.assert_allclose(mapped, homogeneous[..., :2] / homogeneous[..., 2:], rtol=1e-5)
  np.testing.assert_allclose(w, homogeneous[..., 2], rtol=1e-5)


def test_apply_to_points_is_safe_at_infinity():
  # The third row is (1, 0, 0), so w = x: (0, 5) maps to infinity, (0, 0) to zero.
  horizon = jnp.asarray([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
  points = jnp.asarray([[0.0, 5.0], [0.0, 0.0], [-2.0, 1.0]])
  (mapped, w), grads = jax.jit(lambda m, p: (
      hm.apply_to_points(m, p),
      jax.grad(lambda a, b: jnp.sum(hm.apply_to_points(a, b)[0]), argnums=(0, 1))(m, p)))(
          horizon, points)
  np.testing.assert_array_equal(w, [0.0, 0.0, -2.0])
  big = 1.0 / np.finfo(np.float32).eps
  np.testing.assert_allclose(mapped, [[0.0, big], [0.0, 0.0], [1.0, -0.5]])
  assert all(np.all(np.isfinite(g)) for g in grads)


def test_square_to_quad_maps_unit_square():
  quads = _random_quads(np.random.default_rng(7), 4, size=100.0)
  mapped, w = _apply(_square_to_quad(quads), np.r_[UNIT_SQUARE, [[0.5, 0.5]]])
  np.testing.assert_allclose(mapped[:, :4], quads, atol=1e-3)
  assert np.all(w > 0)
  np.testing.assert_array_equal(hm.square_to_quad(UNIT_SQUARE), np.eye(3))


def test_homography_from_corners_matches_opencv():
  rng = np.random.default_rng(8)
  src = _random_quads(rng, 32, size=300.0)
  dst = _random_quads(rng, 32, size=300.0)
  h = np.asarray(_from_corners(src, dst), np.float64)
  for h_ours, s, d in zip(h, src, dst):
    h_cv = cv2.getPerspectiveTransform(s, d)
    h_ours, h_cv = h_ours / h_ours[2, 2], h_cv / h_cv[2, 2]
    np.testing.assert_allclose(h_ours, h_cv, rtol=1e-4, atol=1e-4 * np.abs(h_cv).max())
  mapped, w = _apply(h.astype(np.float32), src)
  np.testing.assert_allclose(mapped, dst, atol=1e-2)
  assert np.all(w > 0)


def test_host_homography_from_corners_matches_opencv():
  rng = np.random.default_rng(8)
  src = _random_quads(rng, 32, size=300.0).astype(np.float64)
  dst = _random_quads(rng, 32, size=300.0).astype(np.float64)
  h = hm.host_homography_from_corners(src, dst)
  assert h.dtype == np.float64 and h.shape == (32, 3, 3)
  for h_ours, s, d in zip(h, src, dst):
    h_cv = cv2.getPerspectiveTransform(s.astype(np.float32), d.astype(np.float32))
    np.testing.assert_allclose(h_ours, h_cv / h_cv[2, 2], rtol=1e-6, atol=1e-9 * np.abs(h_cv).max())


def test_corner_offsets_round_trip_and_identity():
  x = np.random.default_rng(9).uniform(-8, 8, size=(4, 8)).astype(np.float32)
  h = _to_h(x, SHAPE)
  np.testing.assert_allclose(_to_x(h, SHAPE), x, atol=1e-4)
  corners = hm.rect_corners(SHAPE)
  expected = _from_corners(corners, corners + x.reshape(4, 4, 2))
  np.testing.assert_allclose(h / h[:, 2:, 2:], expected / expected[:, 2:, 2:], atol=1e-5)
  _, w = _apply(h, np.r_[corners, [[31.5, 23.5]]])
  assert np.all(w > 0)
  np.testing.assert_array_equal(_to_h(np.zeros((4, 8), np.float32), SHAPE),
                                np.broadcast_to(np.eye(3), (4, 3, 3)))
  np.testing.assert_allclose(_to_x(np.broadcast_to(np.eye(3, dtype=np.float32), (4, 3, 3)),
                                   SHAPE), np.zeros((4, 8)))


def test_corner_error():
  h = _random_homographies(10)
  np.testing.assert_allclose(_corner_error(h, 3.0 * h, SHAPE), 0.0, atol=1e-4)
  shift = np.broadcast_to(hm.translation(jnp.asarray(3.0), jnp.asarray(4.0)), (4, 3, 3))
  np.testing.assert_allclose(_corner_error(shift, np.eye(3, dtype=np.float32)[None], SHAPE), 5.0,
                             rtol=1e-6)
  grad = jax.jit(jax.grad(lambda m: hm.corner_error(m, m, SHAPE)))(jnp.eye(3))
  np.testing.assert_array_equal(grad, np.zeros((3, 3)))


@pytest.mark.parametrize("level", [1, 2, -1])
def test_pyramid_levels(level):
  h = _random_homographies(11)
  h_l = hm.homography_to_level(h, level)
  np.testing.assert_allclose(hm.homography_from_level(h_l, level), h, rtol=1e-6)
  points = _random_points(12)
  scale = 2.0**-level
  np.testing.assert_allclose(_apply(h_l, points * scale)[0], _apply(h, points)[0] * scale,
                             rtol=1e-5, atol=1e-4)


def test_degenerate_quad_is_finite_with_finite_gradients():
  corners = hm.rect_corners(SHAPE)
  collinear = jnp.asarray([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
  quads = jnp.stack([collinear, jnp.zeros((4, 2))])

  def loss(quad):
    return hm.corner_error(hm.homography_from_corners(corners, quad), jnp.eye(3), SHAPE)

  value, grad = jax.jit(jax.vmap(jax.value_and_grad(loss)))(quads)
  assert np.all(np.isfinite(value)) and np.all(np.isfinite(grad))
  _, w = _apply(_square_to_quad(quads), UNIT_SQUARE[:1])
  assert not np.any(w > 0)


@pytest.mark.parametrize("call, name, error", [
    (lambda: hm.inverse(jnp.ones((3, 4))), "h", ValueError),
    (lambda: hm.inverse(jnp.eye(3, dtype=jnp.int32)), "h", TypeError),
    (lambda: hm.inverse(jnp.full((3, 3), jnp.nan)), "h", ValueError),
    (lambda: hm.compose(jnp.eye(3), jnp.ones(3)), "b", ValueError),
    (lambda: hm.apply_to_points(jnp.eye(3), jnp.ones(2)), "points", ValueError),
    (lambda: hm.apply_to_points(jnp.eye(3), jnp.ones((4, 3))), "points", ValueError),
    (lambda: hm.square_to_quad(jnp.ones((3, 2))), "quad", ValueError),
    (lambda: hm.homography_from_corners(jnp.ones((4, 2)), jnp.ones((4, 2), jnp.int32)),
     "dst", TypeError),
    (lambda: hm.translation(jnp.asarray(1), jnp.asarray(2.0)), "tx", TypeError),
    (lambda: hm.corner_offsets_to_homography(jnp.zeros(6), SHAPE), "x", ValueError),
    (lambda: hm.corner_offsets_to_homography(jnp.zeros(8), (1, 5)), "shape", ValueError),
    (lambda: hm.rect_corners((0, 5)), "shape", ValueError),
    (lambda: hm.corner_error(jnp.eye(3), jnp.eye(2), SHAPE), "h_true", ValueError),
    (lambda: hm.homography_to_level(jnp.eye(3), 1.5), "level", TypeError),
])
def test_bad_input_names_argument(call, name, error):
  with pytest.raises(error, match=rf"\b{name}\b"):
    call()
