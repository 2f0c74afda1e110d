"""Similarity measures between a template and warped patches: SSD, ZNCC, MI, NMI.

Every measure takes `a, b` of shape (..., h, w), broadcasting over the leading
axes, and an optional validity `mask` (from `warp_image`), so a whole swarm is
scored in one call: `mi(template[None], patches, mask)`.  Sums run over the
valid pixels only.  Where fewer than `min_valid` of the window's pixels are
valid the score is the worst possible (+inf for `ssd`, -inf for the others),
never NaN.  `ssd` is an error (lower is better); the others are similarities
(higher is better).  The optimizer applies the sign in one place.

Mutual information uses soft-binned (Parzen-window) histograms with the cubic
B-spline kernel, as in Mattes et al. 2003 and Dame & Marchand 2012: an
intensity v maps to the bin coordinate s = 1 + (v - lo) / (hi - lo) · (bins - 3)
in [1, bins - 2] and adds β₃(s - j) to bin j; since the kernel spans 4 bins the
weights of every pixel sum to exactly 1 and the histogram is a smooth
function of the intensities, so MI has exact, finite gradients.  Intensities
outside `value_range` are counted in the edge bins (their gradient is zero).

The joint histogram of the template (fixed during a frame) against n patches
is one matrix product of the template's (h·w, bins) weights, computed once,
with the patches' (bins, h·w) weights, chunk by chunk of patches.  `soft_bins(template)` does the
template side ahead of time; pass its result as `a`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxpso._src import checks

DEFAULT_BINS = 8
DEFAULT_MIN_VALID = 0.25


class SoftBins(NamedTuple):
  """The template side of a soft joint histogram, binned once.

  Attributes:
    weights: (..., h, w, bins) cubic B-spline weights of every pixel.
    lo: lower end of the intensity range the patches are binned over
      (`soft_bins` bins the template over the same range; a tracker may bin
      the template over its own range and the image over another).
    hi: upper end of that range.
  """
  weights: jax.Array
  lo: float
  hi: float


def _bspline3(d):
  """Centred cubic B-spline β₃(d), support (-2, 2), written branch-free."""
  a = jnp.abs(d)
  outer = jnp.maximum(2.0 - a, 0.0)
  inner = jnp.maximum(1.0 - a, 0.0)
  return (outer * outer * outer - 4.0 * inner * inner * inner) * (1.0 / 6.0)


def _parzen(x, bins: int, lo, hi):
  """(..., ) intensities -> (..., bins) cubic B-spline weights summing to 1."""
  s = 1.0 + (jnp.clip(x, lo, hi) - lo) * ((bins - 3) / (hi - lo))
  return _bspline3(s[..., None] - jnp.arange(bins, dtype=s.dtype))


def _check_bins(bins) -> int:
  if isinstance(bins, bool) or not isinstance(bins, int) or bins < 4:
    raise ValueError(
        f"bins must be an int >= 4 (the cubic B-spline window spans 4 bins), got {bins!r}")
  return bins


def _check_range(value_range) -> tuple:
  """(lo, hi) as floats; traced values (inside jit) pass unchecked."""
  if isinstance(value_range, (tuple, list)) and len(value_range) == 2 and any(
      isinstance(v, jax.core.Tracer) for v in value_range):
    return tuple(value_range)
  try:
    lo, hi = (float(v) for v in value_range)
  except (TypeError, ValueError):
    raise ValueError(f"value_range must be a pair (lo, hi), got {value_range!r}") from None
  if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
    raise ValueError(f"value_range must be finite with lo < hi, got {value_range!r}")
  return lo, hi


def _check_min_valid(min_valid) -> float:
  try:
    fraction = float(min_valid)
  except (TypeError, ValueError):
    fraction = math.nan
  if not 0.0 < fraction <= 1.0:
    raise ValueError(f"min_valid must be a fraction in (0, 1], got {min_valid!r}")
  return fraction


def _check_window(x, name: str) -> jax.Array:
  x = checks.as_float_array(x, name)
  checks.check_min_rank(x, 2, name, "(..., h, w)")
  checks.check_finite_if_concrete(x, name)
  return x


def _check_pair(a, b, mask):
  """Validates `a, b, mask` and returns them with the mask as a float array."""
  b = _check_window(b, "b")
  a_shape = a.weights.shape[:-1] if isinstance(a, SoftBins) else _check_window(a, "a").shape
  try:
    shape = jnp.broadcast_shapes(a_shape, b.shape)
  except ValueError:
    raise ValueError(
        f"a and b must broadcast over their leading axes and share (h, w),"
        f" got shapes {a_shape} and {b.shape}") from None
  if shape[-2:] != b.shape[-2:] or shape[-2:] != a_shape[-2:]:
    raise ValueError(
        f"a and b must have the same window (h, w), got shapes {a_shape} and {b.shape}")
  if mask is None:
    mask = jnp.ones(shape[-2:], b.dtype)
  else:
    mask = jnp.asarray(mask)
    if mask.dtype != jnp.bool_ and not jnp.issubdtype(mask.dtype, jnp.floating):
      raise TypeError(f"mask must be bool or float, got dtype {mask.dtype}")
    checks.check_finite_if_concrete(mask, "mask")
    try:
      jnp.broadcast_shapes(mask.shape, shape)
    except ValueError:
      raise ValueError(
          f"mask of shape {mask.shape} does not broadcast with a, b of shape {shape}") from None
    mask = mask.astype(b.dtype)
  return a, b, mask


def _enough(count, window_size: int, min_valid: float):
  """True where the number of valid pixels reaches `min_valid` of the window."""
  return count >= max(1.0, min_valid * window_size)


def _masked_pair(a, b, mask, min_valid):
  """Checked `a, b`, the mask broadcast to their shape, its count and the
  enough-valid-pixels flag (...)."""
  a, b, mask = _check_pair(a, b, mask)
  min_valid = _check_min_valid(min_valid)
  mask = jnp.broadcast_to(mask, jnp.broadcast_shapes(a.shape, b.shape, mask.shape))
  count = jnp.sum(mask, axis=(-2, -1))
  return a, b, mask, count, _enough(count, b.shape[-1] * b.shape[-2], min_valid)


def ssd(a, b, mask=None, *, min_valid: float = DEFAULT_MIN_VALID) -> jax.Array:
  """Sum of squared differences per valid pixel (an error: lower is better).

  ssd = Σ m (a - b)² / Σ m, the paper's eq. 6 divided by the number of valid
  pixels so that candidates with different masks compare fairly.

  Args:
    a: (..., h, w) template.
    b: (..., h, w) patches; leading axes broadcast with `a`.
    mask: optional (..., h, w) bool or float validity weights.
    min_valid: fraction of the h·w pixels that must be valid.

  Returns:
    (...) errors; +inf where too few pixels are valid.

  Examples:
    >>> import jax.numpy as jnp
    >>> from jaxpso import similarity
    >>> float(similarity.ssd(jnp.zeros((2, 2)), jnp.full((2, 2), 0.5)))
    0.25
  """
  a, b, mask, count, ok = _masked_pair(a, b, mask, min_valid)
  total = jnp.sum(mask * (a - b) ** 2, axis=(-2, -1))
  return jnp.where(ok, total / jnp.where(ok, count, 1.0), jnp.inf)


def ncc(a, b, mask=None, *, min_valid: float = DEFAULT_MIN_VALID) -> jax.Array:
  """Zero-mean normalised cross-correlation (ZNCC) over the valid pixels.

  ncc = Σ m (a - μa)(b - μb) / sqrt(Σ m (a - μa)² · Σ m (b - μb)²), in [-1, 1].
  The paper's eq. 7 is ill-formed; this is the standard ZNCC.  A flat window
  (standard deviation below 1e-6 · (1 + |mean|)) has no defined correlation
  and scores 0, with zero gradient.

  Args:
    a: (..., h, w) template.
    b: (..., h, w) patches; leading axes broadcast with `a`.
    mask: optional (..., h, w) bool or float validity weights.
    min_valid: fraction of the h·w pixels that must be valid.

  Returns:
    (...) correlations; -inf where too few pixels are valid.
  """
  a, b, mask, count, ok = _masked_pair(a, b, mask, min_valid)
  n = jnp.where(ok, count, 1.0)
  mean_a = jnp.sum(mask * a, axis=(-2, -1)) / n
  mean_b = jnp.sum(mask * b, axis=(-2, -1)) / n
  ca = a - mean_a[..., None, None]
  cb = b - mean_b[..., None, None]
  # Corrected two-pass sums: subtracting (Σ m c)² / n cancels the rounding
  # error of the float mean, so a flat window has exactly zero variance.
  sum_a = jnp.sum(mask * ca, axis=(-2, -1))
  sum_b = jnp.sum(mask * cb, axis=(-2, -1))
  var_a = jnp.sum(mask * ca * ca, axis=(-2, -1)) - sum_a * sum_a / n
  var_b = jnp.sum(mask * cb * cb, axis=(-2, -1)) - sum_b * sum_b / n
  cov = jnp.sum(mask * ca * cb, axis=(-2, -1)) - sum_a * sum_b / n
  textured = ((var_a > n * (1e-6 * (1 + jnp.abs(mean_a))) ** 2)
              & (var_b > n * (1e-6 * (1 + jnp.abs(mean_b))) ** 2))
  denominator = jnp.sqrt(jnp.where(textured, var_a * var_b, 1.0))
  score = jnp.where(textured, cov / denominator, 0.0)
  return jnp.where(ok, score, -jnp.inf)


def soft_bins(a, *, bins: int = DEFAULT_BINS, value_range=(0.0, 1.0)) -> SoftBins:
  """Bins a template once, for repeated `mi`/`nmi` calls against many patches.

  Args:
    a: (..., h, w) template intensities.
    bins: number of histogram bins (>= 4).
    value_range: (lo, hi) intensity range mapped onto the bins.

  Returns:
    `SoftBins` with (..., h, w, bins) weights, each pixel's summing to 1.
  """
  a = _check_window(a, "a")
  bins = _check_bins(bins)
  lo, hi = _check_range(value_range)
  return SoftBins(_parzen(a, bins, lo, hi), lo, hi)


def joint_histogram(a, b, mask=None, *, bins: int = DEFAULT_BINS,
                    value_range=(0.0, 1.0)) -> jax.Array:
  """Soft joint intensity histogram of `a` (rows) and `b` (columns).

  P(i, j) = Σ_p m_p β₃(s(a_p) - i) β₃(s(b_p) - j) / Σ_p m_p.

  Args:
    a: (..., h, w) template, or its `soft_bins`.
    b: (..., h, w) patches; leading axes broadcast with `a`.
    mask: optional (..., h, w) bool or float validity weights.
    bins: number of bins (taken from `a` when it is `SoftBins`).
    value_range: (lo, hi) intensity range (taken from `a` when it is `SoftBins`).

  Returns:
    (..., bins, bins) probabilities summing to 1 (all zero where no pixel is valid).
  """
  a, b, mask = _check_pair(a, b, mask)
  if not isinstance(a, SoftBins):
    a = soft_bins(a, bins=bins, value_range=value_range)
  counts = _joint_counts(a, b, mask)
  total = jnp.sum(counts, axis=(-2, -1), keepdims=True)
  return counts / jnp.where(total > 0, total, 1.0)


# Patches are histogrammed this many at a time, so the (chunk, bins, h·w)
# weights stay small and their buffer is reused (benchmarks/similarity.py).
_CHUNK = 16


def _joint_counts(a: SoftBins, b, mask):
  """Unnormalised joint histogram (..., bins, bins), a rows, b columns.

  One template against n patches (the swarm case) is a single matrix product
  per chunk of patches: the patches' weights, laid out bin-major as
  (chunk·bins, h·w) so that the B-spline evaluation runs along the long pixel
  axis, times the template's (h·w, bins) weights binned once.
  """
  bins = a.weights.shape[-1]
  lead = jnp.broadcast_shapes(a.weights.shape[:-3], b.shape[:-2], mask.shape[:-2])
  window = b.shape[-2:]
  if any(s != 1 for s in a.weights.shape[:-3]):
    wa = jnp.broadcast_to(a.weights, lead + a.weights.shape[-3:])
    wb = _parzen(b, bins, a.lo, a.hi) * mask[..., None]
    return jnp.einsum("...hwi,...hwj->...ij", wa, jnp.broadcast_to(wb, wa.shape))
  wa = a.weights.reshape(-1, bins)
  grid = jnp.arange(bins, dtype=b.dtype)[:, None]
  scale = (bins - 3) / (a.hi - a.lo)

  def counts(b_row, m_row):  # (h·w,) -> (bins, bins)
    s = 1.0 + (jnp.clip(b_row, a.lo, a.hi) - a.lo) * scale
    wb = _bspline3(s - grid) * m_row
    return (wb @ wa).T

  flat_b = jnp.broadcast_to(b, lead + window).reshape(-1, window[0] * window[1])
  flat_m = jnp.broadcast_to(mask, lead + window).reshape(flat_b.shape)
  if flat_b.shape[0] <= _CHUNK:
    joint = jax.vmap(counts)(flat_b, flat_m)
  else:
    joint = jax.lax.map(lambda xs: counts(*xs), (flat_b, flat_m), batch_size=_CHUNK)
  return joint.reshape(lead + (bins, bins))


def _neg_entropy(p, axes):
  """Σ p log p over `axes`, with 0 log 0 = 0 and finite gradients at p = 0."""
  positive = p > 0
  return jnp.sum(jnp.where(positive, p * jnp.log(jnp.where(positive, p, 1.0)), 0.0),
                 axis=axes)


def entropies(counts):
  """Marginal and joint entropies (nats) of joint histogram counts (..., bins, bins), rows a.

  All zero where the counts are (no valid pixel).
  """
  total = jnp.sum(counts, axis=(-2, -1))
  # × the reciprocal, not ÷: one rounding in every program (batching.each)
  p = counts * (1.0 / jnp.where(total > 0, total, 1.0))[..., None, None]
  h_a = -_neg_entropy(jnp.sum(p, axis=-1), -1)
  h_b = -_neg_entropy(jnp.sum(p, axis=-2), -1)
  h_ab = -_neg_entropy(p, (-2, -1))
  return h_a, h_b, h_ab


def _entropies(a, b, mask, min_valid):
  """Marginal and joint entropies (nats) and the enough-valid-pixels flag."""
  counts = _joint_counts(a, b, mask)
  ok = _enough(jnp.sum(counts, axis=(-2, -1)), b.shape[-1] * b.shape[-2], min_valid)
  return entropies(counts) + (ok,)


def _prepare_mi(a, b, mask, bins, value_range, min_valid):
  a, b, mask = _check_pair(a, b, mask)
  min_valid = _check_min_valid(min_valid)
  if not isinstance(a, SoftBins):
    a = soft_bins(a, bins=bins, value_range=value_range)
  return _entropies(a, b, mask, min_valid)


def mi(a, b, mask=None, *, bins: int = DEFAULT_BINS, value_range=(0.0, 1.0),
       min_valid: float = DEFAULT_MIN_VALID) -> jax.Array:
  """Shannon mutual information of soft-binned intensities, in nats.

  MI = H(a) + H(b) - H(a, b) with H(p) = -Σ p log p over the soft marginal
  and joint histograms (paper eq. 8).  MI >= 0, = 0 for independent or flat
  windows, invariant to exchanging a and b and to reversing the intensities
  (v → lo + hi - v), and near-invariant to monotone intensity changes.

  Args:
    a: (..., h, w) template, or its `soft_bins` (then `bins` and
      `value_range` come from it).
    b: (..., h, w) patches; leading axes broadcast with `a`.
    mask: optional (..., h, w) bool or float validity weights.
    bins: number of histogram bins (>= 4).
    value_range: (lo, hi) intensity range mapped onto the bins.
    min_valid: fraction of the h·w pixels that must be valid.

  Returns:
    (...) mutual information; -inf where too few pixels are valid.

  Examples:
    >>> import jax
    >>> from jaxpso import similarity
    >>> a = jax.random.uniform(jax.random.key(0), (32, 32))
    >>> bool(similarity.mi(a, 1 - a) > similarity.mi(a, a[::-1]))
    True
  """
  h_a, h_b, h_ab, ok = _prepare_mi(a, b, mask, bins, value_range, min_valid)
  return jnp.where(ok, h_a + h_b - h_ab, -jnp.inf)


def nmi(a, b, mask=None, *, bins: int = DEFAULT_BINS, value_range=(0.0, 1.0),
        min_valid: float = DEFAULT_MIN_VALID) -> jax.Array:
  """Normalised mutual information 2 MI / (H(a) + H(b)), in [0, 1].

  The symmetric uncertainty coefficient: 1 when one window determines the
  other through a hard histogram, 0 for independent windows, and 0 when both
  windows are flat (H(a) + H(b) = 0).  Arguments as for `mi`.

  Returns:
    (...) normalised mutual information; -inf where too few pixels are valid.
  """
  h_a, h_b, h_ab, ok = _prepare_mi(a, b, mask, bins, value_range, min_valid)
  marginal = h_a + h_b
  informative = marginal > 1e-12
  score = jnp.where(informative, 2 * (marginal - h_ab) / jnp.where(informative, marginal, 1.0),
                    0.0)
  return jnp.where(ok, score, -jnp.inf)


def entropy(a, mask=None, *, bins: int = DEFAULT_BINS, value_range=(0.0, 1.0)) -> jax.Array:
  """Shannon entropy of the soft (cubic B-spline) histogram of `a`, in nats.

  Args:
    a: (..., h, w) intensities.
    mask: optional (..., h, w) bool or float validity weights.
    bins: number of histogram bins (>= 4).
    value_range: (lo, hi) intensity range mapped onto the bins.

  Returns:
    (...) entropies (0 where no pixel is valid).
  """
  a = _check_window(a, "a")
  _, _, mask = _check_pair(a, a, mask)
  bins = _check_bins(bins)
  lo, hi = _check_range(value_range)
  counts = jnp.sum(_parzen(a, bins, lo, hi) * mask[..., None], axis=(-3, -2))
  total = jnp.sum(counts, axis=-1, keepdims=True)
  return -_neg_entropy(counts / jnp.where(total > 0, total, 1.0), -1)
