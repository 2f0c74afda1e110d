"""The swarm's random numbers: seeds and a counter-based generator.

Every random number of the swarm is a pure function of (seed, iteration,
stream, element), so that `init`, `step`, `run` and `trace` give
bit-identical results for a key however the loop is driven.  `_as_seed`
turns the user's key into the (2,) uint32 seed kept in `PSOState.seed`;
`_uniform` and `_uniform_pair` draw U[0, 1) numbers from it with the "hash"
generator (a 32-bit integer hash, plain integer arithmetic that XLA fuses
into the velocity update) or one of JAX's PRNG implementations
(`PSOConfig.rng`).  One stream per use within an iteration keeps the draws
independent.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np


def _as_seed(key) -> jax.Array | np.ndarray:
  """(2,) uint32 seed drawn from an int seed (on the host), a raw uint32[2] key or a typed key."""
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
def _int_seed(key: int) -> np.ndarray:
  """`_as_seed(jax.random.key(key))` on the host, JAX's default settings (32-bit keys); read-only.

  Threefry-2x32 of the key (0, key mod 2³²) at counters 0 and 1, the two
  words XOR-ed, as `jax.random.bits`; as eager JAX operations it compiled
  several programs in every process.  Remembered: its 0.1 ms was 2 % of a
  short `align`.
  """
  words = _threefry2x32(np.uint32(0), np.uint32(key & 0xFFFFFFFF), np.zeros(2, np.uint32),
                        np.arange(2, dtype=np.uint32))
  seed = words[0] ^ words[1]
  seed.setflags(write=False)
  return seed


def _threefry2x32(k0, k1, x0, x1):
  """Threefry-2x32 (20 rounds) of the counter words (x0, x1) under the key (k0, k1), uint32 NumPy."""
  keys = (k0, k1, k0 ^ k1 ^ np.uint32(0x1BD11BDA))
  x0, x1 = x0 + keys[0], x1 + keys[1]
  for block in range(5):
    for r in ((13, 15, 26, 6), (17, 29, 16, 24))[block % 2]:
      x0 = x0 + x1
      x1 = ((x1 << np.uint32(r)) | (x1 >> np.uint32(32 - r))) ^ x0
    x0, x1 = x0 + keys[(block + 1) % 3], x1 + keys[(block + 2) % 3] + np.uint32(block + 1)
  return x0, x1


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
