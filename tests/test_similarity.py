"""Tests for the public similarity measures, `jaxpso.similarity`.

Expected values come from a NumPy float64 re-implementation of the soft
(cubic B-spline) joint histogram written here from the module docstring, from
hard histograms (`np.histogram2d`) and from mathematical identities.
Compilation dominates the runtime, so the tests share a few jitted functions
and reuse two window shapes: RAND (12×12 random values) and REAL (48×48 camera
patches).
"""

from __future__ import annotations

import functools
import pathlib

import cv2
import jax
import jax.numpy as jnp
import jax.test_util
import numpy as np
import pytest

import jaxpso
from jaxpso import similarity

RAND = (12, 12)
REAL = (48, 48)

_mi = jax.jit(similarity.mi, static_argnames=("bins", "value_range", "min_valid"))
_nmi = jax.jit(similarity.nmi, static_argnames=("bins", "value_range", "min_valid"))
_joint = jax.jit(similarity.joint_histogram, static_argnames=("bins", "value_range"))
_entropy = jax.jit(similarity.entropy, static_argnames=("bins", "value_range"))

_SIMILARITIES = ("ncc", "mi", "nmi")
_ALL = ("ssd",) + _SIMILARITIES


@functools.partial(jax.jit, static_argnames=("min_valid",))
def _scores_jit(a, b, mask, min_valid=similarity.ssd.__kwdefaults__["min_valid"]):
  return {name: getattr(similarity, name)(a, b, mask, min_valid=min_valid) for name in _ALL}


def _all_scores(a, b, mask=None, **kwargs):
  """Dict of the four measures (default bins) as NumPy arrays, from one jitted call."""
  return {k: np.asarray(v) for k, v in _scores_jit(a, b, mask, **kwargs).items()}


# ---------------------------------------------------------------------------
# Data.

_CAMERA = cv2.imread(str(pathlib.Path(jaxpso.__file__).parent / "data" / "camera.png"),
                     cv2.IMREAD_GRAYSCALE)


def _camera_patch(y, x, shape=REAL):
  return (_CAMERA[y:y + shape[0], x:x + shape[1]] / 255.0).astype(np.float32)


def _rand(seed, shape=RAND, low=0.05, high=0.95, dtype=np.float32):
  return np.random.default_rng(seed).uniform(low, high, shape).astype(dtype)


def _rand_mask(seed, shape=RAND, p_valid=0.8):
  return np.random.default_rng(seed).random(shape) < p_valid


# A textured camera patch and perturbed versions of it.
_A = _camera_patch(300, 250)
_ONES_REAL = np.ones(REAL, bool)
_NOISY = np.clip(_A + np.random.default_rng(1).normal(0, 0.05, REAL), 0, 1).astype(np.float32)
_SHIFTED = _camera_patch(302, 251)
_SHUFFLED = np.random.default_rng(2).permutation(_A.ravel()).reshape(REAL)
_PERTURBED = {"noisy": _NOISY, "shifted": _SHIFTED, "shuffled": _SHUFFLED}


# ---------------------------------------------------------------------------
# NumPy float64 references, written from the documentation.

def _bspline3_np(d):
  """Cubic B-spline, piecewise form: 2/3 - d² + |d|³/2 on |d| < 1, (2 - |d|)³/6 on [1, 2)."""
  d = np.abs(np.asarray(d, np.float64))
  return np.where(d < 1, 2 / 3 - d**2 + d**3 / 2, np.where(d < 2, (2 - d)**3 / 6, 0.0))


def _weights_np(v, bins, lo=0.0, hi=1.0):
  """(n,) intensities -> (n, bins) weights beta3(s - j), s = 1 + (v - lo)/(hi - lo)(bins - 3)."""
  v = np.clip(np.asarray(v, np.float64).ravel(), lo, hi)
  s = 1 + (v - lo) / (hi - lo) * (bins - 3)
  return _bspline3_np(s[:, None] - np.arange(bins)[None, :])


def _soft_joint_np(a, b, mask=None, bins=8, lo=0.0, hi=1.0):
  m = np.ones(np.size(a)) if mask is None else np.asarray(mask, np.float64).ravel()
  counts = (_weights_np(a, bins, lo, hi) * m[:, None]).T @ _weights_np(b, bins, lo, hi)
  return counts / counts.sum()


def _hard_joint_np(a, b, bins):
  counts, _, _ = np.histogram2d(np.ravel(a).astype(np.float64), np.ravel(b).astype(np.float64),
                                bins=bins, range=[[0, 1], [0, 1]])
  return counts / counts.sum()


def _h_np(p):
  p = np.asarray(p, np.float64).ravel()
  p = p[p > 0]
  return float(-np.sum(p * np.log(p)))


def _mi_np(p):
  return _h_np(p.sum(1)) + _h_np(p.sum(0)) - _h_np(p)


def _nmi_np(p):
  marginal = _h_np(p.sum(1)) + _h_np(p.sum(0))
  return 2 * (marginal - _h_np(p)) / marginal


def _ssd_np(a, b, mask):
  m = np.asarray(mask, np.float64)
  return float(np.sum(m * (np.float64(a) - b)**2) / m.sum())


def _ncc_np(a, b, mask):
  m = np.asarray(mask, bool)
  x = np.float64(a)[m]
  y = np.float64(b)[m]
  x -= x.mean()
  y -= y.mean()
  return float(np.sum(x * y) / np.sqrt(np.sum(x * x) * np.sum(y * y)))


# ---------------------------------------------------------------------------
# Agreement with the references.

@pytest.mark.parametrize("bins", [8, 16])
@pytest.mark.parametrize("masked", [False, True])
def test_soft_histogram_and_mi_match_numpy_reference(bins, masked):
  a = _rand(10, low=-0.1, high=1.1)  # a few values outside value_range: edge bins
  b = _rand(11)
  mask = _rand_mask(12) if masked else None
  p_ref = _soft_joint_np(a, b, mask, bins)
  p = np.asarray(_joint(a, b, mask, bins=bins))
  assert p.shape == (bins, bins)
  np.testing.assert_allclose(p, p_ref, atol=1e-6)
  np.testing.assert_allclose(p.sum(), 1.0, atol=1e-5)
  np.testing.assert_allclose(float(_mi(a, b, mask, bins=bins)), _mi_np(p_ref), atol=1e-5)
  np.testing.assert_allclose(float(_nmi(a, b, mask, bins=bins)), _nmi_np(p_ref), atol=1e-5)
  np.testing.assert_allclose(float(_entropy(a, mask, bins=bins)), _h_np(p_ref.sum(1)),
                             atol=1e-5)


def test_value_range_matches_reference():
  a = _rand(13, low=-1.0, high=3.0)
  b = _rand(14, low=-1.5, high=2.5)
  p_ref = _soft_joint_np(a, b, None, 8, -1.0, 2.0)
  np.testing.assert_allclose(_joint(a, b, bins=8, value_range=(-1.0, 2.0)), p_ref, atol=1e-6)
  np.testing.assert_allclose(float(_mi(a, b, bins=8, value_range=(-1.0, 2.0))),
                             _mi_np(p_ref), atol=1e-5)


def test_ssd_and_ncc_match_numpy_reference():
  a, b, mask = _rand(15), _rand(16), _rand_mask(17)
  for m in (mask, None):
    ref_mask = np.ones(RAND, bool) if m is None else m
    scores = _all_scores(a, b, m)
    np.testing.assert_allclose(scores["ssd"], _ssd_np(a, b, ref_mask), rtol=1e-5)
    np.testing.assert_allclose(scores["ncc"], _ncc_np(a, b, ref_mask), atol=1e-5)


def test_soft_mi_approaches_hard_mi_as_bins_grow():
  # With few bins soft MI is far below hard MI: the cubic B-spline smears
  # every sample over 4 neighbouring bins, so the soft histogram is a blurred
  # (lower-resolution) version of the hard one and blurring loses mutual
  # information.  The kernel spans 4 / (bins - 3) of the range, so the gap
  # shrinks as the bins get finer.  A 128×128 patch (16384 samples) keeps the
  # hard plug-in estimator's own upward bias (about bins² / 2N nats) small up
  # to 32 bins; at 64 bins that bias is comparable to the remaining smear, so
  # there the gap is only required to stay small.
  a = _camera_patch(100, 200, (128, 128))
  assert a.std() > 0.2  # a textured patch whose intensities span the range
  noise = np.random.default_rng(3).normal(0, 0.02, a.shape)
  b = np.clip(_camera_patch(101, 201, (128, 128)) + noise, 0, 1).astype(np.float32)
  gaps = {}
  for bins in (8, 16, 32, 64):
    hard = _mi_np(_hard_joint_np(a, b, bins))
    soft = float(_mi(a, b, bins=bins))
    assert soft < hard
    gaps[bins] = (hard - soft) / hard
  assert gaps[8] > gaps[16] > gaps[32], gaps
  assert gaps[8] > 0.3, gaps  # the smear matters at few bins ...
  assert gaps[32] < 0.15 and gaps[64] < 0.15, gaps  # ... and fades with many


# ---------------------------------------------------------------------------
# Properties of MI, NMI and NCC.

def test_self_information_identity_and_maximum():
  # Both sides are Parzen-windowed, so the joint histogram of (a, a) is not
  # diagonal: mi(a, a) = 2 H(a) - H(a, a) < H(a).
  a = _A
  h_a = float(_entropy(a))
  h_aa = _h_np(np.asarray(_joint(a, a)))
  mi_aa = float(_mi(a, a))
  np.testing.assert_allclose(mi_aa, 2 * h_a - h_aa, atol=1e-5)
  assert mi_aa <= h_a
  assert h_aa > h_a  # strictly: the soft joint spreads off the diagonal
  nmi_aa = float(_nmi(a, a))
  for name, b in _PERTURBED.items():
    assert mi_aa >= float(_mi(a, b)), name
    assert nmi_aa >= float(_nmi(a, b)), name
  np.testing.assert_allclose(float(_nmi(a, 1 - a)), nmi_aa, atol=1e-5)


def test_mi_invariant_to_intensity_reversal():
  # s(1 - v) = (bins - 1) - s(v): reversal mirrors the bins exactly.
  a, b, mask = _A, _NOISY, _rand_mask(18, REAL)
  np.testing.assert_allclose(float(_mi(a, 1 - a)), float(_mi(a, a)), atol=1e-5)
  np.testing.assert_allclose(float(_mi(a, 1 - b, mask)), float(_mi(a, b, mask)), atol=1e-5)
  np.testing.assert_allclose(float(_mi(1 - a, b, mask)), float(_mi(a, b, mask)), atol=1e-5)


def test_mi_near_invariant_to_monotone_remap_unlike_ssd_and_ncc():
  # Fixed-range binning makes MI only nearly invariant, and only for a patch
  # whose intensities fill value_range: a gamma curve then moves samples
  # between bins without merging many of them.  (For a narrow-band patch a
  # gamma curve widens or narrows the occupied band and MI changes by
  # factors.)  The patch is histogram-equalised to span the range; 16 bins.
  a8 = np.ascontiguousarray(_CAMERA[300:300 + REAL[0], 250:250 + REAL[1]])
  a = (cv2.equalizeHist(a8) / 255.0).astype(np.float32)
  mi_aa = float(_mi(a, a, bins=16))
  for gamma in (0.5, 2.0):
    b = a**gamma
    assert abs(float(_mi(a, b, bins=16)) / mi_aa - 1) < 0.15, gamma
    scores = _all_scores(a, b, _ONES_REAL)
    assert scores["ncc"] < 1 - 1e-3, gamma
    assert scores["ssd"] > 1e-2, gamma


@pytest.mark.parametrize("alpha, beta, expected", [(2.5, -0.3, 1.0), (0.3, 0.6, 1.0),
                                                    (-0.7, 0.9, -1.0)])
def test_ncc_of_affine_remap_is_sign(alpha, beta, expected):
  a = _A
  mask = _rand_mask(19, REAL)
  b = (alpha * a + beta).astype(np.float32)
  np.testing.assert_allclose(_all_scores(a, b, _ONES_REAL)["ncc"], expected, atol=1e-5)
  np.testing.assert_allclose(_all_scores(a, b, mask)["ncc"], expected, atol=1e-5)


def test_symmetry_and_ranges():
  pairs = [(_rand(20), _rand(21)), (_rand(22), _rand(22) ** 3)]
  pairs += [(_A, b) for b in _PERTURBED.values()]
  for i, (a, b) in enumerate(pairs):
    mask = _rand_mask(23 + i, a.shape)
    ab = _all_scores(a, b, mask)
    ba = _all_scores(b, a, mask)
    for name in ab:
      np.testing.assert_allclose(ab[name], ba[name], atol=1e-6, err_msg=name)
    assert ab["mi"] >= -1e-6
    assert -1e-6 <= ab["nmi"] <= 1 + 1e-6
    assert -1 - 1e-6 <= ab["ncc"] <= 1 + 1e-6
    assert ab["ssd"] >= 0


# ---------------------------------------------------------------------------
# Flat and degenerate windows.

@pytest.mark.parametrize("value", [0.3, 0.7])
def test_flat_window_scores(value):
  # 48×48 at 0.3 is a case where float32 rounding of the mean makes a flat
  # window look textured unless the flatness test allows for it.
  flat = np.full(REAL, value, np.float32)
  b = _A
  for x, y in ((flat, b), (b, flat), (flat, flat)):
    scores = _all_scores(x, y, _ONES_REAL)
    assert all(np.isfinite(v) for v in scores.values()), scores
    assert scores["ncc"] == 0.0, scores  # documented: a flat window scores 0
    assert abs(scores["mi"]) < 1e-6, scores
    assert abs(scores["nmi"]) < 1e-6, scores
  # The entropy of a flat window is that of the kernel weights of one value:
  # at most log 4 (the kernel spans 4 bins), well below a textured window's.
  h_flat = float(_entropy(flat))
  np.testing.assert_allclose(h_flat, _h_np(_weights_np([value], 8)[0]), atol=1e-5)
  assert h_flat <= np.log(4) + 1e-6
  assert h_flat < float(_entropy(b))


@jax.jit
def _grads_wrt_b(a, b, mask):
  return {name: jax.grad(lambda x, f=getattr(similarity, name): f(a, x, mask))(b)
          for name in _ALL}


@pytest.mark.parametrize("case", ["flat_a", "flat_b", "narrow_band", "all_masked"])
def test_gradients_finite_in_degenerate_cases(case):
  a, b, mask = _rand(24), _rand(25), np.ones(RAND, bool)
  if case == "flat_a":
    a = np.full(RAND, 0.4, np.float32)
  elif case == "flat_b":
    b = np.full(RAND, 0.4, np.float32)
  elif case == "narrow_band":  # most bins empty
    a = 0.5 + 0.01 * a
    b = 0.3 + 0.01 * b
  else:
    mask = np.zeros(RAND, bool)
  grads = _grads_wrt_b(a, b, mask)
  for name, g in grads.items():
    assert np.all(np.isfinite(g)), (case, name)
    if case == "all_masked":
      assert np.all(np.asarray(g) == 0), name


# ---------------------------------------------------------------------------
# Masks.

def test_all_masked_is_worst_score_without_nan():
  a, b = _rand(26), _rand(27)
  scores = _all_scores(a, b, np.zeros(RAND, bool))
  assert scores["ssd"] == np.inf
  for name in _SIMILARITIES:
    assert scores[name] == -np.inf, name
  assert float(_entropy(a, np.zeros(RAND, bool))) == 0.0
  assert not np.any(np.isnan(np.asarray(_joint(a, b, np.zeros(RAND, bool)))))


def test_min_valid_threshold():
  a, b = _rand(28), _rand(29)
  n = RAND[0] * RAND[1]
  order = np.random.default_rng(30).permutation(n)
  for min_valid in (0.25, 0.5):
    needed = int(np.ceil(min_valid * n))
    for count, worst in ((needed - 1, True), (needed, False)):
      mask = np.zeros(n, bool)
      mask[order[:count]] = True
      scores = _all_scores(a, b, mask.reshape(RAND), min_valid=min_valid)
      if worst:
        assert scores["ssd"] == np.inf
        assert all(scores[k] == -np.inf for k in _SIMILARITIES), scores
      else:
        assert all(np.isfinite(v) for v in scores.values()), (min_valid, scores)


def test_masked_out_pixels_do_not_matter():
  a, b, mask = _rand(31), _rand(32), _rand_mask(33, p_valid=0.6)
  garbage = np.random.default_rng(34).uniform(-50, 50, RAND).astype(np.float32)
  a2 = np.where(mask, a, garbage)
  b2 = np.where(mask, b, garbage[::-1])
  ref = _all_scores(a, b, mask)
  got = _all_scores(a2, b2, mask)
  for name in ref:
    np.testing.assert_allclose(got[name], ref[name], rtol=1e-5, atol=1e-6, err_msg=name)
  np.testing.assert_allclose(_joint(a2, b2, mask), _joint(a, b, mask), atol=1e-7)
  np.testing.assert_allclose(float(_entropy(a2, mask)), float(_entropy(a, mask)), atol=1e-6)


def test_float_mask_of_ones_equals_no_mask():
  a, b = _rand(35), _rand(36)
  ref = _all_scores(a, b)
  got = _all_scores(a, b, np.ones(RAND, np.float32))
  for name in ref:
    np.testing.assert_allclose(got[name], ref[name], rtol=1e-6, atol=1e-7, err_msg=name)


# ---------------------------------------------------------------------------
# Broadcasting, SoftBins, jit.

_N = 5


def _patches(seed):
  return _rand(seed, (_N,) + RAND), _rand_mask(seed + 1, (_N,) + RAND)


@jax.jit
def _binned_scores(template, patches, masks):
  # Bins come from the SoftBins (16) although mi/nmi/joint_histogram default to 8.
  sb = similarity.soft_bins(template, bins=16)
  return (sb.weights, similarity.mi(sb, patches, masks), similarity.nmi(sb, patches, masks),
          similarity.joint_histogram(sb, patches, masks))


@jax.jit
def _unbinned_scores(template, patches, masks):
  return (similarity.mi(template, patches, masks, bins=16),
          similarity.nmi(template, patches, masks, bins=16),
          similarity.joint_histogram(template, patches, masks, bins=16))


def test_swarm_broadcast_equals_loop():
  t = _rand(40)
  patches, masks = _patches(41)
  swarm = _all_scores(t[None], patches, masks)
  loop = [_all_scores(t, p, m) for p, m in zip(patches, masks)]
  for name in _ALL:
    assert swarm[name].shape == (_N,)
    np.testing.assert_allclose(swarm[name], [s[name] for s in loop], rtol=1e-5, atol=1e-6,
                               err_msg=name)
  # The template binned ahead of time gives the same scores.
  weights, *binned = _binned_scores(t, patches, masks)
  assert weights.shape == RAND + (16,)
  np.testing.assert_allclose(weights.sum(-1), 1.0, atol=1e-6)
  np.testing.assert_allclose(weights, _weights_np(t, 16).reshape(RAND + (16,)), atol=1e-6)
  for got, ref in zip(binned, _unbinned_scores(t, patches, masks)):
    assert got.shape == ref.shape
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6)


def test_leading_dims_broadcast():
  mask = _rand_mask(46)
  b = _rand(43)
  a = _rand(42, (2, 3) + RAND)
  a_col = _rand(44, (2, 1) + RAND)
  b_row = _rand(45, (3,) + RAND)
  grid = _all_scores(a, b, mask)
  outer = _all_scores(a_col, b_row, mask)
  for i in range(2):
    for j in range(3):
      one = _all_scores(a[i, j], b, mask)
      other = _all_scores(a_col[i, 0], b_row[j], mask)
      for name in _ALL:
        assert grid[name].shape == (2, 3) and outer[name].shape == (2, 3)
        np.testing.assert_allclose(grid[name][i, j], one[name], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(outer[name][i, j], other[name], rtol=1e-5, atol=1e-6)
  joint = _joint(a, b, mask)
  assert joint.shape == (2, 3, 8, 8)
  np.testing.assert_allclose(joint[1, 2], _soft_joint_np(a[1, 2], b, mask), atol=1e-6)


def test_jit_matches_eager():
  a, b, mask = _rand(46), _rand(47), _rand_mask(48)
  eager = {"ssd": similarity.ssd(a, b, mask), "ncc": similarity.ncc(a, b, mask),
           "mi": similarity.mi(a, b, mask), "nmi": similarity.nmi(a, b, mask)}
  jitted = _all_scores(a, b, mask)
  for name in eager:
    # mi = H(a) + H(b) - H(a, b) cancels entropies of about 2 nats in float32.
    np.testing.assert_allclose(jitted[name], eager[name], rtol=1e-6, atol=2e-6, err_msg=name)


_TRACES = []


@jax.jit
def _counted(a, b, mask):
  _TRACES.append(1)
  return similarity.mi(a, b, mask), similarity.ncc(a, b, mask)


def test_no_retrace_for_new_data_of_same_shape():
  _counted(_rand(49), _rand(50), _rand_mask(51))
  traces = len(_TRACES)
  assert traces >= 1
  out = _counted(_rand(52), _rand(53), _rand_mask(54))
  assert len(_TRACES) == traces
  np.testing.assert_allclose(out[0], _mi(_rand(52), _rand(53), _rand_mask(54)), rtol=1e-6)


# ---------------------------------------------------------------------------
# Gradients against finite differences (float64).

def _scores_tuple(a, b, mask):
  return (similarity.ssd(a, b, mask), similarity.ncc(a, b, mask),
          similarity.mi(a, b, mask, bins=16), similarity.nmi(a, b, mask))


def test_gradients_match_finite_differences():
  # Rev-mode derivatives w.r.t. both a and b against central differences.
  with jax.enable_x64(True):
    a = _rand(55, dtype=np.float64)
    b = _rand(56, dtype=np.float64)
    mask = _rand_mask(57)
    assert not mask.all()
    f = jax.jit(lambda x, y: _scores_tuple(x, y, mask))
    assert all(v.dtype == jnp.float64 for v in f(a, b))
    jax.test_util.check_grads(f, (a, b), order=1, modes=("rev",))


# ---------------------------------------------------------------------------
# Bad input.

def _expect(error, match, f, *args, **kwargs):
  with pytest.raises(error, match=match):
    f(*args, **kwargs)


def test_bad_input():
  good = np.zeros((4, 5), np.float32)
  ints = np.zeros((4, 5), np.int32)
  for f in (similarity.ssd, similarity.ncc, similarity.mi, similarity.nmi,
            similarity.joint_histogram):
    _expect(TypeError, r"^a\b.*int32", f, ints, good)
    _expect(TypeError, r"^b\b.*int32", f, good, ints)
    _expect(ValueError, r"^b\b.*\(5,\)", f, good, np.zeros(5, np.float32))
    _expect(ValueError, r"^a\b.*\(5,\)", f, np.zeros(5, np.float32), good)
    _expect(ValueError, r"\ba and b\b.*\(4, 5\).*\(4, 6\)", f, good,
            np.zeros((4, 6), np.float32))
    _expect(ValueError, r"\ba and b\b.*\(2, 4, 5\).*\(3, 4, 5\)", f,
            np.zeros((2, 4, 5), np.float32), np.zeros((3, 4, 5), np.float32))
    _expect(ValueError, r"mask.*\(5, 5\)", f, good, good, np.ones((5, 5), bool))
  for f in (similarity.ssd, similarity.ncc, similarity.mi, similarity.nmi):
    for min_valid in (0, 1.5):
      _expect(ValueError, "min_valid", f, good, good, min_valid=min_valid)
  for f in (similarity.mi, similarity.nmi, similarity.joint_histogram):
    for bins in (3, 8.5):
      _expect(ValueError, "bins", f, good, good, bins=bins)
    _expect(ValueError, r"value_range.*\(1, 0\)", f, good, good, value_range=(1, 0))
  _expect(ValueError, "bins", similarity.soft_bins, good, bins=3)
  _expect(ValueError, "bins", similarity.entropy, good, bins=8.5)
  _expect(ValueError, "value_range", similarity.entropy, good, value_range=(1, 0))
  _expect(TypeError, r"^a\b", similarity.entropy, ints)
  _expect(TypeError, r"^a\b", similarity.soft_bins, ints)
