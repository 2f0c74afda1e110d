"""challenges.py's seven sequences as a POT-210 dataset, scored by `jaxpso evaluate`.

The sequences of challenges.py (seed 0, 150 frames, 640×480) are written in POT-210's layout
as V01_1 … V01_7, whose suffix names the challenge as in POT-210 (scale change, rotation,
perspective distortion, motion blur, occlusion, out of view, unconstrained), with the frames
challenges.py does not count as trackable (under half of the region visible, or blurred over
8 px) flagged, as POT-210 flags the frames it leaves out.  `jaxpso.evaluate` then runs
--methods over it and scores them as the toolkits do: precision (alignment error ≤ 5 px) and
success (homography discrepancy ≤ 30) on the annotated, unflagged frames after the first, the
mean over sequences.

  python challenges_pot.py [--methods pso,pso:ncc,ecc,sift] [--out DIR]
"""

from __future__ import annotations

import argparse
import os
import tempfile

import numpy as np

import challenges
import common
import jaxpso
from jaxpso import datasets


def write_dataset(root: str, frames: int) -> None:
  for k, category in enumerate(challenges.CATEGORIES, start=1):
    seq = challenges.render(category, frames=frames, seed=0)
    datasets.write(root, "pot", f"V01_{k}", seq.frames, seq.corners, excluded=~seq.trackable)
    print(category, int(np.sum(~seq.trackable)), "frames flagged", flush=True)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--methods", default="pso,pso:ncc,ecc,sift")
  parser.add_argument("--frames", type=int, default=150)
  parser.add_argument("--out", default=None, help="keep the dataset and evaluation here")
  args = parser.parse_args()
  with tempfile.TemporaryDirectory() as scratch:
    root = args.out or scratch
    write_dataset(os.path.join(root, "dataset"), args.frames)
    report = jaxpso.evaluate(os.path.join(root, "dataset"), "pot", args.methods,
                             os.path.join(root, "evaluation"))
  info = common.machine()
  attributes = list(dict.fromkeys(r["attribute"] for r in report.rows))
  methods = list(dict.fromkeys(r["method"] for r in report.rows))
  cell = {(r["method"], r["attribute"]): r for r in report.rows}
  lines = [
      "# challenges.py's sequences as a POT-210 dataset, scored by `jaxpso evaluate`", "",
      common.machine_line(info), "",
      f"The seven sequences of challenges.py (seed 0, {args.frames} frames, 640×480) in POT-210's"
      " layout (V01_1 … V01_7, the suffix naming the challenge), the frames challenges.py does"
      " not count as trackable (under half visible, or blurred over 8 px) flagged.  Precision:"
      " share of the scored frames (annotated, unflagged, after the first) with an alignment"
      " error ≤ 5 px; success: homography discrepancy ≤ 30; each the mean over sequences, as"
      " the POT-210 / PlanarTrack toolkits rank.  Methods: `jaxpso.datasets.method` names"
      " (pso-mi, pso-ncc: `TrackConfig()` with MI / NCC; ecc-ncc: OpenCV's ECC from the last"
      " estimate, `TrackConfig(method=\"ecc\")`; sift: SIFT + RANSAC against frame 0's region).",
      "", "## Precision (alignment error ≤ 5 px)", "",
      "| method | " + " | ".join(attributes) + " |",
      "|---|" + "---:|" * len(attributes)]
  lines += [f"| {m} | " + " | ".join(f"{cell[(m, a)]['precision']:.3f}" for a in attributes) + " |"
            for m in methods]
  lines += ["", "## Success (homography discrepancy ≤ 30) and time", "",
            "| method | success, all | scored frames | ms/frame |", "|---|---:|---:|---:|"]
  lines += [f"| {m} | {cell[(m, 'all')]['success']:.3f} | {cell[(m, 'all')]['frames']} |"
            f" {cell[(m, 'all')]['ms_per_frame']:.1f} |" for m in methods]
  common.write("challenges_pot", {"machine": info, "args": vars(args), "rows": report.rows,
                                  "seconds": report.seconds,
                                  "tracker_seconds": report.tracker_seconds},
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
