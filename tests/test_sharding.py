"""Sharding over devices: results bit-identical to one device's, and each device holds its share.

The checks need several devices, which XLA fakes on the CPU with
`--xla_force_host_platform_device_count`; that flag must be set before JAX
starts, so the test runs this file as a subprocess (`_checks` below).
"""

import os
import subprocess
import sys

DEVICES = 4


def test_sharded_results_equal_unsharded_and_each_device_holds_its_share():
  env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={DEVICES}",
             JAX_PLATFORMS="cpu")
  done = subprocess.run([sys.executable, __file__], env=env, capture_output=True, text=True,
                        timeout=900)
  assert done.returncode == 0, done.stdout + done.stderr
  assert done.stdout.split() == ["pso", "track", "align"], done.stdout


def _checks():
  import jax
  import jax.numpy as jnp
  import numpy as np
  from jax.sharding import PartitionSpec

  import jaxpso
  from jaxpso import pso
  from jaxpso._src import atlas
  from jaxpso._src import batching
  from jaxpso._src import programs
  from jaxpso._src import sharding
  from jaxpso._src import template as templates
  from jaxpso._src import track as track_module

  devices = jax.devices()
  assert len(devices) == DEVICES, devices
  keys = [11, 12, 13]  # one per element: element i as alone with keys[i]

  def shards(array):
    """{device: shard shape} of a JAX array."""
    return {s.device: s.data.shape for s in array.addressable_shards}

  # One swarm of 64 particles in 5-D split over the 4 devices: bit-identical.
  sphere = lambda x, target: jnp.sum((x - target) ** 2, axis=-1)  # noqa: E731
  config = pso.PSOConfig(swarm_size=64, max_iterations=30, patience=None, batched=True)
  box = jnp.ones(5)
  alone = pso.run(0, sphere, -box, box, jnp.full(5, 0.3), config=config, devices=devices[:1])
  split = pso.run(0, sphere, -box, box, jnp.full(5, 0.3), config=config)
  for a, b in zip(jax.tree.leaves(alone), jax.tree.leaves(split)):
    np.testing.assert_array_equal(a, b)
  assert split.state.x.sharding.spec == PartitionSpec(None, sharding.AXIS)
  assert shards(split.state.x) == {d: (5, 16) for d in devices}
  print("pso", flush=True)

  # Three regions tracked on one device and on several: on the four (3 used)
  # and on two (padded to 4), MI with prediction (the richest carry).  Each
  # device runs the one-device program on its regions
  # (`sharding.per_device`): bit-identical (NCC 4.8e-3 px apart under XLA's
  # SPMD partitioner, 1e-4 to 1.7e-3 px with divisions XLA turned into
  # multiplications in some programs only; benchmarks/results/invariance.md).
  # One similarity: the split is the same for each, and each sharded program
  # is a compilation of 10-30 s that the disk cache does not keep; a region
  # of a batch tracks as alone for each similarity in tests/test_batch.py.
  sequence = jaxpso.synthetic.make_sequence(0, num_frames=4, frame_shape=(96, 128),
                                            roi_size=(32, 32))
  x, y, w, h = sequence.roi
  rois = np.array([sequence.roi, (x + 5, y - 3, w, h), (x - 4, y + 4, w, h)])
  config = jaxpso.TrackConfig(similarity="mi", levels=2, swarm_size=8, max_iterations=5,
                              search_radius=6.0, predict=True)
  one = jaxpso.track(sequence.frames, rois, config=config, devices=devices[:1], key=keys)
  for chosen in (None, devices[:2]):
    many = jaxpso.track(sequence.frames, rois, config=config, devices=chosen, key=keys)
    np.testing.assert_array_equal(many.homographies, one.homographies)
    np.testing.assert_array_equal(many.status, one.status)
  # A lone region stays where JAX puts it (a one-device mesh among several cost
  # it 1.3–1.4× its time per frame); named devices are honoured.
  assert sharding.batch_mesh(None, 1) is None
  assert list(sharding.batch_mesh(devices[1:2], 1).devices) == [devices[1]]
  # The frame step keeps the regions split: each device's carry holds its
  # region.  The step is the four devices' track above (its mesh, statics and
  # shapes), so no program is compiled for it.
  mesh = sharding.batch_mesh(None, 3)
  template = np.ascontiguousarray(sequence.frames[0, :32, :32])
  statics = config.statics()
  prepared = batching.stack([templates.prepared(template, 2, config.pixels, config.bins,
                                                statics.resolution)] * 3)
  constants = sharding.split(track_module._Constants(
      prepared, None, batching.element_seeds(keys, 3, True), None), mesh)
  assert shards(constants.template.values) == {d: (1, templates.capacity()) for d in devices[:3]}
  eye = np.stack([np.eye(3, dtype=np.float32)] * 3)
  carry = sharding.split(track_module._Carry(eye, eye, np.ones(3, np.int32),
                                             np.ones(3, np.float32)), mesh)
  frame_shape = sequence.frames.shape[1:]
  capacity = atlas.capacity(sum(a * b for a, b in atlas.level_shapes(frame_shape, 2)))
  image = sharding.replicate(atlas.build(np.asarray(sequence.frames[1]), 2, capacity), mesh)
  knobs = sharding.replicate(config.knobs(), mesh)
  before = programs.counts()["compiled"]
  carry, out = track_module._frame_step(carry, image, constants, knobs, config=statics, mesh=mesh)
  assert programs.counts()["compiled"] == before
  assert shards(carry.estimate) == {d: (1, 3, 3) for d in devices[:3]}
  assert shards(out["quality"]) == {d: (1,) for d in devices[:3]}
  print("track", flush=True)

  # Three alignments on two devices (padded to 4) equal them on one (each
  # equals its alignment alone: tests/test_batch.py).
  image = sequence.frames[0]
  starts = np.stack([np.float32([[1, 0, x + dx], [0, 1, y + dy], [0, 0, 1]])
                     for dx, dy in ((1, -1), (-2, 1), (0, 2))])
  templates_ = np.stack([image[y:y + 32, x:x + 32]] * 3)
  one, many = (jaxpso.align(np.stack([image] * 3), templates_, starts, config=config, devices=d,
                            key=keys) for d in (devices[:1], devices[:2]))
  for a, b in zip(one, many):
    np.testing.assert_array_equal(a, b)
  # A gradient baseline's batch is split per device the same way: equal
  # within 1e-3 px, not bit for bit (its solvers round an ulp apart across
  # devices; benchmarks/results/invariance.md).
  inverse = jaxpso.TrackConfig(method="ic", similarity="ssd", levels=2)
  one, two = (jaxpso.align(np.stack([image] * 3), templates_, starts, config=inverse, devices=d)
              for d in (devices[:1], devices[:2]))
  rect = np.float64([[0, 0, 1], [31, 0, 1], [31, 31, 1], [0, 31, 1]])
  corners = [np.einsum("nij,kj->nki", np.float64(r.homography), rect) for r in (one, two)]
  corners = [c[..., :2] / c[..., 2:] for c in corners]
  np.testing.assert_allclose(corners[1], corners[0], rtol=0, atol=1e-3)
  print("align", flush=True)


if __name__ == "__main__":
  _checks()
