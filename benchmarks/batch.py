"""Batch throughput: templates × frames per second of `jaxpso.track` against the batch size R.

R regions of one synthetic video (240×320, smooth 6-DOF camera motion, the
embedded image on the plane): R boxes of SIZE×SIZE at seeded random places
inside the textured plane, tracked together in one call (one compiled frame
step for the whole batch; on a CPU each region runs its own program, one
after another, `batching.each`).  Each R is tracked
once on a few frames to compile, then timed over the sequence (best of
`--repeats`); throughput = R × (T − 1) / seconds.  The batching gain is
measured in the same run two ways: against the first row (region 0 alone,
for R = 1), and against the same R regions tracked one at a time (each
region alone, best of `--repeats`, the times summed).  Regions differ: a
low-texture one runs the swarm on many frames, alone as in a batch, so
region 0 alone is not the batch's per-template cost.  The swarm runs only
for the regions that need it (`batching.where_needed`); the table gives the
fraction of frames on which any region's swarm ran and the fraction of
region-frames, and the status's precision: region-frames TRACKED or
RECOVERED but more than 5 px off, and region-frames within 5 px reported
LOST.

With `--cpu-devices N` the CPU is N JAX devices and every batch is split
over them (`track`'s default `devices`), each running its share's
per-element programs; a lone region uses one.

Usage: python benchmarks/batch.py [--sizes 1,4,16,64,256] [--frames 20] [--repeats 2]
  [--cpu-devices N] [--name batch]
"""

from __future__ import annotations

import argparse
import os
import time

import cv2
import jax
import numpy as np

import common
import jaxpso

SIZE = 48


# Boxes of lower intensity spread are skipped: at std 0.07 the sky of the
# embedded image tracks poorly alone too (quality 0.5–0.9, the swarm on every
# frame), and one such region would make the batch run its swarm throughout.
MIN_STD = 0.12


def regions(sequence, count: int, seed: int = 0) -> np.ndarray:
  """(count, 4) boxes at random places inside the sequence's ROI (the textured plane)."""
  x, y, w, h = sequence.roi
  rng = np.random.default_rng(seed)
  boxes = []
  while len(boxes) < count:
    bx, by = np.array([x, y]) + rng.integers(0, [w - SIZE + 1, h - SIZE + 1])
    if sequence.frames[0][by:by + SIZE, bx:bx + SIZE].std() >= MIN_STD:
      boxes.append([bx, by, SIZE, SIZE])
  return np.array(boxes)


def errors(sequence, boxes, corners) -> np.ndarray:
  """(R, T) corner RMS (px) of tracked corners (R, T, 4, 2) from where the plane's motion carries each box."""
  truth = sequence.corners[0]
  out = np.zeros(corners.shape[:2])
  for r, (x, y, w, h) in enumerate(boxes):
    box = np.float32([[x, y], [x + w - 1, y], [x + w - 1, y + h - 1], [x, y + h - 1]])
    for t in range(corners.shape[1]):
      m = cv2.getPerspectiveTransform(np.float32(truth), np.float32(sequence.corners[t]))
      moved = cv2.perspectiveTransform(box[None], m)[0]
      out[r, t] = np.sqrt(np.mean(np.sum((corners[r, t] - moved) ** 2, -1)))
  return out


def timed_batch(sequence, boxes, config, repeats: int):
  """(seconds of the first call on 2 frames, best seconds of `repeats` whole calls, the last result)."""
  start = time.perf_counter()
  jaxpso.track(sequence.frames[:2], boxes, config=config)
  compile_s = time.perf_counter() - start
  best = np.inf
  for _ in range(repeats):
    start = time.perf_counter()
    result = jaxpso.track(sequence.frames, boxes, config=config)
    best = min(best, time.perf_counter() - start)
  return compile_s, best, result


def alone_seconds(sequence, boxes, config, repeats: int) -> np.ndarray:
  """(R,) seconds to track each box alone (best of `repeats`; one compiled program for all)."""
  jaxpso.track(sequence.frames[:2], boxes[0], config=config)
  seconds = np.full(len(boxes), np.inf)
  for _ in range(repeats):
    for r, box in enumerate(boxes):
      start = time.perf_counter()
      jaxpso.track(sequence.frames, box, config=config)
      seconds[r] = min(seconds[r], time.perf_counter() - start)
  return seconds


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--sizes", default="1,4,16,64,256")
  parser.add_argument("--frames", type=int, default=20)
  parser.add_argument("--repeats", type=int, default=2)
  parser.add_argument("--name", default="batch")
  parser.add_argument("--cpu-devices", type=int, default=1,
                      help="run with the CPU as this many JAX devices (jax_num_cpu_devices)")
  args = parser.parse_args()
  if args.cpu_devices > 1:  # before JAX starts its CPU backend
    jax.config.update("jax_num_cpu_devices", args.cpu_devices)
  sizes = [int(s) for s in args.sizes.split(",")]
  sequence = jaxpso.synthetic.make_sequence(0, num_frames=args.frames, frame_shape=(240, 320),
                                            roi_size=(100, 100))
  config = jaxpso.TrackConfig()
  load_before = os.getloadavg()
  alone = alone_seconds(sequence, regions(sequence, max(sizes)), config, args.repeats)
  print(f"alone: {np.sum(alone):.1f} s for {len(alone)} regions", flush=True)
  rows = []
  for count in sizes:
    boxes = regions(sequence, count)
    compile_s, best, result = timed_batch(sequence, boxes, config, args.repeats)
    searched = result.num_evaluations[:, 1:] > config.swarm_size  # (R, T - 1)
    error = errors(sequence, boxes, result.corners)
    throughput = count * (args.frames - 1) / best
    rows.append(dict(batch=count, seconds=best, compile_s=compile_s,
                     templates_frames_per_s=throughput,
                     alone_seconds=float(np.sum(alone[:count])),
                     gain_vs_alone=float(np.sum(alone[:count]) / best),
                     swarm_frames=float(np.mean(np.any(searched, axis=0))),
                     swarm_regions=float(np.mean(searched)),
                     within_2px=float(np.mean(error <= 2.0)),
                     lost=int(np.sum(result.status == jaxpso.TrackStatus.LOST)),
                     **common.status_precision(result.status, error)))
    print(rows[-1], flush=True)
  for row in rows:
    row["gain_vs_first"] = row["templates_frames_per_s"] / rows[0]["templates_frames_per_s"]
  payload = {"machine": common.machine(), "frames": args.frames, "template": [SIZE, SIZE],
             "alone_seconds": alone.tolist(),
             "frame_shape": [240, 320], "config": "TrackConfig()", "load_average_before":
             load_before, "load_average_after": os.getloadavg(), "devices": str(jax.devices()),
             "rows": rows}
  lines = [
      "# Batch throughput of jaxpso.track (R regions of one video, one compiled program)",
      "",
      common.machine_line(payload["machine"]),
      "",
      f"{args.frames} frames of 240×320 on {len(jax.devices())} JAX device(s),"
      f" {SIZE}×{SIZE} regions inside the 100×100 ROI"
      f" of the textured plane (intensity std ≥ {MIN_STD}), `TrackConfig()` defaults, best of"
      f" {args.repeats} timed calls after a compiling call.  \"vs alone\": the same R regions"
      f" tracked one at a time (each the best of {args.repeats}, summed) over the batch's"
      f" time; region 0 alone took {alone[0]:.3f} s, the {len(alone)} regions alone"
      f" {np.min(alone):.3f}–{np.max(alone):.3f} s.  Load average before"
      f" {', '.join(f'{v:.2f}' for v in load_before)}, after"
      f" {', '.join(f'{v:.2f}' for v in os.getloadavg())} on {os.cpu_count()} cores.",
      "",
      f"| batch R | seconds | templates × frames / s | vs R = {sizes[0]} (region 0) |"
      " vs the same R regions alone | frames with a swarm | regions × frames with a swarm |"
      " within 2 px | lost | tracked but > 5 px off | good but LOST | compile s |",
      "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
  ]
  for row in rows:
    lines.append(
        f"| {row['batch']} | {row['seconds']:.2f} | {row['templates_frames_per_s']:.0f} |"
        f" {row['gain_vs_first']:.1f}× | {row['gain_vs_alone']:.1f}× |"
        f" {100 * row['swarm_frames']:.0f} % |"
        f" {100 * row['swarm_regions']:.1f} % |"
        f" {100 * row['within_2px']:.1f} % | {row['lost']} |"
        f" {row['tracked_but_off']}/{row['tracked']} | {row['good_but_lost']}/{row['good']} |"
        f" {row['compile_s']:.0f} |")
  common.write(args.name, payload, "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
