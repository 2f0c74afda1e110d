"""PSO variants × topologies on the Baker–Matthews protocol (the paper's Fig. 8).

The trials of benchmarks/convergence.py (the same templates, corner
perturbations of σ px and keys, condition "none"; images cut to 320×320
around the template as in benchmarks/swarm_size.py) aligned by `jaxpso.align`
with `TrackConfig(variant=..., topology=..., accept_quality=None,
retry_quality=-1e9)`, otherwise defaults (32 particles, at most 40
iterations, stagnation stop after 10): the swarm always runs, exactly once,
so the swarm and the refinement alone decide.  Each combination also runs
with refine_steps=0, the swarm alone as in the paper: its estimate is then
the swarm's best at the coarsest pyramid level (1/8 resolution), so the
success threshold of 1 px is out of its reach and the 5 px one is the
informative one.

Grids (--grid): "full", every variant × every topology; "cross", every
variant with von_neumann plus every topology with constriction (the
defaults).  Each combination and refine_steps value is one compilation of
`align` (about a minute on a busy 2-core machine).

Usage: python benchmarks/variants.py [--grid cross] [--trials N] [--refine-steps 10,0]
"""

from __future__ import annotations

import argparse
import os

import jax
import numpy as np

import common
import jaxpso
from swarm_size import run_protocol

DEFAULT = jaxpso.TrackConfig()


def combinations(grid: str, variants, topologies):
  """(variant, topology) pairs of a grid (see the module docstring)."""
  if grid == "full":
    return [(v, t) for v in variants for t in topologies]
  pairs = [(v, DEFAULT.topology) for v in variants]
  return pairs + [(DEFAULT.variant, t) for t in topologies if (DEFAULT.variant, t) not in pairs]


def plot(rows, sigmas, path: str) -> None:
  """Success (refined), success within 5 px and median error (swarm alone) per combination."""
  import matplotlib

  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  labels = list(dict.fromkeys(f"{r['variant']} / {r['topology']}" for r in rows))
  panels = [("success <= 1 px (%), refined", True, lambda r: 100 * r["success"]),
            ("success <= 5 px (%), swarm alone", False, lambda r: 100 * r["success_5px"]),
            ("median corner error (px), swarm alone", False, lambda r: r["median_error_px"])]
  panels = [p for p in panels if any((r["refine_steps"] > 0) == p[1] for r in rows)]
  figure, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 0.3 * len(labels) + 1.5),
                              sharey=True, squeeze=False)
  height = 0.8 / len(sigmas)
  for axis, (title, refined, value) in zip(axes[0], panels):
    for k, sigma in enumerate(sigmas):
      by_label = {f"{r['variant']} / {r['topology']}": value(r) for r in rows
                  if (r["refine_steps"] > 0) == refined and r["sigma"] == sigma}
      axis.barh(np.arange(len(labels)) + k * height, [by_label.get(l, np.nan) for l in labels],
                height, label=f"σ = {sigma:g} px")
    axis.set_title(title, fontsize=9)
    axis.grid(axis="x", alpha=0.3)
  axes[0][0].set_yticks(np.arange(len(labels)) + 0.4 - height / 2, labels, fontsize=8)
  axes[0][0].invert_yaxis()
  axes[0][-1].legend(fontsize=8)
  figure.tight_layout()
  figure.savefig(path, dpi=80)


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--grid", choices=("full", "cross"), default="full")
  parser.add_argument("--variants", default=",".join(jaxpso.pso.VARIANTS))
  parser.add_argument("--topologies", default=",".join(jaxpso.pso.TOPOLOGIES))
  parser.add_argument("--refine-steps", default="10,0")
  parser.add_argument("--sigmas", default="12,20")
  parser.add_argument("--trials", type=int, default=50, help="trials per σ")
  args = parser.parse_args()
  sigmas = [float(s) for s in args.sigmas.split(",")]
  pairs = combinations(args.grid, args.variants.split(","), args.topologies.split(","))
  rows = []
  for steps in (int(s) for s in args.refine_steps.split(",")):
    for variant, topology in pairs:
      config = jaxpso.TrackConfig(variant=variant, topology=topology, refine_steps=steps,
                                  accept_quality=None, retry_quality=-1e9)
      for sigma in sigmas:
        out = run_protocol(config, sigma, args.trials)
        rows.append({"variant": variant, "topology": topology, "refine_steps": steps,
                     "sigma": sigma, "trials": args.trials,
                     "success": float(np.mean(out["error"] <= 1.0)),
                     "success_5px": float(np.mean(out["error"] <= 5.0)),
                     "median_error_px": float(np.median(out["error"])),
                     "median_swarm_iterations": float(np.median(out["swarm_iterations"])),
                     "median_evaluations": float(np.median(out["evaluations"])),
                     "median_ms": 1e3 * float(np.median(out["seconds"]))})
        print(rows[-1], flush=True)
      jax.clear_caches()  # two dozen compiled `align`s in one process ran out of memory maps

  info = common.machine()
  lines = [
      "# PSO variants × topologies: convergence (Baker–Matthews protocol, jaxpso.align)",
      "",
      common.machine_line(info),
      "",
      f"{args.trials} trials per σ (the first trials and keys of benchmarks/convergence.py,"
      " condition \"none\", images cut to 320×320 around the template); grid"
      f" \"{args.grid}\".  `TrackConfig(variant, topology, refine_steps,"
      " accept_quality=None, retry_quality=-1e9)`, otherwise defaults (32 particles, at most"
      " 40 iterations, patience 10): one swarm per alignment, then refine_steps Gauss–Newton"
      " steps per level (0: the swarm's coarsest-level best is the result).  Success ="
      " corner RMS error <= 1 px (and <= 5 px).  Swarm iterations: until the stagnation stop"
      " or 40.  Times are medians per alignment after compilation on a shared machine.",
      "",
      "| refine steps | variant | topology | σ (px) | success | ≤ 5 px | median error (px) | swarm iterations | median ms |",
      "|---:|---|---|---:|---:|---:|---:|---:|---:|",
  ]
  for r in rows:
    lines.append(f"| {r['refine_steps']} | {r['variant']} | {r['topology']} | {r['sigma']:g} |"
                 f" {100 * r['success']:.0f} % | {100 * r['success_5px']:.0f} % |"
                 f" {r['median_error_px']:.2f} | {r['median_swarm_iterations']:.0f} |"
                 f" {r['median_ms']:.1f} |")
  plot(rows, sigmas, os.path.join(common.RESULTS, "variants.png"))
  common.write("variants", {"machine": info, "grid": args.grid, "rows": rows},
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
