"""Similarity surfaces under a non-linear intensity change (the paper's Fig. 1).

A 100×100 template from the embedded image, a frame whose intensities are
changed non-linearly (1 − √v: gamma 0.5 and inverted) and shifted by
(7, −5) px, and the SSD, ZNCC and MI surfaces over a grid of translations,
each grid evaluated as one swarm in one vectorised call.  Prints where each
measure peaks against the true shift: SSD and ZNCC peak at the wrong place,
MI at the true shift.  (This was the `jaxpso demo` command before the
tracker.)

Writes results/surfaces.csv (dx, dy and the three scores per shift),
results/surfaces.png (the three surfaces, needs matplotlib) and
results/surfaces.json/.md (peaks, errors and rates with the machine).

Usage: python benchmarks/surfaces.py [--radius R] [--out DIR]
"""

from __future__ import annotations

import argparse
import csv
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import common
from jaxpso import similarity
from jaxpso import warp
from jaxpso._src import data

SHAPE = (100, 100)
ORIGIN = (206.0, 156.0)
TRUE_SHIFT = (7.0, -5.0)


def surfaces(radius: int):
  """Scores of every measure over a (2·radius+1)² grid of translations."""
  image = jnp.asarray(data.load_image("camera"))
  template = warp.warp_image(image, warp.translation(*map(jnp.float32, ORIGIN)), SHAPE)[0]
  frame_to_image = warp.translation(jnp.float32(-TRUE_SHIFT[0]), jnp.float32(-TRUE_SHIFT[1]))
  frame = warp.warp_image(image, frame_to_image, image.shape)[0]
  frame = 1.0 - jnp.sqrt(frame)  # a non-linear, decreasing intensity change
  steps = jnp.arange(-radius, radius + 1, dtype=jnp.float32)
  dx, dy = jnp.meshgrid(steps, steps)
  homographies = warp.translation(ORIGIN[0] + dx.ravel(), ORIGIN[1] + dy.ravel())
  measures = {"ssd": similarity.ssd, "ncc": similarity.ncc, "mi": similarity.mi}
  results = {}
  for name, measure in measures.items():
    evaluate = jax.jit(
        lambda h, measure=measure: measure(template, *warp.warp_image(frame, h, SHAPE)))
    jax.block_until_ready(evaluate(homographies))
    start = time.perf_counter()
    scores = np.asarray(evaluate(homographies))
    seconds = time.perf_counter() - start
    results[name] = (scores.reshape(dx.shape), seconds)
  return np.asarray(dx), np.asarray(dy), results


def plot(dx, dy, results, path: str) -> None:
  """Writes the three surfaces as a PNG if matplotlib is installed."""
  try:
    import matplotlib
  except ImportError:
    print("matplotlib is not installed (pip install jaxpso[plots]); no PNG written")
    return
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  figure, axes = plt.subplots(1, len(results), figsize=(4 * len(results), 3.6))
  for axis, (name, (scores, _)) in zip(axes, results.items()):
    shown = np.where(np.isfinite(scores), scores, np.nan)
    image = axis.imshow(-shown if name == "ssd" else shown, origin="lower",
                        extent=(dx.min(), dx.max(), dy.min(), dy.max()))
    axis.plot(*TRUE_SHIFT, "r+", markersize=12)
    axis.set_title(f"{'-ssd' if name == 'ssd' else name} (+: true shift)")
    axis.set_xlabel("dx (px)")
    axis.set_ylabel("dy (px)")
    figure.colorbar(image, ax=axis)
  figure.tight_layout()
  figure.savefig(path, dpi=80)
  print(f"wrote {path}")


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--radius", type=int, default=15, help="search radius in px (default 15)")
  parser.add_argument("--out", default=common.RESULTS,
                      help="folder for surfaces.csv and surfaces.png (default benchmarks/results)")
  args = parser.parse_args()
  radius = args.radius
  if radius < 1:
    parser.error(f"--radius must be >= 1, got {radius}")
  dx, dy, results = surfaces(radius)
  n = dx.size
  print(f"template 100×100 from the embedded image; frame = 1 - sqrt(image) shifted by"
        f" {TRUE_SHIFT}; {n} candidate shifts per measure, one vectorised call each")
  print(f"{'measure':8s} {'peak (dx, dy)':>16s} {'error px':>9s} {'M px/s':>8s}")
  rows = []
  for name, (scores, seconds) in results.items():
    best = np.argmin(scores) if name == "ssd" else np.argmax(scores)
    peak = (float(dx.flat[best]), float(dy.flat[best]))
    error = float(np.hypot(peak[0] - TRUE_SHIFT[0], peak[1] - TRUE_SHIFT[1]))
    rate = n * SHAPE[0] * SHAPE[1] / seconds / 1e6
    print(f"{name:8s} {str(peak):>16s} {error:9.2f} {rate:8.1f}")
    rows.append({"measure": name, "peak": peak, "error_px": error, "mpx_per_s": rate})
  os.makedirs(args.out, exist_ok=True)
  path = os.path.join(args.out, "surfaces.csv")
  with open(path, "w", newline="") as f:
    writer = csv.writer(f)
    writer.writerow(["dx", "dy"] + list(results))
    for i in range(n):
      writer.writerow([dx.flat[i], dy.flat[i]] + [results[m][0].flat[i] for m in results])
  print(f"wrote {path}")
  plot(dx, dy, results, os.path.join(args.out, "surfaces.png"))
  if os.path.abspath(args.out) == os.path.abspath(common.RESULTS):
    info = common.machine()
    markdown = "\n".join([
        "# Similarity surfaces under a non-linear intensity change",
        "",
        common.machine_line(info),
        "",
        (f"100×100 template from the embedded camera image; the frame is 1 − √image shifted"
         f" by {TRUE_SHIFT} px; {n} candidate shifts (radius {radius}) per measure, one"
         " vectorised call each.  Surfaces: surfaces.csv, surfaces.png."),
        "",
        "| measure | peak (dx, dy) | error (px) | M px/s |",
        "|---|---|---:|---:|",
        *(f"| {r['measure']} | {r['peak']} | {r['error_px']:.2f} | {r['mpx_per_s']:.1f} |"
          for r in rows),
        "",
    ])
    common.write("surfaces", {"machine": info, "radius": radius, "true_shift": TRUE_SHIFT,
                              "rows": rows}, markdown)


if __name__ == "__main__":
  main()
