"""Tracking error per frame through an intensity change (the paper's Figs. 9 and 10).

A synthetic sequence (`jaxpso.synthetic.make_sequence`: the embedded camera
image on a fronto-parallel plane, 240×320 frames, the 100×100 region at the
centre, smooth 6-DOF camera motion, Gaussian noise 0.01) whose frames from
--change-at on are changed: gamma (v ↦ √v) or inverted (v ↦ 1 − v), two
sequences with the same motion and noise.  Tracked by `jaxpso.track` with

  pso (MI, motion "homography", 8 DOF), `TrackConfig()` defaults;
  pso with motion "plane", 2, 4 and 6 DOF, the true camera and normal (MI);
  the gradient baselines ic, fc, ha and esm (similarity "ssd", motion
  "homography", at most 40 iterations per pyramid level) and ecc (OpenCV,
  similarity "ncc", 100 iterations).

Normalised RMSE per frame = RMS of the 4 corner errors / the template's
diagonal (the paper plots a "normalized root mean squared error" without
defining it; this is our reading).  Times per frame exclude the compiling
first call.

Usage: python benchmarks/sequence.py [--frames 150] [--change-at 75] [--changes gamma,invert]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

import common
import jaxpso

METHODS = {
    "pso MI 8 DOF": dict(),
    "pso MI plane 6 DOF": dict(motion="plane", dof=6),
    "pso MI plane 4 DOF": dict(motion="plane", dof=4),
    "pso MI plane 2 DOF": dict(motion="plane", dof=2),
    "ic (SSD)": dict(method="ic", similarity="ssd"),
    "fc (SSD)": dict(method="fc", similarity="ssd"),
    "ha (SSD)": dict(method="ha", similarity="ssd"),
    "esm (SSD)": dict(method="esm", similarity="ssd"),
    "ecc (NCC)": dict(method="ecc", similarity="ncc", max_iterations=100),
}


def plot(curves, change_at: int, path: str) -> None:
  """nRMSE vs frame: one row per intensity change, methods left and PSO per DOF right."""
  import matplotlib

  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  changes = list(curves)
  figure, axes = plt.subplots(len(changes), 2, figsize=(12, 3.4 * len(changes)), sharex=True,
                              sharey=True, squeeze=False)
  for row, change in zip(axes, changes):
    for axis, title, names in (
        (row[0], "methods", [m for m in curves[change] if "plane" not in m]),
        (row[1], "pso per DOF", [m for m in curves[change] if m.startswith("pso")])):
      for name in names:
        axis.plot(np.maximum(curves[change][name], 1e-4), label=name, lw=1)
      axis.axvline(change_at, color="k", ls="--", lw=0.8)
      axis.set_yscale("log")
      axis.set_title(f"{change} from frame {change_at}: {title}", fontsize=9)
      axis.grid(alpha=0.3)
      axis.legend(fontsize=7, ncol=2)
    row[0].set_ylabel("corner RMS error / template diagonal")
  for axis in axes[-1]:
    axis.set_xlabel("frame")
  figure.tight_layout()
  figure.savefig(path, dpi=72)


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--frames", type=int, default=150)
  parser.add_argument("--change-at", type=int, default=75)
  parser.add_argument("--changes", default="gamma,invert")
  parser.add_argument("--seed", type=int, default=0)
  parser.add_argument("--methods", default=",".join(METHODS))
  args = parser.parse_args()
  names = args.methods.split(",")
  sequences = {change: jaxpso.synthetic.make_sequence(
      args.seed, num_frames=args.frames, noise=0.01, intensity_change=(args.change_at, change))
               for change in args.changes.split(",")}
  first = next(iter(sequences.values()))
  diagonal = float(np.hypot(first.roi[2] - 1, first.roi[3] - 1))
  rows, curves = [], {change: {} for change in sequences}
  for name in names:
    config = jaxpso.TrackConfig(**METHODS[name])
    extra = (dict(camera=first.camera, plane_normal=first.normal)
             if config.motion == "plane" else {})
    jaxpso.track(first.frames[:2], first.roi, config=config, **extra)  # compile
    for change, sequence in sequences.items():
      begin = time.perf_counter()
      result = jaxpso.track(sequence.frames, sequence.roi, config=config, key=args.seed, **extra)
      seconds = (time.perf_counter() - begin) / (args.frames - 1)
      error = np.sqrt(np.mean(np.sum((result.corners - sequence.corners) ** 2, -1), -1))
      curves[change][name] = error / diagonal
      before, after = error[1:args.change_at], error[args.change_at:]
      rows.append({"change": change, "method": name,
                   "nrmse_before": float(np.mean(before / diagonal)),
                   "nrmse_after": float(np.mean(after / diagonal)),
                   "within_5px_before": float(np.mean(before <= 5.0)),
                   "within_5px_after": float(np.mean(after <= 5.0)),
                   "max_error_px": float(error.max()),
                   "lost": int(np.sum(result.status == jaxpso.TrackStatus.LOST)),
                   "ms_per_frame": 1e3 * seconds})
      print(rows[-1], flush=True)

  info = common.machine()
  lines = [
      "# Tracking error per frame through an intensity change (jaxpso.track)",
      "",
      common.machine_line(info),
      "",
      f"{args.frames} frames (seed {args.seed}), smooth 6-DOF motion, noise 0.01, 100×100 region"
      f" of the embedded camera image; from frame {args.change_at} on the frames are changed"
      " (gamma: v ↦ √v; invert: v ↦ 1 − v).  nRMSE = corner RMS error / template diagonal"
      f" ({diagonal:.1f} px), mean over frames 1–{args.change_at - 1} (before) and"
      f" {args.change_at}–{args.frames - 1} (after).  pso: `TrackConfig()` defaults (MI);"
      " plane: true camera and normal; baselines: similarity ssd (ecc: ncc, 100 iterations)."
      "  Per-frame curves: sequence.json, sequence.png.  ms/frame after compilation, shared"
      " machine.",
      "",
      "| change | method | nRMSE before | nRMSE after | within 5 px before | within 5 px after | max error (px) | lost | ms/frame |",
      "|---|---|---:|---:|---:|---:|---:|---:|---:|",
  ]
  for r in rows:
    lines.append(f"| {r['change']} | {r['method']} | {r['nrmse_before']:.4f} |"
                 f" {r['nrmse_after']:.4f} | {100 * r['within_5px_before']:.0f} % |"
                 f" {100 * r['within_5px_after']:.0f} % | {r['max_error_px']:.1f} | {r['lost']} |"
                 f" {r['ms_per_frame']:.0f} |")
  plot(curves, args.change_at, os.path.join(common.RESULTS, "sequence.png"))
  per_frame = {change: {name: [float(f"{v:.4g}") for v in curve] for name, curve in c.items()}
               for change, c in curves.items()}
  common.write("sequence", {"machine": info, "rows": rows, "nrmse_per_frame": per_frame},
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
