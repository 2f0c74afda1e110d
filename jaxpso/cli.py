"""The `jaxpso` command.

  jaxpso demo [--out DIR] [--radius R]

Until the tracker lands, `demo` is the core showcase (the paper's Fig. 1): a
100×100 template from the embedded image, a frame whose intensities are
changed non-linearly (gamma 0.5 and inverted), and the SSD, ZNCC and MI
surfaces over a grid of translations, each grid evaluated as one swarm in one
vectorised call.  It prints where each measure peaks against the true shift.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso import similarity
from jaxpso import warp
from jaxpso._src import data

_SHAPE = (100, 100)
_ORIGIN = (206.0, 156.0)
_TRUE_SHIFT = (7.0, -5.0)


def _surfaces(radius: int):
  """Scores of every measure over a (2·radius+1)² grid of translations."""
  image = jnp.asarray(data.load_image("camera"))
  template = warp.warp_image(image, warp.translation(*map(jnp.float32, _ORIGIN)), _SHAPE)[0]
  frame_to_image = warp.translation(jnp.float32(-_TRUE_SHIFT[0]), jnp.float32(-_TRUE_SHIFT[1]))
  frame = warp.warp_image(image, frame_to_image, image.shape)[0]
  frame = 1.0 - jnp.sqrt(frame)  # a non-linear, decreasing intensity change
  steps = jnp.arange(-radius, radius + 1, dtype=jnp.float32)
  dx, dy = jnp.meshgrid(steps, steps)
  homographies = warp.translation(_ORIGIN[0] + dx.ravel(), _ORIGIN[1] + dy.ravel())
  measures = {"ssd": similarity.ssd, "ncc": similarity.ncc, "mi": similarity.mi}
  results = {}
  for name, measure in measures.items():
    evaluate = jax.jit(lambda h, measure=measure: measure(template, *warp.warp_image(frame, h, _SHAPE)))
    jax.block_until_ready(evaluate(homographies))
    start = time.perf_counter()
    scores = np.asarray(evaluate(homographies))
    seconds = time.perf_counter() - start
    results[name] = (scores.reshape(dx.shape), seconds)
  return np.asarray(dx), np.asarray(dy), results


def _demo(args) -> int:
  radius = args.radius
  if radius < 1:
    raise ValueError(f"--radius must be >= 1, got {radius}")
  dx, dy, results = _surfaces(radius)
  n = dx.size
  print(f"template 100×100 from the embedded image; frame = 1 - sqrt(image) shifted by"
        f" {_TRUE_SHIFT}; {n} candidate shifts per measure, one vectorised call each")
  print(f"{'measure':8s} {'peak (dx, dy)':>16s} {'error px':>9s} {'M px/s':>8s}")
  for name, (scores, seconds) in results.items():
    best = np.argmin(scores) if name == "ssd" else np.argmax(scores)
    peak = (float(dx.flat[best]), float(dy.flat[best]))
    error = float(np.hypot(peak[0] - _TRUE_SHIFT[0], peak[1] - _TRUE_SHIFT[1]))
    rate = n * _SHAPE[0] * _SHAPE[1] / seconds / 1e6
    print(f"{name:8s} {str(peak):>16s} {error:9.2f} {rate:8.1f}")
  if args.out:
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "surfaces.csv")
    with open(path, "w", newline="") as f:
      writer = csv.writer(f)
      writer.writerow(["dx", "dy"] + list(results))
      for i in range(n):
        writer.writerow([dx.flat[i], dy.flat[i]] + [results[m][0].flat[i] for m in results])
    print(f"wrote {path}")
    _plot(dx, dy, results, os.path.join(args.out, "surfaces.png"))
  return 0


def _plot(dx, dy, results, path: str) -> None:
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
    axis.plot(*_TRUE_SHIFT, "r+", markersize=12)
    axis.set_title(f"{'-ssd' if name == 'ssd' else name} (+: true shift)")
    axis.set_xlabel("dx (px)")
    axis.set_ylabel("dy (px)")
    figure.colorbar(image, ax=axis)
  figure.tight_layout()
  figure.savefig(path, dpi=80)
  print(f"wrote {path}")


def main(argv=None) -> int:
  """Entry point of the `jaxpso` console script; returns the exit status."""
  parser = argparse.ArgumentParser(prog="jaxpso", description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--version", action="store_true", help="print the version and exit")
  commands = parser.add_subparsers(dest="command")
  demo = commands.add_parser("demo", help="the similarity showcase on the embedded image")
  demo.add_argument("--out", help="folder for surfaces.csv and surfaces.png")
  demo.add_argument("--radius", type=int, default=15, help="search radius in px (default 15)")
  args = parser.parse_args(argv)
  if args.version:
    from jaxpso import __version__
    print(__version__)
    return 0
  if args.command is None:
    parser.print_help()
    return 2
  try:
    return _demo(args)
  except (ValueError, TypeError, OSError) as error:
    print(f"jaxpso: error: {error}", file=sys.stderr)
    return 1


if __name__ == "__main__":
  sys.exit(main())
