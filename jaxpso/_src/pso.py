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
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec

from jaxpso._src import checks
from jaxpso._src import sharding

VARIANTS = ("inertia", "linear_inertia", "constriction", "trelea1", "trelea2", "spso2011")
"""Names accepted by `PSOConfig.variant` (see the module docstring)."""
TOPOLOGIES = ("global", "ring", "local", "wheel", "von_neumann", "dynamic", "random")
"""Names accepted by `PSOConfig.topology` (see the module docstring)."""
BOUNDARIES = ("clip", "reflect", "reinit")
"""Names accepted by `PSOConfig.boundary`."""
RNGS = ("hash", "threefry2x32", "rbg", "unsafe_rbg")
"""Names accepted by `PSOConfig.rng`."""


class Status(enum.IntEnum):
  """Why a run stopped; 0 is success."""
  TARGET_REACHED = 0
  STAGNATED = 1
  MAX_ITERATIONS = 2
  COMBINED = 3
  NON_FINITE = 4


@dataclasses.dataclass(frozen=True)
class PSOConfig:
  """Settings of a swarm.

  The termination settings (`max_iterations`, `patience`, `tolerance`,
  `target_loss`, `stop_weights`) are runtime values: `run` compiles for
  `static()` and passes `limits()` as arrays, so changing them does not
  recompile (`trace` recompiles for a new `max_iterations`, its scan
  length).  Every other setting is static: a change recompiles.

  Attributes:
    swarm_size: number of particles (>= 2).
    variant: one of `VARIANTS`.
    topology: one of `TOPOLOGIES`.
    neighbours: ring neighbours of the "local" topology (even, >= 2).
    informants: informants per particle of the "random" topology (>= 1).
    max_iterations: iterations after the initial evaluation (>= 1).
    patience: stop after this many iterations without an improvement of the
      swarm's best by more than `tolerance · max(1, |best|)`; None disables.
    tolerance: relative improvement that resets the stagnation count (>= 0).
    target_loss: stop once the best loss is <= this; None disables.
    stop_weights: the paper's weighted combination of the criteria: stop when
      a · t / max_iterations + b · stall / patience + c · [best <= target] >= 1
      for (a, b, c); None disables.
    boundary: "clip" (to the box, velocity component reset to 0), "reflect"
      (mirror at the bound, velocity reversed) or "reinit" (coordinate
      re-drawn uniformly in the box, velocity component reset).
    grid_step: discretise the search space: positions snap to
      lower + k · step (a float or one per dimension); None for continuous.
    batched: `loss_fn` takes the whole swarm (n, d) and returns (n,);
      otherwise it takes one (d,) position and is `vmap`ped.
    rng: the generator of the swarm's random numbers. "hash" (default): a
      counter-based generator, two rounds of a 32-bit integer hash of
      (element, iteration, stream) keyed by 64 bits drawn from the key; it is
      plain integer arithmetic, fused into the velocity update, and several
      times faster on the CPU than JAX's own.  "threefry2x32", "rbg",
      "unsafe_rbg": JAX's PRNG implementations, keyed per iteration
      (benchmarks/pso_throughput.py measures all four).
  """
  swarm_size: int = 32
  variant: str = "inertia"
  topology: str = "global"
  neighbours: int = 4
  informants: int = 3
  max_iterations: int = 100
  patience: int | None = 20
  tolerance: float = 1e-6
  target_loss: float | None = None
  stop_weights: tuple[float, float, float] | None = None
  boundary: str = "clip"
  grid_step: float | tuple[float, ...] | None = None
  batched: bool = False
  rng: str = "hash"

  def __post_init__(self):
    def whole(name, value, minimum):
      checks.check_int(value, f"PSOConfig.{name}", minimum)

    def named(name, value, allowed):
      if value not in allowed:
        raise ValueError(f"PSOConfig.{name} must be one of {allowed}, got {value!r}")

    whole("swarm_size", self.swarm_size, 2)
    whole("max_iterations", self.max_iterations, 1)
    whole("informants", self.informants, 1)
    whole("neighbours", self.neighbours, 2)
    if self.neighbours % 2:
      raise ValueError(f"PSOConfig.neighbours must be even, got {self.neighbours}")
    if self.patience is not None:
      whole("patience", self.patience, 1)
    named("variant", self.variant, VARIANTS)
    named("topology", self.topology, TOPOLOGIES)
    named("boundary", self.boundary, BOUNDARIES)
    named("rng", self.rng, RNGS)
    if not (isinstance(self.tolerance, (int, float)) and self.tolerance >= 0
            and math.isfinite(self.tolerance)):
      raise ValueError(f"PSOConfig.tolerance must be a finite number >= 0, got {self.tolerance!r}")
    if self.target_loss is not None and not isinstance(self.target_loss, (int, float)):
      raise TypeError(f"PSOConfig.target_loss must be a number or None, got {self.target_loss!r}")
    if self.target_loss is not None and math.isnan(self.target_loss):
      raise ValueError(f"PSOConfig.target_loss must not be NaN, got {self.target_loss!r}")
    if not isinstance(self.batched, bool):
      raise TypeError(f"PSOConfig.batched must be a bool, got {self.batched!r}")
    if self.stop_weights is not None:
      weights = tuple(self.stop_weights)
      if len(weights) != 3 or not all(isinstance(w, (int, float)) and w >= 0 for w in weights):
        raise ValueError(
            f"PSOConfig.stop_weights must be three numbers >= 0, got {self.stop_weights!r}")
      if weights[1] > 0 and self.patience is None:
        raise ValueError("PSOConfig.stop_weights weighs stagnation but patience is None")
      if weights[2] > 0 and self.target_loss is None:
        raise ValueError("PSOConfig.stop_weights weighs the target but target_loss is None")
      object.__setattr__(self, "stop_weights", weights)
    if self.grid_step is not None:
      steps = np.atleast_1d(np.asarray(self.grid_step, dtype=float))
      if steps.ndim != 1 or not np.all(np.isfinite(steps) & (steps > 0)):
        raise ValueError(f"PSOConfig.grid_step must be positive and finite, got {self.grid_step!r}")
      object.__setattr__(self, "grid_step", tuple(float(s) for s in steps))

  def limits(self) -> PSOLimits:
    """The termination settings as `PSOLimits` (NumPy scalars: no device dispatch)."""
    return PSOLimits(
        max_iterations=np.int32(self.max_iterations),
        patience=np.int32(_NO_PATIENCE if self.patience is None else self.patience),
        tolerance=np.float32(self.tolerance),
        target_loss=np.float32(-np.inf if self.target_loss is None else self.target_loss),
        stop_weights=np.asarray(self.stop_weights or (0.0, 0.0, 0.0), np.float32))

  def static(self) -> PSOConfig:
    """This config with the termination settings at their defaults.

    Configs that differ only in those share it, and so one compiled program.
    """
    return dataclasses.replace(self, **_RUNTIME_DEFAULTS)


class PSOLimits(NamedTuple):
  """Termination settings of a swarm, as arrays (a change never recompiles `run`).

  Attributes:
    max_iterations: () int32 iterations after the initial evaluation; also
      the length of the linear inertia schedule and of the "dynamic"
      topology's growth.
    patience: () int32 iterations without sufficient improvement that stop
      the swarm; 2**31 − 1 disables.
    tolerance: () float32 relative improvement that resets the stagnation count.
    target_loss: () float32 stop once the best loss is <= this; −inf disables.
    stop_weights: (3,) float32 weights (a, b, c) of the combined criterion
      (see `PSOConfig`); zeros disable.
  """
  max_iterations: jax.Array
  patience: jax.Array
  tolerance: jax.Array
  target_loss: jax.Array
  stop_weights: jax.Array


_RUNTIME_DEFAULTS = {f.name: f.default for f in dataclasses.fields(PSOConfig)
                     if f.name in PSOLimits._fields}
_NO_PATIENCE = np.iinfo(np.int32).max  # the patience of `PSOConfig(patience=None)`


def _reciprocal(count):
  """1 / count in float32, for a () int32 limit: t / count is computed as t · (1 / count).

  XLA computed the divisions by the formerly static limits so; the product
  keeps the results bit-identical to theirs.
  """
  return 1 / jnp.asarray(count, jnp.float32)


def _as_limits(limits: PSOLimits) -> PSOLimits:
  """`limits` with the documented dtypes (values may be traced)."""
  dtypes = (jnp.int32, jnp.int32, jnp.float32, jnp.float32, jnp.float32)
  return PSOLimits(*(jnp.asarray(v, t) for v, t in zip(limits, dtypes)))


class PSOHParams(NamedTuple):
  """Coefficients of the velocity update, a pytree of arrays (no recompiles).

  Attributes:
    inertia_start: inertia w at the first iteration.
    inertia_end: inertia w at `max_iterations` (linear schedule in between).
    c1: cognitive coefficient (towards the particle's own best).
    c2: social coefficient (towards the neighbourhood's best).
    chi: constriction factor multiplying the whole update (1 if unused).
    velocity_clamp: largest |v| per dimension as a fraction of upper − lower
      (inf disables).
  """
  inertia_start: jax.Array
  inertia_end: jax.Array
  c1: jax.Array
  c2: jax.Array
  chi: jax.Array
  velocity_clamp: jax.Array


_DEFAULTS = {
    # variant: (inertia_start, inertia_end, c1, c2, chi, velocity_clamp)
    "inertia": (0.7, 0.7, 1.5, 1.5, 1.0, math.inf),
    "linear_inertia": (0.9, 0.4, 2.0, 2.0, 1.0, 0.5),
    "constriction": (1.0, 1.0, 2.05, 2.05, 0.72984, math.inf),
    "trelea1": (0.6, 0.6, 1.7, 1.7, 1.0, math.inf),
    "trelea2": (0.729, 0.729, 1.494, 1.494, 1.0, math.inf),
    "spso2011": (1 / (2 * math.log(2)), 1 / (2 * math.log(2)), 0.5 + math.log(2),
                 0.5 + math.log(2), 1.0, math.inf),
}


def default_hparams(variant: str = "inertia") -> PSOHParams:
  """The published coefficients of a variant (see the module docstring).

  Args:
    variant: one of `VARIANTS`.

  Returns:
    `PSOHParams` of float32 scalars (NumPy, so building them costs no dispatch).
  """
  if variant not in _DEFAULTS:
    raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
  return PSOHParams(*(np.float32(v) for v in _DEFAULTS[variant]))


class PSOState(NamedTuple):
  """The swarm between iterations.

  Swarm arrays are stored dimension-major, (d, n), particles along the
  contiguous axis: measured twice as fast on the CPU as (n, d) for small d.

  Attributes:
    x: (d, n) positions.
    v: (d, n) velocities.
    loss: (n,) losses at `x` (+inf where not finite).
    best_x: (d, n) personal best positions.
    best_loss: (n,) personal best losses.
    swarm_x: (d,) best position found so far.
    swarm_loss: () best loss found so far.
    informants: (n, k) informant indices of the "random" topology ((n, 0) otherwise).
    iteration: () int32 iterations done.
    stall: () int32 iterations since the last sufficient improvement.
    num_evaluations: () int32 loss evaluations so far.
    seed: (2,) uint32 key of the swarm's random numbers (drawn from `key`).
  """
  x: jax.Array
  v: jax.Array
  loss: jax.Array
  best_x: jax.Array
  best_loss: jax.Array
  swarm_x: jax.Array
  swarm_loss: jax.Array
  informants: jax.Array
  iteration: jax.Array
  stall: jax.Array
  num_evaluations: jax.Array
  seed: jax.Array


class PSOResult(NamedTuple):
  """Outcome of `run` or `trace`.

  Attributes:
    x: (d,) best position.
    loss: () its loss.
    status: () int32 `Status` value.
    num_iterations: () int32 iterations done.
    num_evaluations: () int32 loss evaluations.
    state: the final `PSOState` (to warm-start a following run).
  """
  x: jax.Array
  loss: jax.Array
  status: jax.Array
  num_iterations: jax.Array
  num_evaluations: jax.Array
  state: PSOState


class PSOTrace(NamedTuple):
  """Per-iteration record of `trace`.

  Attributes:
    best_loss: (T,) swarm's best loss after each iteration.
    x: (T, n, d) positions after each iteration, or None.
  """
  best_loss: jax.Array
  x: jax.Array | None


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


def _as_seed(key) -> jax.Array:
  """(2,) uint32 seed drawn from an int seed, a raw uint32[2] key or a typed key."""
  if isinstance(key, int):
    return _int_seed(key)
  given = key
  try:
    key = jnp.asarray(key)
  except TypeError:
    raise TypeError(f"key must be an int seed or a JAX PRNG key, got {given!r}") from None
  if not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
    if key.dtype == jnp.uint32 and key.shape == (2,):
      key = jax.random.wrap_key_data(key)
    elif jnp.issubdtype(key.dtype, jnp.integer) and key.shape == ():
      key = jax.random.key(key)
    else:
      raise TypeError(f"key must be an int seed or a JAX PRNG key, got {key.dtype}{key.shape}")
  if key.shape != ():
    raise ValueError(f"key must be a single key, got shape {key.shape}")
  return jax.random.bits(key, (2,), jnp.uint32)


@functools.lru_cache(maxsize=256)
def _int_seed(key: int) -> jax.Array:
  """`_as_seed` of an int (cached: deriving it is a few eager dispatches)."""
  return _as_seed(jax.random.key(key))


# Random streams: one per use within an iteration.
_VELOCITY, _DIRECTION, _LENGTH, _BOUNDARY, _TOPOLOGY, _INIT_X, _INIT_V = range(7)


def _mix(x):
  """A 32-bit integer hash with full avalanche (Wellons' "lowbias32")."""
  x = x ^ (x >> 16)
  x = x * jnp.uint32(0x7FEB352D)
  x = x ^ (x >> 15)
  x = x * jnp.uint32(0x846CA68B)
  return x ^ (x >> 16)


def _tag(seed, iteration, stream: int):
  """A 32-bit key for (seed, iteration, stream); 8 streams per iteration."""
  return _mix(seed[0] ^ _mix(iteration.astype(jnp.uint32) * jnp.uint32(8) + jnp.uint32(stream)))


def _hash_bits(seed, iteration, stream: int, shape):
  """One keyed 32-bit hash per element of `shape`."""
  element = jax.lax.iota(jnp.uint32, int(np.prod(shape))).reshape(shape)
  return _mix(element ^ _mix(_tag(seed, iteration, stream) + seed[1]))


def _uniform(seed, iteration, stream: int, shape, dtype, rng: str):
  """U[0, 1) numbers of `shape` for (seed, iteration, stream); pure function."""
  if rng != "hash":
    key = jax.random.key(_mix(_tag(seed, iteration, stream) ^ seed[1]), impl=rng)
    return jax.random.uniform(key, shape, dtype)
  bits = _hash_bits(seed, iteration, stream, shape)
  return (bits >> 8).astype(dtype) * jnp.asarray(2.0**-24, dtype)


def _uniform_pair(seed, iteration, stream: int, shape, dtype, rng: str):
  """Two arrays of U[0, 1) numbers of `shape`.

  With the "hash" generator both come from one 32-bit hash per element, 16
  bits each (a resolution of 2⁻¹⁶, ample for PSO's random coefficients),
  which halves the generator's cost in the velocity update.
  """
  if rng != "hash":
    r = _uniform(seed, iteration, stream, (2,) + tuple(shape), dtype, rng)
    return r[0], r[1]
  bits = _hash_bits(seed, iteration, stream, shape)
  scale = jnp.asarray(2.0**-16, dtype)
  return (bits >> 16).astype(dtype) * scale, (bits & jnp.uint32(0xFFFF)).astype(dtype) * scale


# ---------------------------------------------------------------- topologies
def _von_neumann_table(n: int) -> np.ndarray:
  """(n, 5) self, up, down, left, right on the most square wrapped grid."""
  rows = max(r for r in range(1, int(math.isqrt(n)) + 1) if n % r == 0)
  cols = n // rows
  i = np.arange(n)
  r, c = i // cols, i % cols
  return np.stack([i, ((r - 1) % rows) * cols + c, ((r + 1) % rows) * cols + c,
                   r * cols + (c - 1) % cols, r * cols + (c + 1) % cols], axis=1)


def _first_min(values):
  """Index of the first minimum of a 1-D array, as jnp.argmin.

  Two plain reductions, which XLA vectorises on the CPU, instead of the
  (value, index) reduction of argmin: 5× faster for 4096 particles.
  """
  lowest = jnp.min(values)
  index = jax.lax.iota(jnp.int32, values.shape[0])
  return jnp.min(jnp.where(values == lowest, index, values.shape[0]))


def _best_of(candidates, best_loss):
  """Index (n,) of the lowest loss among each row of `candidates` (n, k)."""
  choice = jnp.argmin(best_loss[candidates], axis=1)
  return jnp.take_along_axis(candidates, choice[:, None], axis=1)[:, 0]


def _ring_window_best(best_loss, radius):
  """Index of the best within ring distance `radius` (traced) of each particle.

  A sparse table of window minima over power-of-two lengths answers every
  window [i − r, i + r] with two lookups, O(n log n) for any radius.
  """
  n = best_loss.shape[0]
  i = jnp.arange(n)
  values, index = [best_loss], [i]
  span = 1
  while span < n:
    shifted_v = jnp.roll(values[-1], -span)
    shifted_i = jnp.roll(index[-1], -span)
    left = values[-1] <= shifted_v
    values.append(jnp.where(left, values[-1], shifted_v))
    index.append(jnp.where(left, index[-1], shifted_i))
    span *= 2
  values, index = jnp.stack(values), jnp.stack(index)
  width = jnp.minimum(2 * radius + 1, n)
  level = jnp.floor(jnp.log2(width.astype(jnp.float32))).astype(jnp.int32)
  start = (i - radius) % n
  end = (i - radius + width - (1 << level)) % n
  v0, v1 = values[level, start], values[level, end]
  return jnp.where(v0 <= v1, index[level, start], index[level, end])


def _neighbourhood_best(state: PSOState, limits: PSOLimits, config: PSOConfig):
  """(d, n) best position of each particle's neighbourhood."""
  n = config.swarm_size
  best_loss = state.best_loss
  topology = config.topology
  if topology == "global":
    return jnp.broadcast_to(state.swarm_x[:, None], state.x.shape)
  if topology in ("ring", "local"):
    radius = 1 if topology == "ring" else config.neighbours // 2
    offsets = np.arange(-radius, radius + 1)
    table = (np.arange(n)[:, None] + offsets[None, :]) % n
    index = _best_of(jnp.asarray(table), best_loss)
  elif topology == "wheel":
    hub = _first_min(best_loss)
    index = jnp.where(best_loss[0] < best_loss, 0, jnp.arange(n)).at[0].set(hub)
  elif topology == "von_neumann":
    index = _best_of(jnp.asarray(_von_neumann_table(n)), best_loss)
  elif topology == "dynamic":
    growth = state.iteration.astype(jnp.float32) * _reciprocal(limits.max_iterations)
    radius = 1 + jnp.floor(growth * (n // 2)).astype(jnp.int32)
    index = _ring_window_best(best_loss, radius)
  else:  # random
    own = jnp.arange(n)[:, None]
    index = _best_of(jnp.concatenate([own, state.informants], axis=1), best_loss)
  return state.best_x[:, index]


# ------------------------------------------------------------------ the step
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
  direction = direction / jnp.where(norm > 0, norm, 1.0)
  # The radius is uniform in [0, |G - x|] (denser towards G).  A volume-uniform
  # radius, |G - x| u^(1/d), puts x' near the surface in 10-D and the swarm
  # stalled (median 169 on the 10-D sphere; benchmarks/pso_quality.py).
  length = radius * _uniform(state.seed, state.iteration, _LENGTH, radius.shape, dtype, config.rng)
  return hparams.chi * (w * state.v + centre + length * direction - x)


def _random_indices(seed, iteration, shape, config: PSOConfig):
  """Uniform particle indices in [0, n) of `shape` (the random topology)."""
  draw = _uniform(seed, iteration, _TOPOLOGY, shape, jnp.float32, config.rng)
  return jnp.minimum((draw * config.swarm_size).astype(jnp.int32), config.swarm_size - 1)


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
  v = _velocity(state, local, hparams, limits, config)
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


def _run_impl(key, lower, upper, args, hparams, positions, velocities, centre, scale, *,
              loss_fn, config, mesh=None, limits=None):
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


_run = jax.jit(_run_impl, static_argnames=("loss_fn", "config", "mesh"))


@functools.lru_cache(maxsize=256)
def _static_and_limits(config: PSOConfig) -> tuple[PSOConfig, PSOLimits]:
  """`config.static()` and `config.limits()`, cached: building them cost 5 % of a short `run`."""
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
  bounds, `hparams` or termination settings do not recompile.

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
  return _run(key, lower, upper, args, hparams, positions, velocities, centre, scale,
              loss_fn=loss_fn, config=static, limits=limits,
              mesh=_swarm_mesh(devices, config.swarm_size))


@functools.partial(jax.jit, static_argnames=("loss_fn", "config", "keep_positions"))
def _trace(key, lower, upper, args, hparams, positions, velocities, centre, scale, limits, *,
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
