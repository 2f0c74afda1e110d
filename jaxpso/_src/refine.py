"""Gauss–Newton refinement with the template's intensities remapped to the image's (the hybrid's gradient half).

The swarm lands in the basin; a few Levenberg–Marquardt steps on the sum of
squared differences between the warped image and a photometrically adapted
template T̃ reach sub-pixel accuracy.  T̃ follows the similarity being
maximised, so the refinement keeps its invariances:

* "mi": two phases.  First T̃ = a·T + b, gain and bias fitted by least
  squares (expressed in the template's cubic B-spline bins, which reproduce
  linear functions); then, once that has converged, T̃ = X·c, a B-spline
  remap of the template's intensities fitted to the image's by least
  squares (in the spirit of the sum of conditional variance of Richa et
  al., 2011: invariant to any smooth one-to-one intensity mapping).  Why
  both: the remap's 16 coefficients, fitted to a misaligned patch, absorb
  part of the misalignment, and from a few pixels off on a small smooth
  template its steps stalled where MI still rose towards the alignment
  (regions TRACKED 5–10 px off); two coefficients cannot absorb it.  The
  remap then removes the bias a gain and bias leave under a nonlinear
  intensity change (gamma 0.5: median 0.05–0.08 px, the Baker–Matthews
  trials of convergence.py).  Per-bin mean intensities, the
  earliest fit, are biased wherever the template's histogram is uneven
  (benchmarks/convergence.py's gamma trials);
* "ncc": T̃ = a·T + b, the least-squares gain and bias;
* "ssd": T̃ = T.

T̃ is re-estimated at every step from sums over the template's points
(`adapted_coefficients`), and a step is accepted only when it improves the
similarity itself, not the SSD.  The caller linearises (it knows the image and the
template, `jaxpso._src.problem`); this module holds the photometric model
and the damped loop.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from jaxpso._src import measures
from jaxpso._src import template as templates

# Damping of the first step, relative to the diagonal of JᵀJ; multiplied by
# _GROW after a rejected step and by _SHRINK after an accepted one.
_DAMPING, _GROW, _SHRINK = 1e-3, 10.0, 0.3
# Stop after this many rejected steps in a row, or after one rejected step
# moving no parameter by more than _NOISE × the tolerance: there the loss no
# longer resolves the moves (more steps would only spend evaluations).
_MAX_REJECTED, _NOISE = 3, 4.0
# The second phase begins once the first phase's steps move no parameter by
# more than _SWITCH × the tolerance (or where it would stop): closer, its
# gain and bias only spend steps converging to their own fixed point
# (convergence.py, none and gamma: 0.5–1 step fewer, the median gamma error
# 0.016–0.040 px per σ instead of 0.019–0.049).
_SWITCH = 10.0
# MI's adapted template is fitted by least squares while at most this share
# of the set's points is invalid (outside the image), else by bin means.
_INVALID_SHARE = 1e-3


def adapted_coefficients(similarity: str, stats, per_bin=None, linear=False):
  """c with T̃ = X·c: X the template's bin weights (bins,) per point for "mi", else [T, 1].

  Args:
    similarity: "mi", "ncc" or "ssd".
    stats: the "ncc" statistics over the valid points (`measures`).
    per_bin: "mi": (bins,) Σ m·I·β(T) and (bins,) Σ m·β(T), the image's
      intensity summed per template bin over the valid points (m) and the
      bins' weights, `template.Template.remap` (bins, bins: level 0's set,
      the one the remap is fitted on) and () the set's number of points.
    linear: "mi": () bool, fit the gain and bias (c = a·k + b over the bin
      indices k) instead of the remap.
  """
  if similarity == "mi":
    sums, counts, inverse, size = per_bin
    mean = jnp.sum(sums) / jnp.maximum(jnp.sum(counts), 1.0)
    # Every point valid (the usual case): c = argmin Σ (I − X·c)² + r·|c − mean|²,
    # least squares ridged toward the mean intensity, with the set's
    # precomputed (XᵀX + r·I)⁻¹, r = `template.REMAP_RIDGE`.  Otherwise
    # that inverse is not the valid points' and c is each bin's mean
    # intensity, a pseudo-count of one pixel at the mean keeping empty bins
    # finite.
    everywhere = jnp.sum(counts) >= (1.0 - _INVALID_SHARE) * size  # Σ_b β_b = 1 per point
    remap = jnp.where(everywhere, inverse @ (sums + templates.REMAP_RIDGE * mean),
                      (sums + mean) / (counts + 1.0))
    return jnp.where(linear, _gain_and_bias(sums, counts), remap)
  if similarity == "ncc":
    _, mean_t, mean_i, var_t, _, cov = measures.ncc_moments(stats)
    gain = jnp.where(var_t > 1e-12, cov / jnp.where(var_t > 1e-12, var_t, 1.0), 0.0)
    return jnp.stack([gain, mean_i - gain * mean_t])
  return jnp.asarray([1.0, 0.0], jnp.float32)


def _gain_and_bias(sums, counts):
  """(bins,) c = a·k + b: I ≈ a·s + b by least squares, s the template's value in bin units.

  The cubic B-spline bins reproduce s and s² + 1/3 (Σ_k k β_k(s) = s,
  Σ_k k² β_k(s) = s² + 1/3), so the moments of s come from the per-bin
  sums alone: Σ s = k·counts, Σ s² = k²·counts − n/3, Σ s·I = k·sums.
  A flat template (no variance) gets a = 0, T̃ the mean.
  """
  k = jnp.arange(counts.shape[0], dtype=counts.dtype)
  n = jnp.maximum(jnp.sum(counts), 1.0)
  s, ss, si, i = k @ counts, (k * k) @ counts - n / 3.0, k @ sums, jnp.sum(sums)
  spread = n * ss - s * s  # n² var(s)
  informative = spread > 1e-6 * n * n
  gain = jnp.where(informative, (n * si - s * i) / jnp.where(informative, spread, 1.0), 0.0)
  return gain * k + (i - gain * s) / n


def levenberg_marquardt(u0, linearise: Callable, loss_at: Callable, steps, tolerance,
                        first=False, second=True, polish=False):
  """Damped Gauss–Newton steps, each accepted only if it lowers the loss.

  A rejected step grows the damping (to at least `_DAMPING` × `_GROW`) and
  is retried from the best estimate, so the refinement never loses ground
  beyond the loss's noise (and a T̃ gone flat from a poor start cannot drag
  the warp to a flat region).

  Args:
    u0: (D,) starting parameters.
    linearise: (u, first) → (loss (), JᵀJ (D, D), Jᵀr (D,)) at u; `first`
      () bool: the first phase's photometric model, else the second's.
    loss_at: u → () loss (the final step's, which is not linearised).
    steps: () int32 linearisations at most; fewer once a step moves no
      parameter by more than `tolerance` or after `_MAX_REJECTED` rejected
      steps in a row.
    tolerance: () stop threshold, in units of u (a rejected step under
      `_NOISE` × tolerance stops too).
    first: () bool: begin with the first phase.
    second: () bool: where the first phase would stop, or once its steps
      move less than `_SWITCH` × the tolerance, the second begins (damping
      and rejections reset), within the same `steps`.
    polish: (static) where the undamped step from the lowest-loss
      parameters stays within `_NOISE` × tolerance, return its end instead
      (up to twice that, part of the way there).
      Only where the step's fixed point is the loss's optimum ("ssd",
      "ncc"): MI's remap is ridged, and its fixed point lies off the
      optimum; polishing there moved the Baker–Matthews errors and
      invariance.py's batch and device differences.

  Returns:
    ((D,) the lowest-loss parameters visited (or polished), () int32 loss
    evaluations made).
  """
  d = u0.shape[0]

  def body(carry):
    step, u, best_u, best_loss, normal, gradient, damping, rejected, _, _, first = carry
    loss, a, g = linearise(u, first)
    better = loss < best_loss
    settled = ~better & (jnp.max(jnp.abs(u - best_u)) <= _NOISE * tolerance)
    best_u = jnp.where(better, u, best_u)
    best_loss = jnp.where(better, loss, best_loss)
    normal = jnp.where(better, a, normal)
    gradient = jnp.where(better, g, gradient)
    damping = jnp.where(better, damping * _SHRINK, jnp.maximum(damping, _DAMPING) * _GROW)
    rejected = jnp.where(better, 0, rejected + 1)
    delta = _step(normal, gradient, damping)
    moved = jnp.max(jnp.abs(delta))
    stop = (moved <= tolerance) | (rejected >= _MAX_REJECTED) | settled
    switch = first & (stop | (moved <= _SWITCH * tolerance)) & second
    # The second phase starts afresh from the best estimate, one step on.
    damping = jnp.where(switch, _DAMPING, damping)
    rejected = jnp.where(switch, 0, rejected)
    return (step + 1, best_u + delta, best_u, best_loss, normal, gradient, damping, rejected,
            settled & ~switch, stop & ~switch, first & ~switch)

  def running(carry):
    step, *_, done, _ = carry
    return (step < steps) & ~done

  zero = jnp.zeros(d, u0.dtype)
  carry = (jnp.zeros([], jnp.int32), u0, u0, jnp.asarray(jnp.inf, u0.dtype),
           jnp.eye(d, dtype=u0.dtype), zero, jnp.asarray(_DAMPING, u0.dtype),
           jnp.zeros([], jnp.int32), jnp.asarray(False), jnp.asarray(False), jnp.asarray(first))
  taken, u, best_u, best_loss, normal, gradient, _, _, settled, _, _ = jax.lax.while_loop(
      running, body, carry)
  # The last step, unless the loop settled (its loss could not resolve it).
  # Computed either way: a `cond` on a per-element flag would, under `vmap`,
  # copy everything its branches close over (the image) per element.
  last = jnp.where(settled, jnp.inf, loss_at(u))
  better = last < best_loss
  u = jnp.where(better, u, best_u)
  if not polish:
    return u, taken + 1
  # Which of the last steps the loss accepted within its noise is decided by
  # its rounding, which differs between compiled programs (a batch or a lone
  # region, 1, 2 or 4 devices).  The undamped step is a smooth function of
  # the estimate: ending with it, the result no longer hangs on those
  # decisions (NCC tracks 4.8e-3 px apart before, 1e-4 after:
  # tests/test_sharding.py).
  # Taken whole up to `_NOISE` × tolerance and fading out by twice that: a
  # step taken or not at a band's edge was itself a decision (NCC, 1 of 48
  # templates 0.04 px apart on 1 and 2 devices, benchmarks/invariance.py).
  step = _step(normal, gradient, 0.0)
  share = jnp.clip(2.0 - jnp.max(jnp.abs(step)) / (_NOISE * tolerance), 0.0, 1.0)
  return u + share * (best_u + step - u), taken + 1


def _step(normal, gradient, damping):
  """(D,) the Levenberg–Marquardt step: (JᵀJ + damping·diag(JᵀJ) + ε)⁻¹ (−Jᵀr), 0 if not finite."""
  diagonal = jnp.diagonal(normal)
  lhs = normal + jnp.diag(damping * diagonal + 1e-9 * (1.0 + jnp.max(diagonal)))
  delta = jnp.linalg.solve(lhs, -gradient)
  return jnp.where(jnp.all(jnp.isfinite(delta)), delta, 0.0)
