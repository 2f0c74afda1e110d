"""Swarm size: convergence, time per alignment and the cost of one swarm iteration.

The Baker–Matthews protocol of benchmarks/convergence.py (the same 100×100
templates, corner perturbations of σ px and keys; success = corner RMS error
<= 1 px) with `jaxpso.align` and swarms of 8 to 4096 particles.  Every
configuration has accept_quality=None (the start refined by Gauss–Newton alone
is never accepted), retry_quality=-1e9 (no second swarm) and patience=None (no
stagnation stop), so every alignment runs exactly one swarm of
`max_iterations` iterations, then the refinement, and a swarm iteration has
the same meaning at every size.

Each image is cut to 320×320 around its template (at least the protocol's
80 px on every side) so that `align` works in one window shape and compiles
once per swarm size; alignment times exclude that compilation.

Cost curve: time per swarm iteration = median time per alignment /
(max_iterations + 1) (the swarm is evaluated once more at initialisation); it
includes the alignment's fixed cost (pyramids, Gauss–Newton), which only the
small swarms notice.  A straight line is fitted to the sizes >= --fit-from.

Usage: python benchmarks/swarm_size.py [--trials N] [--big-trials M] [--sizes 8,16,...]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import time

import jax
import numpy as np

import common
import convergence
import jaxpso
from jaxpso._src.data import load_image

CROP = 320
"""Side of the image cut around each template."""


@functools.cache
def _image(name: str) -> np.ndarray:
  """The embedded image `name`, loaded once."""
  return load_image(name)


def protocol_trials(count: int, sigma: float):
  """convergence.py's trials, the unchanged images cut to CROP × CROP around the template.

  Args:
    count: trials.  sigma: corner noise (px).

  Yields:
    (image crop, template, start homography in crop pixels, template origin in
    crop pixels).
  """
  for name, origin, start in convergence.trials(count, sigma, int(sigma) * 7):
    image = _image(name)
    x, y = int(origin[0]), int(origin[1])
    template = image[y:y + convergence.SIZE, x:x + convergence.SIZE]
    limit = np.array(image.shape[::-1]) - CROP
    corner = np.clip(origin + (convergence.SIZE - CROP) / 2, 0, limit).astype(int)
    shift = np.float32([[1, 0, -corner[0]], [0, 1, -corner[1]], [0, 0, 1]])
    crop = image[corner[1]:corner[1] + CROP, corner[0]:corner[0] + CROP]
    yield crop, template, shift @ start, origin - corner


def swarm_iterations(result, config: jaxpso.TrackConfig) -> float:
  """The swarm iterations k of an alignment that ran one swarm, from its counts.

  `align` counts k plus the refinement's steps g as iterations and
  n·(k + 1) + g evaluations, plus one full-resolution loss per refined
  candidate (two) when `pixels` < 1; hence k = (E − I − n − extra)/(n − 1).
  A second swarm would make this a non-integer or larger than
  `max_iterations`.
  """
  n = config.swarm_size
  extra = 2 if config.pixels < 1 else 0
  return (int(result.num_evaluations) - int(result.num_iterations) - n - extra) / (n - 1)


def run_protocol(config: jaxpso.TrackConfig, sigma: float, count: int) -> dict:
  """`align` on `count` trials at σ; per-trial corner errors, seconds and counts.

  The first trial is aligned once more beforehand, untimed, to compile.
  """
  cases = list(protocol_trials(count, sigma))
  crop, template, start, _ = cases[0]
  jax.block_until_ready(jaxpso.align(crop, template, start, config=config))
  out = {"error": [], "seconds": [], "evaluations": [], "swarm_iterations": []}
  for i, (crop, template, start, origin) in enumerate(cases):
    begin = time.perf_counter()
    result = jax.block_until_ready(jaxpso.align(crop, template, start, config=config, key=i))
    out["seconds"].append(time.perf_counter() - begin)
    out["error"].append(common.corner_error(result.homography, origin))
    out["evaluations"].append(int(result.num_evaluations))
    out["swarm_iterations"].append(swarm_iterations(result, config))
  return {key: np.asarray(value) for key, value in out.items()}


def plot(rows, curve, fit, path: str) -> None:
  """Success and median error vs swarm size, and the cost curve, as a PNG."""
  import matplotlib

  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  figure, axes = plt.subplots(1, 3, figsize=(13, 3.8))
  for sigma in sorted({r["sigma"] for r in rows}):
    mine = [r for r in rows if r["sigma"] == sigma]
    sizes = [r["swarm_size"] for r in mine]
    axes[0].plot(sizes, [100 * r["success"] for r in mine], "o-", label=f"σ = {sigma:g} px")
    axes[1].plot(sizes, [r["median_error_px"] for r in mine], "o-", label=f"σ = {sigma:g} px")
  axes[0].set_ylabel("success (%)")
  axes[1].set_ylabel("median corner error (px)")
  axes[1].set_yscale("log")
  sizes = np.array([c["swarm_size"] for c in curve])
  axes[2].plot(sizes, [c["ms_per_iteration"] for c in curve], "o", label="measured")
  upper = sizes[sizes >= fit["from"]]
  axes[2].plot(upper, fit["intercept_ms"] + fit["slope_us"] * 1e-3 * upper, "-",
               label=f"fit: {fit['slope_us']:.1f} µs / particle")
  axes[2].set_yscale("log")
  axes[2].set_ylabel("ms per swarm iteration")
  for axis in axes:
    axis.set_xscale("log", base=2)
    axis.set_xlabel("swarm size")
    axis.legend(fontsize=8)
    axis.grid(alpha=0.3)
  figure.tight_layout()
  figure.savefig(path, dpi=80)


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--sizes", default=",".join(str(2 ** k) for k in range(3, 13)))
  parser.add_argument("--sigmas", default="12,20")
  parser.add_argument("--trials", type=int, default=50, help="trials per σ")
  parser.add_argument("--big-trials", type=int, default=10,
                      help="trials per σ for swarms of --big-from particles or more")
  parser.add_argument("--big-from", type=int, default=1024)
  parser.add_argument("--fit-from", type=int, default=512,
                      help="smallest swarm of the straight-line fit of the cost curve")
  args = parser.parse_args()
  sizes = [int(s) for s in args.sizes.split(",")]
  sigmas = [float(s) for s in args.sigmas.split(",")]
  base = jaxpso.TrackConfig(accept_quality=None, retry_quality=-1e9, patience=None)
  rows, curve = [], []
  for size in sizes:
    config = dataclasses.replace(base, swarm_size=size)
    count = args.big_trials if size >= args.big_from else args.trials
    seconds = []
    for sigma in sigmas:
      out = run_protocol(config, sigma, count)
      seconds.extend(out["seconds"])
      rows.append({"swarm_size": size, "sigma": sigma, "trials": count,
                   "success": float(np.mean(out["error"] <= 1.0)),
                   "median_error_px": float(np.median(out["error"])),
                   "median_ms": 1e3 * float(np.median(out["seconds"])),
                   "median_evaluations": float(np.median(out["evaluations"])),
                   "swarm_iterations": sorted(set(out["swarm_iterations"].tolist()))})
      print(rows[-1], flush=True)
    curve.append({"swarm_size": size,
                  "ms_per_iteration": 1e3 * float(np.median(seconds)) / (base.max_iterations + 1)})
  for previous, entry in zip([None] + curve[:-1], curve):
    entry["ratio_to_previous"] = (None if previous is None else
                                  entry["ms_per_iteration"] / previous["ms_per_iteration"])
  upper = [c for c in curve if c["swarm_size"] >= args.fit_from]
  slope, intercept = np.polyfit([c["swarm_size"] for c in upper],
                                [c["ms_per_iteration"] for c in upper], 1)
  fit = {"from": args.fit_from, "slope_us": 1e3 * float(slope), "intercept_ms": float(intercept)}

  info = common.machine()
  lines = [
      "# Swarm size: convergence and cost (Baker–Matthews protocol, jaxpso.align)",
      "",
      common.machine_line(info),
      "",
      f"Trials per σ: {args.trials}, {args.big_trials} for swarms of {args.big_from} particles"
      " or more (same trials and keys as benchmarks/convergence.py, the first ones when"
      " fewer), condition \"none\"; images cut to 320×320 around the template.  Success ="
      " corner RMS error <= 1 px.  `TrackConfig(swarm_size=n, accept_quality=None,"
      " retry_quality=-1e9, patience=None)`, otherwise defaults: exactly one swarm of"
      f" {base.max_iterations} iterations per alignment, then Gauss–Newton.  Times are medians"
      " per alignment after compilation; the machine is shared, so compare within this run.",
      "",
      "| swarm | σ (px) | trials | success | median error (px) | median ms | median evaluations | swarm iterations |",
      "|---:|---:|---:|---:|---:|---:|---:|---|",
  ]
  for r in rows:
    lines.append(f"| {r['swarm_size']} | {r['sigma']:g} | {r['trials']} | {100 * r['success']:.0f} % |"
                 f" {r['median_error_px']:.2f} | {r['median_ms']:.1f} | {r['median_evaluations']:.0f} |"
                 f" {', '.join(f'{k:g}' for k in r['swarm_iterations'])} |")
  lines += [
      "",
      "## Cost curve",
      "",
      f"ms per swarm iteration = median ms per alignment (all σ) / {base.max_iterations + 1};"
      " ratio = to the next smaller swarm (2 = linear in the swarm size).  Straight line"
      f" fitted to swarms >= {args.fit_from}: {fit['slope_us']:.2f} µs per particle per"
      f" iteration + {fit['intercept_ms']:.2f} ms.",
      "",
      "| swarm | ms per swarm iteration | ratio | fit (ms) |",
      "|---:|---:|---:|---:|",
  ]
  for c in curve:
    ratio = "" if c["ratio_to_previous"] is None else f"{c['ratio_to_previous']:.2f}"
    fitted = fit["intercept_ms"] + fit["slope_us"] * 1e-3 * c["swarm_size"]
    lines.append(f"| {c['swarm_size']} | {c['ms_per_iteration']:.3f} | {ratio} | {fitted:.3f} |")
  plot(rows, curve, fit, os.path.join(common.RESULTS, "swarm_size.png"))
  common.write("swarm_size", {"machine": info, "config": repr(base), "rows": rows,
                              "cost_curve": curve, "fit": fit}, "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
