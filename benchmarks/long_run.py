"""Long runs: memory, recompilation and time per frame over a 5,000-frame sequence.

A 64×64 region of the embedded image on a plane seen by a camera moving
smoothly in 6 DOF (periods of 40–120 frames), jumps at a third and two thirds,
gain drift 0.1 and noise 0.01, 240×180 frames (`jaxpso.synthetic` with
`lazy=True`: each frame is rendered when the tracker asks for it, so the
frames never sit in memory), tracked by `jaxpso.track` with `TrackConfig()`.
Each call of the tracker's compiled frame step is timed to completion
(`common.timed_frame_steps`), and after frames 500, 1000, ... the script
reads the process's resident memory (now and peak, /proc/self/status VmRSS
and VmHWM) and the number of compiled frame-step programs.  The results
grow by design (a few numbers per frame); nothing else should.

Usage: python benchmarks/long_run.py [--frames 5000] [--block 500] [--seed 0]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

import common
import jaxpso
from jaxpso._src import programs


def memory_mib() -> tuple[float, float]:
  """(current, peak) resident memory of this process in MiB (VmRSS, VmHWM)."""
  values = {}
  with open("/proc/self/status") as f:
    for line in f:
      key, _, rest = line.partition(":")
      if key in ("VmRSS", "VmHWM"):
        values[key] = int(rest.split()[0]) / 1024  # kB
  return values["VmRSS"], values["VmHWM"]


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--frames", type=int, default=5000)
  parser.add_argument("--block", type=int, default=500)
  parser.add_argument("--seed", type=int, default=0)
  args = parser.parse_args()
  n = args.frames
  load_before = os.getloadavg()
  sequence = jaxpso.synthetic.make_sequence(
      args.seed, num_frames=n, frame_shape=(180, 240), roi_size=(64, 64),
      jumps=(n // 3, 2 * n // 3), gain_drift=0.1, noise=0.01, lazy=True)

  checkpoints = []

  def made():  # programs compiled or loaded so far
    counts = programs.counts()
    return counts["compiled"] + counts["loaded"]

  def checkpoint(calls):
    frames_done = calls + 1  # frame 0 is the template
    if frames_done == 2:
      checkpoints.append(dict(frames=2, programs=made()))
    if frames_done % args.block == 0 or frames_done == n:
      current, peak = memory_mib()
      checkpoints.append(dict(frames=frames_done, rss_mib=current, peak_rss_mib=peak,
                              programs=made(), time=time.perf_counter()))
      print(checkpoints[-1], flush=True)

  programs_before = made()
  rss_before, _ = memory_mib()
  with common.timed_frame_steps(checkpoint) as seconds:
    result = jaxpso.track(sequence.frames, sequence.roi, key=args.seed)
  assembly = time.perf_counter() - checkpoints[-1]["time"]  # after the last frame step
  rss_after, peak_after = memory_mib()
  load_after = os.getloadavg()

  error = np.sqrt(np.mean(np.sum((result.corners - sequence.corners) ** 2, -1), -1))
  per_frame = np.concatenate([[np.nan, np.nan], seconds[1:]])  # frame 1 compiles
  blocks = []
  for first in range(0, n, args.block):
    last = min(first + args.block, n)
    blocks.append(dict(
        frames=f"{first}–{last - 1}",
        median_ms=float(1e3 * np.nanmedian(per_frame[first:last])),
        p90_ms=float(1e3 * np.nanpercentile(per_frame[first:last], 90)),
        within_5px=float(np.mean(error[first:last] <= 5.0)),
        lost=int(np.sum(result.status[first:last] == jaxpso.TrackStatus.LOST)),
        rss_mib=next((c["rss_mib"] for c in checkpoints if c["frames"] == last), None)))
  after_first = checkpoints[0]["programs"]
  payload = {
      "machine": common.machine(), "frames": n, "frame_shape": [180, 240], "roi": [64, 64],
      "rss_before_mib": rss_before, "rss_after_mib": rss_after, "peak_rss_after_mib": peak_after,
      "result_assembly_s": assembly, "first_step_s": seconds[0],
      "programs_before": programs_before,
      "programs_after_first_frame": after_first,
      "compilations_after_first_frame": checkpoints[-1]["programs"] - after_first,
      "within_5px": float(np.mean(error <= 5.0)), "median_error_px": float(np.median(error)),
      "max_error_px": float(error.max()),
      "status_counts": {s.name: int(np.sum(result.status == s)) for s in jaxpso.TrackStatus},
      "load_average_before": load_before, "load_average_after": load_after,
      "checkpoints": checkpoints, "blocks": blocks,
      "frames_beyond_5px": [dict(frame=int(k), error_px=float(error[k]),
                                 status=jaxpso.TrackStatus(result.status[k]).name,
                                 quality=float(result.quality[k]))
                            for k in np.flatnonzero(error > 5.0)],
  }
  beyond = ", ".join(f"frame {f['frame']} {f['error_px']:.1f} px {f['status']} (quality"
                     f" {f['quality']:.2f})" for f in payload["frames_beyond_5px"])
  at = {c["frames"]: c for c in checkpoints}
  first_block = at[args.block] if args.block in at else checkpoints[1]
  lines = [
      "# Long run: memory, recompilation and time per frame (jaxpso.track)",
      "",
      common.machine_line(payload["machine"]),
      "",
      f"{n} frames of 240×180, 64×64 region, smooth 6-DOF motion, jumps at 1/3 and 2/3, gain"
      " drift 0.1, noise 0.01, frames rendered lazily; `TrackConfig()` defaults.  Each frame"
      " step timed to completion.  Load average (1, 5, 15 min) before"
      f" {', '.join(f'{v:.2f}' for v in load_before)}, after"
      f" {', '.join(f'{v:.2f}' for v in load_after)} on {os.cpu_count()} cores.",
      "",
      f"- Resident memory before tracking (JAX loaded, nothing compiled): {rss_before:.0f} MiB;"
      f" after {first_block['frames']} frames: {first_block['rss_mib']:.0f} MiB"
      f" (peak {first_block['peak_rss_mib']:.0f} MiB); after {n}:"
      f" {checkpoints[-1]['rss_mib']:.0f} MiB (peak {checkpoints[-1]['peak_rss_mib']:.0f} MiB),"
      f" {1024 * (checkpoints[-1]['rss_mib'] - first_block['rss_mib']) / (n - first_block['frames']):.1f}"
      f" KiB per frame; after track returned (result assembly {assembly:.2f} s): {rss_after:.0f}"
      f" MiB (peak {peak_after:.0f} MiB).",
      f"- Frame-step programs compiled after the first frame:"
      f" {payload['compilations_after_first_frame']} (first frame step, with its compilation:"
      f" {seconds[0]:.1f} s).",
      f"- Frames within 5 px of the true corners: {100 * payload['within_5px']:.2f} %"
      f" (median {payload['median_error_px']:.2f} px, max {payload['max_error_px']:.1f} px);"
      f" status {payload['status_counts']}; beyond 5 px: {beyond or 'none'}.",
      "",
      "| frames | median ms/frame | 90th percentile ms | within 5 px | lost | RSS at the end (MiB) |",
      "|---|---:|---:|---:|---:|---:|",
  ]
  for b in blocks:
    rss = "" if b["rss_mib"] is None else f"{b['rss_mib']:.0f}"
    lines.append(f"| {b['frames']} | {b['median_ms']:.1f} | {b['p90_ms']:.1f} |"
                 f" {100 * b['within_5px']:.1f} % | {b['lost']} | {rss} |")
  common.write("long_run", payload, "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
