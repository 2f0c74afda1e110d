"""Multi-host (multi-process) tracking with `jax.distributed`: a runnable example and check.

Every process runs the same program: `jax.distributed.initialize` joins the
processes, after which `jax.devices()` lists the devices of all of them and
`jaxpso.track(frames, rois)` splits the regions over every device of every
process (each process feeds the same frames; the results are gathered on
all of them).  On a cluster, start one process per host with the
coordinator's address (or let `jax.distributed.initialize()` detect a
SLURM/TPU/Kubernetes cluster):

    python benchmarks/multihost.py --coordinator HOST0:9876 --processes N --process-id I

Without arguments the script starts 2 local processes of 2 CPU devices each
(`--xla_force_host_platform_device_count`, CPU collectives over gloo), tracks
8 regions over the 4 devices and checks the result against one process
alone.

Usage: python benchmarks/multihost.py [--coordinator ADDR --processes N --process-id I]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

import numpy as np

REGIONS = 8


def regions(sequence) -> np.ndarray:
  """(REGIONS, 4) 32×32 boxes inside the sequence's ROI."""
  x, y, w, h = sequence.roi
  return np.array([[x + dx, y + dy, 32, 32] for dx, dy in
                   np.random.default_rng(0).integers(0, w - 32, size=(REGIONS, 2))])


def tracked():
  """The regions of a short synthetic sequence tracked on every device."""
  import jaxpso
  sequence = jaxpso.synthetic.make_sequence(0, num_frames=5, frame_shape=(120, 160),
                                            roi_size=(64, 64))
  config = jaxpso.TrackConfig(levels=2, swarm_size=16, max_iterations=10)
  return jaxpso.track(sequence.frames, regions(sequence), config=config)


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--coordinator")
  parser.add_argument("--processes", type=int)
  parser.add_argument("--process-id", type=int)
  parser.add_argument("--save", help="write the corners to this .npy file (process 0)")
  args = parser.parse_args()
  if args.coordinator is None:  # the local demonstration
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu")
    out = [f"/tmp/jaxpso_multihost_{i}.npy" for i in range(2)]
    workers = [subprocess.Popen([sys.executable, __file__, "--coordinator", "localhost:9876",
                                 "--processes", "2", "--process-id", str(i), "--save", out[i]],
                                env=env) for i in range(2)]
    if any(w.wait() != 0 for w in workers):
      sys.exit("a process failed")
    alone = tracked().corners
    for path in out:
      np.testing.assert_array_equal(np.load(path), alone)
    print(f"2 processes × 2 devices: {REGIONS} regions tracked; both processes' corners equal"
          " one process's bit for bit")
    return
  import jax
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  jax.distributed.initialize(args.coordinator, args.processes, args.process_id)
  print(f"process {jax.process_index()}: {len(jax.local_devices())} local of"
        f" {len(jax.devices())} devices", flush=True)
  result = tracked()
  if args.save:
    np.save(args.save, result.corners)


if __name__ == "__main__":
  main()
