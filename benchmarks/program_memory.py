"""What compiled `pso.run` programs hold in a process, and what `jax.clear_caches()` frees.

A sweep over swarm settings compiles one program per (loss function, static
setting, dimension); jaxpso keeps the 16 last used (`programs.MAX_PROGRAMS`)
and releases the others.  This compiles `--programs` programs (a 6-D sphere
with 2, 3, ... particles: one each), reading the process's memory mappings
(/proc/self/maps, Linux) and resident memory every `--every`, then calls
`jax.clear_caches()` and reads them again.  What each program adds once the
table is full (from the first reading on) is what a long sweep accumulates;
Linux stops a process at `vm.max_map_count` mappings (65 530 by default),
and the table gives how many programs that allows.

Writes results/program_memory.{json,md}.

Usage: python benchmarks/program_memory.py [--programs 700] [--every 100]
"""

from __future__ import annotations

import argparse
import gc

import jax
import jax.numpy as jnp

import common
from jaxpso import pso
from jaxpso._src import programs


def reading() -> dict:
  """The process's memory mappings and resident MiB now."""
  with open("/proc/self/maps") as f:
    maps = sum(1 for _ in f)
  with open("/proc/self/statm") as f:
    resident = int(f.read().split()[1]) * 4096 / 2**20
  return {"maps": maps, "resident_mib": round(resident, 1)}


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--programs", type=int, default=700)
  parser.add_argument("--every", type=int, default=100)
  args = parser.parse_args()
  if args.every < programs.MAX_PROGRAMS or args.programs < 2 * args.every:
    parser.error(f"--every must be at least {programs.MAX_PROGRAMS} and --programs at least"
                 " twice --every")
  sphere = lambda x, _: jnp.sum(x * x)  # noqa: E731
  lower, upper = -jnp.ones(6), jnp.ones(6)
  rows = [dict(programs=0, **reading())]
  for count in range(1, args.programs + 1):
    config = pso.PSOConfig(swarm_size=count + 1, max_iterations=5, patience=None)
    jax.block_until_ready(pso.run(0, sphere, lower, upper, config=config).x)
    if count % args.every == 0:
      rows.append(dict(programs=count, **reading()))
  jax.clear_caches()
  gc.collect()
  cleared = reading()
  full = rows[1]  # the table holds its 16 programs from here on
  per_program = (rows[-1]["maps"] - full["maps"]) / (rows[-1]["programs"] - full["programs"])
  per_program_mib = ((rows[-1]["resident_mib"] - full["resident_mib"])
                     / (rows[-1]["programs"] - full["programs"]))
  with open("/proc/sys/vm/max_map_count") as f:
    limit = int(f.read())
  if per_program > 0.5:
    bound = (f"`vm.max_map_count` {limit}: about"
             f" {(limit - full['maps']) / per_program + full['programs']:.0f} programs in one"
             " process.")
  else:
    bound = f"the mappings do not grow towards `vm.max_map_count` ({limit})."
  info = common.machine()
  lines = ["# Memory held by compiled `pso.run` programs", "", common.machine_line(info), "",
           f"One program per swarm size 2–{args.programs + 1} (a 6-D sphere, 5 iterations);"
           f" jaxpso keeps the {programs.MAX_PROGRAMS} last used.  From {full['programs']} programs"
           f" on, each adds {per_program:.1f} memory mappings and {per_program_mib:.1f} MiB;"
           f" {bound}"
           "  After `jax.clear_caches()`: "
           f"{cleared['maps']} mappings, {cleared['resident_mib']:.0f} MiB.", "",
           "| programs compiled | memory mappings | resident MiB |", "|---:|---:|---:|"]
  lines += [f"| {r['programs']} | {r['maps']} | {r['resident_mib']:.0f} |" for r in rows]
  lines.append(f"| after `jax.clear_caches()` | {cleared['maps']} | {cleared['resident_mib']:.0f} |")
  common.write("program_memory", {"machine": info, "rows": rows, "cleared": cleared,
                                  "maps_per_program": per_program,
                                  "mib_per_program": per_program_mib, "max_map_count": limit},
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
