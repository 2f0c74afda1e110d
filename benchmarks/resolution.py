"""The points-per-set budget `TrackConfig.resolution`: accuracy against time.

`python benchmarks/resolution.py [--resolutions 640,1280,2560,5120]
[--trials 40] [--frames 80]` measures, for each budget, in one process:

* align (MI, defaults otherwise): the Baker–Matthews trials of
  convergence.py (100×100 templates of the camera and brick images, corners
  perturbed by N(0, σ²)) at σ 4, 8 and 12 px, under no change and under
  image noise (σ 0.03): success (≤ 1 px) and the median time per call;
* track (MI and NCC): the hand-held clips of video.py (200–280 px regions),
  every frame and every 4th: P@5, mean error and ms per frame, with the
  chained OpenCV ECC tracker's ms per frame on the same frames as the
  reference.

A 100×100 template has 10 000 pixels, so its sets hold 2 500 points at
most from budget 2 560 up (level 0's 25 % of largest gradient, level 1, and
the full-resolution set's every second row and column): only the video's
regions see the budgets above the default.  Writes results/resolution.md
and .json.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import common
import convergence
import jaxpso
import video
from jaxpso._src.data import load_image

SIGMAS = (4.0, 8.0, 12.0)
CONDITIONS = ("none", "noise")
STRIDES = (1, 4)


def align_rows(resolution: int, count: int) -> list[dict]:
  """Success and median ms of `align` (MI) per (condition, σ) at budget `resolution`."""
  config = jaxpso.TrackConfig(resolution=resolution)
  images = {name: load_image(name) for name in ("camera", "brick")}
  rows = []
  for condition in CONDITIONS:
    change = convergence.CONDITIONS[condition][1]
    for sigma in SIGMAS:
      errors, seconds = [], []
      for i, (name, origin, start) in enumerate(convergence.trials(count, sigma, int(sigma) * 7)):
        x, y = int(origin[0]), int(origin[1])
        template = images[name][y:y + convergence.SIZE, x:x + convergence.SIZE]
        image = change(images[name], np.random.default_rng([int(sigma), i])).astype(np.float32)
        h, spent, _ = convergence.align_once(image, template, start, config, i)
        errors.append(common.corner_error(h, origin))
        seconds.append(spent)
      rows.append({"resolution": resolution, "condition": condition, "sigma": sigma,
                   "trials": count, "success": float(np.mean(np.asarray(errors) <= 1.0)),
                   "median_ms": 1e3 * float(np.median(seconds))})
      print(rows[-1], flush=True)
  return rows


def track_rows(resolutions, frames: int) -> list[dict]:
  """P@5, mean error and ms per frame of `track` per (clip, stride, similarity, budget), and ECC's ms."""
  rows = []
  for seed, name in enumerate(video.SIDES):
    clip, truth, box = video.make_clip(name, frames, seed)
    for stride in STRIDES:
      kept, kept_truth = clip[::stride], truth[::stride]
      start = time.perf_counter()
      video.track_ecc(kept, box)
      ecc_ms = 1e3 * (time.perf_counter() - start) / (len(kept) - 1)
      for similarity in ("mi", "ncc"):
        for resolution in resolutions:
          config = jaxpso.TrackConfig(similarity=similarity, resolution=resolution)
          jaxpso.track(kept, box, config=config)  # compiles (or loads) and warms up
          start = time.perf_counter()
          result = jaxpso.track(kept, box, config=config)
          ms = 1e3 * (time.perf_counter() - start) / (len(kept) - 1)
          errors = jaxpso.io.corner_errors(result.corners, kept_truth)
          rows.append({"clip": name, "stride": stride, "similarity": similarity,
                       "resolution": resolution, "frames": int(errors.size),
                       "p_at_5": float(np.mean(errors <= video.GOOD_PX)),
                       "mean_error_px": float(np.mean(errors)), "ms_per_frame": ms,
                       "ecc_ms_per_frame": ecc_ms})
          print(rows[-1], flush=True)
  return rows


def _pooled(rows, key: str) -> float:
  """`key` averaged over every clip's frames."""
  return sum(r[key] * r["frames"] for r in rows) / sum(r["frames"] for r in rows)


def markdown(align, track, resolutions, info, args) -> str:
  """The results table."""
  lines = ["# TrackConfig.resolution: accuracy against time", "", common.machine_line(info), "",
           "See the script's docstring for the trials and clips.", "",
           f"## align (MI), 100×100 templates, {args.trials} trials per cell: success ≤ 1 px"
           " (median ms)", "",
           "| resolution | " + " | ".join(f"{c} σ {s:g}" for c in CONDITIONS for s in SIGMAS) + " |",
           "|---" * (1 + len(CONDITIONS) * len(SIGMAS)) + "|"]
  for resolution in resolutions:
    cells = [f"{r['success']:.0%} ({r['median_ms']:.1f})" for r in align
             if r["resolution"] == resolution]
    lines.append(f"| {resolution} | " + " | ".join(cells) + " |")
  lines += ["", f"## track, hand-held clips (video.py, {args.frames} frames, 200–280 px regions),"
            " every clip pooled", "",
            "| similarity | stride | resolution | P@5 | mean error (px) | ms/frame | × ECC's ms |",
            "|---|---|---|---|---|---|---|"]
  for similarity in ("mi", "ncc"):
    for stride in STRIDES:
      for resolution in resolutions:
        mine = [r for r in track if r["similarity"] == similarity and r["stride"] == stride
                and r["resolution"] == resolution]
        p5, error, ms, ecc = (_pooled(mine, key) for key in
                              ("p_at_5", "mean_error_px", "ms_per_frame", "ecc_ms_per_frame"))
        lines.append(f"| {similarity.upper()} | {stride} | {resolution} | {p5:.1%} | {error:.2f}"
                     f" | {ms:.1f} | {ms / ecc:.2f} |")
  return "\n".join(lines) + "\n"


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--resolutions", default="640,1280,2560,5120")
  parser.add_argument("--trials", type=int, default=40)
  parser.add_argument("--frames", type=int, default=80)
  args = parser.parse_args()
  resolutions = [int(r) for r in args.resolutions.split(",")]
  align = [row for resolution in resolutions for row in align_rows(resolution, args.trials)]
  track = track_rows(resolutions, args.frames)
  info = common.machine()
  common.write("resolution", {"machine": info, "align": align, "track": track},
               markdown(align, track, resolutions, info, args))


if __name__ == "__main__":
  main()
