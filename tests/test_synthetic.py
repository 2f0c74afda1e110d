"""Synthetic sequences: ground truth against the rendered frames, options, bad input."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaxpso import similarity, synthetic, warp

SMALL = dict(num_frames=12, frame_shape=(120, 160), roi_size=(48, 48))


@pytest.fixture(scope="module")
def tilted():
  return synthetic.make_sequence(3, normal=(0.3, -0.2, 1.0), jumps=(6,), jump_size=2.0, **SMALL)


def _template_in(seq, t):
  """The frame-0 template, and frame t pulled back through the true homography."""
  x, y, w, h = seq.roi
  template = seq.frames[0, y:y + h, x:x + w]
  patch, mask = warp.warp_image(jnp.asarray(seq.frames[t]), jnp.asarray(seq.homographies[t]),
                                (h, w))
  return template, np.asarray(patch), np.asarray(mask)


def test_true_homographies_map_the_template_onto_every_frame(tilted):
  for t in range(tilted.frames.shape[0]):
    template, patch, mask = _template_in(tilted, t)
    assert mask.mean() > 0.99
    assert float(similarity.ncc(template, patch, mask)) > 0.995
    assert np.median(np.abs(template - patch)[mask]) < 0.01


def test_a_wrong_homography_does_not_fit(tilted):
  x, y, w, h = tilted.roi
  template = tilted.frames[0, y:y + h, x:x + w]
  shifted = tilted.homographies[5] @ np.array([[1, 0, 4.0], [0, 1, 0], [0, 0, 1]], np.float32)
  patch, mask = warp.warp_image(jnp.asarray(tilted.frames[5]), jnp.asarray(shifted), (h, w))
  assert float(similarity.ncc(template, patch, mask)) < 0.95


def test_homographies_are_plane_induced_by_the_poses(tilted):
  x, y, _, _ = tilted.roi
  expected = warp.plane_homography(jnp.asarray(tilted.poses), jnp.asarray(tilted.camera),
                                   jnp.asarray(tilted.normal), tilted.distance)
  expected = np.asarray(expected) @ np.array([[1, 0, x], [0, 1, y], [0, 0, 1]], np.float32)
  expected /= expected[:, 2:3, 2:3]
  np.testing.assert_allclose(tilted.homographies, expected, rtol=1e-4, atol=1e-3)
  np.testing.assert_allclose(tilted.poses[0], np.eye(4), atol=1e-6)
  np.testing.assert_allclose(tilted.corners[0], [[x, y], [x + 47, y], [x + 47, y + 47], [x, y + 47]],
                             atol=1e-4)


def test_a_jump_is_a_sudden_large_motion(tilted):
  motion = np.linalg.norm(np.diff(tilted.corners, axis=0), axis=-1).mean(-1)
  assert motion[5] > 4 * np.median(motion)


def test_same_seed_same_sequence_and_seeds_differ():
  a = synthetic.make_sequence(1, noise=0.02, **SMALL)
  b = synthetic.make_sequence(1, noise=0.02, **SMALL)
  c = synthetic.make_sequence(2, noise=0.02, **SMALL)
  np.testing.assert_array_equal(a.frames, b.frames)
  np.testing.assert_array_equal(a.homographies, b.homographies)
  assert not np.array_equal(a.homographies, c.homographies)


def test_photometric_options():
  base = synthetic.make_sequence(4, **SMALL)
  inverted = synthetic.make_sequence(4, intensity_change=(5, "invert"), **SMALL)
  np.testing.assert_array_equal(inverted.frames[:5], base.frames[:5])
  np.testing.assert_allclose(inverted.frames[5:], 1 - base.frames[5:], atol=1e-6)
  gamma = synthetic.make_sequence(4, intensity_change=(0, "gamma"), **SMALL)
  np.testing.assert_allclose(gamma.frames, np.sqrt(base.frames), atol=1e-6)
  noisy = synthetic.make_sequence(4, noise=0.05, **SMALL)
  inner = (base.frames > 0.1) & (base.frames < 0.9)
  assert abs(np.std((noisy.frames - base.frames)[inner]) - 0.05) < 0.005
  blurred = synthetic.make_sequence(4, blur=2.0, **SMALL)
  assert np.abs(np.diff(blurred.frames, axis=-1)).mean() < 0.7 * np.abs(np.diff(base.frames, axis=-1)).mean()
  drift = synthetic.make_sequence(4, gain_drift=0.2, **SMALL)
  assert not np.allclose(drift.frames[3], base.frames[3], atol=0.02)
  np.testing.assert_array_equal(drift.homographies, base.homographies)
  for seq in (inverted, gamma, noisy, blurred, drift):
    assert seq.frames.dtype == np.float32 and seq.frames.min() >= 0 and seq.frames.max() <= 1


def test_occlusion_hides_the_region_only_in_its_frames():
  base = synthetic.make_sequence(4, noise=0.01, **SMALL)
  occluded = synthetic.make_sequence(4, noise=0.01, occlusion=(3, 7), **SMALL)
  np.testing.assert_array_equal(occluded.visible, (np.arange(12) < 3) | (np.arange(12) >= 7))
  np.testing.assert_array_equal(base.visible, True)
  np.testing.assert_array_equal(occluded.homographies, base.homographies)
  visible = occluded.visible
  np.testing.assert_array_equal(occluded.frames[visible], base.frames[visible])
  for t in range(3, 7):
    # The whole region is covered, by something that is not the target, and
    # nothing beyond a quarter of the 48 px region past its bounding box.
    template, patch, mask = _template_in(occluded, t)
    assert mask.mean() > 0.99
    assert float(similarity.ncc(template, patch, mask)) < 0.2
    changed = np.argwhere(occluded.frames[t] != base.frames[t])
    lo, hi = occluded.corners[t].min(axis=0), occluded.corners[t].max(axis=0)
    assert np.all(changed.min(axis=0)[::-1] >= np.floor(lo - 12))
    assert np.all(changed.max(axis=0)[::-1] <= np.ceil(hi + 12))
  again = synthetic.make_sequence(4, noise=0.01, occlusion=(3, 7), **SMALL)
  np.testing.assert_array_equal(again.frames, occluded.frames)


def test_lazy_frames_equal_the_eager_ones():
  settings = dict(SMALL, noise=0.02, gain_drift=0.1, blur=1.0, occlusion=(2, 5),
                  intensity_change=(6, "gamma"))
  eager = synthetic.make_sequence(5, **settings)
  lazy = synthetic.make_sequence(5, lazy=True, **settings)
  assert not isinstance(lazy.frames, np.ndarray)
  np.testing.assert_array_equal(np.stack(list(lazy.frames)), eager.frames)
  np.testing.assert_array_equal(lazy.homographies, eager.homographies)


@pytest.mark.parametrize("kwargs, name", [
    (dict(num_frames=0), "num_frames"),
    (dict(roi_size=(500, 40)), "roi_size"),
    (dict(normal=(0, 0, 0)), "normal"),
    (dict(distance=-1.0), "distance"),
    (dict(camera=np.zeros((3, 3))), "camera"),
    (dict(jumps=(0,)), "jumps"),
    (dict(intensity_change=(2, "sepia")), "intensity_change"),
    (dict(occlusion=(0, 3)), "occlusion"),
    (dict(occlusion=(5, 5)), "occlusion"),
    (dict(occlusion=(5, 13)), "occlusion"),
    (dict(occlusion=5), "occlusion"),
    (dict(frame_shape=(0, 10)), "frame_shape"),
])
def test_bad_input_names_the_argument(kwargs, name):
  settings = dict(SMALL, **kwargs)
  with pytest.raises(ValueError, match=name):
    synthetic.make_sequence(0, **settings)
