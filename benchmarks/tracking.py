"""Tracking synthetic 6-DOF sequences: frames within 5 px of the true corners.

A 100×100 region of the embedded image on a plane seen by a camera moving
smoothly in 6 DOF, with sudden jumps at a third and two thirds of the
sequence, gain drift 0.1 and Gaussian noise 0.01 (`jaxpso.synthetic`).
Tracked with `TrackConfig()` defaults for motion "homography", and for motion
"plane" with 6 DOF given the true camera matrix and the true normal, then a
normal tilted 20° off.  Also the same with `predict=True` (a start carrying
half the last inter-frame motion).  Status precision: frames TRACKED or
RECOVERED but more than 5 px off, and frames within 5 px reported LOST.
Times per frame exclude the first call (compilation).  Slowest frame: a
third call with each frame step blocked on (`common.frame_seconds`: the step
and the host's work after it), its slowest frame over its median one.

Usage: python benchmarks/tracking.py [--frames 200] [--seeds 0,1]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import common
import jaxpso

CASES = {
    "homography": (dict(motion="homography"), None),
    "plane dof 6, true normal": (dict(motion="plane", dof=6), 0.0),
    "plane dof 6, normal 20° off": (dict(motion="plane", dof=6), 20.0),
    "homography, predict": (dict(motion="homography", predict=True), None),
    "plane dof 6, true normal, predict": (dict(motion="plane", dof=6, predict=True), 0.0),
}


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--frames", type=int, default=200)
  parser.add_argument("--seeds", default="0,1")
  args = parser.parse_args()
  rows = []
  for seed in (int(s) for s in args.seeds.split(",")):
    n = args.frames
    seq = sequence(seed, n)
    for name, (fields, tilt) in CASES.items():
      config = jaxpso.TrackConfig(**fields)
      extra = plane_arguments(seq, tilt)
      jaxpso.track(seq.frames[:2], seq.roi, config=config, **extra)  # compile
      start = time.perf_counter()
      result = jaxpso.track(seq.frames, seq.roi, config=config, key=seed, **extra)
      seconds = (time.perf_counter() - start) / (n - 1)
      frame = common.frame_seconds(
          lambda: jaxpso.track(seq.frames, seq.roi, config=config, key=seed, **extra))
      error = np.sqrt(np.mean(np.sum((result.corners - seq.corners) ** 2, -1), -1))
      rows.append({"seed": seed, "case": name, "frames": n,
                   "within_5px": float(np.mean(error <= 5.0)),
                   "median_error_px": float(np.median(error)), "max_error_px": float(error.max()),
                   "lost": int(np.sum(result.status == jaxpso.TrackStatus.LOST)),
                   "recovered": int(np.sum(result.status == jaxpso.TrackStatus.RECOVERED)),
                   **common.status_precision(result.status, error),
                   "ms_per_frame": 1e3 * seconds,
                   "slowest_over_median": float(np.max(frame) / np.median(frame))})
      print(rows[-1], flush=True)

  info = common.machine()
  lines = [
      "# Tracking synthetic 6-DOF sequences (jaxpso.track)",
      "",
      common.machine_line(info),
      "",
      f"{args.frames} frames per sequence, jumps at 1/3 and 2/3, gain drift 0.1, noise 0.01,"
      " 100×100 region of the embedded camera image, `TrackConfig()` defaults except the"
      " fields named.  Success = corner RMS error <= 5 px.  ms/frame after compilation;"
      " slowest / median: a third call, each frame step blocked on, its slowest frame (the step"
      " and the host's work after it) over its median.",
      "",
      "| seed | case | frames within 5 px | median error (px) | max error (px) | lost | recovered"
      " | tracked but > 5 px off | good but LOST | ms/frame | slowest / median frame |",
      "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
  ]
  for r in rows:
    lines.append(f"| {r['seed']} | {r['case']} | {100 * r['within_5px']:.1f} % |"
                 f" {r['median_error_px']:.2f} | {r['max_error_px']:.1f} | {r['lost']} |"
                 f" {r['recovered']} | {r['tracked_but_off']}/{r['tracked']} |"
                 f" {r['good_but_lost']}/{r['good']} | {r['ms_per_frame']:.0f} |"
                 f" {r['slowest_over_median']:.1f} |")
  common.write("tracking", {"machine": info, "rows": rows}, "\n".join(lines) + "\n")


def sequence(seed: int, frames: int):
  """The benchmark's synthetic sequence: jumps at 1/3 and 2/3, gain drift 0.1, noise 0.01."""
  return jaxpso.synthetic.make_sequence(seed, num_frames=frames,
                                        jumps=(frames // 3, 2 * frames // 3), gain_drift=0.1,
                                        noise=0.01)


def plane_arguments(seq, tilt) -> dict:
  """`track`'s camera and plane normal for a case whose normal is `tilt` degrees off (None:
  a case without them)."""
  if tilt is None:
    return {}
  angle = np.deg2rad(tilt)
  tilted = np.array([np.sin(angle), 0.0, np.cos(angle)])
  return dict(camera=seq.camera, plane_normal=rotate_towards(seq.normal, tilted))


def rotate_towards(normal, tilted):
  """The frame-0 normal tilted the way `tilted` is tilted from (0, 0, 1)."""
  z = np.array([0.0, 0.0, 1.0])
  axis = np.cross(z, tilted)
  s, c = np.linalg.norm(axis), float(z @ tilted)
  if s < 1e-12:
    return normal
  k = axis / s
  skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
  rotation = np.eye(3) + s * skew + (1 - c) * skew @ skew
  return rotation @ normal


if __name__ == "__main__":
  main()
