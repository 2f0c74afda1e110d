"""Detection with no start: `jaxpso.detect` on templates placed anywhere in a 640×480 frame.

Each trial cuts a square template of 60–200 px from one of the CC0
photographs (camera, brick, gravel, grass; `JAXPSO_IMAGES`), and renders it
into a 640×480 frame over a background made from another of them (scaled
and blurred, so the background is textured but not the template), through
a homography: any in-plane rotation, a scale of 0.5–2× (log-uniform), a
perspective tilt of up to 0.1 in the corners' relative positions, the whole
template inside the frame; then sensor noise and 8-bit quantisation.  The
truth is that homography.  A trial succeeds when the RMS of the 4 template
corners' errors is within 2 px.

`jaxpso.detect` runs with its defaults (MI, candidates_tried 4) and with
the variants named by `--variants`; ms per call after one warm-up call (the
first compiles `align`'s program).  The table gives success, the median
and 90th percentile of the time and of the error, and how many candidates
were refined.

`--supersample 4` renders the template at 4× the frame's resolution and
area-averages it down, as a camera's pixel integrates light; by default each
pixel samples the warped template at its centre, which aliases a fine
template shrunk under half its size.

`--reference DIR` (an earlier checkout) measures each variant with it too,
each variant's two measurements in fresh processes one after the other, so
that their times compare on a shared machine.

Usage: python benchmarks/detection.py [--trials 100] [--seed 0] [--variants default,ncc]
       [--supersample 1] [--reference DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import cv2
import numpy as np

import common
import jaxpso

NAMES = common.PHOTOS
FRAME = (480, 640)
SIDES = (60, 200)
SCALES = (0.5, 2.0)
GOOD_PX = 2.0
VARIANTS = {
    "default": dict(),
    "ncc": dict(config=jaxpso.TrackConfig(similarity="ncc")),
    "candidates 1": dict(candidates_tried=1),
    "candidates 8": dict(candidates_tried=8),
    "swarm 8": dict(config=jaxpso.TrackConfig(swarm_size=8)),
    "swarm 16": dict(config=jaxpso.TrackConfig(swarm_size=16)),
    "swarm 64": dict(config=jaxpso.TrackConfig(swarm_size=64)),
}


def scene(rng, images: dict, supersample: int = 1):
  """(frame (480, 640) uint8, template (m, m) float32, truth (3, 3)) of one trial; the template
  warped at `supersample`× the frame's resolution and area-averaged down (as a camera's pixel
  integrates light), or at 1 sampled at each pixel's centre."""
  source, back = rng.choice(len(NAMES), 2, replace=False)
  picture = images[NAMES[source]]
  side = int(rng.integers(SIDES[0], SIDES[1] + 1))
  y, x = rng.integers(0, picture.shape[0] - side + 1, 2)
  template = picture[y:y + side, x:x + side]
  if np.std(template) < 0.05:  # a flat crop (the sky of "camera"): another one
    return scene(rng, images, supersample)
  background = cv2.resize(images[NAMES[back]], None, fx=1.7, fy=1.7)
  background = cv2.GaussianBlur(background, (0, 0), 1.0)
  background = np.tile(background, (2, 2))[:FRAME[0], :FRAME[1]]
  for _ in range(100):
    scale = float(np.exp(rng.uniform(*np.log(SCALES))))
    angle = rng.uniform(-np.pi, np.pi)
    rect = np.array([[0, 0], [side - 1, 0], [side - 1, side - 1], [0, side - 1]], np.float64)
    centred = (rect - (side - 1) / 2) * scale
    c, s = np.cos(angle), np.sin(angle)
    moved = centred @ np.array([[c, s], [-s, c]])
    moved += rng.uniform(-0.1, 0.1, (4, 2)) * side * scale  # perspective
    size = np.ptp(moved, axis=0)
    if np.any(size + 4 >= [FRAME[1], FRAME[0]]):
      continue
    low = -moved.min(axis=0) + 2
    high = np.array([FRAME[1], FRAME[0]]) - moved.max(axis=0) - 3
    corners = moved + rng.uniform(low, high)
    truth = cv2.getPerspectiveTransform(rect.astype(np.float32), corners.astype(np.float32))
    break
  else:
    return scene(rng, images, supersample)
  # frame pixel x ↔ fine pixel s·x + (s − 1)/2 (pixel centres)
  fine = np.array([[supersample, 0, (supersample - 1) / 2], [0, supersample, (supersample - 1) / 2],
                   [0, 0, 1]]) @ truth
  size = (FRAME[1] * supersample, FRAME[0] * supersample)
  warped, mask = (cv2.resize(cv2.warpPerspective(a, fine, size, flags=cv2.INTER_LINEAR),
                             FRAME[::-1], interpolation=cv2.INTER_AREA)
                  for a in (template, np.ones_like(template)))
  frame = warped + (1 - mask) * background
  frame = frame + rng.normal(0, 0.01, frame.shape)
  frame = np.clip(np.round(frame * 255), 0, 255).astype(np.uint8)
  return frame, template, truth


def rms_corner_error(found, truth, side: int) -> float:
  rect = np.array([[[0, 0], [side - 1, 0], [side - 1, side - 1], [0, side - 1]]], np.float64)
  a = cv2.perspectiveTransform(rect, np.asarray(found, np.float64))[0]
  b = cv2.perspectiveTransform(rect, np.asarray(truth, np.float64))[0]
  return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def measure(trials, variant: str) -> dict:
  options = VARIANTS[variant]
  frame, template, _ = trials[0]
  jaxpso.detect(frame, template, **options)  # compiles align's program
  errors, times = [], []
  for frame, template, truth in trials:
    start = time.perf_counter()
    found = jaxpso.detect(frame, template, **options)
    times.append(time.perf_counter() - start)
    errors.append(rms_corner_error(found.homography, truth, template.shape[0]))
  errors, times = np.array(errors), np.array(times) * 1e3
  return {"variant": variant, "trials": len(trials), "success": float(np.mean(errors <= GOOD_PX)),
          "median_ms": float(np.median(times)), "p90_ms": float(np.percentile(times, 90)),
          "max_ms": float(times.max()), "median_error_px": float(np.median(errors)),
          "errors": np.round(errors, 3).tolist(), "ms": np.round(times, 2).tolist()}


def _probe(checkout: str, variant: str, args) -> dict:
  """`measure`'s row of `variant` in a fresh process importing jaxpso from `checkout`."""
  return common.in_checkout(__file__, checkout, [
      "--probe", "--trials", str(args.trials), "--seed", str(args.seed), "--variants", variant,
      "--supersample", str(args.supersample)])


def markdown(rows, info, args) -> str:
  lines = ["# Detection with no start (`benchmarks/detection.py`)", "", common.machine_line(info),
           "",
           f"{args.trials} trials: a square template of {SIDES[0]}–{SIDES[1]} px rendered anywhere"
           f" in a {FRAME[1]}×{FRAME[0]} frame over another photograph, any rotation, scale"
           f" {SCALES[0]}–{SCALES[1]}×, perspective, "
           + (f"warped at {args.supersample}× and area-averaged down" if args.supersample > 1
              else "sampled at each pixel's centre")
           + f"; success = RMS corner error ≤ {GOOD_PX} px."
           + (f"  Rows marked 'reference': {args.reference}, each measured in a fresh process"
              " beside the row above it." if args.reference else ""),
           "", "| variant | success % | median ms | p90 ms | max ms | median error px |",
           "|---|---|---|---|---|---|"]
  for r in rows:
    lines.append(f"| {r['variant']} | {100 * r['success']:.1f} | {r['median_ms']:.1f} |"
                 f" {r['p90_ms']:.1f} | {r['max_ms']:.1f} | {r['median_error_px']:.3f} |")
  return "\n".join(lines) + "\n"


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--trials", type=int, default=100)
  parser.add_argument("--seed", type=int, default=0)
  parser.add_argument("--variants", default="default")
  parser.add_argument("--supersample", type=int, default=1,
                      help="render the template at this many times the frame's resolution and"
                           " area-average it down (1: each pixel sampled at its centre)")
  parser.add_argument("--name", default="detection")
  parser.add_argument("--reference", help="an earlier checkout to measure alongside")
  parser.add_argument("--probe", action="store_true", help=argparse.SUPPRESS)
  args = parser.parse_args()
  if args.supersample < 1:
    parser.error(f"--supersample must be >= 1, got {args.supersample}")
  if args.reference:
    rows = []
    for variant in args.variants.split(","):
      rows.append(_probe(common.ROOT, variant, args))
      rows.append(dict(_probe(os.path.abspath(args.reference), variant, args),
                       variant=f"{variant}, reference"))
      print(rows[-2:], flush=True)
  else:
    images = {name: common.photo(name) for name in NAMES}
    rng = np.random.default_rng(args.seed)
    trials = [scene(rng, images, args.supersample) for _ in range(args.trials)]
    rows = [measure(trials, v) for v in args.variants.split(",")]
    if args.probe:
      print(json.dumps(rows[0]))
      return
  info = common.machine()
  common.write(args.name, {"machine": info, "rows": rows}, markdown(rows, info, args))


if __name__ == "__main__":
  main()
