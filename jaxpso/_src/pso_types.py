"""The swarm's types: its settings, coefficients, state and outcome.

`PSOConfig` (static settings, hashable), `PSOLimits` (the termination
settings as arrays), `PSOHParams` (the coefficients, a pytree of arrays) with
the published `default_hparams` of each variant, `PSOState` (the swarm between
iterations), `PSOResult`, `PSOTrace` and `Status`, and the names the settings
accept.  They live apart from the algorithm so that its pieces
(`jaxpso._src.swarm_random`, `jaxpso._src.topology`,
`jaxpso._src.swarm_update`) and its entry points (`jaxpso._src.pso`) share
them without importing one another.  The variants, topologies and the split
between static, limit and coefficient settings are described in the module
docstring of `jaxpso._src.pso`.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import checks

VARIANTS = ("inertia", "linear_inertia", "constriction", "trelea1", "trelea2", "spso2011")
"""Names accepted by `PSOConfig.variant` (see the module docstring of `jaxpso._src.pso`)."""
TOPOLOGIES = ("global", "ring", "local", "wheel", "von_neumann", "dynamic", "random")
"""Names accepted by `PSOConfig.topology` (see the module docstring of `jaxpso._src.pso`)."""
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
  """The published coefficients of a variant (see the module docstring of `jaxpso._src.pso`).

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
  contiguous axis: faster on the CPU than (n, d) for small d
  (benchmarks/README.md, pso_throughput.py).

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
