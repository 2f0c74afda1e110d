"""Tests for `jaxpso.warp` (3 of 3): sampling and the pyramid, `jaxpso._src.sampling`.

Expected values come from OpenCV (`cv2.warpPerspective`, `cv2.pyrDown`) and
from NumPy re-implementations of the projection and bilinear sampling written
here.  Compilation dominates the runtime, so the tests share a few jitted
functions and reuse one template shape and two images.
"""

from __future__ import annotations

import pathlib

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpso
from jaxpso import warp

SHAPE = (24, 32)  # template (h, w)
_CAMERA = (cv2.imread(str(pathlib.Path(jaxpso.__file__).parent / "data" / "camera.png"),
                      cv2.IMREAD_GRAYSCALE) / 255.0).astype(np.float32)
# A small non-square frame, narrower and shorter than the template.
_SMALL = np.random.default_rng(0).random((20, 26)).astype(np.float32)

_warp = jax.jit(warp.warp_image, static_argnums=2)
_warp_points = jax.jit(warp.warp_points, static_argnums=2)
_pyr_down = jax.jit(warp.pyr_down)
_pyramid = jax.jit(warp.gaussian_pyramid, static_argnums=1)


def _random_homographies(seed, n, frame_shape=_CAMERA.shape, shape=SHAPE):
  """(n, 3, 3) float32 homographies putting the template near the frame centre.

  Random rotation (±0.3 rad), scale (0.8 to 1.25), shear and perspective terms
  about the template centre, and a translation of up to ±10 px.
  """
  rng = np.random.default_rng(seed)
  h, w = shape
  centre = np.array([[1, 0, -(w - 1) / 2], [0, 1, -(h - 1) / 2], [0, 0, 1]])
  out = []
  for _ in range(n):
    angle = rng.uniform(-0.3, 0.3)
    scale = np.exp(rng.uniform(-0.22, 0.22))
    rot = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    m = np.eye(3)
    m[:2, :2] = rot + rng.normal(scale=0.03, size=(2, 2))
    m[2, :2] = rng.normal(scale=2e-3, size=2)
    m[:2, 2] = np.array(frame_shape[::-1]) / 2 + rng.uniform(-10, 10, size=2)
    out.append(m @ centre)
  return np.stack(out).astype(np.float32)


def _project_np(hs, shape=SHAPE):
  """NumPy float64 projection of the template grid: (x, y, w), each (..., h, w)."""
  v, u = np.mgrid[:shape[0], :shape[1]].astype(np.float64)
  hs = np.asarray(hs, np.float64)[..., None, None, :, :]
  num_x = hs[..., 0, 0] * u + hs[..., 0, 1] * v + hs[..., 0, 2]
  num_y = hs[..., 1, 0] * u + hs[..., 1, 1] * v + hs[..., 1, 2]
  den = hs[..., 2, 0] * u + hs[..., 2, 1] * v + hs[..., 2, 2]
  with np.errstate(divide="ignore", invalid="ignore"):
    return num_x / den, num_y / den, den


def _bilinear_np(image, hs, shape=SHAPE):
  """NumPy float64 reference of warp_image: (patches, mask)."""
  image = np.asarray(image, np.float64)
  height, width = image.shape
  x, y, den = _project_np(hs, shape)
  mask = (den > 0) & (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
  x = np.where(mask, x, 0.0)
  y = np.where(mask, y, 0.0)
  x0 = np.minimum(np.floor(x), width - 2).astype(int)
  y0 = np.minimum(np.floor(y), height - 2).astype(int)
  fx, fy = x - x0, y - y0
  top = (1 - fx) * image[y0, x0] + fx * image[y0, x0 + 1]
  bottom = (1 - fx) * image[y0 + 1, x0] + fx * image[y0 + 1, x0 + 1]
  return np.where(mask, (1 - fy) * top + fy * bottom, 0.0), mask


def _cv2_warp(image, h, shape=SHAPE):
  return cv2.warpPerspective(image, np.asarray(h, np.float64), shape[::-1],
                             flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def _interior(hs, frame_shape, margin=1.0, shape=SHAPE):
  """Template pixels mapped at least `margin` px inside the frame (w > 0)."""
  x, y, den = _project_np(hs, shape)
  height, width = frame_shape
  return ((den > 0) & (x >= margin) & (x <= width - 1 - margin) & (y >= margin)
          & (y <= height - 1 - margin))


# Ten warps inside the camera image and two that leave it partly.
_INSIDE = _random_homographies(1, 10)
_LEAVING = _INSIDE[:2].copy()
_LEAVING[0, 0] -= 240 * _LEAVING[0, 2]  # shifted 240 px left, across the left edge
_LEAVING[1, 1] += 260 * _LEAVING[1, 2]  # shifted 260 px down, across the bottom edge
_SWARM = np.concatenate([_INSIDE, _LEAVING])


# ---------------------------------------------------------------------------
# warp_image against OpenCV and the NumPy reference.

def test_warp_image_matches_opencv():
  patches, mask = map(np.asarray, _warp(_CAMERA, _SWARM, SHAPE))
  assert patches.shape == mask.shape == (len(_SWARM),) + SHAPE
  assert patches.dtype == np.float32 and mask.dtype == bool
  assert mask[:len(_INSIDE)].all()  # these warps stay inside the frame
  interior = _interior(_SWARM, _CAMERA.shape)
  for i, h in enumerate(_SWARM):
    compare = mask[i] & interior[i]
    assert compare.sum() > SHAPE[0] * SHAPE[1] // 3
    ref = _cv2_warp(_CAMERA, h)
    np.testing.assert_allclose(patches[i][compare], ref[compare], atol=1e-4, err_msg=str(i))
  for i in range(len(_INSIDE), len(_SWARM)):
    assert not mask[i].all() and mask[i].any()
  # The mask agrees with the NumPy projection except within 1e-3 px of the
  # frame border, where float32 rounding may decide either way.
  ref_patches, ref_mask = _bilinear_np(_CAMERA, _SWARM)
  near_border = (_interior(_SWARM, _CAMERA.shape, -1e-3)
                 & ~_interior(_SWARM, _CAMERA.shape, 1e-3))
  assert ref_mask[len(_INSIDE):].sum() > 0
  np.testing.assert_array_equal(mask[~near_border], ref_mask[~near_border])
  np.testing.assert_allclose(patches[~near_border], ref_patches[~near_border], atol=1e-4)


def test_swarm_equals_single_calls_and_eager():
  patches, mask = _warp(_CAMERA, _SWARM, SHAPE)
  for i, h in enumerate(_SWARM):
    p1, m1 = _warp(_CAMERA, h, SHAPE)
    assert p1.shape == m1.shape == SHAPE
    np.testing.assert_array_equal(m1, mask[i])
    np.testing.assert_allclose(p1, patches[i], rtol=0, atol=1e-6)
  eager_patches, eager_mask = warp.warp_image(_CAMERA, _SWARM, SHAPE)
  np.testing.assert_array_equal(eager_mask, mask)
  np.testing.assert_allclose(eager_patches, patches, rtol=0, atol=1e-6)


def test_leading_batch_dims():
  hs = _SWARM[:6].reshape(2, 3, 3, 3)
  patches, mask = _warp(_CAMERA, hs, SHAPE)
  assert patches.shape == mask.shape == (2, 3) + SHAPE
  flat_patches, flat_mask = _warp(_CAMERA, _SWARM, SHAPE)
  np.testing.assert_allclose(np.asarray(patches).reshape((6,) + SHAPE), flat_patches[:6],
                             atol=1e-6)
  np.testing.assert_array_equal(np.asarray(mask).reshape((6,) + SHAPE), flat_mask[:6])


# ---------------------------------------------------------------------------
# Mask semantics on a small frame.

def _translation(tx, ty):
  return np.array([[1, 0, tx], [0, 1, ty], [0, 0, 1]], np.float32)


def test_mask_semantics():
  height, width = _SMALL.shape
  last_x = width - 1 - (SHAPE[1] - 1)  # template column w-1 lands on frame column W-1
  last_y = height - 1 - (SHAPE[0] - 1)
  hs = np.stack([
      _translation(-3.5, 2.25),  # partly outside: left, right and bottom
      _translation(last_x, last_y),  # exactly onto the last row and column
      _translation(last_x + 1e-3, last_y + 1e-3),  # just past them
      np.diag([1.0, 1.0, -1.0]).astype(np.float32),  # w = -1 everywhere
      -np.eye(3, dtype=np.float32),  # w = -1, although x/w, y/w land inside
      np.array([[1, 0, 0], [0, 1, 0], [0.05, 0, -0.5]], np.float32),  # w <= 0 for u <= 10
  ])
  patches, mask = map(np.asarray, _warp(_SMALL, hs, SHAPE))
  assert not np.any(np.isnan(patches))
  ref_patches, ref_mask = _bilinear_np(_SMALL, hs)
  np.testing.assert_array_equal(mask, ref_mask)
  np.testing.assert_allclose(patches, ref_patches, atol=1e-6)
  assert np.all(patches[~mask] == 0)
  # Exactly the last row and column: valid, and equal to the frame's pixels.
  v, u = np.mgrid[:SHAPE[0], :SHAPE[1]]
  expected = (u + last_x >= 0) & (v + last_y >= 0)
  np.testing.assert_array_equal(mask[1], expected)
  assert mask[1, -1, -1]
  np.testing.assert_allclose(patches[1, -1, -1], _SMALL[-1, -1], atol=1e-6)
  np.testing.assert_allclose(patches[1][:, -1][expected[:, -1]],
                             _SMALL[v[:, -1] + last_y, width - 1][expected[:, -1]], atol=1e-6)
  # Just past them: the last row and column are invalid.
  assert not mask[2, -1, :].any() and not mask[2, :, -1].any()
  assert mask[2, :-1, :-1].any()
  # w <= 0: invalid everywhere (even where x/w, y/w land inside), no NaN.
  assert not mask[3].any() and not mask[4].any()
  assert not mask[5][:, :11].any() and np.all(patches[3:5] == 0)


# ---------------------------------------------------------------------------
# Gradients.

_grad_sum = jax.jit(jax.vmap(jax.grad(lambda h, image: jnp.sum(warp.warp_image(
    image, h, SHAPE)[0])), in_axes=(0, None)))


def test_gradient_is_finite():
  hs = np.concatenate([_SWARM, np.stack([np.diag([1.0, 1.0, -1.0]),
                                         np.array([[1, 0, 0], [0, 1, 0], [0.05, 0, -0.5]])
                                         ]).astype(np.float32)])
  grads = np.asarray(_grad_sum(hs, _CAMERA))
  assert grads.shape == hs.shape
  assert np.all(np.isfinite(grads))
  assert np.all(np.abs(grads[:len(_SWARM)]).sum(axis=(1, 2)) > 0)
  assert np.all(grads[-2] == 0)  # nothing valid: zero gradient


def test_gradient_matches_finite_differences():
  # Bilinear sampling has kinks where a sample crosses a pixel row or column;
  # the step of each entry is scaled so that no sample moves by more than
  # about 1e-5 px, and the image is smooth so that the kinks are small.
  blurred = cv2.GaussianBlur(_CAMERA, (0, 0), 3.0)[200:280, 220:300].astype(np.float64)
  h0 = _random_homographies(2, 1, blurred.shape)[0].astype(np.float64)
  with jax.enable_x64(True):
    value = jax.jit(lambda h: jnp.sum(warp.warp_image(blurred, h, SHAPE)[0]))
    grad = np.asarray(jax.jit(jax.grad(value))(h0))
    assert grad.dtype == np.float64
    x, y, den = _project_np(h0)
    reach = max(np.abs(x).max(), np.abs(y).max())
    # d(x, y)/dh_ij is at most |(u, v, 1)_j| · max(1, reach) / den.
    extent = np.array([SHAPE[1], SHAPE[0], 1.0]) * max(1.0, reach) / den.min()
    fd = np.zeros((3, 3))
    for i in range(3):
      for j in range(3):
        step = 1e-5 / extent[j]
        e = np.zeros((3, 3))
        e[i, j] = step
        fd[i, j] = (float(value(h0 + e)) - float(value(h0 - e))) / (2 * step)
  assert bool(np.asarray(_bilinear_np(blurred, h0)[1]).all())
  np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())


# ---------------------------------------------------------------------------
# warp_points and template_grid.

def test_warp_points_matches_numpy_projection():
  frame = _SMALL.shape
  hs = np.concatenate([_random_homographies(3, 3, frame, (10, 12)),
                       _translation(30, 0)[None], -np.eye(3, dtype=np.float32)[None],
                       np.diag([1.0, 1.0, -1.0]).astype(np.float32)[None]])
  points = np.array([[0, 0], [5, 3], [11, 9], [-40, 2], [25, 19], [3.5, 7.25]], np.float32)
  mapped, valid = map(np.asarray, _warp_points(hs, points, frame))
  assert mapped.shape == (len(hs), len(points), 2) and valid.shape == (len(hs), len(points))
  homogeneous = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ np.swapaxes(
      hs.astype(np.float64), 1, 2)
  w = homogeneous[..., 2]
  ref = homogeneous[..., :2] / w[..., None]
  np.testing.assert_allclose(mapped, ref, rtol=1e-5, atol=1e-4)
  inside = ((w > 0) & (ref[..., 0] >= 0) & (ref[..., 0] <= frame[1] - 1) & (ref[..., 1] >= 0)
            & (ref[..., 1] <= frame[0] - 1))
  np.testing.assert_array_equal(valid, inside)
  assert valid[:3].sum() > 6  # the random warps keep several points inside
  assert not valid[3].any()  # shifted out of the frame
  assert not valid[4:].any()  # behind the camera: -I maps (5, 3) onto itself but w = -1
  np.testing.assert_allclose(mapped[4, 1], [5, 3], atol=1e-6)


def test_template_grid():
  grid = np.asarray(warp.template_grid(SHAPE))
  assert grid.shape == SHAPE + (2,)
  x, y = np.meshgrid(np.arange(SHAPE[1]), np.arange(SHAPE[0]))
  np.testing.assert_array_equal(grid[..., 0], x)
  np.testing.assert_array_equal(grid[..., 1], y)
  # The identity warp samples the frame's top-left corner.
  patches, mask = _warp(_CAMERA, np.eye(3, dtype=np.float32), SHAPE)
  assert bool(mask.all())
  np.testing.assert_allclose(patches, _CAMERA[:SHAPE[0], :SHAPE[1]], atol=1e-6)


# ---------------------------------------------------------------------------
# Pyramid.

@pytest.mark.parametrize("shape", [(24, 32), (23, 17), (5, 2)])
def test_pyr_down_matches_opencv(shape):
  image = np.random.default_rng(4).random(shape).astype(np.float32)
  out = np.asarray(_pyr_down(image))
  ref = cv2.pyrDown(image)
  assert out.shape == ref.shape == ((shape[0] + 1) // 2, (shape[1] + 1) // 2)
  np.testing.assert_allclose(out, ref, atol=1e-5)


def test_gaussian_pyramid_matches_opencv():
  pyramid = _pyramid(_CAMERA, 4)
  assert [p.shape for p in pyramid] == [(512, 512), (256, 256), (128, 128), (64, 64)]
  ref = _CAMERA
  np.testing.assert_array_equal(pyramid[0], ref)
  for level in pyramid[1:]:
    ref = cv2.pyrDown(ref)
    np.testing.assert_allclose(level, ref, atol=1e-5)
  assert len(_pyramid(_CAMERA, 1)) == 1


def test_atlas_holds_the_pyramid_read_only():
  # The atlas is read-only and 64-byte aligned so that the CPU client hands
  # it to a program without copying it (a 4 MiB copy per call took 0.3 ms);
  # its levels are OpenCV's pyramid, level after level.
  from jaxpso._src import atlas
  from jaxpso._src import batching
  from jaxpso._src import template as templates

  def uncopied(array):
    return jax.device_put(array).unsafe_buffer_pointer() == array.ctypes.data

  image = np.ascontiguousarray(_CAMERA[:90, :70])
  built = atlas.build(image, 3)
  assert not built.pixels.flags.writeable and not built.levels.flags.writeable
  expected = image
  for index in range(3):
    offset, width, height = built.levels[index]
    assert (height, width) == expected.shape
    np.testing.assert_array_equal(built.pixels[offset:offset + width * height].reshape(height, width),
                                  expected)
    expected = cv2.pyrDown(expected)
  np.testing.assert_array_equal(built.levels[3:], np.repeat(built.levels[2:3], 3, axis=0))
  for stacked in (batching.stack([built]), batching.stack([built, built])):
    assert not any(leaf.flags.writeable for leaf in stacked)
    assert uncopied(stacked.pixels)
    np.testing.assert_array_equal(stacked.pixels[-1], built.pixels)
  assert all(uncopied(leaf) for leaf in batching.stack([built, built]))  # stacked aligned
  for shape in ((240, 320), (480, 640)):
    assert uncopied(atlas.build(np.ascontiguousarray(_CAMERA[:shape[0], :shape[1]]), 3).pixels)
  prepared = batching.stack([templates.prepare(image[:48, :48], 2, 0.25, 16)])  # one: a view
  assert uncopied(prepared.points) and uncopied(prepared.values)


def _pyramid_shapes(shape, levels):
  shapes = [tuple(shape)]
  for _ in range(levels - 1):
    shapes.append(tuple((s + 1) // 2 for s in shapes[-1]))
  return shapes


def test_gaussian_pyramid_rejects_too_many_levels():
  for shape, levels in [((8, 8), 4), ((64, 5), 4), ((2, 2), 2)]:
    assert min(_pyramid_shapes(shape, levels)[-1]) < 2
    with pytest.raises(ValueError, match=rf"levels={levels}.*{shape}"):
      warp.gaussian_pyramid(np.zeros(shape, np.float32), levels)
  for levels in (0, 1.5):
    with pytest.raises(ValueError, match="levels"):
      warp.gaussian_pyramid(_SMALL, levels)


@pytest.mark.parametrize("shape, levels", [((3, 3), 2), ((6, 6), 3), ((12, 5), 3)])
def test_gaussian_pyramid_allows_a_coarsest_level_of_2x2(shape, levels):
  # Documented: "every level must stay at least 2×2"; pyr_down rounds up, so
  # these pyramids end exactly at 2 pixels.
  expected = _pyramid_shapes(shape, levels)
  assert min(expected[-1]) == 2
  image = np.random.default_rng(5).random(shape).astype(np.float32)
  pyramid = warp.gaussian_pyramid(image, levels)
  assert [p.shape for p in pyramid] == expected


def test_homography_to_level_matches_pyramid_coordinates():
  # Level-1 pixel i sits at level-0 pixel 2i, so H_1 maps p/2 to H_0(p)/2.
  h0 = _INSIDE[3].astype(np.float64)
  h1 = np.asarray(warp.homography_to_level(h0, 1), np.float64)
  p = np.array([[0, 0, 1], [31, 0, 1], [31, 23, 1], [7, 11, 1]], np.float64)
  q0 = p @ h0.T
  q1 = (p * [0.5, 0.5, 1]) @ h1.T
  np.testing.assert_allclose(q1[:, :2] / q1[:, 2:], q0[:, :2] / q0[:, 2:] / 2, rtol=1e-6)
  # Sampling the level-1 image with H_1 approximates pyr_down of the level-0
  # warp on a blurred image ("blur then warp" is close to "warp then blur").
  # The other common convention, pixel areas (p_1 = (p_0 + 0.5) / 2 - 0.5),
  # differs by a quarter level-1 pixel, which a rotation by 1 rad turns into a
  # clearly larger error.
  blurred = cv2.GaussianBlur(_CAMERA, (0, 0), 2.0)
  big = (2 * SHAPE[0], 2 * SHAPE[1])
  c, s = np.cos(1.0), np.sin(1.0)
  h0 = np.array([[c, -s, 200.3], [s, c, 180.7], [1e-4, -1e-4, 1]], np.float32)
  full, full_mask = _warp(blurred, h0, big)
  assert bool(full_mask.all())
  expected = np.asarray(_pyr_down(full))
  level1 = _pyr_down(blurred)
  h1 = warp.homography_to_level(h0, 1)
  got, mask = map(np.asarray, _warp(level1, h1, SHAPE))
  assert mask.all()
  offset = np.array([[1, 0, -0.25], [0, 1, -0.25], [0, 0, 1]], np.float32)
  wrong, _ = _warp(level1, offset @ np.asarray(h1) @ np.linalg.inv(offset), SHAPE)
  inner = (slice(1, -1), slice(1, -1))  # pyr_down's reflected border differs at the edge
  error = np.abs(got - expected)[inner].mean()
  wrong_error = np.abs(np.asarray(wrong) - expected)[inner].mean()
  assert error < 2.5e-3, error
  assert error < 0.4 * wrong_error, (error, wrong_error)


# ---------------------------------------------------------------------------
# Bad input.

def test_bad_input():
  h = np.eye(3, dtype=np.float32)
  cases = [
      (TypeError, r"^image\b.*int", (np.zeros((8, 8), np.int32), h, SHAPE)),
      (ValueError, r"^image\b.*\(2, 8, 8\)", (np.zeros((2, 8, 8), np.float32), h, SHAPE)),
      (ValueError, r"^image\b.*\(0, 5\)", (np.zeros((0, 5), np.float32), h, SHAPE)),
      (ValueError, r"^image\b.*\(1, 5\)", (np.zeros((1, 5), np.float32), h, SHAPE)),
      (ValueError, r"^homographies\b.*\(3, 4\)", (_SMALL, np.zeros((3, 4), np.float32), SHAPE)),
      (TypeError, r"^homographies\b.*int", (_SMALL, np.eye(3, dtype=np.int32), SHAPE)),
      (ValueError, r"^shape\b.*\(0, 5\)", (_SMALL, h, (0, 5))),
      (ValueError, r"^shape\b", (_SMALL, h, (4, 5, 6))),
  ]
  for value in (np.nan, np.inf):
    bad = np.stack([h, h])
    bad[1, 2, 0] = value
    cases.append((ValueError, rf"^homographies\b.*{value}.*\(2, 3, 3\)", (_SMALL, bad, SHAPE)))
  for error, match, args in cases:
    with pytest.raises(error, match=match):
      warp.warp_image(*args)
  with pytest.raises(TypeError, match=r"^image\b"):
    warp.pyr_down(np.zeros((8, 8), np.uint8))
  with pytest.raises(ValueError, match=r"^image\b.*\(8,\)"):
    warp.gaussian_pyramid(np.zeros(8, np.float32), 1)
  with pytest.raises(ValueError, match=r"^shape\b"):
    warp.template_grid((0, 5))
  with pytest.raises(ValueError, match=r"^frame_shape\b"):
    warp.warp_points(h, np.zeros((3, 2), np.float32), (-1, 5))
