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
the variants named by `--variants`; ms per call after warm-up calls on the
first trial and on the one covering most of its frame (they compile
`align`'s programs, one per image buffer size).  The table gives success,
the median, 90th percentile and maximum of the time, and the median error.

`--supersample 4` renders the template at 4× the frame's resolution and
area-averages it down, as a camera's pixel integrates light; by default each
pixel samples the warped template at its centre, which aliases a fine
template shrunk under half its size.

`--aspect A` cuts rectangles instead of squares, of the same area, their
long side A times their short one: the coarse stage correlates the
template's inner disc, a smaller part of an elongated template.

`--reference DIR` (an earlier checkout) measures each variant with it too,
each variant's two measurements in fresh processes one after the other, so
that their times compare on a shared machine.

Usage: python benchmarks/detection.py [--trials 100] [--seed 0] [--variants default,ncc]
       [--supersample 1] [--aspect 1] [--reference DIR]
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


def template_shape(rng, aspect: float) -> tuple[int, int]:
  """(rows, cols) of a trial's template: a square of `SIDES`, or with `aspect` > 1 a rectangle of
  the same area, its long side `aspect` times its short one, lying or standing at random."""
  side = int(rng.integers(SIDES[0], SIDES[1] + 1))
  if aspect == 1:
    return side, side
  long, short = round(side * aspect ** 0.5), round(side / aspect ** 0.5)
  return (short, long) if rng.integers(2) else (long, short)


def scene(rng, images: dict, supersample: int = 1, aspect: float = 1.0):
  """(frame (480, 640) uint8, template (rows, cols) float32, truth (3, 3)) of one trial; the
  template warped at `supersample`× the frame's resolution and area-averaged down (as a camera's
  pixel integrates light), or at 1 sampled at each pixel's centre."""
  source, back = rng.choice(len(NAMES), 2, replace=False)
  picture = images[NAMES[source]]
  rows, cols = template_shape(rng, aspect)
  if rows > min(picture.shape[0], FRAME[0]) or cols > min(picture.shape[1], FRAME[1]):
    return scene(rng, images, supersample, aspect)  # detect takes none larger than the frame
  if rows == cols:  # the draw of the committed square trials (detection.md reproduces)
    y, x = rng.integers(0, picture.shape[0] - rows + 1, 2)
  else:
    y, x = (int(rng.integers(0, n - m + 1)) for n, m in zip(picture.shape, (rows, cols)))
  template = picture[y:y + rows, x:x + cols]
  if np.std(template) < 0.05:  # a flat crop (the sky of "camera"): another one
    return scene(rng, images, supersample, aspect)
  background = cv2.resize(images[NAMES[back]], None, fx=1.7, fy=1.7)
  background = cv2.GaussianBlur(background, (0, 0), 1.0)
  background = np.tile(background, (2, 2))[:FRAME[0], :FRAME[1]]
  rect = corners((rows, cols))
  for _ in range(100):
    scale = float(np.exp(rng.uniform(*np.log(SCALES))))
    angle = rng.uniform(-np.pi, np.pi)
    centred = (rect - [(cols - 1) / 2, (rows - 1) / 2]) * scale
    c, s = np.cos(angle), np.sin(angle)
    moved = centred @ np.array([[c, s], [-s, c]])
    moved += rng.uniform(-0.1, 0.1, (4, 2)) * np.sqrt(rows * cols) * scale  # perspective
    size = np.ptp(moved, axis=0)
    if np.any(size + 4 >= [FRAME[1], FRAME[0]]):
      continue
    low = -moved.min(axis=0) + 2
    high = np.array([FRAME[1], FRAME[0]]) - moved.max(axis=0) - 3
    placed = moved + rng.uniform(low, high)
    truth = cv2.getPerspectiveTransform(rect.astype(np.float32), placed.astype(np.float32))
    break
  else:
    return scene(rng, images, supersample, aspect)
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


def corners(shape) -> np.ndarray:
  """(4, 2) float64 corners TL, TR, BR, BL of a template of `shape` (rows, cols)."""
  rows, cols = shape
  return np.array([[0, 0], [cols - 1, 0], [cols - 1, rows - 1], [0, rows - 1]], np.float64)


def rms_corner_error(found, truth, shape) -> float:
  rect = corners(shape)[None]
  a = cv2.perspectiveTransform(rect, np.asarray(found, np.float64))[0]
  b = cv2.perspectiveTransform(rect, np.asarray(truth, np.float64))[0]
  return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def measure(trials, variant: str) -> dict:
  options = VARIANTS[variant]
  # Compiles align's programs: the image's buffer grows with the template's extent in the frame,
  # so the trial covering most of it too (a larger buffer is another program).
  largest = max(trials, key=lambda t: np.prod(np.ptp(
      cv2.perspectiveTransform(corners(t[1].shape)[None], t[2])[0], axis=0)))
  for frame, template, _ in (trials[0], largest):
    jaxpso.detect(frame, template, **options)
  errors, times = [], []
  for frame, template, truth in trials:
    start = time.perf_counter()
    found = jaxpso.detect(frame, template, **options)
    times.append(time.perf_counter() - start)
    errors.append(rms_corner_error(found.homography, truth, template.shape))
  errors, times = np.array(errors), np.array(times) * 1e3
  return {"variant": variant, "trials": len(trials), "success": float(np.mean(errors <= GOOD_PX)),
          "median_ms": float(np.median(times)), "p90_ms": float(np.percentile(times, 90)),
          "max_ms": float(times.max()), "median_error_px": float(np.median(errors)),
          "errors": np.round(errors, 3).tolist(), "ms": np.round(times, 2).tolist()}


def _probe(checkout: str, variant: str, args) -> dict:
  """`measure`'s row of `variant` in a fresh process importing jaxpso from `checkout`."""
  return common.in_checkout(__file__, checkout, [
      "--probe", "--trials", str(args.trials), "--seed", str(args.seed), "--variants", variant,
      "--supersample", str(args.supersample), "--aspect", str(args.aspect)])


def markdown(rows, info, args) -> str:
  lines = ["# Detection with no start (`benchmarks/detection.py`)", "", common.machine_line(info),
           "",
           f"{args.trials} trials: a square template of {SIDES[0]}–{SIDES[1]} px"
           + (f" (a rectangle of its area, {args.aspect:g}:1, lying or standing)"
              if args.aspect != 1 else "")
           + f" rendered anywhere"
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
  parser.add_argument("--aspect", type=float, default=1.0,
                      help="the template's long side over its short one (1: a square)")
  parser.add_argument("--name", default="detection")
  parser.add_argument("--reference", help="an earlier checkout to measure alongside")
  parser.add_argument("--probe", action="store_true", help=argparse.SUPPRESS)
  args = parser.parse_args()
  if args.supersample < 1:
    parser.error(f"--supersample must be >= 1, got {args.supersample}")
  if not args.aspect >= 1:
    parser.error(f"--aspect must be >= 1, got {args.aspect}")
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
    trials = [scene(rng, images, args.supersample, args.aspect) for _ in range(args.trials)]
    rows = [measure(trials, v) for v in args.variants.split(",")]
    if args.probe:
      print(json.dumps(rows[0]))
      return
  info = common.machine()
  common.write(args.name, {"machine": info, "rows": rows}, markdown(rows, info, args))


if __name__ == "__main__":
  main()
