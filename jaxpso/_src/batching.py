"""`align`'s and `track`'s batches: on the host (NumPy, around the compiled call) and in the program.

A batch of N alignments or R regions is one compiled program over a leading
axis: its arguments arrive as lists (`elements`), are prepared element by
element and stacked (`stack`), each element gets its own swarm seed
(`element_seeds`); an unbatched call is a batch of one whose program
returns element 0 (`align._result`).

In the program, a batch is a pytree with that leading axis on every leaf,
except an `atlas.Atlas` with 1-D pixels, which the batch shares (`track`'s
frame: one image for every region) and which is neither mapped nor
indexed.  `each` maps an unbatched function (`problem.Problem`'s steps,
a whole registration) over the elements: on a CPU one element at a time,
through the computation a lone element runs, elsewhere by `vmap`.  `select`
and `take` pick per element, and `where_needed` runs a computation only for
the elements that need it: under `vmap` a per-element `lax.cond` runs both
branches for every element (and a `while_loop` with a per-element
condition becomes selects over its whole carry), so on an accelerator
`register.run`'s later stages, the swarm above all, would run for the whole
batch.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import atlas
from jaxpso._src import swarm_random


def elements(value, batched: bool, name: str) -> list:
  """The elements of a batched argument (a list of one if not batched)."""
  if not batched:
    return [value]
  if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
    raise TypeError(f"{name} must be a batch (a leading N axis), got {type(value).__name__}")
  return list(value)


def stack(trees: list):
  """A list of equally structured NumPy pytrees → one with a leading axis (a view for one tree).

  The leaves are read-only and stacked into aligned arrays (`atlas.empty`): the
  program then reads them without a copy.
  """
  if len(trees) == 1:
    return jax.tree.map(lambda leaf: _read_only(np.asarray(leaf)[None]), trees[0])

  def stacked(*leaves):
    first = np.asarray(leaves[0])
    return _read_only(np.stack(leaves, out=atlas.empty((len(leaves),) + first.shape,
                                                       first.dtype)))

  return jax.tree.map(stacked, *trees)


def _read_only(array: np.ndarray) -> np.ndarray:
  array.setflags(write=False)
  return array


def element_seeds(key, count: int, batched: bool) -> np.ndarray:
  """(count, 2) uint32 swarm seeds of a batch: from one key, or one key per element.

  One key (an int, a typed key or a raw uint32[2] key): element 0's seed is
  the key's own and element i's follows from it.  For a batch (`batched`),
  also one key per element: a list of ints or keys, (count,) ints or typed
  keys, or (count, 2) raw uint32 keys; element i's seed is then that of
  the unbatched call with key[i].  Int seeds are drawn on the host: as
  device operations they cost a noticeable share of a short `align`.

  Raises:
    ValueError: a batch given another number of keys than elements.
  """
  keys = _per_element(key) if batched else None
  if keys is not None:
    if len(keys) != count:
      raise ValueError(f"key must be one key or one per element of the batch: {len(keys)} keys"
                       f" for a batch of {count}")
    return np.stack([np.asarray(swarm_random._as_seed(k)) for k in keys]).astype(np.uint32)
  seed = np.asarray(swarm_random._as_seed(key))
  offsets = np.arange(count, dtype=np.uint32) * np.uint32(0x9E3779B9)  # wraps modulo 2³²
  return np.stack([np.full(count, seed[0]), seed[1] + offsets], axis=-1)


def _per_element(key) -> list | None:
  """The keys of a per-element `key` (`element_seeds`), or None for a single key."""
  if isinstance(key, (list, tuple)):
    return [int(k) if isinstance(k, np.integer) else k for k in key]
  if isinstance(key, (int, np.integer)) or not hasattr(key, "shape"):
    return None
  if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
    return list(key) if key.ndim == 1 else None
  if key.dtype == np.uint32:
    return list(key) if key.ndim == 2 else None  # (2,) is one raw key
  if np.issubdtype(key.dtype, np.integer) and key.ndim == 1:
    return [int(k) for k in np.asarray(key)]
  return None


# ------------------------------------------------------------ in the program
def _shared(node) -> bool:
  """Whether `node` is an `atlas.Atlas` shared by a batch (1-D pixels)."""
  return isinstance(node, atlas.Atlas) and node.pixels.ndim == 1


def _axes(tree):
  """vmap axes of a batched pytree: 0, but None for a shared `atlas.Atlas`."""
  return jax.tree.map(lambda node: None if _shared(node) else 0, tree, is_leaf=_shared)


def _size(args) -> int:
  """The batch size R of batched pytrees: the leading axis of any leaf outside a shared `atlas.Atlas`."""
  return next(a.shape[0] for a in jax.tree.leaves(args, is_leaf=_shared) if not _shared(a))


def _mapped(fn, tree):
  """`fn` on every leaf of `tree` but a shared `atlas.Atlas`'s."""
  return jax.tree.map(lambda node: node if _shared(node) else fn(node), tree, is_leaf=_shared)


def one_at_a_time() -> bool:
  """Whether a batch runs one element at a time (`each`): on a CPU; accelerators vectorise."""
  return jax.default_backend() == "cpu"


def each(fn: Callable, *args):
  """`fn` (unbatched) on every element of the leading axis: one after another on a CPU, else `vmap`.

  An `atlas.Atlas` with 1-D pixels is shared by the batch (not mapped).  A
  batch of one calls `fn` on the element itself.  On a CPU an element runs
  the very computation it runs alone, so its result does not depend on the
  batch it is in (`vmap` vectorises by the batch's width, and XLA then
  rounds sums and fused multiply-adds otherwise: a registration that stops
  where its steps fall under a tolerance ended up to 9e-3 px elsewhere,
  benchmarks/results/invariance.md); its loops stop where the element's
  own do, where under `vmap` every `while_loop` runs to the batch's slowest
  element as selects over the whole carry.  Accelerators, whose lanes run
  in parallel, `vmap`.

  Across devices (`sharding.per_device`) the same holds only if every
  program rounds alike: XLA rewrites x / broadcast(y) as x · broadcast(1/y)
  in some programs and not in others (a homography's normalisation then
  differed by an ulp, and tracks by up to 1.7e-3 px), so the registration
  writes such divisions as multiplications by the reciprocal.
  """
  count = _size(args)
  if count == 1:
    return jax.tree.map(lambda a: a[None], fn(*_mapped(lambda a: a[0], args)))
  if one_at_a_time():
    return jax.lax.map(lambda i: fn(*_mapped(lambda a: a[i], args)), jnp.arange(count))
  return jax.vmap(fn, in_axes=_axes(args))(*args)


def select(mask, first, second):
  """Per batch element `first` where the (R,) or () `mask` holds, else `second` (pytrees)."""
  return jax.tree.map(
      lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - mask.ndim)), a, b),
      first, second)


def as_batch(tree):
  """One element's pytree as a batch of one (a shared `atlas.Atlas` as it is)."""
  return _mapped(lambda a: a[None], tree)


def take(tree, indices):
  """The elements `indices` (C,) of every leaf's leading axis (a shared `atlas.Atlas` as it is)."""
  return _mapped(lambda a: a[indices], tree)


def _capacity(size: int) -> int:
  """Elements per round of `where_needed` for a batch of `size`: ceil(size / 8), in parallel slots.

  (A CPU runs a batch one element at a time, `each`, and needs no rounds.)
  Not measured on a GPU.
  """
  return -(-size // 8)


def where_needed(mask, compute: Callable, otherwise):
  """`otherwise` with the elements where the (R,) `mask` holds replaced by `compute`'s.

  `compute(indices)` gets (C,) element indices and returns those elements'
  results (leading C).  Only the elements that need it are computed, C =
  `_capacity(R)` at a time in a `lax.while_loop` of as many rounds as
  needed (none when no element does).
  """
  size = mask.shape[0]
  capacity = _capacity(size)
  padded = -(-size // capacity) * capacity
  needed = jnp.sum(mask)
  # The needing elements first; every other slot is the out-of-range index `size`.
  order = jnp.argsort(~mask, stable=True)
  order = jnp.where(jnp.arange(size) < needed, order, size)
  order = jnp.concatenate([order, jnp.full(padded - size, size, order.dtype)])

  def round_(state):
    done, results = state
    indices = jax.lax.dynamic_slice(order, (done,), (capacity,))
    found = compute(jnp.minimum(indices, size - 1))
    results = jax.tree.map(lambda a, f: a.at[indices].set(f, mode="drop"), results, found)
    return done + capacity, results

  def rounds(_):
    return jax.lax.while_loop(lambda state: state[0] < needed, round_,
                              (jnp.zeros([], needed.dtype), otherwise))[1]

  # The cond keeps batches that need nothing from entering the loop at all.
  return jax.lax.cond(needed > 0, rounds, lambda _: otherwise, None)
