"""Neighbourhoods: the best position each particle is drawn towards.

`_neighbourhood_best` gives, for every particle, the personal best of the
best particle in its neighbourhood under `PSOConfig.topology` (the topologies
are described in the module docstring of `jaxpso._src.pso`); every topology
is computed with index arrays and gathers, without a loop over particles.
`_random_indices` draws the informants of the "random" topology, and
`_first_min` is the index reduction the topologies and the swarm's best share.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src.pso_types import PSOConfig
from jaxpso._src.pso_types import PSOLimits
from jaxpso._src.pso_types import PSOState
from jaxpso._src.pso_types import _reciprocal
from jaxpso._src.swarm_random import _TOPOLOGY
from jaxpso._src.swarm_random import _uniform


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
  (value, index) reduction of argmin, which it does not
  (benchmarks/README.md, pso_throughput.py).
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


def _random_indices(seed, iteration, shape, config: PSOConfig):
  """Uniform particle indices in [0, n) of `shape` (the random topology)."""
  draw = _uniform(seed, iteration, _TOPOLOGY, shape, jnp.float32, config.rng)
  return jnp.minimum((draw * config.swarm_size).astype(jnp.int32), config.swarm_size - 1)
