"""Periodic textures: `track` of regions that match themselves shifted, with and without its check.

A region of a periodic texture (stripes, checkerboards) matches itself
moved by its period, or anywhere along its stripes; only its border tells
the truth from those places.  Each trial pastes a 24–120 px texture on a
CC0 photograph and moves it by a random integer step a frame (each axis
N(0, 1.5²) px) for 6 frames of (h + 120) × (w + 160), exact truth.  The
textures: stripes of period 2–4 at any angle, diagonal stripes (x + y
modulo 2–5), checkerboards of 2–6 px squares, a mixed periodic texture, a
photograph with a 1 px checkerboard added, and white noise (a control,
never periodic).  Every trial is tracked twice with `TrackConfig` defaults
(`redetect` on) and one key: as the code stands, and with the periodic
check off (`periodic.aliased` forced False: a match is never moved to a
better shift nor judged ambiguous).  Per texture and similarity: P@5 (frames
1–5 within 5 px, corner RMS), frames TRACKED or RECOVERED more than 5 px
off, DOUBTFUL frames, and ms per call (6 frames, compiled beforehand).

Usage: python benchmarks/periodic.py [--trials 20] [--seed 0]
"""

from __future__ import annotations

import argparse
import time
from unittest import mock

import numpy as np

import common
import jaxpso
from jaxpso._src import periodic

KINDS = ("stripes", "diagonal", "checkerboard", "mixed", "photo+checker", "noise")
SIMILARITIES = ("mi", "ncc", "ssd")
FRAMES, TOLERANCE_PX = 6, 5.0


def texture(kind: str, rng, rows: int, cols: int, photo: np.ndarray) -> np.ndarray:
  """(rows, cols) float32 texture of `kind`."""
  import cv2

  yy, xx = np.mgrid[:rows, :cols]
  if kind == "stripes":
    period, angle = rng.integers(2, 5), rng.uniform(0, np.pi)
    phase = 2 * np.pi * (xx * np.cos(angle) + yy * np.sin(angle)) / period
    return (0.5 + 0.2 * np.sign(np.sin(phase))).astype(np.float32)
  if kind == "diagonal":
    return np.where((yy + xx) % rng.integers(2, 6) == 0, 0.7, 0.3).astype(np.float32)
  if kind == "checkerboard":
    side = rng.integers(2, 7)
    return (0.3 + 0.4 * ((yy // side + xx // side) % 2)).astype(np.float32)
  if kind == "mixed":
    return (0.5 + 0.2 * ((yy % 2) ^ (xx // 3 % 2))).astype(np.float32)
  if kind == "photo+checker":
    y, x = rng.integers(0, photo.shape[0] - 150, 2)
    patch = cv2.resize(photo[y:y + 150, x:x + 150], (cols, rows))
    return (patch + 0.2 * ((yy + xx) % 2 - 0.5)).astype(np.float32)
  return rng.random((rows, cols)).astype(np.float32)


def trial(kind: str, index: int, seed: int, photo: np.ndarray):
  """(frames (6, H, W), roi (x, y, w, h), truth corners (6, 4, 2)) of trial `index`."""
  import cv2

  rng = np.random.default_rng([seed, KINDS.index(kind), index])
  rows, cols = rng.integers(24, 121, 2)
  patch = texture(kind, rng, rows, cols, photo)
  y, x = rng.integers(0, photo.shape[0] - 300, 2)
  background = cv2.resize(photo[y:y + 300, x:x + 300], (cols + 160, rows + 120))
  step = rng.normal(0, 1.5, 2)
  frames, truth = [], []
  for t in range(FRAMES):
    left, top = (np.round(np.array([60, 80]) + step * t)).astype(int)
    frame = background.copy()
    frame[top:top + rows, left:left + cols] = patch
    frames.append(frame)
    truth.append([[left, top], [left + cols - 1, top], [left + cols - 1, top + rows - 1],
                  [left, top + rows - 1]])
  return np.stack(frames), (60, 80, int(cols), int(rows)), np.array(truth, np.float64)


def run(kind: str, similarity: str, trials: int, seed: int, photo: np.ndarray, check: bool):
  """Figures of one texture, similarity and variant over `trials` trials."""
  config = jaxpso.TrackConfig(similarity=similarity)
  errors, statuses, seconds = [], [], []
  with mock.patch.object(periodic, "aliased", periodic.aliased if check else lambda t: False):
    for index in range(trials):
      frames, roi, truth = trial(kind, index, seed, photo)
      start = time.perf_counter()
      result = jaxpso.track(frames, roi, config=config, key=index)
      seconds.append(time.perf_counter() - start)
      errors.append(np.sqrt(np.mean(np.sum((result.corners - truth) ** 2, -1), -1))[1:])
      statuses.append(result.status[1:])
  errors, statuses = np.concatenate(errors), np.concatenate(statuses)
  counts = common.status_precision(statuses, errors, TOLERANCE_PX)
  return dict(kind=kind, similarity=similarity, check=check, frames=int(errors.size),
              within=float(np.mean(errors <= TOLERANCE_PX)), **counts,
              ms_per_call=1e3 * float(np.median(seconds)))


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--trials", type=int, default=20)
  parser.add_argument("--seed", type=int, default=0)
  args = parser.parse_args()
  photo = common.photo("camera")
  for similarity in SIMILARITIES:  # compiles (or loads) every program first
    frames, roi, _ = trial("noise", 0, args.seed, photo)
    jaxpso.track(frames, roi, config=jaxpso.TrackConfig(similarity=similarity))
  rows = []
  for kind in KINDS:
    for similarity in SIMILARITIES:
      for check in (True, False):
        rows.append(run(kind, similarity, args.trials, args.seed, photo, check))
        print(rows[-1], flush=True)

  info = common.machine()
  lines = [
      "# Periodic textures (jaxpso.track, with and without its periodic check)", "",
      common.machine_line(info), "",
      f"{args.trials} trials per texture and similarity (seed {args.seed}), {FRAMES} frames each:"
      " a 24–120 px texture pasted on the CC0 camera photograph, moving N(0, 1.5²) px a frame"
      " per axis; `TrackConfig` defaults.  \"off\": `periodic.aliased` forced False.  P@5 over"
      " frames 1–5; off = TRACKED or RECOVERED more than 5 px off; ms per call of 6 frames"
      " (median).  Script: benchmarks/periodic.py.", "",
      "| texture | similarity | P@5 | P@5 off | off | off, check off | DOUBTFUL |"
      " DOUBTFUL, check off | ms per call | ms, check off |",
      "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
  ]
  for on, off in zip(rows[::2], rows[1::2]):
    lines.append(
        f"| {on['kind']} | {on['similarity']} | {100 * on['within']:.0f} % |"
        f" {100 * off['within']:.0f} % | {on['tracked_but_off']} / {on['tracked']} |"
        f" {off['tracked_but_off']} / {off['tracked']} | {on['doubtful']} | {off['doubtful']} |"
        f" {on['ms_per_call']:.0f} | {off['ms_per_call']:.0f} |")
  total = {check: sum(r["tracked_but_off"] for r in rows if r["check"] == check)
           for check in (True, False)}
  lines += ["", f"Frames TRACKED or RECOVERED more than 5 px off, all textures: {total[True]}"
            f" with the check, {total[False]} without."]
  common.write("periodic", dict(machine=info, args=vars(args), rows=rows), "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
