"""What each compiled `pso.run` program holds in a process, and what `jax.clear_caches()` frees.

A sweep over swarm settings compiles one program per (loss function, static
setting, dimension), and JAX keeps every one.  This compiles `--programs`
programs (a sphere in 1, 2, ... dimensions: one each), reading the process's
memory mappings (/proc/self/maps, Linux) and resident memory every
`--every`, then calls `jax.clear_caches()` and reads them again.  Linux
stops a process at `vm.max_map_count` mappings (65 530 by default): the
table gives how many programs that allows.

Writes results/program_memory.{json,md}.

Usage: python benchmarks/program_memory.py [--programs 200] [--every 50]
"""

from __future__ import annotations

import argparse
import gc

import jax
import jax.numpy as jnp

import common
from jaxpso import pso


def reading() -> dict:
  """The process's memory mappings and resident MiB now."""
  with open("/proc/self/maps") as f:
    maps = sum(1 for _ in f)
  with open("/proc/self/statm") as f:
    resident = int(f.read().split()[1]) * 4096 / 2**20
  return {"maps": maps, "resident_mib": round(resident, 1)}


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--programs", type=int, default=200)
  parser.add_argument("--every", type=int, default=50)
  args = parser.parse_args()
  config = pso.PSOConfig(swarm_size=16, max_iterations=5, patience=None)
  sphere = lambda x, _: jnp.sum(x * x)  # noqa: E731
  rows = [dict(programs=0, **reading())]
  for d in range(1, args.programs + 1):
    jax.block_until_ready(pso.run(0, sphere, -jnp.ones(d), jnp.ones(d), config=config).x)
    if d % args.every == 0:
      rows.append(dict(programs=d, **reading()))
  jax.clear_caches()
  gc.collect()
  cleared = reading()
  per_program = (rows[-1]["maps"] - rows[0]["maps"]) / args.programs
  with open("/proc/sys/vm/max_map_count") as f:
    limit = int(f.read())
  info = common.machine()
  lines = ["# Memory held by compiled `pso.run` programs", "", common.machine_line(info), "",
           f"One program per dimension 1–{args.programs} (a sphere, 16 particles, 5 iterations)."
           f"  {per_program:.0f} memory mappings per program; `vm.max_map_count` {limit}: about"
           f" {(limit - rows[0]['maps']) / per_program:.0f} programs in one process."
           "  After `jax.clear_caches()`: "
           f"{cleared['maps']} mappings, {cleared['resident_mib']:.0f} MiB.", "",
           "| programs compiled | memory mappings | resident MiB |", "|---:|---:|---:|"]
  lines += [f"| {r['programs']} | {r['maps']} | {r['resident_mib']:.0f} |" for r in rows]
  lines.append(f"| after `jax.clear_caches()` | {cleared['maps']} | {cleared['resident_mib']:.0f} |")
  common.write("program_memory", {"machine": info, "rows": rows, "cleared": cleared,
                                  "maps_per_program": per_program, "max_map_count": limit},
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
