"""One iteration of the swarm, and its creation: the compiled core of the optimizer.

`_init` draws (or warm-starts) and evaluates a swarm; `_step` moves it by one
iteration: neighbourhood bests (`jaxpso._src.topology`), the velocity of the
configured variant, the velocity clamp, boundary handling, the grid, the
evaluation of the loss and the personal and swarm bests with the stagnation
count.  Both are pure, un-jitted functions of arrays and static settings, so
that `jaxpso._src.pso` can place them in a `lax.while_loop` or a `lax.scan`.
The update rules are given in the module docstring of `jaxpso._src.pso`.
`_check_loss` lives here because `_init` traces `loss_fn` first.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxpso._src.pso_types import PSOConfig
from jaxpso._src.pso_types import PSOHParams
from jaxpso._src.pso_types import PSOLimits
from jaxpso._src.pso_types import PSOState
from jaxpso._src.pso_types import _reciprocal
from jaxpso._src.swarm_random import _BOUNDARY
from jaxpso._src.swarm_random import _DIRECTION
from jaxpso._src.swarm_random import _INIT_V
from jaxpso._src.swarm_random import _INIT_X
from jaxpso._src.swarm_random import _LENGTH
from jaxpso._src.swarm_random import _VELOCITY
from jaxpso._src.swarm_random import _as_seed
from jaxpso._src.swarm_random import _uniform
from jaxpso._src.swarm_random import _uniform_pair
from jaxpso._src.topology import _first_min
from jaxpso._src.topology import _neighbourhood_best
from jaxpso._src.topology import _random_indices


def _check_loss(loss_fn, args, dim: int, dtype, config: PSOConfig) -> None:
  """Traces `loss_fn` abstractly and checks it returns one float per particle."""
  if not callable(loss_fn):
    raise TypeError(f"loss_fn must be callable, got {type(loss_fn).__name__}")
  n = config.swarm_size
  probe = jax.ShapeDtypeStruct((n, dim) if config.batched else (dim,), dtype)
  out = jax.eval_shape(loss_fn, probe, args)
  expected = (n,) if config.batched else ()
  if not hasattr(out, "shape") or out.shape != expected:
    shape = getattr(out, "shape", type(out).__name__)
    what = "an (n,) array for the batched swarm" if config.batched else "a scalar"
    raise ValueError(f"loss_fn must return {what}, got shape {shape}")
  if not jnp.issubdtype(out.dtype, jnp.floating):
    raise TypeError(f"loss_fn must return floats, got dtype {out.dtype}")


def _evaluate(loss_fn, x, args, config: PSOConfig):
  loss = loss_fn(x.T, args) if config.batched else jax.vmap(loss_fn, (1, None))(x, args)
  return jnp.where(jnp.isfinite(loss), loss, jnp.inf).astype(x.dtype)


def _snap(x, lower, upper, config: PSOConfig):
  """Applies the grid discretisation, if any, keeping x inside the box."""
  if config.grid_step is None:
    return x
  step = jnp.asarray(config.grid_step, x.dtype)[:, None]
  last = jnp.floor((upper - lower) / step)  # the highest grid index inside the box
  return lower + _inside(jnp.round((x - lower) / step), 0.0, last) * step


def _inside(x, lower, upper):
  """Clips x to [lower, upper] with selects (faster than min/max on the CPU)."""
  return jnp.where(x < lower, lower, jnp.where(x > upper, upper, x))


def _confine(seed, iteration, x, v, lower, upper, config: PSOConfig):
  """Boundary handling: brings positions back into the box."""
  below, above = x < lower, x > upper
  outside = below | above
  if config.boundary == "clip":
    return _inside(x, lower, upper), jnp.where(outside, 0.0, v)
  if config.boundary == "reflect":
    reflected = jnp.where(below, 2 * lower - x, jnp.where(above, 2 * upper - x, x))
    return _inside(reflected, lower, upper), jnp.where(outside, -v, v)
  draw = _uniform(seed, iteration, _BOUNDARY, x.shape, x.dtype, config.rng)
  fresh = lower + draw * (upper - lower)
  return jnp.where(outside, fresh, x), jnp.where(outside, 0.0, v)


def _inertia(hparams: PSOHParams, iteration, limits: PSOLimits):
  fraction = iteration.astype(jnp.float32) * _reciprocal(limits.max_iterations)
  return hparams.inertia_start + (hparams.inertia_end - hparams.inertia_start) * fraction


def _velocity(state: PSOState, local, hparams: PSOHParams, limits: PSOLimits,
              config: PSOConfig):
  """New velocities (d, n) of the configured variant."""
  x, dtype = state.x, state.x.dtype
  w = _inertia(hparams, state.iteration, limits).astype(dtype)
  if config.variant != "spso2011":
    r1, r2 = _uniform_pair(state.seed, state.iteration, _VELOCITY, x.shape, dtype, config.rng)
    pull = hparams.c1 * r1 * (state.best_x - x) + hparams.c2 * r2 * (local - x)
    return hparams.chi * (w * state.v + pull)
  # SPSO-2011: a uniform point in the sphere around the centre of gravity.
  alone = jnp.all(local == state.best_x, axis=0, keepdims=True)
  centre = jnp.where(alone, x + hparams.c1 * (state.best_x - x) / 2,
                     x + hparams.c1 * (state.best_x + local - 2 * x) / 3)
  radius = jnp.sqrt(jnp.sum((centre - x) ** 2, axis=0, keepdims=True))
  u1, u2 = _uniform_pair(state.seed, state.iteration, _DIRECTION, x.shape, dtype, config.rng)
  direction = jnp.sqrt(-2.0 * jnp.log1p(-u1)) * jnp.cos(2 * jnp.pi * u2)  # Box–Muller
  norm = jnp.sqrt(jnp.sum(direction**2, axis=0, keepdims=True))
  # × the reciprocal, not ÷: one rounding in every program (batching.each)
  direction = direction * (1.0 / jnp.where(norm > 0, norm, 1.0))
  # The radius is uniform in [0, |G - x|] (denser towards G).  A volume-uniform
  # radius, |G - x| u^(1/d), puts x' near the surface in 10-D and the swarm
  # stalled (median 169 on the 10-D sphere; benchmarks/pso_quality.py).
  length = radius * _uniform(state.seed, state.iteration, _LENGTH, radius.shape, dtype, config.rng)
  return hparams.chi * (w * state.v + centre + length * direction - x)


def _update_bests(state: PSOState, x, v, loss, limits: PSOLimits,
                  config: PSOConfig) -> PSOState:
  improved = loss < state.best_loss
  best_x = jnp.where(improved[None, :], x, state.best_x)
  best_loss = jnp.where(improved, loss, state.best_loss)
  i = _first_min(best_loss)
  new_loss = best_loss[i]
  finite = jnp.isfinite(state.swarm_loss)
  old = jnp.where(finite, state.swarm_loss, 0.0)
  threshold = limits.tolerance * jnp.maximum(1.0, jnp.abs(old))
  # The first finite best after +inf always counts as progress.
  gained = jnp.where(finite, old - new_loss > threshold, jnp.isfinite(new_loss))
  informants = state.informants
  if config.topology == "random":
    redraw = _random_indices(state.seed, state.iteration, informants.shape, config)
    informants = jnp.where(new_loss < state.swarm_loss, informants, redraw)
  return PSOState(
      x=x, v=v, loss=loss, best_x=best_x, best_loss=best_loss,
      swarm_x=jnp.where(new_loss < state.swarm_loss, best_x[:, i], state.swarm_x),
      swarm_loss=jnp.minimum(new_loss, state.swarm_loss), informants=informants,
      iteration=state.iteration + 1, stall=jnp.where(gained, 0, state.stall + 1),
      num_evaluations=state.num_evaluations + config.swarm_size, seed=state.seed)


def _step(state: PSOState, loss_fn, lower, upper, args, hparams, limits: PSOLimits,
          config: PSOConfig) -> PSOState:
  lower, upper = lower[:, None], upper[:, None]
  local = _neighbourhood_best(state, limits, config)
  if config.batched:
    v = _velocity(state, local, hparams, limits, config)
  else:
    # A per-particle loss: inside the loop XLA:CPU drops the barriers below and
    # computes v, random numbers included, in the position's fusion as well as
    # its own; a conditional (always true) is a fusion boundary.  6-D
    # Rastrigin, 200 iterations: 4096 particles 35.7-38.2 -> 33.7-37.3 ms, 256
    # 19.0-20.1 -> 16.5-16.8 (interleaved, same losses).  Not for a batched
    # loss: there it slowed `track` (1.35-1.46 -> 1.53-2.07 ms per frame).
    v = jax.lax.cond(state.iteration >= 0,
                     lambda: _velocity(state, local, hparams, limits, config),
                     lambda: jnp.zeros_like(state.x))
  # Clamping with selects: jnp.clip's NaN-propagating min/max halved the
  # throughput of the whole step on the CPU (benchmarks/pso_throughput.py).
  limit = hparams.velocity_clamp * (upper - lower)
  # Materialise v: otherwise XLA recomputes it, random numbers included, in
  # the position fusion as well as in the velocity fusion.
  v = jax.lax.optimization_barrier(jnp.where(jnp.abs(v) > limit, jnp.sign(v) * limit, v))
  x, v = _confine(state.seed, state.iteration, state.x + v, v, lower, upper, config)
  # Materialise the move before the loss, which would otherwise absorb it.
  x, v = jax.lax.optimization_barrier((_snap(x, lower, upper, config), v))
  loss = _evaluate(loss_fn, x, args, config)
  return _update_bests(state, x, v, loss, limits, config)


def _init(key, loss_fn, lower, upper, args, config: PSOConfig, positions, velocities,
          centre, scale) -> PSOState:
  seed = _as_seed(key)
  start = jnp.zeros([], jnp.int32)
  n, d = config.swarm_size, lower.shape[0]
  dtype = lower.dtype
  _check_loss(loss_fn, args, d, dtype, config)
  lower, upper = lower[:, None], upper[:, None]
  span = upper - lower
  if positions is not None:
    x = _inside(positions.T.astype(dtype), lower, upper)
    spread = span
  elif centre is not None:
    spread = jnp.broadcast_to(scale, (d,)).astype(dtype)[:, None]
    x = centre[:, None] + spread * (2 * _uniform(seed, start, _INIT_X, (d, n), dtype, config.rng) - 1)
    x = _inside(x.at[:, 0].set(centre), lower, upper)
  else:
    spread = span
    x = lower + span * _uniform(seed, start, _INIT_X, (d, n), dtype, config.rng)
  if velocities is not None:
    v = velocities.T.astype(dtype)
  else:
    v = 0.5 * spread * (2 * _uniform(seed, start, _INIT_V, (d, n), dtype, config.rng) - 1)
  x = _snap(x, lower, upper, config)
  loss = _evaluate(loss_fn, x, args, config)
  i = _first_min(loss)
  k = config.informants if config.topology == "random" else 0
  return PSOState(
      x=x, v=v, loss=loss, best_x=x, best_loss=loss, swarm_x=x[:, i], swarm_loss=loss[i],
      informants=_random_indices(seed, start - 1, (n, k), config),
      iteration=start, stall=jnp.zeros([], jnp.int32),
      num_evaluations=jnp.asarray(n, jnp.int32), seed=seed)
