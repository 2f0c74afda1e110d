"""Time per call once compiled, this code against an earlier checkout, interleaved.

`python benchmarks/runtime.py [--reference DIR] [--rounds 2] [--parts align,track,batch]
[--name runtime]` runs each
measurement in a fresh process (`--probe`), alternating between this
checkout and `DIR` (e.g. a git worktree of the code before a change) for
`--rounds` rounds, so both see the same machine load; the table gives the
range over the rounds.  Every process compiles first and times afterwards.

* align: `TRIALS` trials per σ (2, 8 px), each a new 100×100 template of
  the embedded camera image with its 4 corners perturbed by N(0, σ²);
  OpenCV's ECC (homography, 100 iterations, eps 1e-6) on the same trial in
  the same process; the median of each, their ratio, jaxpso's 90th
  percentile over its median, the ratio of the means (the slow tail of
  low-texture templates that run the retries) and the share of trials
  ending more than 1 px off (corner RMS) for each.  200 trials, not 40:
  the cost has two modes (accepted start or coarser start), and on 40
  trials the median fell on one or the other (benchmarks/README.md).
* track, one region: the default `TrackConfig` with MI and NCC on an
  80-frame synthetic sequence (100×100 region, a jump at frame 40), best of
  3 calls, ms per frame, median corner error.
* track, a batch: 64 regions of 48×48 (`batch.regions`) over 20 frames of
  a 240×320 sequence, best of 3; the default and `accept_quality=0` (no
  swarm: Gauss–Newton and the check alone), ms per region-frame.
  `batch_devices` (not in the default `--parts`): the same with the CPU's
  cores as many JAX devices (`jax_num_cpu_devices`), the batch split
  over them.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

import common

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SIGMAS = (2.0, 8.0)
TRIALS = 200


def align_trials(image, sigma: float, count: int = TRIALS, seed: int = 0):
  """`count` (template (100, 100), start (3, 3), origin (2,)) trials: the corners moved by N(0, σ²)."""
  import cv2

  square = np.float32([[0, 0], [99, 0], [99, 99], [0, 99]])
  rng = np.random.default_rng([seed, int(sigma)])
  for _ in range(count):
    x, y = rng.integers(60, 512 - 160, 2)
    moved = square + [x, y] + rng.normal(0, sigma, (4, 2)).astype(np.float32)
    yield (image[y:y + 100, x:x + 100], cv2.getPerspectiveTransform(square, moved.astype(np.float32)),
           np.array([x, y]))


def ecc(image, template, start):
  """(3, 3) OpenCV's ECC homography from `start` (100 iterations, eps 1e-6); `start` where it throws."""
  import cv2

  criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
  try:
    return cv2.findTransformECC(template, image, start.astype(np.float32), cv2.MOTION_HOMOGRAPHY,
                                criteria, None, 5)[1]
  except cv2.error:
    return start.astype(np.float32)


def _align_rows():
  import jaxpso

  image = np.asarray(jaxpso.data.load_image("camera"), np.float32)
  config = jaxpso.TrackConfig(similarity="mi")
  jaxpso.align(image, image[100:200, 100:200], np.float32([[1, 0, 101], [0, 1, 99], [0, 0, 1]]),
               config=config)

  rows = []
  for sigma in SIGMAS:
    ours, theirs, off, ecc_off = [], [], [], []
    for template, start, origin in align_trials(image, sigma):
      begin = time.perf_counter()
      found = np.asarray(jaxpso.align(image, template, start, config=config).homography)
      ours.append(time.perf_counter() - begin)
      begin = time.perf_counter()
      warp = ecc(image, template, start)
      theirs.append(time.perf_counter() - begin)
      off.append(common.corner_error(found, origin) > 1.0)
      ecc_off.append(common.corner_error(warp, origin) > 1.0)
    rows.append({"call": f"align MI σ = {sigma:g} px, × ECC's median",
                 "value": float(np.median(ours) / np.median(theirs)),
                 "detail": f"{np.median(ours) * 1e3:.1f} vs {np.median(theirs) * 1e3:.1f} ms;"
                           f" 90th percentile {np.percentile(ours, 90) / np.median(ours):.1f}×"
                           f" its median; mean {np.mean(ours) / np.mean(theirs):.1f}× ECC's;"
                           f" {np.mean(off):.0%} of trials > 1 px off (ECC {np.mean(ecc_off):.0%})"})
  return rows


def _best_seconds(fn, repeats: int = 3) -> float:
  fn()
  best = np.inf
  for _ in range(repeats):
    begin = time.perf_counter()
    fn()
    best = min(best, time.perf_counter() - begin)
  return best


def _track_rows():
  import jaxpso

  sequence = jaxpso.synthetic.make_sequence(0, num_frames=80, jumps=(40,), noise=0.01)
  rows = []
  for similarity in ("mi", "ncc"):
    config = jaxpso.TrackConfig(similarity=similarity)
    result = []
    seconds = _best_seconds(
        lambda: result.append(jaxpso.track(sequence.frames, sequence.roi, config=config)))
    error = np.sqrt(np.mean(np.sum((result[-1].corners - sequence.corners) ** 2, -1), -1))
    rows.append({"call": f"track {similarity.upper()}, one 100×100 region, ms/frame",
                 "value": seconds / 79 * 1e3, "detail": f"median error {np.median(error):.3f} px"})
  return rows


def _batch_rows(cpu_devices: int = 1):
  import jax
  if cpu_devices > 1:  # before JAX starts its CPU backend
    jax.config.update("jax_num_cpu_devices", cpu_devices)
  import batch  # the 48×48 regions of benchmarks/batch.py
  import jaxpso

  sequence = jaxpso.synthetic.make_sequence(0, num_frames=20, frame_shape=(240, 320),
                                            roi_size=(100, 100))
  boxes = batch.regions(sequence, 64)
  where = f", the CPU as {len(jax.devices())} devices" if cpu_devices > 1 else ""
  rows = []
  for label, config in (("", jaxpso.TrackConfig()),
                        (" without swarm", jaxpso.TrackConfig(accept_quality=0.0))):
    seconds = _best_seconds(lambda: jaxpso.track(sequence.frames, boxes, config=config))
    rows.append({"call": f"track 64 regions of 48×48{label}{where}, ms per region-frame",
                 "value": seconds / (64 * 19) * 1e3, "detail": ""})
  return rows


PARTS = {"align": _align_rows, "track": _track_rows, "batch": _batch_rows,
         "batch_devices": lambda: _batch_rows(cpu_devices=os.cpu_count())}


def _probe(checkout: str, part: str) -> list:
  """`part`'s rows measured in a fresh process importing jaxpso from `checkout`."""
  env = dict(os.environ, PYTHONPATH=checkout)
  out = subprocess.run([sys.executable, os.path.abspath(__file__), "--probe", part],
                       env=env, cwd=checkout, check=True, capture_output=True, text=True).stdout
  return json.loads(out.strip().splitlines()[-1])


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--reference", help="an earlier checkout to measure alongside")
  parser.add_argument("--rounds", type=int, default=2)
  parser.add_argument("--parts", default="align,track,batch", help=",".join(PARTS))
  parser.add_argument("--name", default="runtime", help="results/NAME.{json,md}")
  parser.add_argument("--probe", choices=sorted(PARTS), help=argparse.SUPPRESS)
  args = parser.parse_args()
  if args.probe:
    print(json.dumps(PARTS[args.probe]()))
    return
  trees = {"now": ROOT}
  if args.reference:
    trees = {"reference": os.path.abspath(args.reference), "now": ROOT}
  measured = {name: [] for name in trees}
  for round_ in range(args.rounds):
    for part in args.parts.split(","):
      for name, checkout in trees.items():
        measured[name].append(_probe(checkout, part))
        print(f"round {round_ + 1} {part} {name}: {measured[name][-1]}", flush=True)
  calls = {}
  for name in trees:
    for rows in measured[name]:
      for row in rows:
        calls.setdefault(row["call"], {}).setdefault(name, []).append(row)
  info = common.machine()
  header = " | ".join(["call"] + list(trees))
  lines = [f"# Time per call once compiled{' against a reference checkout' if args.reference else ''}",
           "", common.machine_line(info), "",
           f"Range over {args.rounds} interleaved rounds, each measurement in a fresh process"
           f"{f' (reference: {args.reference})' if args.reference else ''}; see the script's"
           " docstring for the trials.", "", f"| {header} | detail ({list(trees)[-1]}) |",
           "|---" * (len(trees) + 2) + "|"]
  for call, by_tree in calls.items():
    cells = []
    for name in trees:
      values = [row["value"] for row in by_tree.get(name, [])]
      cells.append(f"{min(values):.2f}–{max(values):.2f}" if values else "–")
    lines.append(f"| {call} | {' | '.join(cells)} | {by_tree[list(trees)[-1]][-1]['detail']} |")
  common.write(args.name, {"machine": info, "calls": calls}, "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
