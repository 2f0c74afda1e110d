"""Convergence per degree of freedom and similarity (the paper's Fig. 5).

Two-frame synthetic sequences.  Frame 0 is `jaxpso.synthetic.make_sequence`'s
first frame (the embedded camera or brick image on a plane tilted by up to
20°, 240×320 pixels, the 100×100 region at the centre); frame 1 is frame 0
after a random camera motion, resampled (bilinear) through the exact
plane-induced homography K (R + t nᵀ) K⁻¹ of that motion (plane distance 1),
so the true frame-1 corners are exact.  The motion moves 2 (tx, ty), 4 (+ tz
and the rotation about the optical axis) or 6 pose parameters along a random
direction (each parameter in the unit that moves the template by about one
pixel, `TrackConfig.motion` "plane"), scaled so that the template's corners
move by `magnitude` px RMS: the same start error for every DOF.  One scene
and one direction per trial serve every DOF (the direction restricted to the
DOF's parameters) and every magnitude.

DOF 2, 4 and 6: `jaxpso.track` with motion "plane", that dof, the true camera
and normal; DOF 8: motion "homography" on the 6-DOF frames.  All with
accept_quality=None (the swarm always runs), otherwise `TrackConfig()`
defaults, for each similarity; with the Gauss–Newton refinement after the
swarm (refine_steps 10) and without it (0: the swarm alone, as in the paper,
whose estimate is its best at the coarsest pyramid level, 1/8 resolution).
Success = frame-1 corner RMS error <= 1 px (and <= 5 px, the informative
threshold for the swarm alone).

Usage: python benchmarks/dof.py [--trials N] [--magnitudes 8,24,40] [--refine-steps 10,0]
"""

from __future__ import annotations

import argparse
import itertools
import os
import time

import jax
import numpy as np

import common
import jaxpso
from jaxpso import warp
from jaxpso._src import motion

DOFS = (2, 4, 6, 8)
SIMILARITIES = ("ssd", "ncc", "mi")
MAX_TILT = np.deg2rad(20.0)


def scene(rng):
  """Frame 0 of a plane tilted by up to 20° carrying a random embedded image, and its geometry."""
  tilt, azimuth = rng.uniform(0, MAX_TILT), rng.uniform(0, 2 * np.pi)
  normal = (np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt))
  texture = ("camera", "brick")[rng.integers(2)]
  return jaxpso.synthetic.make_sequence(num_frames=1, texture=texture, normal=normal)


def moved(sequence, direction, magnitude: float):
  """(frames (2, H, W), true frame-1 corners (4, 2)) after the motion `direction` (6,).

  `direction` holds pose parameters in the units of `motion.plane_geometry`
  (about one pixel each); it is scaled until the corners move by `magnitude`
  px RMS.
  """
  w, h = sequence.roi[2:]
  unit = np.asarray(motion.plane_geometry(sequence.camera, sequence.normal,
                                          sequence.homographies[0], (h, w), 6).unit)
  corners0 = sequence.corners[0].astype(np.float64)

  def frame0_to_frame1(scale):
    pose = warp.pose_from_params(np.float32(scale * direction * unit))
    return np.asarray(warp.plane_homography(pose, sequence.camera, sequence.normal), np.float64)

  def corners(h):
    mapped = np.c_[corners0, np.ones(4)] @ h.T
    return mapped[:, :2] / mapped[:, 2:]

  scale = magnitude / np.sqrt(np.mean(direction ** 2))
  for _ in range(4):  # the corner motion is almost linear in the scale
    shift = np.sqrt(np.mean(np.sum((corners(frame0_to_frame1(scale)) - corners0) ** 2, -1)))
    scale *= magnitude / shift
  h = frame0_to_frame1(scale)
  frame1 = warp.warp_image(sequence.frames[0], np.float32(np.linalg.inv(h)),
                           sequence.frames.shape[1:])[0]
  return np.stack([sequence.frames[0], np.asarray(frame1)]), corners(h)


def config_of(dof: int, similarity: str, refine_steps: int) -> jaxpso.TrackConfig:
  """The tracker's settings for a DOF (8: motion "homography") with the swarm always run."""
  fields = dict(motion="homography") if dof == 8 else dict(motion="plane", dof=dof)
  return jaxpso.TrackConfig(similarity=similarity, accept_quality=None,
                            refine_steps=refine_steps, **fields)


def plot(rows, path: str) -> None:
  """Success vs magnitude: a row of panels per refine_steps, one per similarity, a line per DOF."""
  import matplotlib

  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  steps = list(dict.fromkeys(r["refine_steps"] for r in rows))
  figure, axes = plt.subplots(len(steps), len(SIMILARITIES), figsize=(12, 3.3 * len(steps)),
                              sharex=True, sharey=True, squeeze=False)
  for row, refine_steps in zip(axes, steps):
    for axis, similarity in zip(row, SIMILARITIES):
      for k, dof in enumerate(DOFS):
        mine = [r for r in rows if r["similarity"] == similarity and r["dof"] == dof
                and r["refine_steps"] == refine_steps]
        if not mine:
          continue
        x = [r["magnitude_px"] for r in mine]
        axis.plot(x, [100 * r["success"] for r in mine], "o-", color=f"C{k}", label=f"DOF {dof}")
        axis.plot(x, [100 * r["success_5px"] for r in mine], ":", color=f"C{k}")
      axis.set_title(f"{similarity}, refine_steps {refine_steps} (solid: <= 1 px, dotted: <= 5 px)",
                     fontsize=8)
      axis.grid(alpha=0.3)
    row[0].set_ylabel("success (%)")
  for axis in axes[-1]:
    axis.set_xlabel("corner motion (px RMS)")
  axes[0][0].legend(fontsize=8)
  figure.tight_layout()
  figure.savefig(path, dpi=80)


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--trials", type=int, default=30, help="trials per magnitude")
  parser.add_argument("--magnitudes", default="8,24,40", help="corner motion, px RMS")
  parser.add_argument("--refine-steps", default="10,0")
  parser.add_argument("--similarities", default=",".join(SIMILARITIES))
  parser.add_argument("--dofs", default=",".join(map(str, DOFS)))
  args = parser.parse_args()
  magnitudes = [float(m) for m in args.magnitudes.split(",")]
  dofs = [int(d) for d in args.dofs.split(",")]
  rng = np.random.default_rng(0)
  scenes = [(scene(rng), rng.normal(size=6)) for _ in range(args.trials)]
  cases = {}  # (DOF of the motion, magnitude) -> [(frames, true corners, sequence)]
  for frames_dof in sorted({min(d, 6) for d in dofs}):
    mask = np.isin(np.arange(6), warp.DOF_AXES[frames_dof])
    for magnitude in magnitudes:
      cases[frames_dof, magnitude] = [
          (*moved(sequence, direction * mask, magnitude), sequence)
          for sequence, direction in scenes]

  rows = []
  for refine_steps, similarity, dof in itertools.product(
      map(int, args.refine_steps.split(",")), args.similarities.split(","), dofs):
    config = config_of(dof, similarity, refine_steps)

    def run(frames, sequence, key, config=config, dof=dof):
      extra = {} if dof == 8 else dict(camera=sequence.camera, plane_normal=sequence.normal)
      return jaxpso.track(frames, sequence.roi, config=config, key=key, **extra)

    frames, _, sequence = cases[min(dof, 6), magnitudes[0]][0]
    run(frames, sequence, 0)  # compile
    for magnitude in magnitudes:
      errors, seconds, evaluations, recovered = [], [], [], 0
      for key, (frames, truth, sequence) in enumerate(cases[min(dof, 6), magnitude]):
        begin = time.perf_counter()
        result = run(frames, sequence, key)
        seconds.append(time.perf_counter() - begin)
        errors.append(np.sqrt(np.mean(np.sum((result.corners[1] - truth) ** 2, -1))))
        evaluations.append(int(result.num_evaluations[1]))
        recovered += int(result.status[1] != jaxpso.TrackStatus.TRACKED)
      errors = np.asarray(errors)
      rows.append({"refine_steps": refine_steps, "similarity": similarity, "dof": dof,
                   "magnitude_px": magnitude,
                   "trials": len(errors), "success": float(np.mean(errors <= 1.0)),
                   "success_5px": float(np.mean(errors <= 5.0)),
                   "median_error_px": float(np.median(errors)),
                   "median_evaluations": float(np.median(evaluations)),
                   "recovery_searches": recovered,
                   "median_ms": 1e3 * float(np.median(seconds))})
      print(rows[-1], flush=True)
    jax.clear_caches()  # two dozen compiled `track`s in one process can run out of memory maps

  info = common.machine()
  lines = [
      "# Convergence per DOF and similarity (two-frame synthetic sequences, jaxpso.track)",
      "",
      common.machine_line(info),
      "",
      f"{args.trials} trials per magnitude: frame 0 of a plane tilted by up to 20° (camera or"
      " brick image), frame 1 after a random 2-, 4- or 6-DOF camera motion moving the 100×100"
      " template's corners by the magnitude (px RMS).  DOF 2/4/6: motion \"plane\" with the"
      " true camera and normal; DOF 8: motion \"homography\" on the 6-DOF frames.  All"
      " `TrackConfig(similarity, refine_steps, accept_quality=None)`, otherwise defaults (32"
      " particles, 40 iterations at most); refine steps 0 = the swarm alone, its best at the"
      " coarsest pyramid level (1/8 resolution).  Success = frame-1 corner RMS error <= 1 px."
      "  Recovery searches: frames whose quality fell below lost_quality"
      " after the first search.  ms = whole `track` call on the 2 frames (template"
      " preparation included), median, after compilation, shared machine.",
      "",
      "| refine steps | similarity | DOF | motion (px) | success | ≤ 5 px | median error (px) | median evaluations | recovery searches | median ms |",
      "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
  ]
  for r in rows:
    lines.append(f"| {r['refine_steps']} | {r['similarity']} | {r['dof']} | {r['magnitude_px']:g} |"
                 f" {100 * r['success']:.0f} % | {100 * r['success_5px']:.0f} % |"
                 f" {r['median_error_px']:.2f} | {r['median_evaluations']:.0f} |"
                 f" {r['recovery_searches']} | {r['median_ms']:.0f} |")
  plot(rows, os.path.join(common.RESULTS, "dof.png"))
  common.write("dof", {"machine": info, "rows": rows}, "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
