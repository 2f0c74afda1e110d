"""Gauss–Newton refinement after the swarm, with the template's intensities
remapped to the image's (the hybrid's gradient half).

The swarm lands in the basin; a few Levenberg–Marquardt steps on the sum of
squared differences between the warped image and a photometrically adapted
template T̃ reach sub-pixel accuracy.  T̃ follows the similarity being
maximised, so the refinement keeps its invariances:

* "mi": T̃ = E[I | T], the image's mean intensity in each soft template bin
  (the sum of conditional variance of Richa et al., 2011: invariant to any
  one-to-one intensity mapping, inversion included);
* "ncc": T̃ = a·T + b, the least-squares gain and bias;
* "ssd": T̃ = T.

T̃ is re-estimated at every step, and a step is accepted only when it
improves the similarity itself, not the SSD.  The Jacobian is
the image gradient (central differences, read from the same packed table) at
the warped points times the warped points' derivative with respect to the
homography (closed form) times the homography's derivative with respect to
the motion parameters (forward mode), so any motion model of
`jaxpso._src.motion` refines alike.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from jaxpso._src import sampling

# Damping of the first step, relative to the diagonal of JᵀJ; multiplied by
# _GROW after a rejected step and by _SHRINK after an accepted one.
_DAMPING, _GROW, _SHRINK = 1e-3, 10.0, 0.3
# Stop after this many rejected steps in a row (the damping then barely
# changes the step any more: with the old rule, damping > 1e6, most coarse
# levels spent 5–8 of their 10 steps on rejections).
_MAX_REJECTED = 3


def adapted_template(template, bin_weights, patch, mask, similarity: str):
  """T̃ (h, w): the template in the image's intensities.

  Args:
    template: (h, w) template.
    bin_weights: (h, w, bins) soft bins of the template (used by "mi").
    patch: (h, w) image sampled at the current warp.
    mask: (h, w) bool validity of `patch`.
    similarity: "mi", "ncc" or "ssd".
  """
  m = mask.astype(patch.dtype)
  count = jnp.maximum(jnp.sum(m), 1.0)
  mean_i = jnp.sum(m * patch) / count
  if similarity == "mi":
    # A pseudo-count of one pixel at the mean intensity keeps empty bins finite.
    bins = bin_weights.shape[-1]
    sums = jnp.stack([patch * m, m]).reshape(2, -1) @ bin_weights.reshape(-1, bins)
    per_bin = (sums[0] + mean_i) / (sums[1] + 1.0)
    return bin_weights @ per_bin
  if similarity == "ncc":
    mean_t = jnp.sum(m * template) / count
    dt = (template - mean_t) * m
    var_t = jnp.sum(dt * dt)
    gain = jnp.where(var_t > 1e-12, jnp.sum(dt * patch) / jnp.where(var_t > 1e-12, var_t, 1.0), 0.0)
    return mean_i + gain * (template - mean_t)
  return template


def gauss_newton(u0, quads, frame_shape, grid, template, bin_weights, loss_of: Callable,
                 to_level_homography: Callable, steps: int, similarity: str,
                 tolerance: float):
  """Levenberg–Marquardt steps on ‖I(W(p; u)) − T̃‖², accepted by the similarity.

  Each step re-estimates T̃ at the current estimate and solves the damped
  normal equations; a step is kept only when it lowers `loss_of` (the
  similarity being maximised), otherwise the damping grows and the step is
  retried from the best estimate, so the refinement never loses ground (and
  a T̃ gone flat from a poor start cannot drag the warp to a flat region).

  Args:
    u0: (D,) starting motion parameters.
    quads: the level's image packed by `sampling.pack_quads`.
    frame_shape: (H, W) of the level's image.
    grid: (h, w, 2) template points used (all the level's pixels, or a
      selection shaped (1, n, 2)), in level pixels.
    template: (h, w) template values at `grid`.
    bin_weights: (h, w, bins) their soft bins ("mi") or None.
    loss_of: (homography (3, 3), patch (h, w), mask (h, w)) → () loss of the
      similarity (+inf for a warp that is not admissible).
    to_level_homography: u (D,) → (3, 3) template → level-image homography.
    steps: iterations at most (one warp, one loss and one D×D solve each);
      fewer once a step moves less than `tolerance` or after
      `_MAX_REJECTED` rejected steps in a row.
    similarity: which photometric model T̃ follows.
    tolerance: stop once a proposed step moves no parameter by more than
      this (in units of u).

  Returns:
    ((D,) the lowest-loss parameters visited (u0 if no step helped), () that
    loss, () int32 loss evaluations made).
  """
  flat = grid.reshape(-1, 2)
  points = jnp.concatenate([flat, jnp.ones_like(flat[:, :1])], axis=1)  # (h·w, 3)

  def linearise(u):
    """Loss at u, and the normal equations (JᵀJ, Jᵀr) of the adapted SSD."""
    h = to_level_homography(u)
    value, gx, gy, valid, (x, y, w) = sampling.sample_with_gradient(
        quads, frame_shape, h, grid, projection=True)
    target = adapted_template(template, bin_weights, value, valid, similarity)
    # J = B·M: B = ∂I(W(p))/∂h per pixel (h·w, 9) in closed form (the
    # gradients are 0 where invalid), M = ∂h/∂u (9, D) by forward mode
    # through the motion model.  JᵀJ = Mᵀ(BᵀB)M and Jᵀr = Mᵀ(Bᵀr) come from
    # one 10×10 Gram of [B r]: forming the (h·w, D) J and multiplying it
    # twice took 14 of the 82 ms of a 64-region frame step (profiled).
    gx, gy = (gx / w).reshape(-1), (gy / w).reshape(-1)
    across = -(gx * x.reshape(-1) + gy * y.reshape(-1))
    residual = (value - target).reshape(-1) * valid.reshape(-1).astype(value.dtype)
    stacked = jnp.concatenate([gx[:, None] * points, gy[:, None] * points,
                               across[:, None] * points, residual[:, None]], axis=1)
    gram = stacked.T @ stacked
    by_motion = jax.jacfwd(to_level_homography)(u).reshape(9, -1)
    return (loss_of(h, value, valid), by_motion.T @ gram[:9, :9] @ by_motion,
            by_motion.T @ gram[:9, 9])

  d = u0.shape[0]

  def body(carry):
    step, u, best_u, best_loss, normal, gradient, damping, rejected, _ = carry
    loss, a, g = linearise(u)
    better = loss < best_loss
    best_u = jnp.where(better, u, best_u)
    best_loss = jnp.where(better, loss, best_loss)
    normal = jnp.where(better, a, normal)
    gradient = jnp.where(better, g, gradient)
    damping = jnp.where(better, damping * _SHRINK, damping * _GROW)
    rejected = jnp.where(better, 0, rejected + 1)
    diagonal = jnp.diagonal(normal)
    lhs = normal + jnp.diag(damping * diagonal + 1e-9 * (1.0 + jnp.max(diagonal)))
    delta = jnp.linalg.solve(lhs, -gradient)
    delta = jnp.where(jnp.all(jnp.isfinite(delta)), delta, 0.0)
    return step + 1, best_u + delta, best_u, best_loss, normal, gradient, damping, rejected, delta

  def running(carry):
    step, *_, rejected, delta = carry
    return (step < steps) & (jnp.max(jnp.abs(delta)) > tolerance) & (rejected < _MAX_REJECTED)

  zero = jnp.zeros(d, u0.dtype)
  carry = (jnp.zeros([], jnp.int32), u0, u0, jnp.asarray(jnp.inf, u0.dtype),
           jnp.eye(d, dtype=u0.dtype), zero, jnp.asarray(_DAMPING, u0.dtype),
           jnp.zeros([], jnp.int32), zero + jnp.inf)
  taken, u, best_u, best_loss, *_ = jax.lax.while_loop(running, body, carry)
  h = to_level_homography(u)
  last = loss_of(h, *sampling.sample_points(quads, frame_shape, h, grid))
  better = last < best_loss
  return jnp.where(better, u, best_u), jnp.where(better, last, best_loss), taken + 1
