"""Property-based tests (hypothesis) of the warps, the similarity measures and the swarm.

Every property runs one function compiled at module level on arrays of one
fixed shape, so an example costs microseconds, not a compile.  Hypothesis
draws the data (corner offsets, intensities, masks, gains, bounds, keys).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from jaxpso import pso
from jaxpso import similarity
from jaxpso import warp

# No example database: nothing is written to the working tree.  Derandomised: every run (CI
# included) draws the same examples, so a failure reproduces.
SETTINGS = settings(max_examples=25, deadline=None, database=None, derandomize=True)

SHAPE = (24, 32)  # template (h, w)
RECT = np.float32([[0, 0], [31, 0], [31, 23], [0, 23]])


def _floats(lo, hi):
  """float32 values in [lo, hi] (the bounds rounded to float32)."""
  return st.floats(float(np.float32(lo)), float(np.float32(hi)), width=32)


# Offsets of up to 6 px per corner of a 32×24 template keep the quad convex.
OFFSETS = hnp.arrays(np.float32, (8,), elements=_floats(-6, 6))
SHIFTS = hnp.arrays(np.float32, (2,), elements=_floats(-100, 100))
POINTS = hnp.arrays(np.float32, (16, 2), elements=_floats(0, 23))  # inside the template


def _homography(offsets, shift):
  """Corner offsets then a translation: a well-conditioned, orientation-preserving warp."""
  return warp.compose(warp.translation(shift[0], shift[1]),
                      warp.corner_offsets_to_homography(offsets, SHAPE))


@jax.jit
def _warp_round_trips(x, shift, y, points):
  """Quantities each of which a property compares with its expected value."""
  a, b = _homography(x, shift), _homography(y, -shift)
  mapped, w = warp.apply_to_points(a, points)
  back, _ = warp.apply_to_points(warp.inverse(a), mapped)
  composed, composed_w = warp.apply_to_points(warp.compose(a, b), points)
  in_turn, _ = warp.apply_to_points(a, warp.apply_to_points(b, points)[0])
  identity = warp.compose(a, warp.inverse(a))
  offsets = warp.homography_to_corner_offsets(warp.corner_offsets_to_homography(x, SHAPE), SHAPE)
  levels = [warp.homography_from_level(warp.homography_to_level(a, level), level)
            for level in (1, 2, 3)]
  normalised = warp.normalize(a)
  return dict(w=w, back=back, composed=composed, composed_w=composed_w, in_turn=in_turn,
              identity=identity / identity[2, 2], offsets=offsets, a=a, levels=jnp.stack(levels),
              det=jnp.linalg.det(normalised),
              normalised_points=warp.apply_to_points(normalised, points)[0], mapped=mapped,
              from_corners=warp.homography_from_corners(RECT, RECT + x.reshape(4, 2)))


@SETTINGS
@given(OFFSETS, SHIFTS, OFFSETS, POINTS)
def test_warp_composition_inverse_and_parametrisation(x, shift, y, points):
  out = jax.tree.map(np.asarray, _warp_round_trips(x, shift, y, points))
  assert np.all(out["w"] > 0)  # a convex quad in the template's order: w > 0 inside
  # Points through H and H⁻¹ come back; H H⁻¹ ~ I.
  np.testing.assert_allclose(out["back"], points, atol=2e-3)
  np.testing.assert_allclose(out["identity"], np.eye(3), atol=1e-4)
  # (A B)(p) = A(B(p)), away from A B's horizon (B's shift takes points up to 123 px outside
  # the template, where w -> 0 and float32 coordinates of 10^4 px lose their last digits).
  far = out["composed_w"] > 0.05
  np.testing.assert_allclose(out["composed"][far], out["in_turn"][far], rtol=1e-5, atol=2e-3)
  # Corner offsets → homography → corner offsets.
  np.testing.assert_allclose(out["offsets"], x, atol=1e-3)
  # The corner homography maps each template corner to the corner plus its offset.
  corners, _ = warp.apply_to_points(out["from_corners"], RECT)
  np.testing.assert_allclose(corners, RECT + x.reshape(4, 2), atol=2e-3)
  # To a pyramid level and back: exact (powers of two).
  np.testing.assert_array_equal(out["levels"], np.broadcast_to(out["a"], (3, 3, 3)))
  # normalize: unit determinant, the same map.
  np.testing.assert_allclose(out["det"], 1.0, rtol=1e-4)
  np.testing.assert_allclose(out["normalised_points"], out["mapped"], rtol=1e-5, atol=2e-3)


# --- similarities -------------------------------------------------------------------------------

WINDOW = (12, 12)
BINS = 8
_MEASURES = {"ssd": similarity.ssd, "ncc": similarity.ncc, "mi": similarity.mi,
             "nmi": similarity.nmi}
PATCHES = hnp.arrays(np.float32, WINDOW, elements=_floats(0, 1))
MASKS = hnp.arrays(np.bool_, WINDOW)


def _half(mask):
  """The mask with its first half valid, so every measure has enough pixels (min_valid 0.25)."""
  return np.concatenate([np.ones((6, 12), bool), mask[6:]])


@jax.jit
def _scores(a, b, mask):
  return {name: f(a, b, mask) for name, f in _MEASURES.items()}


@jax.jit
def _gradients(a, b, mask):
  """d score / d b of every measure."""
  return {name: jax.grad(lambda b, f=f: f(a, b, mask))(b) for name, f in _MEASURES.items()}


@SETTINGS
@given(PATCHES, PATCHES, MASKS)
def test_similarity_bounds_and_symmetry(a, b, mask):
  mask = _half(mask)
  ab = jax.tree.map(float, _scores(a, b, mask))
  ba = jax.tree.map(float, _scores(b, a, mask))
  assert ab["ssd"] >= 0
  assert -1 - 1e-5 <= ab["ncc"] <= 1 + 1e-5
  assert ab["mi"] >= -1e-6
  assert -1e-6 <= ab["nmi"] <= 1 + 1e-5
  for name in _MEASURES:
    np.testing.assert_allclose(ba[name], ab[name], rtol=1e-4, atol=1e-6, err_msg=name)


@SETTINGS
@given(PATCHES, PATCHES, MASKS, _floats(0.2, 5), _floats(-1, 1))
def test_ncc_invariant_to_gain_and_bias_mi_to_inversion(a, b, mask, gain, bias):
  mask = _half(mask)
  plain = _scores(a, b, mask)
  brighter = _scores(a, gain * b + bias, mask)
  negated = _scores(a, bias - gain * b, mask)
  inverted = _scores(a, 1 - b, mask)  # v → lo + hi − v over the default value_range (0, 1)
  np.testing.assert_allclose(brighter["ncc"], plain["ncc"], atol=1e-4)
  np.testing.assert_allclose(negated["ncc"], -plain["ncc"], atol=1e-4)
  np.testing.assert_allclose(inverted["mi"], plain["mi"], rtol=1e-4, atol=1e-5)
  np.testing.assert_allclose(inverted["nmi"], plain["nmi"], rtol=1e-4, atol=1e-5)


@SETTINGS
@given(PATCHES, _floats(0, 1), _floats(0, 0.9), _floats(0, 0.1), MASKS)
def test_gradients_are_finite_for_flat_patches_and_empty_bins(a, level, low, spread, mask):
  # A flat patch; a patch within a band of `spread` (most histogram bins
  # empty); and the same with a sparse random mask, below min_valid or not.
  band = low + spread * a
  for b, m in [(np.full(WINDOW, level, np.float32), np.ones(WINDOW, bool)),
               (band, np.ones(WINDOW, bool)), (band, mask), (a, mask)]:
    for name, value in _gradients(a, b, m).items():
      assert np.all(np.isfinite(value)), name
    for name, value in _scores(a, b, m).items():
      assert not np.isnan(value), name  # a score, or the worst (±inf) with too few pixels


# --- the swarm ----------------------------------------------------------------------------------

D = 3
_CONFIGS = {boundary: pso.PSOConfig(swarm_size=8, max_iterations=15, patience=None,
                                    variant="linear_inertia", boundary=boundary)
            for boundary in pso.BOUNDARIES}


def _rastrigin(x, target):
  z = x - target
  return jnp.sum(z * z - 3 * jnp.cos(2 * jnp.pi * z))


@SETTINGS
@given(st.integers(0, 2**31 - 1), hnp.arrays(np.float32, (D,), elements=_floats(-5, 4)),
       hnp.arrays(np.float32, (D,), elements=_floats(0.01, 10)),
       hnp.arrays(np.float32, (D,), elements=_floats(-6, 6)))
@pytest.mark.parametrize("boundary", pso.BOUNDARIES)
def test_swarm_best_never_worsens_and_stays_in_the_box(boundary, key, lower, width, target):
  upper = (lower + width).astype(np.float32)
  result, record = pso.trace(key, _rastrigin, lower, upper, target, config=_CONFIGS[boundary],
                             keep_positions=True)
  best, x = np.asarray(record.best_loss), np.asarray(record.x)
  assert np.all(np.diff(best) <= 0), best
  assert np.all((x >= lower) & (x <= upper)), "a particle left the box"
  assert np.all((np.asarray(result.x) >= lower) & (np.asarray(result.x) <= upper))
  assert float(result.loss) == best[-1]
  np.testing.assert_allclose(float(result.loss), float(_rastrigin(result.x, target)), rtol=1e-5,
                             atol=1e-5)
