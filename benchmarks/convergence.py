"""Frequency of convergence, the Baker–Matthews protocol, for every alignment method.

100×100 templates cut at random places of the embedded camera and brick
images; the 4 corners perturbed by Gaussian noise of σ px define the initial
homography; success when the RMS of the 4 corner errors is <= 1 px.  A start whose quad
the horizon cuts (the corners' w of both signs, possible at σ >= 16) is a
ValueError of `jaxpso.align`, counted as a failure of every jaxpso method
(`rejected_starts`) and left out of its times; OpenCV's ECC still runs it.  The
photometric condition changes the image only (the template always comes from
the unchanged image): none, gain/bias (v ↦ 0.7 v + 0.2), gamma 0.5 (v ↦ √v),
inverted (v ↦ 1 − v), noise (Gaussian, σ 0.03, clipped to [0, 1]) and
shading (v ↦ g v, clipped, g a linear ramp from 0.5 at the top-left corner
to 1.3 at the bottom-right).  Every
method aligns the same trials: the same templates and starts for a σ (drawn
from the seed 7σ whatever the condition), and under "noise" the same noisy
image.

Methods (`--methods`): `jaxpso.align` with the swarm (the default
`TrackConfig`, MI; and with NCC and SSD), every gradient baseline of
`jaxpso.METHODS` with a similarity it supports ("fa", "fc", "ic", "esm", "ha":
SSD; "adam", "lbfgs": MI; "ecc": NCC, `max_iterations=100`), and OpenCV's
`cv2.findTransformECC` called directly (homography, 100 iterations, eps 1e-6,
gaussFiltSize 5; an exception counts as a failure) and its pyramid version
`cv2.findTransformECCMultiScale` (the same settings per level, 2 pyramid
levels, `ECC_LEVELS`).  Times are wall-clock
medians per alignment, the alignments of a trial run one after the other; a
call that compiled is repeated for its time.

Equal evaluation budget (`--budget E`, on `--budget-conditions`): every
method is capped at E similarity evaluations, counted as `AlignResult.
num_evaluations` counts them (one swarm particle, one Gauss–Newton, Adam or
ECC iteration, one L-BFGS line-search step; a gradient comes with its
evaluation):

* pso: `retry_quality=-inf` (no second swarm) and `max_iterations` =
  ⌊(E − G) / swarm_size⌋ − 1, where G = refine_steps × (2 + levels) + 2 is
  the most the Gauss–Newton refinements spend (from the start on levels 1
  and 0, after the swarm on every level, plus two full-template losses) and
  the swarm evaluates swarm_size particles at its start and per iteration;
* gradient baselines: `max_iterations` = ⌊(E − 1) / L⌋ over the L pyramid
  levels they align on (`baselines.pyramid_levels`), plus the final loss.
  L-BFGS's line search can take several evaluations per iteration, so its
  count can exceed E (the measured maximum is reported);
* ECC (jaxpso's and OpenCV's): E iterations at full resolution.

The equal-time view is success against median time per method over all the
trials run (the PNG's last panel and a table).

Writes results/convergence.{json,md,png} (`--name` for another name).

Usage: python benchmarks/convergence.py [--trials N] [--sigmas 2,4,...]
  [--methods pso-mi,ic,...] [--conditions none,gamma,...] [--budget E]
  [--budget-trials N] [--budget-conditions none,...]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

import cv2
import jax
import numpy as np

import common
import jaxpso
from jaxpso._src import programs
from jaxpso._src import baselines
from jaxpso._src.data import load_image

SIZE = 100
SOURCE = np.float32([[0, 0], [SIZE - 1, 0], [SIZE - 1, SIZE - 1], [0, SIZE - 1]])


def _ramp(shape) -> np.ndarray:
  """A smooth illumination: gain 0.5 at the image's top-left corner to 1.3 at its bottom-right."""
  rows, columns = np.mgrid[:shape[0], :shape[1]]
  return 0.5 + 0.4 * (rows / (shape[0] - 1) + columns / (shape[1] - 1))


CONDITIONS = {  # name → (label, image ↦ changed image, given the trial's generator)
    "none": ("none", lambda v, rng: v),
    "gain": ("gain/bias 0.7 v + 0.2", lambda v, rng: 0.7 * v + 0.2),
    "gamma": ("gamma 0.5", lambda v, rng: np.sqrt(v)),
    "inverted": ("inverted", lambda v, rng: 1.0 - v),
    "noise": ("noise σ 0.03", lambda v, rng: np.clip(v + rng.normal(0, 0.03, v.shape), 0, 1)),
    "shading": ("shading ramp", lambda v, rng: np.clip(v * _ramp(v.shape), 0, 1)),
}
METHODS = {  # name → (label, TrackConfig fields, or None for OpenCV's ECC)
    "pso-mi": ("pso (MI)", {}),
    "pso-mi-one-retry": ("pso (MI), retries=0", {"retries": 0}),
    "pso-ncc": ("pso (NCC)", {"similarity": "ncc"}),
    "pso-ssd": ("pso (SSD)", {"similarity": "ssd"}),
    "fa": ("fa (SSD)", {"method": "fa", "similarity": "ssd"}),
    "fc": ("fc (SSD)", {"method": "fc", "similarity": "ssd"}),
    "ic": ("ic (SSD)", {"method": "ic", "similarity": "ssd"}),
    "esm": ("esm (SSD)", {"method": "esm", "similarity": "ssd"}),
    "ha": ("ha (SSD)", {"method": "ha", "similarity": "ssd"}),
    "adam": ("adam (MI)", {"method": "adam"}),
    "lbfgs": ("lbfgs (MI)", {"method": "lbfgs"}),
    "ecc": ("ecc (NCC)", {"method": "ecc", "similarity": "ncc", "max_iterations": 100}),
    "opencv-ecc": ("OpenCV ECC", None),
    "opencv-ecc-ms": ("OpenCV ECC multi-scale", None),
}
ECC_ITERATIONS = 100
# findTransformECCMultiScale's levels: of 1-4, 2 converged most often on 50 trials of the
# unchanged image at σ 2, 8, 16 (88 / 56 / 20 %; OpenCV's default 4: 44 / 40 / 12 %).
ECC_LEVELS = 2
# Targets for pso (MI): (condition, σ, least success).
TARGETS = (("none", 16, 0.97), ("none", 20, 0.90), ("gamma", 8, 0.90), ("inverted", 8, 0.90))
TIME_RATIO = 3.0  # pso (MI)'s median time at most this × OpenCV ECC's


def trials(count: int, sigma: float, seed: int):
  """(image name, template origin, initial homography) for each trial."""
  rng = np.random.default_rng(seed)
  for _ in range(count):
    name = ("camera", "brick")[rng.integers(2)]
    origin = rng.integers(80, 512 - SIZE - 80, size=2).astype(np.float32)
    start = SOURCE + origin + rng.normal(0, sigma, (4, 2)).astype(np.float32)
    yield name, origin, cv2.getPerspectiveTransform(SOURCE, start).astype(np.float32)


def trial_images(images: dict, condition: str, sigma: float, count: int, offset: int = 0):
  """(i, origin, image, template, start) of each trial of (condition, σ); `offset` shifts the
  trials' seeds (0: the committed trials)."""
  change = CONDITIONS[condition][1]
  for i, (name, origin, start) in enumerate(trials(count, sigma, int(sigma) * 7 + offset)):
    x, y = int(origin[0]), int(origin[1])
    template = images[name][y:y + SIZE, x:x + SIZE]
    image = change(images[name], np.random.default_rng([int(sigma), i + offset]))
    yield i, origin, image.astype(np.float32), template, start


def run_ecc(image, template, start, iterations: int = ECC_ITERATIONS):
  criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 1e-6)
  try:
    _, h = cv2.findTransformECC(template, image, start.copy(), cv2.MOTION_HOMOGRAPHY, criteria,
                                None, 5)
    return h
  except cv2.error:
    return None


def run_ecc_multiscale(image, template, start, iterations: int = ECC_ITERATIONS):
  """`cv2.findTransformECCMultiScale` on `ECC_LEVELS` pyramid levels, `iterations` per level."""
  params = cv2.ECCParameters()
  params.motionType = cv2.MOTION_HOMOGRAPHY
  params.nlevels = ECC_LEVELS
  params.criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 1e-6)
  params.gaussFiltSize = 5
  try:
    _, h = cv2.findTransformECCMultiScale(template, image, start.copy(), params)
    return h
  except cv2.error:
    return None


OPENCV = {"opencv-ecc": run_ecc, "opencv-ecc-ms": run_ecc_multiscale}


def budget_config(config: jaxpso.TrackConfig, budget: int) -> jaxpso.TrackConfig:
  """`config` capped at `budget` similarity evaluations (module docstring), levels resolved."""
  config = config.for_template((SIZE, SIZE))
  if config.method == "pso":
    refinements = config.refine_steps * (2 + config.levels) + 2
    iterations = (budget - refinements) // config.swarm_size - 1
    if iterations < 1:
      raise ValueError(f"a budget of {budget} evaluations leaves the swarm no iteration")
    return dataclasses.replace(config, max_iterations=iterations, retry_quality=-np.inf)
  if config.method == "ecc":
    return dataclasses.replace(config, max_iterations=budget)
  used = baselines.pyramid_levels(config.method, (SIZE, SIZE), config.levels)
  return dataclasses.replace(config, max_iterations=max(1, (budget - 1) // used))


def _programs_made() -> int:
  counts = programs.counts()
  return counts["compiled"] + counts["loaded"]


def align_once(image, template, start, config, key):
  """(homography, seconds, evaluations) of one `jaxpso.align`; a compiling call is timed again."""
  compiled = _programs_made()
  t0 = time.perf_counter()
  result = jax.block_until_ready(jaxpso.align(image, template, start, config=config, key=key))
  seconds = time.perf_counter() - t0
  if _programs_made() != compiled:
    t0 = time.perf_counter()
    result = jax.block_until_ready(jaxpso.align(image, template, start, config=config, key=key))
    seconds = time.perf_counter() - t0
  return np.asarray(result.homography), seconds, int(result.num_evaluations)


def measure(methods: dict, conditions, sigmas, count: int, images, log):
  """One row per (condition, σ, method): success, median error, time and evaluations."""
  rows, agreement = [], []
  for condition in conditions:
    for sigma in sigmas:
      errors = {name: [] for name in methods}
      seconds = {name: [] for name in methods}
      evaluations = {name: [] for name in methods}
      rejected = {name: 0 for name in methods}
      for i, origin, image, template, start in trial_images(images, condition, sigma, count):
        found = {}
        for method, (config, iterations) in methods.items():
          if config is None:
            t0 = time.perf_counter()
            h = OPENCV[method](image, template, start, iterations)
            seconds[method].append(time.perf_counter() - t0)
            evaluations[method].append(iterations)
          else:
            try:
              h, spent, used = align_once(image, template, start, config, i)
            except ValueError:  # a start quad the horizon cuts: rejected, a failure
              h, spent, used = None, np.nan, 0
              rejected[method] += 1
            seconds[method].append(spent)
            evaluations[method].append(used)
          found[method] = h
          errors[method].append(np.inf if h is None else common.corner_error(h, origin))
        if "ecc" in found and "opencv-ecc" in found and found["opencv-ecc"] is not None:
          direct = cv2.perspectiveTransform(SOURCE[None], found["opencv-ecc"].astype(np.float64))
          ours = cv2.perspectiveTransform(SOURCE[None], found["ecc"].astype(np.float64))
          agreement.append(float(np.max(np.abs(direct - ours))))
      for method in methods:
        e = np.asarray(errors[method])
        rows.append({"condition": condition, "sigma": sigma, "method": method,
                     "label": METHODS[method][0], "trials": len(e),
                     "success": float(np.mean(e <= 1.0)),
                     "median_error_px": float(np.median(e)),
                     "median_ms": float(np.nanmedian(seconds[method]) * 1e3),
                     "rejected_starts": rejected[method],
                     "median_evaluations": float(np.median(evaluations[method])),
                     "max_evaluations": int(np.max(evaluations[method]))})
        log(rows[-1])
  return rows, agreement


def percent(value) -> str:
  return f"{100 * value:.0f} %"


def find(rows, condition, sigma, method):
  return next((r for r in rows if r["condition"] == condition and r["sigma"] == sigma
               and r["method"] == method), None)


def success_matrix(rows, methods, conditions, sigmas) -> list[str]:
  """Markdown tables: success % (median error px) per method × σ, one per condition."""
  lines = []
  for condition in conditions:
    lines += [f"**{CONDITIONS[condition][0]}** ({rows_trials(rows, condition)} trials per σ)", "",
              "| method | " + " | ".join(f"σ {s:g}" for s in sigmas) + " | median ms |",
              "|---|" + "---:|" * (len(sigmas) + 1)]
    for method in methods:
      cells = [find(rows, condition, s, method) for s in sigmas]
      times = [c["median_ms"] for c in cells if c]
      lines.append(f"| {METHODS[method][0]} | " + " | ".join(
          f"{percent(c['success'])} ({c['median_error_px']:.2f})" for c in cells)
          + f" | {np.median(times):.1f} |")
    lines.append("")
  return lines


def rows_trials(rows, condition) -> int:
  return max(r["trials"] for r in rows if r["condition"] == condition)


def pooled(rows, method, conditions=None):
  """(success over the rows' trials, median of the rows' median times) of one method."""
  chosen = [r for r in rows if r["method"] == method
            and (conditions is None or r["condition"] in conditions)]
  trials_run = sum(r["trials"] for r in chosen)
  success = sum(r["success"] * r["trials"] for r in chosen) / trials_run
  return success, float(np.median([r["median_ms"] for r in chosen]))


def plot(rows, budget_rows, methods, conditions, sigmas, path: str) -> None:
  """Success vs σ per condition (and under the budget), and success vs time."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  panels = [(c, rows) for c in conditions] + [(c, budget_rows) for c in
                                                sorted({r["condition"] for r in budget_rows})]
  figure, axes = plt.subplots(2, (len(panels) + 2) // 2, figsize=(4.2 * ((len(panels) + 2) // 2), 8),
                              squeeze=False)
  axes = axes.ravel()
  palette = list(plt.get_cmap("tab10").colors) + ["black", "0.55"]
  colors = [palette[list(METHODS).index(m) % len(palette)] for m in methods]
  styles = {m: ("-" if m.startswith("pso") else "--" if "ecc" in m else ":") for m in methods}
  for axis, (condition, table) in zip(axes, panels):
    for color, method in zip(colors, methods):
      points = [find(table, condition, s, method) for s in sigmas]
      if all(points):
        axis.plot(sigmas, [100 * p["success"] for p in points], styles[method], color=color,
                  marker="o", markersize=3, linewidth=2 if method == "pso-mi" else 1.2,
                  label=METHODS[method][0])
    budget = f", ≤ {budget_rows[0]['budget']} evaluations" if table is budget_rows else ""
    axis.set_title(CONDITIONS[condition][0] + budget, fontsize=9)
    axis.set_xlabel("σ (px)")
    axis.set_ylabel("success (%)")
    axis.set_ylim(-3, 103)
    axis.grid(alpha=0.3)
  axes[0].legend(fontsize=6, loc="lower left")
  axis = axes[len(panels)]
  for color, method in zip(colors, methods):
    success, ms = pooled(rows, method)
    axis.scatter(ms, 100 * success, color=color)
    axis.annotate(METHODS[method][0], (ms, 100 * success), fontsize=6,
                  xytext=(3, 3), textcoords="offset points")
  axis.set_xscale("log")
  axis.set_xlabel("median ms per alignment")
  axis.set_ylabel("success over all trials (%)")
  axis.set_title("equal-time view (all conditions and σ)", fontsize=9)
  axis.grid(alpha=0.3)
  for axis in axes[len(panels) + 1:]:
    axis.axis("off")
  figure.tight_layout()
  figure.savefig(path, dpi=110)
  plt.close(figure)


def main():
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--trials", type=int, default=50, help="trials per σ and condition")
  parser.add_argument("--trials-for", default="",
                      help='other counts for some conditions, e.g. "gain=20,noise=20"')
  parser.add_argument("--sigmas", default="2,4,8,12,16,20")
  parser.add_argument("--methods", default=",".join(METHODS), help=", ".join(METHODS))
  parser.add_argument("--conditions", default=",".join(CONDITIONS), help=", ".join(CONDITIONS))
  parser.add_argument("--budget", type=int, default=400,
                      help="similarity evaluations per alignment of the equal-budget run (0: none)")
  parser.add_argument("--budget-trials", type=int, default=50)
  parser.add_argument("--budget-conditions", default="none")
  parser.add_argument("--name", default="convergence",
                      help="results/NAME.{json,md,png} (to keep runs of different scope apart)")
  args = parser.parse_args()
  sigmas = [float(s) for s in args.sigmas.split(",")]
  names = args.methods.split(",")
  conditions = args.conditions.split(",")
  budget_conditions = args.budget_conditions.split(",") if args.budget else []
  for name in names:
    if name not in METHODS:
      parser.error(f"unknown method {name!r}; choose from {', '.join(METHODS)}")
  for name in conditions + budget_conditions:
    if name not in CONDITIONS:
      parser.error(f"unknown condition {name!r}; choose from {', '.join(CONDITIONS)}")
  counts = {c: args.trials for c in conditions}
  for item in filter(None, args.trials_for.split(",")):
    condition, count = item.split("=")
    counts[condition.strip()] = int(count)
  images = {name: load_image(name) for name in ("camera", "brick")}
  configs = {n: jaxpso.TrackConfig(**METHODS[n][1]) if METHODS[n][1] is not None else None
             for n in names}
  began = time.perf_counter()

  def log(row):
    print(f"[{time.perf_counter() - began:6.0f} s] {row}", flush=True)

  rows, agreement = [], []
  for condition in conditions:
    more, agrees = measure({n: (c, ECC_ITERATIONS) for n, c in configs.items()}, [condition],
                           sigmas, counts[condition], images, log)
    rows += more
    agreement += agrees
  budget_rows = []
  if args.budget:
    capped = {n: (None if c is None else budget_config(c, args.budget), args.budget)
              for n, c in configs.items()}
    budget_rows, _ = measure(capped, budget_conditions, sigmas, args.budget_trials, images, log)
    for row in budget_rows:
      row["budget"] = args.budget
  minutes = (time.perf_counter() - began) / 60

  info = common.machine()
  lines = [
      "# Frequency of convergence (Baker–Matthews protocol): every jaxpso method and OpenCV ECC",
      "",
      common.machine_line(info) + f"  Run time {minutes:.0f} min.",
      "",
      "100×100 templates at random places of the embedded camera and brick images, the 4"
      " corners of the start perturbed by Gaussian noise of σ px; success = corner RMS error"
      " <= 1 px.  The condition changes the image only (gain/bias v ↦ 0.7 v + 0.2, gamma"
      " v ↦ √v, inverted v ↦ 1 − v, noise + N(0, 0.03²) clipped to [0, 1], shading v ↦ g v"
      " clipped, g from 0.5 at the top-left corner to 1.3 at the bottom-right).  Every method"
      " aligns the same trials (templates, starts, noisy images).  jaxpso methods:"
      " `TrackConfig` defaults with the method and similarity named (pso (MI) is"
      f" `TrackConfig()`: {jaxpso.TrackConfig()}); ecc (NCC) with max_iterations=100."
      "  OpenCV ECC: `cv2.findTransformECC`, homography, 100 iterations, eps 1e-6,"
      " gaussFiltSize 5, called directly; multi-scale: `cv2.findTransformECCMultiScale`,"
      f" the same settings per level, {ECC_LEVELS} levels.  Times: median wall time per alignment on a"
      " machine shared with other work (compare within this run only); a call that"
      " compiled was repeated for its time.",
      "",
  ]
  if "pso-mi" in names and "opencv-ecc" in names:
    lines += ["## Targets, pso (MI)", "",
              "| target | measured | met |", "|---|---:|---|"]
    for condition, sigma, least in TARGETS:
      row = find(rows, condition, sigma, "pso-mi")
      if row:
        lines.append(f"| success >= {percent(least)} at σ {sigma:g}, {CONDITIONS[condition][0]}"
                     f" | {percent(row['success'])} | {'yes' if row['success'] >= least else 'no'} |")
    for condition in conditions:
      ours = np.median([r["median_ms"] for r in rows
                        if r["method"] == "pso-mi" and r["condition"] == condition])
      ecc = np.median([r["median_ms"] for r in rows
                       if r["method"] == "opencv-ecc" and r["condition"] == condition])
      lines.append(f"| median time <= {TIME_RATIO:g}× OpenCV ECC's, {CONDITIONS[condition][0]}"
                   f" (median over σ of the medians) | {ours:.1f} ms = {ours / ecc:.1f}×"
                   f" ({ecc:.1f} ms) | {'yes' if ours <= TIME_RATIO * ecc else 'no'} |")
    lines.append("")
  opencv = [m for m in OPENCV if m in names]
  if "pso-mi" in names and opencv:
    below = [f"{CONDITIONS[r['condition']][0]} σ {r['sigma']:g} ({METHODS[m][0]}"
             f" {percent(find(rows, r['condition'], r['sigma'], m)['success'])})"
             for r in rows if r["method"] == "pso-mi" for m in opencv
             if find(rows, r["condition"], r["sigma"], m)["success"] > r["success"]]
    lines += [f"pso (MI) below {' or '.join(METHODS[m][0] for m in opencv)} in"
              f" {len(below)} of {sum(r['method'] == 'pso-mi' for r in rows)} cells"
              f"{': ' + ', '.join(below) if below else ''}.", ""]
  lines += ["## Success (median corner error, px) per σ", ""]
  lines += success_matrix(rows, names, conditions, sigmas)
  if agreement:
    lines += [f"jaxpso's ecc (NCC) against the direct OpenCV call on the same {len(agreement)}"
              f" trials: largest corner difference {max(agreement):.2g} px, more than 0.01 px"
              f" in {sum(a > 0.01 for a in agreement)}.", ""]
  lines += ["## Equal-time view", "",
            "Success over every trial run (all conditions and σ) against the median of the"
            " rows' median times; the PNG's last panel plots it.", "",
            "| method | success, all trials | success, condition none | median ms |",
            "|---|---:|---:|---:|"]
  for method in sorted(names, key=lambda m: pooled(rows, m)[1]):
    success, ms = pooled(rows, method)
    none = pooled(rows, method, ["none"])[0] if "none" in conditions else float("nan")
    lines.append(f"| {METHODS[method][0]} | {percent(success)} | {percent(none)} | {ms:.1f} |")
  lines.append("")
  if budget_rows:
    lines += [f"## Equal evaluation budget: at most {args.budget} similarity evaluations", "",
              "Caps as in the script's docstring; the measured evaluations per alignment"
              " (median / largest over the run) are listed.", "",
              "| method | cap | " + " | ".join(f"σ {s:g}" for s in sigmas)
              + " | evaluations | median ms |",
              "|---|---|" + "---:|" * (len(sigmas) + 2)]
    for condition in budget_conditions:
      for method in names:
        config = configs[method]
        capped = None if config is None else budget_config(config, args.budget)
        cap = (f"{args.budget} iterations" if capped is None or capped.method == "ecc" else
               f"swarm {capped.swarm_size} × {capped.max_iterations} iterations, no retry"
               if capped.method == "pso" else
               f"{capped.max_iterations} iterations × "
               f"{baselines.pyramid_levels(capped.method, (SIZE, SIZE), capped.levels)} levels")
        cells = [find(budget_rows, condition, s, method) for s in sigmas]
        lines.append(
            f"| {METHODS[method][0]} ({CONDITIONS[condition][0]}) | {cap} | "
            + " | ".join(percent(c["success"]) for c in cells)
            + f" | {np.median([c['median_evaluations'] for c in cells]):.0f} /"
            f" {max(c['max_evaluations'] for c in cells)}"
            f" | {np.median([c['median_ms'] for c in cells]):.1f} |")
    lines.append("")
  lines += ["## Every row", "",
            "| condition | σ (px) | method | trials | success | median error (px) | median ms |"
            " median evaluations | rejected starts |", "|---|---:|---|---:|---:|---:|---:|---:|---:|"]
  for r in rows + budget_rows:
    condition = CONDITIONS[r["condition"]][0] + (f", ≤ {r['budget']} evaluations"
                                                 if "budget" in r else "")
    lines.append(f"| {condition} | {r['sigma']:g} | {r['label']} | {r['trials']} |"
                 f" {percent(r['success'])} | {r['median_error_px']:.2f} | {r['median_ms']:.1f} |"
                 f" {r['median_evaluations']:.0f} | {r['rejected_starts']} |")
  png = os.path.join(common.RESULTS, args.name + ".png")
  try:
    plot(rows, budget_rows, names, conditions, sigmas, png)
  except ImportError:
    print("matplotlib is not installed (pip install jaxpso[plots]); no PNG written")
  common.write(args.name, {"machine": info, "minutes": minutes, "rows": rows,
                               "budget_rows": budget_rows, "ecc_agreement_px": agreement},
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
