"""The tracker's similarities as sums over chunks of template points.

A prepared template is a set of points with values (`jaxpso._src.template`);
a candidate warp samples the image at them.  Every similarity is a function
of a few sums over the valid points (its sufficient statistics):

* "ssd": Σm, Σm (a − b)²;
* "ncc": Σm, Σm a, Σm b, Σm a², Σm b², Σm ab, with a and b shifted by one
  reference value each, so that a flat patch has exactly zero variance;
* "mi": the soft joint histogram Σm β(a) β(b)ᵀ of cubic B-spline bin
  weights (`jaxpso.similarity`), the template binned over its own
  intensity range and the image over the image's.

So a set of any size is scored chunk by chunk in a loop whose trip count is
data (`over_chunks`): the compiled program does not depend on the
template's size, and its cost follows the number of points.  The losses
equal `jaxpso.similarity`'s on the same pixels (minimised: SSD, −NCC, −MI),
with the worst value (+inf) where fewer than `min_valid` of the set's
points are valid.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from jaxpso._src import similarity


class Measure(NamedTuple):
  """Static description of a loss: the similarity's name and MI's bins."""
  name: str
  bins: int


class Ranges(NamedTuple):
  """MI's binning ranges, (2,) each: the template's and the image's."""
  template: jax.Array
  image: jax.Array


def empty(measure: Measure, lead: tuple, shift_a=None, shift_b=None):
  """Zero statistics with leading axes `lead`.

  For "ncc", `shift_a` () and `shift_b` (lead) are the reference values
  subtracted from a and b before summing.
  """
  if measure.name == "mi":
    return jnp.zeros(lead + (measure.bins, measure.bins), jnp.float32)
  if measure.name == "ncc":
    return (jnp.zeros(lead + (6,), jnp.float32), jnp.asarray(shift_a, jnp.float32),
            jnp.broadcast_to(jnp.asarray(shift_b, jnp.float32), lead))
  return jnp.zeros(lead + (2,), jnp.float32)


def bin_weights(values, bins: int, value_range, bins_last: bool = False):
  """(…, bins, c) cubic B-spline weights of (…, c) values over value_range (2,), bin-major.

  With `bins_last`, (…, c, bins): computed in that layout, not transposed
  (a transpose became a copy of the whole array).
  """
  lo, hi = value_range[0], value_range[1]
  s = 1.0 + (jnp.clip(values, lo, hi) - lo) * ((bins - 3) / (hi - lo))
  centres = jnp.arange(bins, dtype=values.dtype)
  if bins_last:
    return similarity._bspline3(s[..., :, None] - centres)
  return similarity._bspline3(s[..., None, :] - centres[:, None])


def add(measure: Measure, stats, a, b, mask, ranges: Ranges | None = None, a_bins=None):
  """`stats` plus the chunk's sums: template values a (c,), patches b (…, c), mask (…, c).

  For "mi", `a_bins` (c, bins) are a's `bin_weights` (bins last: the CPU's
  product of (k, c) by (c, k') is the fast one) where already computed.
  """
  m = mask.astype(b.dtype)
  if measure.name == "mi":
    wa = bin_weights(a, measure.bins, ranges.template, True) if a_bins is None else a_bins
    wb = bin_weights(b, measure.bins, ranges.image) * m[..., None, :]
    # Materialised: fused into the product, the weights were recomputed for
    # every one of its outputs.
    wa, wb = jax.lax.optimization_barrier((wa, wb))
    return stats + jnp.swapaxes(wb @ wa, -1, -2)
  if measure.name == "ncc":
    sums, shift_a, shift_b = stats
    da, db = a - shift_a, (b - shift_b[..., None]) * m
    ma = m * da
    chunk = jnp.stack([jnp.sum(m, -1), jnp.sum(ma, -1), jnp.sum(db, -1), jnp.sum(ma * da, -1),
                       jnp.sum(db * db, -1), jnp.sum(ma * db, -1)], axis=-1)
    return sums + chunk, shift_a, shift_b
  d = (a - b) * m
  return stats + jnp.stack([jnp.sum(m, -1), jnp.sum(d * d, -1)], axis=-1)


def add_with_own(stats, own, a_bins, b, mask, measure: Measure, image_range):
  """MI's joint histograms of a chunk against the template and against itself, in one product.

  a_bins (c, bins): the template values' `bin_weights`, bins last; b (c,)
  the patch, binned over image_range (2,); mask (c,).  Returns `stats` and
  `own` plus the chunk's Σm β(a) β(b)ᵀ and Σm β(b) β(b)ᵀ: one (bins, c) by
  (c, 2·bins) product took half the time of the two.
  """
  # b is binned in both layouts: taking wb.T instead was slower (a layout copy).
  wb = bin_weights(b, measure.bins, image_range)
  right = jnp.concatenate([a_bins, bin_weights(b, measure.bins, image_range, True)], axis=-1)
  left, right = jax.lax.optimization_barrier((wb * mask.astype(b.dtype)[None], right))
  # The barrier keeps XLA from folding the transpose into the product (a
  # transposed operand made it several times slower).
  both = jax.lax.optimization_barrier(left @ right)
  return stats + both[:, :measure.bins].T, own + both[:, measure.bins:]


def valid_count(measure: Measure, stats):
  """(…) number of valid points summed in `stats`."""
  if measure.name == "mi":
    return jnp.sum(stats, axis=(-2, -1))
  if measure.name == "ncc":
    return stats[0][..., 0]
  return stats[..., 0]


def ncc_moments(stats):
  """(n, mean_a, mean_b, var_a, var_b, cov) of "ncc" statistics; variances and covariance summed, not averaged."""
  sums, shift_a, shift_b = stats
  n, sa, sb, saa, sbb, sab = (sums[..., i] for i in range(6))
  count = jnp.maximum(n, 1.0)
  return (n, shift_a + sa / count, shift_b + sb / count, saa - sa * sa / count,
          sbb - sb * sb / count, sab - sa * sb / count)


def loss(measure: Measure, stats, count, min_valid):
  """(…) loss to minimise: SSD, −ZNCC or −MI; +inf where under `min_valid` of `count` points are valid."""
  enough = valid_count(measure, stats) >= jnp.maximum(1.0, min_valid * count)
  if measure.name == "mi":
    h_a, h_b, h_ab = similarity.entropies(stats)
    value = -(h_a + h_b - h_ab)
  elif measure.name == "ncc":
    n, mean_a, mean_b, var_a, var_b, cov = ncc_moments(stats)
    textured = ((var_a > n * (1e-6 * (1 + jnp.abs(mean_a))) ** 2)
                & (var_b > n * (1e-6 * (1 + jnp.abs(mean_b))) ** 2))
    value = -jnp.where(textured, cov / jnp.sqrt(jnp.where(textured, var_a * var_b, 1.0)), 0.0)
  else:
    value = stats[..., 1] / jnp.maximum(stats[..., 0], 1.0)
  return jnp.where(enough, value, jnp.inf)


def over_chunks(count, chunk: int, body: Callable, state, capacity: int | None = None):
  """`state ← body(start, state)` for start = 0, chunk, 2·chunk, … below `count` (a traced int).

  When `count` is known to be at most `capacity` <= `chunk`, one call, no loop.
  """
  if capacity is not None and capacity <= chunk:
    return body(jnp.zeros([], jnp.int32), state)
  trips = (count + chunk - 1) // chunk
  return jax.lax.fori_loop(0, trips, lambda i, s: body(i * chunk, s), state)


# MI bins intensities over the range between these quantiles of the template
# (and, for the image, the union of that and the same range of the image where
# the start puts the template), widened by _RANGE_MARGIN of its span each way
# and at least _MIN_SPAN wide, so that a low-contrast template fills the bins
# instead of two or three of them.  The
# quantiles are read off a histogram of _RANGE_HISTOGRAM bins between the
# extremes (to 1/1000 of the span): XLA's CPU sort, which jnp.quantile uses,
# cost a third of a whole accepted alignment.
_RANGE_QUANTILES, _RANGE_MARGIN, _MIN_SPAN = (0.01, 0.99), 0.1, 0.05
_RANGE_HISTOGRAM = 1024


def intensity_range(values, mask) -> jax.Array:
  """(2,) MI's binning range of `values` (any shape) where `mask`; (0, 1) if none is valid."""
  valid = mask & jnp.isfinite(values)
  least = jnp.min(jnp.where(valid, values, jnp.inf))
  span = jnp.max(jnp.where(valid, values, -jnp.inf)) - least
  span = jnp.where(span > 0, span, 1.0)
  # × the reciprocal, not ÷: one rounding in every program (batching.each)
  index = jnp.clip(((values - least) * (_RANGE_HISTOGRAM / span)).astype(jnp.int32), 0,
                   _RANGE_HISTOGRAM - 1)
  counts = jnp.zeros(_RANGE_HISTOGRAM, jnp.float32).at[
      jnp.where(valid, index, _RANGE_HISTOGRAM).reshape(-1)].add(1.0, mode="drop")
  cumulative = jnp.cumsum(counts)
  bins = jnp.searchsorted(cumulative, jnp.asarray(_RANGE_QUANTILES) * cumulative[-1])
  lo, hi = least + (bins + 0.5) * (span / _RANGE_HISTOGRAM)
  centre = 0.5 * (lo + hi)
  half = jnp.maximum(hi - lo, _MIN_SPAN) * (0.5 + _RANGE_MARGIN)
  both = jnp.stack([centre - half, centre + half])
  return jnp.where(jnp.any(mask) & jnp.all(jnp.isfinite(both)), both, jnp.asarray([0.0, 1.0]))
