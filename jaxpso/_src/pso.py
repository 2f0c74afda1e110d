"""Particle swarm optimisation: the whole swarm's step in one compiled function.

`run` minimises `loss_fn(x, args)` over a box with one `lax.while_loop` whose
condition combines the termination criteria; `trace` runs a fixed number of
iterations with `lax.scan` and returns the per-iteration best loss (and
optionally the positions) for plots; `init` and `step` are the pure pieces for
users who drive the loop themselves.

All settings live in the hashable `PSOConfig`.  The structural ones (swarm
size, variant, topology, neighbours, informants, boundary handling, grid,
batched loss, generator) are static: a change recompiles.  The termination
settings (max_iterations, patience, tolerance, target_loss, stop_weights)
reach the compiled loop as arrays, `PSOLimits`: `run` compiles once for all
of them (`trace` once per `max_iterations`, its scan length).  The
coefficients (inertia schedule, c1, c2, constriction, velocity clamp) are the
`PSOHParams` pytree of arrays, so changing them never recompiles and they can
be `vmap`ped.

Velocity update of the inertia/constriction family, with r1, r2 ~ U(0, 1)
drawn per particle and per dimension:

  v ← χ (w v + c1 r1 (p − x) + c2 r2 (l − x)),  x ← x + v,

p the particle's best, l the best of its neighbourhood (the topology), w the
inertia (linearly scheduled from `inertia_start` to `inertia_end` over
`max_iterations`).  SPSO-2011 moves instead towards a random point x' around the centre of
gravity G = x + c (p + l − 2x) / 3: a uniform direction and a radius uniform
in [0, |G − x|], with v ← w v + x' − x.

Variants (`VARIANTS`, defaults from `default_hparams`):
  inertia:        constant inertia w = 0.7, c1 = c2 = 1.5 — Shi & Eberhart, "A
                  modified particle swarm optimizer", ICEC 1998 (inside the
                  order-2 stability region c1 + c2 < 24 (1 − w²) / (7 − 5w),
                  Poli 2009).
  linear_inertia: w 0.9 → 0.4 linearly, c1 = c2 = 2.0, |v| ≤ 0.5 of the box —
                  Shi & Eberhart, "Empirical study of particle swarm
                  optimization", CEC 1999.
  constriction:   χ = 0.72984, c1 = c2 = 2.05, w = 1 — Clerc & Kennedy, "The
                  particle swarm — explosion, stability, and convergence in a
                  multidimensional complex space", IEEE TEC 2002.
  trelea1:        w = 0.6, c1 = c2 = 1.7 — Trelea, "The particle swarm
                  optimization algorithm: convergence analysis and parameter
                  selection", IPL 2003 (parameter set 1).
  trelea2:        w = 0.729, c1 = c2 = 1.494 — Trelea 2003 (parameter set 2).
  spso2011:       w = 1 / (2 ln 2), c = 0.5 + ln 2, hypersphere sampling —
                  Clerc, "Standard Particle Swarm Optimisation", 2012 (SPSO-2011);
                  pair it with the "random" topology for the standard's
                  adaptive random informants.

Topologies (`TOPOLOGIES`, paper Fig. 3), all computed with index arrays and
gathers: global (star, Kennedy & Eberhart 1995), ring (2 neighbours on the
index ring), local (`neighbours` on the index ring, half on each side), wheel
(particle 0 is the hub: it sees everyone, the others see only the hub;
Kennedy 1999), von_neumann (4 neighbours on a wrapped grid; Kennedy & Mendes
2002), dynamic (a ring neighbourhood whose radius grows linearly from 1 to
the whole swarm over `max_iterations`, explorative first and exploitative
later, after Suganthan 1999, who grew it in position space), random (every
particle hears `informants` random others, re-drawn after an iteration that
did not improve the swarm's best; SPSO-2011).

The pieces live in their own modules: the types in `jaxpso._src.pso_types`,
the random numbers in `jaxpso._src.swarm_random`, the neighbourhoods in
`jaxpso._src.topology` and the compiled `_init` and `_step` in
`jaxpso._src.swarm_update`; this module validates the arguments on the host
and drives the loop.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec

from jaxpso._src import checks
from jaxpso._src import programs
from jaxpso._src import sharding
from jaxpso._src.pso_types import _NO_PATIENCE
from jaxpso._src.pso_types import PSOConfig
from jaxpso._src.pso_types import PSOHParams
from jaxpso._src.pso_types import PSOLimits
from jaxpso._src.pso_types import PSOResult
from jaxpso._src.pso_types import PSOState
from jaxpso._src.pso_types import PSOTrace
from jaxpso._src.pso_types import Status
from jaxpso._src.pso_types import _as_limits
from jaxpso._src.pso_types import _reciprocal
from jaxpso._src.pso_types import default_hparams
from jaxpso._src.swarm_update import _init
from jaxpso._src.swarm_update import _step


# ------------------------------------------------------------------ validation
def _check_bounds(lower, upper):
  lower = checks.as_float_array(lower, "lower")
  upper = checks.as_float_array(upper, "upper")
  if lower.ndim != 1 or lower.shape != upper.shape:
    raise ValueError(
        f"lower and upper must be 1-D of equal shape (d,), got {lower.shape} and {upper.shape}")
  if not isinstance(lower, jax.core.Tracer) and not isinstance(upper, jax.core.Tracer):
    lo, hi = np.asarray(lower), np.asarray(upper)
    bad = ~(np.isfinite(lo) & np.isfinite(hi) & (lo < hi))
    if bad.any():
      i = int(np.argmax(bad))
      raise ValueError(
          f"lower must be < upper and both finite in every dimension; dimension {i} has"
          f" lower={lo[i]}, upper={hi[i]}")
  dtype = jnp.result_type(lower, upper)
  return lower.astype(dtype), upper.astype(dtype)


def _check_hparams(hparams, config: PSOConfig) -> PSOHParams:
  if hparams is None:
    return default_hparams(config.variant)
  if not isinstance(hparams, PSOHParams):
    raise TypeError(f"hparams must be a PSOHParams, got {type(hparams).__name__}")
  for name, value in hparams._asdict().items():  # concrete values only: they may be vmapped
    if isinstance(value, jax.core.Tracer):
      continue
    value = np.asarray(value)
    if np.isnan(value).any() or (name == "velocity_clamp" and not np.all(value > 0)):
      rule = "> 0" if name == "velocity_clamp" else "a number"
      raise ValueError(f"hparams.{name} must be {rule}, got {value}")
  return PSOHParams(*(v if isinstance(v, jax.Array) and v.dtype == jnp.float32
                      else jnp.asarray(v, jnp.float32) for v in hparams))


# --------------------------------------------------------------- termination
def _stopped(state: PSOState, limits: PSOLimits):
  """Bool flags (max iterations, stagnation, target, combined).

  A disabled criterion never fires: the stall never reaches 2**31 − 1, the
  best loss is never −inf (non-finite losses count as +inf) and zero weights
  score 0.
  """
  by_iterations = state.iteration >= limits.max_iterations
  by_stall = state.stall >= limits.patience
  by_target = state.swarm_loss <= limits.target_loss
  a, b, c = limits.stop_weights
  score = (a * state.iteration * _reciprocal(limits.max_iterations)
           + b * state.stall * _reciprocal(limits.patience) + c * by_target)
  return by_iterations, by_stall, by_target, score >= 1.0


def _status(state: PSOState, limits: PSOLimits):
  by_iterations, by_stall, by_target, by_combination = _stopped(state, limits)
  status = jnp.select(
      [~jnp.isfinite(state.swarm_loss), by_target, by_stall, by_combination],
      [Status.NON_FINITE, Status.TARGET_REACHED, Status.STAGNATED, Status.COMBINED],
      Status.MAX_ITERATIONS)
  return status.astype(jnp.int32)


def _result(state: PSOState, limits: PSOLimits) -> PSOResult:
  return PSOResult(x=state.swarm_x, loss=state.swarm_loss, status=_status(state, limits),
                   num_iterations=state.iteration, num_evaluations=state.num_evaluations,
                   state=state)


# ------------------------------------------------------------------ public API
def _exact(value, shape, name: str) -> jax.Array:
  """A finite float array of exactly `shape`, or a ValueError naming `name`."""
  array = checks.as_checked(value, shape, name, str(shape))
  if array.shape != shape:
    raise ValueError(f"{name} must have shape {shape}, got shape {array.shape}")
  return array


def _prepare(lower, upper, hparams, config, positions, velocities, centre, scale):
  """Validates the array arguments of `init`/`run`/`trace` on the host."""
  if not isinstance(config, PSOConfig):
    raise TypeError(f"config must be a PSOConfig, got {type(config).__name__}")
  lower, upper = _check_bounds(lower, upper)
  d = lower.shape[0]
  if config.grid_step is not None and len(config.grid_step) not in (1, d):
    raise ValueError(
        f"PSOConfig.grid_step has {len(config.grid_step)} entries for {d} dimensions")
  shape = (config.swarm_size, d)
  if positions is not None:
    positions = _exact(positions, shape, "positions")
  if velocities is not None:
    velocities = _exact(velocities, shape, "velocities")
  if (centre is None) != (scale is None):
    missing = "centre" if centre is None else "scale"
    raise ValueError(f"centre and scale must be given together, got {missing}=None")
  if centre is not None:
    if positions is not None:
      raise ValueError("give either positions or centre and scale, not both")
    centre = _exact(centre, (d,), "centre")
    if not isinstance(centre, jax.core.Tracer) and not isinstance(lower, jax.core.Tracer) and (
        np.any(np.asarray(centre) < np.asarray(lower))
        or np.any(np.asarray(centre) > np.asarray(upper))):
      raise ValueError(f"centre must lie inside the box [lower, upper], got {np.asarray(centre)}"
                       f" for lower {np.asarray(lower)}, upper {np.asarray(upper)}")
    scale = checks.as_float_array(scale, "scale")
    if scale.shape not in ((), (d,)):
      raise ValueError(f"scale must be a scalar or shape ({d},), got shape {scale.shape}")
    if not isinstance(scale, jax.core.Tracer) and not np.all(np.isfinite(scale) & (scale > 0)):
      raise ValueError(f"scale must be finite and > 0, got {np.asarray(scale)}")
  return lower, upper, _check_hparams(hparams, config), positions, velocities, centre, scale


def init(key, loss_fn: Callable, lower, upper, args: Any = None, *,
         config: PSOConfig = PSOConfig(), positions=None, velocities=None, centre=None,
         scale=None) -> PSOState:
  """Creates and evaluates a swarm.

  Without warm start the positions are uniform in the box and the
  velocities uniform in ±half the box.  A warm start gives either
  `positions` (and optionally `velocities`) of a previous swarm, or a
  `centre` and a `scale`: particle 0 sits at the centre, the others uniformly
  within ±scale of it, velocities within ±scale / 2.

  Args:
    key: PRNG key or int seed.
    loss_fn: `loss_fn(x, args)` -> scalar for x (d,), or (n,) for x (n, d)
      when `config.batched`.
    lower: (d,) lower bounds.
    upper: (d,) upper bounds, > lower.
    args: any pytree passed to `loss_fn` (data travels here, not in closures).
    config: static settings.
    positions: optional (n, d) initial positions (clipped to the box).
    velocities: optional (n, d) initial velocities.
    centre: optional (d,) centre of a warm start.
    scale: () or (d,) spread of a warm start around `centre`.

  Returns:
    The evaluated `PSOState`.
  """
  lower, upper, _, positions, velocities, centre, scale = _prepare(
      lower, upper, None, config, positions, velocities, centre, scale)
  return _init(key, loss_fn, lower, upper, args, config, positions, velocities, centre, scale)


def step(state: PSOState, loss_fn: Callable, lower, upper, args: Any = None, *,
         config: PSOConfig = PSOConfig(), hparams: PSOHParams | None = None) -> PSOState:
  """One iteration: neighbourhood bests, velocities, move, evaluate, bests.

  Args:
    state: the swarm from `init` or a previous `step`.
    loss_fn, lower, upper, args, config: as for `init`.
    hparams: coefficients; `default_hparams(config.variant)` if None.

  Returns:
    The next `PSOState`.
  """
  lower, upper, hparams, *_ = _prepare(lower, upper, hparams, config, None, None, None, None)
  return _step(state, loss_fn, lower, upper, args, hparams, config.limits(), config)


def _split_swarm(state: PSOState, mesh) -> PSOState:
  """`state` constrained to lie particle-wise over the mesh (unchanged without one)."""
  if mesh is None:
    return state
  def spec(*axes):
    return NamedSharding(mesh, PartitionSpec(*axes))
  particles, replicated = spec(None, sharding.AXIS), spec()
  layout = state._replace(
      x=particles, v=particles, best_x=particles, loss=spec(sharding.AXIS),
      best_loss=spec(sharding.AXIS), informants=spec(sharding.AXIS, None), swarm_x=replicated,
      swarm_loss=replicated, iteration=replicated, stall=replicated, num_evaluations=replicated,
      seed=replicated)
  return jax.lax.with_sharding_constraint(state, layout)


def _run_impl(key, lower, upper, args, hparams, positions, velocities, centre, scale,
              limits=None, *, loss_fn, config, mesh=None):
  """`run` on validated arrays, un-jitted: callable inside other compiled programs.

  Args:
    key, lower, upper, args, hparams: as for `run`, checked by `_prepare`.
    positions, velocities, centre, scale: warm start (None each if unused).
    loss_fn: as for `run`.
    config: the static settings; its termination settings are used only
      when `limits` is None.
    mesh: the `Mesh` the particles are split over, or None.
    limits: `PSOLimits` (values may be traced); `config.limits()` if None.

  Returns:
    `PSOResult`.
  """
  limits = _as_limits(config.limits() if limits is None else limits)
  state = _split_swarm(
      _init(key, loss_fn, lower, upper, args, config, positions, velocities, centre, scale), mesh)

  def running(s):
    return ~functools.reduce(jnp.logical_or, _stopped(s, limits))

  def body(s):
    return _split_swarm(_step(s, loss_fn, lower, upper, args, hparams, limits, config), mesh)

  return _result(jax.lax.while_loop(running, body, state), limits)


_run = programs.Program(_run_impl, static_argnames=("loss_fn", "config", "mesh"), stored=False)


@functools.lru_cache(maxsize=256)
def _static_and_limits(config: PSOConfig) -> tuple[PSOConfig, PSOLimits]:
  """`config.static()` and `config.limits()`, cached.

  Building them was a noticeable share of a short `run`
  (benchmarks/README.md, pso_throughput.py).
  """
  return config.static(), config.limits()


def _swarm_mesh(devices, swarm_size: int):
  """The mesh a swarm is split over: as many of `devices` as divide `swarm_size`, or None."""
  mesh = sharding.batch_mesh(devices, swarm_size)
  if mesh is None:
    return None
  count = max(c for c in range(1, mesh.size + 1) if swarm_size % c == 0)
  return None if count == 1 else Mesh(mesh.devices[:count], (sharding.AXIS,))


def run(key, loss_fn: Callable, lower, upper, args: Any = None, *,
        config: PSOConfig = PSOConfig(), hparams: PSOHParams | None = None,
        positions=None, velocities=None, centre=None, scale=None, devices=None) -> PSOResult:
  """Minimises `loss_fn` over the box [lower, upper] with one `lax.while_loop`.

  The loop stops at the first of: `max_iterations`, stagnation for
  `patience` iterations, the best loss reaching `target_loss`, or the
  weighted combination `stop_weights`; `status` says which (`Status`).
  Non-finite losses never become a best; if no finite loss was ever seen the
  status is `Status.NON_FINITE`.  The same key gives a bit-identical result.
  Compiled once per (loss_fn, `config.static()`, shapes): new `args`,
  bounds, `hparams` or termination settings do not recompile.  The
  programs share the bounded table of jaxpso's own (the 16 last used, in
  memory only): a sweep over thousands of configurations holds 16, where
  JAX's caches would keep every one (benchmarks/results/program_memory.md);
  a loop cycling through more raises the bound (`jaxpso.set_max_programs`).

  Args:
    key: PRNG key or int seed.
    loss_fn: `loss_fn(x, args)` -> scalar (or (n,) when `config.batched`).
    lower: (d,) lower bounds.
    upper: (d,) upper bounds.
    args: pytree of data for `loss_fn`.
    config: settings; the termination ones reach the loop as `limits()`.
    hparams: coefficients; `default_hparams(config.variant)` if None.
    positions, velocities, centre, scale: warm start, as for `init`.
    devices: the `jax.Device`s the swarm's particles are split over (XLA's
      SPMD partitioner over a `jax.sharding.Mesh`; the global best is
      reduced across them, results equal one device's); default every
      visible one.  As many are used as divide `config.swarm_size`.

  Returns:
    `PSOResult`.

  Examples:
    >>> import jax.numpy as jnp
    >>> from jaxpso import pso
    >>> sphere = lambda x, args: jnp.sum((x - args) ** 2)
    >>> result = pso.run(0, sphere, -jnp.ones(3), jnp.ones(3), jnp.full(3, 0.5),
    ...                  config=pso.PSOConfig(max_iterations=200, patience=None))
    >>> bool(jnp.allclose(result.x, 0.5, atol=1e-3)), int(result.status)
    (True, 2)
  """
  lower, upper, hparams, positions, velocities, centre, scale = _prepare(
      lower, upper, hparams, config, positions, velocities, centre, scale)
  static, limits = _static_and_limits(config)
  return _run(key, lower, upper, args, hparams, positions, velocities, centre, scale, limits,
              loss_fn=loss_fn, config=static, mesh=_swarm_mesh(devices, config.swarm_size))


def _trace_impl(key, lower, upper, args, hparams, positions, velocities, centre, scale, limits, *,
                loss_fn, config, keep_positions):
  # The scan length, config.max_iterations, is static: the schedules use it as a constant.
  limits = _as_limits(limits._replace(max_iterations=config.max_iterations))
  state = _init(key, loss_fn, lower, upper, args, config, positions, velocities, centre, scale)

  def body(s, _):
    s = _step(s, loss_fn, lower, upper, args, hparams, limits, config)
    return s, (s.swarm_loss, s.x if keep_positions else None)

  state, (best, xs) = jax.lax.scan(body, state, None, length=config.max_iterations)
  xs = None if xs is None else jnp.swapaxes(xs, 1, 2)  # (T, d, n) -> (T, n, d)
  fixed_length = limits._replace(patience=jnp.int32(_NO_PATIENCE),
                                 stop_weights=jnp.zeros(3, jnp.float32))
  return _result(state, fixed_length), PSOTrace(best_loss=best, x=xs)


_trace = programs.Program(_trace_impl, static_argnames=("loss_fn", "config", "keep_positions"),
                          stored=False)


def trace(key, loss_fn: Callable, lower, upper, args: Any = None, *,
          config: PSOConfig = PSOConfig(), hparams: PSOHParams | None = None,
          keep_positions: bool = False, positions=None, velocities=None, centre=None,
          scale=None) -> tuple[PSOResult, PSOTrace]:
  """Runs exactly `config.max_iterations` iterations with `lax.scan`, for plots.

  The other termination criteria do not stop the scan; the status reports
  the target or non-finite outcome, else `Status.MAX_ITERATIONS`.  With only
  `max_iterations` active, `run` and `trace` give bit-identical results.
  Compiled once per (loss_fn, `config.static()`, `max_iterations`, shapes,
  `keep_positions`): the other termination settings do not recompile.

  Args:
    key, loss_fn, lower, upper, args, config, hparams: as for `run`.
    keep_positions: also record the (T, n, d) positions.
    positions, velocities, centre, scale: warm start, as for `init`.

  Returns:
    `(PSOResult, PSOTrace)`.
  """
  lower, upper, hparams, positions, velocities, centre, scale = _prepare(
      lower, upper, hparams, config, positions, velocities, centre, scale)
  static = dataclasses.replace(config.static(), max_iterations=config.max_iterations)
  return _trace(key, lower, upper, args, hparams, positions, velocities, centre, scale,
                config.limits(), loss_fn=loss_fn, config=static, keep_positions=keep_positions)
