"""Tests for the public similarity measures, `jaxpso.similarity`.

Expected values come from a NumPy float64 re-implementation of the soft
(cubic B-spline) joint histogram written here from the module docstring, from
hard histograms (`np.histogram2d`) and from mathematical identities.

Compilation dominates the runtime, so nearly every check goes through one
jitted function, `_measures`, that evaluates all the measures at once, and the
tests reuse two window shapes: RAND (12×12 random values) and REAL (48×48
camera patches), with a bool mask wherever possible.
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
_SIMILARITIES = ("ncc", "mi", "nmi")
_MEASURES = ("ssd",) + _SIMILARITIES


@functools.partial(jax.jit, static_argnames=("bins", "value_range", "min_valid"))
def _measures_jit(a, b, mask, bins=8, value_range=(0.0, 1.0), min_valid=0.25):
  hist = dict(bins=bins, value_range=value_range)
  out = {"ssd": similarity.ssd(a, b, mask, min_valid=min_valid),
         "ncc": similarity.ncc(a, b, mask, min_valid=min_valid),
         "mi": similarity.mi(a, b, mask, min_valid=min_valid, **hist),
         "nmi": similarity.nmi(a, b, mask, min_valid=min_valid, **hist),
         "joint": similarity.joint_histogram(a, b, mask, **hist)}
  if a.ndim == 2:
    out["entropy_a"] = similarity.entropy(a, mask, **hist)
    out["entropy_b"] = similarity.entropy(b, mask, **hist)
  return out


def _measures(a, b, mask=None, bins=8, value_range=(0.0, 1.0), min_valid=0.25):
  """All measures of (a, b) as a dict of NumPy arrays, from one jitted call."""
  # Every static argument is passed explicitly: jit caches `f(x, bins=8)` and
  # `f(x)` separately.
  out = _measures_jit(a, b, mask, bins=bins, value_range=value_range, min_valid=min_valid)
  return {k: np.asarray(v) for k, v in out.items()}


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
_PERTURBED = {
    "noisy": np.clip(_A + np.random.default_rng(1).normal(0, 0.05, REAL), 0, 1).astype(np.float32),
    "shifted": _camera_patch(302, 251),
    "shuffled": np.random.default_rng(2).permutation(_A.ravel()).reshape(REAL),
}


# ---------------------------------------------------------------------------
# NumPy float64 references, written from the documentation.

def _bspline3_np(d):
  """Cubic B-spline, piecewise: 2/3 - d² + |d|³/2 on |d| < 1, (2 - |d|)³/6 on [1, 2)."""
  d = np.abs(np.asarray(d, np.float64))
  return np.where(d < 1, 2 / 3 - d**2 + d**3 / 2, np.where(d < 2, (2 - d)**3 / 6, 0.0))


def _weights_np(v, bins, lo=0.0, hi=1.0):
  """(n,) intensities -> (n, bins) weights β3(s - j), s = 1 + (v - lo)/(hi - lo)·(bins - 3)."""
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
def test_measures_match_numpy_reference(bins):
  a = _rand(10, low=-0.1, high=1.1)  # some values outside value_range: the edge bins
  b = _rand(11)
  for mask in (_rand_mask(12), None):
    ref_mask = np.ones(RAND, bool) if mask is None else mask
    p_ref = _soft_joint_np(a, b, mask, bins)
    got = _measures(a, b, mask, bins=bins)
    assert got["joint"].shape == (bins, bins)
    np.testing.assert_allclose(got["joint"], p_ref, atol=1e-6)
    np.testing.assert_allclose(got["joint"].sum(), 1.0, atol=1e-5)
    np.testing.assert_allclose(got["mi"], _mi_np(p_ref), atol=1e-5)
    np.testing.assert_allclose(got["nmi"], _nmi_np(p_ref), atol=1e-5)
    np.testing.assert_allclose(got["entropy_a"], _h_np(p_ref.sum(1)), atol=1e-5)
    np.testing.assert_allclose(got["entropy_b"], _h_np(p_ref.sum(0)), atol=1e-5)
    np.testing.assert_allclose(got["ssd"], _ssd_np(a, b, ref_mask), rtol=1e-5)
    np.testing.assert_allclose(got["ncc"], _ncc_np(a, b, ref_mask), atol=1e-5)


def test_value_range_matches_reference():
  a = _rand(13, low=-1.0, high=3.0)
  b = _rand(14, low=-1.5, high=2.5)
  mask = _rand_mask(15)
  p_ref = _soft_joint_np(a, b, mask, 8, -1.0, 2.0)
  got = _measures(a, b, mask, value_range=(-1.0, 2.0))
  np.testing.assert_allclose(got["joint"], p_ref, atol=1e-6)
  np.testing.assert_allclose(got["mi"], _mi_np(p_ref), atol=1e-5)
  np.testing.assert_allclose(got["entropy_a"], _h_np(p_ref.sum(1)), atol=1e-5)


@functools.partial(jax.jit, static_argnames=("bins_list",))
def _mi_for_bins(a, b, bins_list):
  return [similarity.mi(a, b, bins=bins) for bins in bins_list]


def test_soft_mi_approaches_hard_mi_as_bins_grow():
  # With few bins soft MI is far below hard MI: the cubic B-spline smears
  # every sample over 4 neighbouring bins, so the soft joint histogram is a
  # blurred (lower-resolution) version of the hard one, and blurring loses
  # mutual information.  The kernel spans 4 / (bins - 3) of the range, so the
  # gap shrinks as the bins get finer.  A 128×128 patch (16384 samples) keeps
  # the hard plug-in estimator's own upward bias (about bins² / 2N nats) small
  # up to 32 bins; at 64 bins that bias is comparable to the remaining smear,
  # so there the gap is only required to stay small.
  size = (128, 128)
  a = _camera_patch(100, 200, size)
  assert a.std() > 0.2  # a textured patch whose intensities span the range
  noise = np.random.default_rng(3).normal(0, 0.02, size)
  b = np.clip(_camera_patch(101, 201, size) + noise, 0, 1).astype(np.float32)
  bins_list = (8, 16, 32, 64)
  gaps = {}
  for bins, soft in zip(bins_list, _mi_for_bins(a, b, bins_list)):
    hard = _mi_np(_hard_joint_np(a, b, bins))
    assert float(soft) < hard
    gaps[bins] = (hard - float(soft)) / hard
  assert gaps[8] > gaps[16] > gaps[32], gaps
  assert gaps[8] > 0.3, gaps  # the smear matters at few bins ...
  assert gaps[32] < 0.15 and gaps[64] < 0.15, gaps  # ... and fades with many


# ---------------------------------------------------------------------------
# Properties of MI, NMI and NCC.

def test_self_information_identity_and_maximum():
  # Both sides are Parzen-windowed, so the soft joint histogram of (a, a) is
  # not diagonal: mi(a, a) = 2 H(a) - H(a, a) < H(a).
  a = _A
  self_ = _measures(a, a, _ONES_REAL)
  h_a = float(self_["entropy_a"])
  h_aa = _h_np(self_["joint"])
  np.testing.assert_allclose(self_["mi"], 2 * h_a - h_aa, atol=1e-5)
  assert self_["mi"] <= h_a
  assert h_aa > h_a  # strictly: the soft joint spreads off the diagonal
  for name, b in _PERTURBED.items():
    other = _measures(a, b, _ONES_REAL)
    assert self_["mi"] >= other["mi"], name
    assert self_["nmi"] >= other["nmi"], name
  reversed_ = _measures(a, 1 - a, _ONES_REAL)
  np.testing.assert_allclose(reversed_["nmi"], self_["nmi"], atol=1e-5)


def test_mi_invariant_to_intensity_reversal():
  # s(1 - v) = (bins - 1) - s(v): reversing either side mirrors the bins exactly.
  a, b, mask = _A, _PERTURBED["noisy"], _rand_mask(18, REAL)
  np.testing.assert_allclose(_measures(a, 1 - a, _ONES_REAL)["mi"],
                             _measures(a, a, _ONES_REAL)["mi"], atol=1e-5)
  ref = _measures(a, b, mask)["mi"]
  np.testing.assert_allclose(_measures(a, 1 - b, mask)["mi"], ref, atol=1e-5)
  np.testing.assert_allclose(_measures(1 - a, b, mask)["mi"], ref, atol=1e-5)


def test_mi_near_invariant_to_monotone_remap_unlike_ssd_and_ncc():
  # Fixed-range binning makes MI only nearly invariant, and only for a patch
  # whose intensities fill value_range: a gamma curve then moves samples
  # between bins without merging many of them.  (For a narrow-band patch a
  # gamma curve widens or narrows the occupied band and MI changes by
  # factors.)  So the patch is histogram-equalised, and 16 bins are used.
  a8 = np.ascontiguousarray(_CAMERA[300:300 + REAL[0], 250:250 + REAL[1]])
  a = (cv2.equalizeHist(a8) / 255.0).astype(np.float32)
  mi_aa = _measures(a, a, _ONES_REAL, bins=16)["mi"]
  for gamma in (0.5, 2.0):
    scores = _measures(a, a**gamma, _ONES_REAL, bins=16)
    assert abs(scores["mi"] / mi_aa - 1) < 0.15, gamma
    assert scores["ncc"] < 1 - 1e-3, gamma
    assert scores["ssd"] > 1e-2, gamma


@pytest.mark.parametrize("alpha, beta, expected", [(2.5, -0.3, 1.0), (0.3, 0.6, 1.0),
                                                    (-0.7, 0.9, -1.0)])
def test_ncc_of_affine_remap_is_its_sign(alpha, beta, expected):
  a = _A
  b = (alpha * a + beta).astype(np.float32)
  for mask in (_ONES_REAL, _rand_mask(19, REAL)):
    np.testing.assert_allclose(_measures(a, b, mask)["ncc"], expected, atol=1e-5)


def test_symmetry_and_ranges():
  pairs = [(_A, b) for b in _PERTURBED.values()] + [(_A, _A**3)]
  for i, (a, b) in enumerate(pairs):
    mask = _rand_mask(23 + i, REAL)
    ab = _measures(a, b, mask)
    ba = _measures(b, a, mask)
    for name in _MEASURES:
      np.testing.assert_allclose(ab[name], ba[name], rtol=1e-6, atol=1e-6, err_msg=name)
    np.testing.assert_allclose(ab["joint"], ba["joint"].T, atol=1e-7)
    assert ab["mi"] >= -1e-6
    assert -1e-6 <= ab["nmi"] <= 1 + 1e-6
    assert -1 - 1e-6 <= ab["ncc"] <= 1 + 1e-6
    assert ab["ssd"] >= 0


# ---------------------------------------------------------------------------
# Flat and degenerate windows.

@pytest.mark.parametrize("value", [0.3, 0.7])
def test_flat_window_scores(value):
  # A 48×48 window of 0.3 or 0.7 has a float32 mean that is off by more than
  # the flatness threshold 1e-6 · (1 + |mean|), a case the flatness test of
  # ncc must survive.
  flat = np.full(REAL, value, np.float32)
  cases = {"flat, textured": (flat, _A), "textured, flat": (_A, flat),
           "flat, flat": (flat, flat)}
  ncc = {}
  for case, (x, y) in cases.items():
    scores = _measures(x, y, _ONES_REAL)
    assert all(np.all(np.isfinite(v)) for v in scores.values()), (case, scores)
    assert abs(scores["mi"]) < 1e-6, (case, scores["mi"])
    assert abs(scores["nmi"]) < 1e-6, (case, scores["nmi"])
    ncc[case] = float(scores["ncc"])
  assert all(v == 0.0 for v in ncc.values()), ncc  # documented: a flat window scores 0
  # The entropy of a flat window is that of the kernel weights of its one
  # value: at most log 4 (the kernel spans 4 bins), below a textured window's.
  h_flat = scores["entropy_a"]
  np.testing.assert_allclose(h_flat, _h_np(_weights_np([value], 8)[0]), atol=1e-5)
  assert h_flat <= np.log(4) + 1e-6
  assert h_flat < _measures(_A, _A, _ONES_REAL)["entropy_a"]


@jax.jit
def _grads_wrt_b(a, b, mask):
  return {name: jax.grad(lambda x, f=getattr(similarity, name): f(a, x, mask))(b)
          for name in _MEASURES}


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
  if case.startswith("flat"):  # documented: a flat window scores 0 with zero gradient
    assert np.all(np.asarray(grads["ncc"]) == 0)
  if case == "narrow_band":
    assert np.any(np.asarray(grads["mi"]) != 0)


# ---------------------------------------------------------------------------
# Masks.

def test_all_masked_is_worst_score_without_nan():
  scores = _measures(_rand(26), _rand(27), np.zeros(RAND, bool))
  assert scores["ssd"] == np.inf
  for name in _SIMILARITIES:
    assert scores[name] == -np.inf, name
  assert np.all(scores["joint"] == 0)
  assert scores["entropy_a"] == 0 and scores["entropy_b"] == 0


@pytest.mark.parametrize("min_valid", [0.25, 0.5])
def test_min_valid_threshold(min_valid):
  a, b = _rand(28), _rand(29)
  n = RAND[0] * RAND[1]
  needed = int(np.ceil(min_valid * n))
  order = np.random.default_rng(30).permutation(n)
  for count in (needed - 1, needed):
    mask = np.zeros(n, bool)
    mask[order[:count]] = True
    scores = _measures(a, b, mask.reshape(RAND), min_valid=min_valid)
    if count < needed:
      assert scores["ssd"] == np.inf
      assert all(scores[k] == -np.inf for k in _SIMILARITIES), scores
    else:
      assert all(np.isfinite(scores[k]) for k in _MEASURES), (min_valid, scores)


def test_masked_out_pixels_do_not_matter():
  a, b, mask = _rand(31), _rand(32), _rand_mask(33, p_valid=0.6)
  garbage = np.random.default_rng(34).uniform(-50, 50, RAND).astype(np.float32)
  ref = _measures(a, b, mask)
  got = _measures(np.where(mask, a, garbage), np.where(mask, b, garbage[::-1]), mask)
  for name in ref:
    np.testing.assert_allclose(got[name], ref[name], rtol=1e-5, atol=1e-6, err_msg=name)


def test_float_mask_of_ones_equals_no_mask():
  a, b = _rand(35), _rand(36)
  ref = _measures(a, b)
  got = _measures(a, b, np.ones(RAND, np.float32))
  for name in ref:
    np.testing.assert_allclose(got[name], ref[name], rtol=1e-6, atol=1e-7, err_msg=name)


# ---------------------------------------------------------------------------
# Broadcasting, SoftBins, jit.

# More patches than the library's histogram chunk (32), and not a multiple of it.
_N = 40


@jax.jit
def _binned_vs_unbinned(template, patches, masks):
  # The bins come from the SoftBins (16) although mi, nmi and
  # joint_histogram default to 8.
  sb = similarity.soft_bins(template, bins=16)
  binned = (similarity.mi(sb, patches, masks), similarity.nmi(sb, patches, masks),
            similarity.joint_histogram(sb, patches, masks))
  unbinned = (similarity.mi(template, patches, masks, bins=16),
              similarity.nmi(template, patches, masks, bins=16),
              similarity.joint_histogram(template, patches, masks, bins=16))
  return sb.weights, binned, unbinned


def test_swarm_broadcast_equals_loop():
  t = _rand(40)
  patches = _rand(41, (_N,) + RAND)
  masks = _rand_mask(42, (_N,) + RAND)
  swarm = _measures(t[None], patches, masks)
  loop = [_measures(t, p, m) for p, m in zip(patches, masks)]
  for name in _MEASURES + ("joint",):
    assert swarm[name].shape == (_N,) + loop[0][name].shape, name
    np.testing.assert_allclose(swarm[name], [s[name] for s in loop], rtol=1e-5, atol=1e-6,
                               err_msg=name)
  for i in (0, 31, 32, _N - 1):  # both sides of the chunk boundary
    np.testing.assert_allclose(swarm["joint"][i], _soft_joint_np(t, patches[i], masks[i]),
                               atol=1e-6)
  # The template binned ahead of time gives the same scores.
  weights, binned, unbinned = _binned_vs_unbinned(t, patches, masks)
  assert weights.shape == RAND + (16,)
  np.testing.assert_allclose(weights, _weights_np(t, 16).reshape(RAND + (16,)), atol=1e-6)
  for got, ref in zip(binned, unbinned):
    assert got.shape == ref.shape
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6)


def test_leading_dims_broadcast():
  mask = _rand_mask(46)
  b = _rand(43)
  a = _rand(44, (2, 3) + RAND)
  a_col = _rand(45, (2, 1) + RAND)
  b_row = _rand(47, (3,) + RAND)
  grid = _measures(a, b, mask)
  outer = _measures(a_col, b_row, mask)
  for name in _MEASURES:
    assert grid[name].shape == (2, 3) and outer[name].shape == (2, 3), name
  assert grid["joint"].shape == (2, 3, 8, 8)
  for i in range(2):
    for j in range(3):
      one = _measures(a[i, j], b, mask)
      other = _measures(a_col[i, 0], b_row[j], mask)
      for name in _MEASURES + ("joint",):
        np.testing.assert_allclose(grid[name][i, j], one[name], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(outer[name][i, j], other[name], rtol=1e-5, atol=1e-6)


def test_jit_matches_eager():
  a, b, mask = _rand(48), _rand(49), _rand_mask(50)
  jitted = _measures(a, b, mask)
  for name in _MEASURES:
    eager = getattr(similarity, name)(a, b, mask)
    # mi = H(a) + H(b) - H(a, b) cancels entropies of about 2 nats in float32.
    np.testing.assert_allclose(jitted[name], eager, rtol=1e-6, atol=2e-6, err_msg=name)


_TRACES = []


@jax.jit
def _counted(a, b, mask):
  _TRACES.append(1)
  return similarity.mi(a, b, mask), similarity.ncc(a, b, mask)


def test_no_retrace_for_new_data_of_same_shape():
  _counted(_rand(51), _rand(52), _rand_mask(53))
  traces = len(_TRACES)
  assert traces >= 1
  a, b, mask = _rand(54), _rand(55), _rand_mask(56)
  mi, ncc = _counted(a, b, mask)
  assert len(_TRACES) == traces
  ref = _measures(a, b, mask)
  np.testing.assert_allclose(mi, ref["mi"], rtol=1e-6, atol=1e-6)
  np.testing.assert_allclose(ncc, ref["ncc"], rtol=1e-6, atol=1e-6)


# ---------------------------------------------------------------------------
# Gradients against finite differences (float64).

def test_gradients_match_finite_differences():
  # Values stay inside (0.05, 0.95): outside value_range the intensities are
  # clipped, with a kink at the range ends that finite differences straddle.
  with jax.enable_x64(True):
    a = _rand(57, dtype=np.float64)
    b = _rand(58, dtype=np.float64)
    mask = _rand_mask(59)
    assert not mask.all()

    @jax.jit
    def f(x, y):
      return (similarity.ssd(x, y, mask), similarity.ncc(x, y, mask),
              similarity.mi(x, y, mask, bins=16), similarity.nmi(x, y, mask))

    assert all(v.dtype == jnp.float64 for v in f(a, b))
    # Rev-mode derivatives w.r.t. both a and b in one check.
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
    _expect(ValueError, r"\bmask\b.*\(5, 5\)", f, good, good, np.ones((5, 5), bool))
  for f in (similarity.ssd, similarity.ncc, similarity.mi, similarity.nmi):
    for min_valid in (0, 1.5):
      _expect(ValueError, rf"\bmin_valid\b.*{min_valid}", f, good, good, min_valid=min_valid)
  for f in (similarity.mi, similarity.nmi, similarity.joint_histogram, similarity.entropy,
            similarity.soft_bins):
    args = (good,) if f in (similarity.entropy, similarity.soft_bins) else (good, good)
    for bins in (3, 8.5):
      _expect(ValueError, rf"\bbins\b.*{bins}", f, *args, bins=bins)
    _expect(ValueError, r"\bvalue_range\b.*\(1, 0\)", f, *args, value_range=(1, 0))
  _expect(TypeError, r"^a\b.*int32", similarity.entropy, ints)
  _expect(TypeError, r"^a\b.*int32", similarity.soft_bins, ints)
  _expect(ValueError, r"^a\b.*\(5,\)", similarity.entropy, np.zeros(5, np.float32))


def test_template_self_losses_match_the_measures():
  # The template's loss against itself is computed once on the host
  # (`template.self_losses`, quality's scale); it must equal the device measures.
  from jaxpso._src import template
  a = _camera_patch(100, 200)
  value_range = template.value_range(a.reshape(-1).astype(np.float64))
  mi, ncc, ssd_scale = template.self_losses(a.reshape(-1).astype(np.float64), 8, value_range)
  got = _measures(a, a, bins=8, value_range=tuple(float(v) for v in value_range))
  np.testing.assert_allclose(-mi, got["mi"], rtol=1e-5)
  assert ncc == -1.0 and got["ncc"] == pytest.approx(1.0, abs=1e-5)
  np.testing.assert_allclose(ssd_scale, a.var(), rtol=1e-5)


def test_mi_adapted_template_is_the_least_squares_remap_of_the_template():
  # MI's Gauss–Newton matches the image against T̃ = X·c, X the template's
  # bin weights.  Fitted by (ridged) least squares, T̃ follows a smooth
  # intensity remap far closer than per-bin mean intensities did, which
  # pulled the fixed point of low-contrast templates off the alignment
  # (measured: RMS residual 0.0054 vs 0.018 under gamma 0.5).
  from jaxpso._src import measures, refine, template
  a = _camera_patch(100, 200).reshape(-1).astype(np.float64)
  value_range = template.value_range(a)
  x = np.asarray(measures.bin_weights(jnp.asarray(a, jnp.float32), 16, jnp.asarray(value_range),
                                      True), np.float64)  # (n, 16)
  image = np.sqrt(np.clip(a, 0, None))  # gamma 0.5
  remap = template.remap(a, 16, value_range)
  sums, counts = x.T @ image, x.sum(0)

  def residual(c):
    return np.sqrt(np.mean((image - x @ np.asarray(c, np.float64)) ** 2))

  fitted = refine.adapted_coefficients("mi", None, (jnp.asarray(sums, jnp.float32),
                                                    jnp.asarray(counts, jnp.float32), remap, a.size))
  per_bin_means = (sums + image.mean()) / (counts + 1.0)
  assert residual(fitted) < 0.5 * residual(per_bin_means), (residual(fitted), residual(per_bin_means))
  # The ridged least squares in float64: T̃ within 1e-3 of it.
  ridge = template.REMAP_RIDGE
  exact = np.linalg.solve(x.T @ x + ridge * np.eye(16), sums + ridge * image.mean())
  np.testing.assert_allclose(x @ np.asarray(fitted, np.float64), x @ exact, atol=1e-3)
  # A third of the points invalid (the darkest): the set's inverse is not the
  # valid points', and T̃ falls back to each bin's mean intensity.
  valid = a > np.quantile(a, 1 / 3)
  sums, counts = x[valid].T @ image[valid], x[valid].sum(0)
  fallback = refine.adapted_coefficients("mi", None, (jnp.asarray(sums, jnp.float32),
                                                      jnp.asarray(counts, jnp.float32), remap,
                                                      a.size))
  means = (sums + sums.sum() / counts.sum()) / (counts + 1.0)
  np.testing.assert_allclose(fallback, means, rtol=1e-5)


def test_mi_first_phase_fits_a_gain_and_bias_in_the_template_bins():
  # MI's first Gauss–Newton phase: T̃ = X·c with c = a·k + b over the bin
  # indices k, the least-squares gain and bias of the image against the
  # template (in bin units), from the per-bin sums alone.
  from jaxpso._src import measures, refine, template
  a = _camera_patch(100, 200).reshape(-1).astype(np.float64)
  value_range = template.value_range(a)
  x = np.asarray(measures.bin_weights(jnp.asarray(a, jnp.float32), 16, jnp.asarray(value_range),
                                      True), np.float64)  # (n, 16)
  remap = template.remap(a, 16, value_range)
  s = x @ np.arange(16.0)  # the template in bin units: the bins reproduce linear functions
  for image in (0.7 * a + 0.2, 1.0 - a, np.sqrt(np.clip(a, 0, None))):
    per_bin = (jnp.asarray(x.T @ image, jnp.float32), jnp.asarray(x.sum(0), jnp.float32), remap,
               a.size)
    c = np.asarray(refine.adapted_coefficients("mi", None, per_bin, linear=True), np.float64)
    gain, bias = np.polyfit(s, image, 1)
    np.testing.assert_allclose(c, gain * np.arange(16.0) + bias, atol=2e-4)
  # A flat template: no gain, T̃ the image's mean.
  flat = np.full_like(a, 0.5)
  x = np.asarray(measures.bin_weights(jnp.asarray(flat, jnp.float32), 16, jnp.asarray(value_range),
                                      True), np.float64)
  per_bin = (jnp.asarray(x.T @ a, jnp.float32), jnp.asarray(x.sum(0), jnp.float32), remap, a.size)
  c = np.asarray(refine.adapted_coefficients("mi", None, per_bin, linear=True))
  np.testing.assert_allclose(c, a.mean(), atol=1e-4)
