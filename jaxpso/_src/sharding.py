"""Splitting a batch (of regions, alignments or particles) over devices with `jax.sharding`.

A batch's leading axis is laid out over a 1-D `Mesh` of the chosen devices
(`NamedSharding(mesh, P("batch"))`); what the whole batch shares (a frame) is
replicated.  `align` and `track` run their program on each device's share
(`per_device`, `jax.shard_map`): an element computes on any number of
devices what it computes on one.  `pso.run`'s particles are split by
XLA's SPMD partitioner, which inserts the swarm's global best.  A batch is
padded, repeating its last element, to a multiple of the number of
devices; the padding is dropped from the results.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec

AXIS = "batch"


def batch_mesh(devices, size: int) -> Mesh | None:
  """The 1-D mesh a batch of `size` elements is split over, or None to leave placement alone.

  Args:
    devices: a sequence of `jax.Device`s, or None for every visible device
      (None is returned when there is only one, or for a single element:
      a mesh of one device among several cost a lone 48×48 region 1.3–1.4×
      its time per frame on a CPU split into 2 devices).
    size: the batch size; no more devices than elements are used.

  Raises:
    TypeError / ValueError: `devices` is not a non-empty sequence of distinct devices.
  """
  if devices is None:
    devices = jax.devices()
    if len(devices) == 1 or size <= 1:
      return None
  else:
    if isinstance(devices, (str, bytes, jax.Device)) or not hasattr(devices, "__iter__"):
      raise TypeError(f"devices must be a sequence of jax.Device, got {devices!r}")
    devices = list(devices)
    if not devices:
      raise ValueError("devices must name at least one device, got none")
    if not all(isinstance(d, jax.Device) for d in devices):
      raise TypeError(f"devices must be a sequence of jax.Device, got {devices!r}")
    if len(set(devices)) != len(devices):
      raise ValueError(f"devices must be distinct, got {devices!r}")
  return Mesh(np.array(devices[:max(1, size)]), (AXIS,))


def _pad(tree, multiple: int):
  """Every leaf's leading axis padded to a multiple of `multiple` by repeating its last element."""
  def grow(a):
    missing = -a.shape[0] % multiple
    if missing == 0:
      return a
    return np.concatenate([np.asarray(a), np.repeat(np.asarray(a)[-1:], missing, axis=0)])
  return jax.tree.map(grow, tree)


def split(tree, mesh: Mesh | None):
  """Lays every leaf's leading axis out over the mesh, padded first to a multiple of its devices.

  Without a mesh the leaves become JAX arrays on the default device: a
  compiled step fed NumPy first and its own JAX outputs next would be
  cached twice.  The caller drops the padding from the results.
  """
  if mesh is None:
    return jax.device_put(tree)  # jnp.asarray compiles a copy program per shape
  return jax.device_put(_pad(tree, mesh.size), NamedSharding(mesh, PartitionSpec(AXIS)))


def per_device(fn, mesh: Mesh | None, shared: tuple[int, ...] = ()):
  """`fn` run by every device of `mesh` on its share of the batch (`jax.shard_map`).

  `fn`'s positional arguments are batched pytrees (leading axis split over
  the mesh), except those at the positions `shared`, which every device
  sees whole; its results are batched.  Without a mesh of several
  devices, `fn` itself.
  """
  if mesh is None or mesh.devices.size == 1:
    return fn

  def split_over_devices(*args):
    specs = tuple(PartitionSpec() if i in shared else PartitionSpec(AXIS)
                  for i in range(len(args)))
    return jax.shard_map(fn, mesh=mesh, in_specs=specs, out_specs=PartitionSpec(AXIS),
                         check_vma=False)(*args)

  return split_over_devices


def replicate(tree, mesh: Mesh | None):
  """A copy of every leaf on every device of the mesh (unchanged without one)."""
  if mesh is None:
    return tree
  return jax.device_put(tree, NamedSharding(mesh, PartitionSpec()))


def to_host(tree):
  """Every leaf as a NumPy array, gathered from all processes when it spans several hosts."""
  def fetch(a):
    if isinstance(a, jax.Array) and not a.is_fully_addressable:
      return np.asarray(multihost_utils.process_allgather(a, tiled=True))
    return np.asarray(jax.device_get(a))
  return jax.tree.map(fetch, tree)
