"""`align`'s and `track`'s batches: on the host (NumPy, around the compiled call) and in the program.

A batch of N alignments or R regions is one compiled program over a leading
axis: its arguments arrive as lists (`elements`), are prepared element by
element and stacked (`stack`), each element gets its own swarm seed
(`element_seeds`); an unbatched call is a batch of one whose program
returns element 0 (`align._result`).

In the program, a batch is a pytree with that leading axis on every leaf,
except an `atlas.Atlas` with 1-D pixels, which the batch shares (`track`'s
frame: one image for every region) and which is neither mapped nor
indexed.  `each` maps an unbatched function (`problem.Problem`'s steps)
over the elements, `in_groups` runs a batched one a group of elements at a
time on a CPU, `select` and `take` pick per element, and `where_needed`
runs a computation only for the elements that need it: under `vmap` a
per-element `lax.cond` runs both branches for every element (and a
`while_loop` with a per-element condition becomes selects over its whole
carry), so `register.run`'s later stages, the swarm above all, would run
for the whole batch.
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

  The leaves are read-only (`atlas`: the program then reads them without a copy).
  """
  if len(trees) == 1:
    return jax.tree.map(lambda leaf: _read_only(np.asarray(leaf)[None]), trees[0])
  return jax.tree.map(lambda *leaves: _read_only(np.stack(leaves)), *trees)


def _read_only(array: np.ndarray) -> np.ndarray:
  array.setflags(write=False)
  return array


def element_seeds(key, count: int) -> np.ndarray:
  """(count, 2) uint32 swarm seeds of a batch from one key; element 0's is the key's own.

  On the host: as device operations they cost a noticeable share of a short `align`.
  """
  seed = np.asarray(swarm_random._as_seed(key))
  offsets = np.arange(count, dtype=np.uint32) * np.uint32(0x9E3779B9)  # wraps modulo 2³²
  return np.stack([np.full(count, seed[0]), seed[1] + offsets], axis=-1)


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


def each(fn: Callable, *args):
  """`jax.vmap(fn)(*args)` over the leading axis, or for a batch of one `fn` on the element itself.

  An `atlas.Atlas` with 1-D pixels is shared by the batch (not mapped).
  Under `vmap`, every `while_loop` with a per-element condition becomes a
  loop of selects over its whole carry (and a `cond` runs both branches):
  for one element that only cost compilation time and run time.
  """
  count = _size(args)
  if count != 1:
    return jax.vmap(fn, in_axes=_axes(args))(*args)
  return jax.tree.map(lambda a: a[None], fn(*_mapped(lambda a: a[0], args)))


# `in_groups`'s largest group on a CPU.  Sweep (R = 16 / 64 / 256 regions of
# 48×48, 20 frames, 2 rounds; benchmarks/README.md, session 10): groups of 8, 16
# or 32 all ran at 0.72–0.89 ms per region-frame, groups of 4 at 0.79–0.91,
# the whole batch at once 0.93–0.97 (R = 64) and 1.12–1.36 (R = 256).  16
# leaves every batch of up to 16 as it was.
GROUP = 16


def in_groups(fn: Callable, *args):
  """`fn(*args)` for a batch, on a CPU in sequential groups of at most `GROUP` elements.

  `fn` maps batched pytrees (leading axis R; a shared `atlas.Atlas` as it
  is) to batched pytrees.  Under `vmap` every `while_loop` runs until the
  batch's slowest element is done, as selects over the whole batch's carry;
  in groups each stops at its own group's slowest, over a carry that stays
  in the cache.  The R elements are split into ceil(R / GROUP) groups of
  equal size (the last padded with copies of element R − 1, whose results
  are dropped).  On accelerators, whose lanes run in parallel: `fn(*args)`.
  """
  count = _size(args)
  if count <= GROUP or jax.default_backend() != "cpu":
    return fn(*args)
  groups = -(-count // GROUP)
  size = -(-count // groups)
  indices = jnp.minimum(jnp.arange(groups * size), count - 1).reshape(groups, size)
  found = jax.lax.map(lambda group: fn(*take(args, group)), indices)
  return jax.tree.map(lambda a: a.reshape((groups * size,) + a.shape[2:])[:count], found)


def select(mask, first, second):
  """Per batch element `first` where the (R,) or () `mask` holds, else `second` (pytrees)."""
  return jax.tree.map(
      lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - mask.ndim)), a, b),
      first, second)


def take(tree, indices):
  """The elements `indices` (C,) of every leaf's leading axis (a shared `atlas.Atlas` as it is)."""
  return _mapped(lambda a: a[indices], tree)


def _capacity(size: int) -> int:
  """Elements per round of `where_needed` for a batch of `size`.

  1 on a CPU: a single element runs its loops and conditionals as such,
  while under `vmap` (`each`) every loop runs to its slowest element as
  selects and every conditional both branches, so one element at a time
  was the fastest even when every element needed the search
  (benchmarks/README.md, runtime before and after issue 17).
  ceil(size / 8) on accelerators, whose slots run in parallel (not
  measured on a GPU).
  """
  return 1 if jax.default_backend() == "cpu" else -(-size // 8)


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
