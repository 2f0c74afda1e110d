"""Time per call once compiled, this code against an earlier checkout, interleaved.

`python benchmarks/runtime.py [--reference DIR] [--rounds 2] [--parts align,track,batch]
[--name runtime] [--trials 40] [--cases clean,…]` runs each
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
  80-frame synthetic sequence of 240×320 and of 480×640 frames (100×100
  region, a jump at frame 40), best of 3 calls, ms per frame, median corner
  error.
* track, a batch: 64 regions of 48×48 (`batch.regions`) over 20 frames of
  a 240×320 sequence, best of 3; the default and `accept_quality=0` (no
  swarm: Gauss–Newton and the check alone), ms per region-frame.
  `batch_devices` (not in the default `--parts`): the same with the CPU's
  cores as many JAX devices (`jax_num_cpu_devices`), the batch split
  over them.
* align_batch (not in the default `--parts`): align MI on `--trials` trials
  of each of `--cases` as one batch (a key per element, so each element is
  its own call's) against the same calls one by one, best of 3 each; on a
  CPU a batch runs its elements one after another, so it should cost at
  most their sum.
* cases (not in the default `--parts`; e.g. `--parts cases --name
  runtime_cases`): `--trials` per case of `--cases`, where the match is
  imperfect and align runs its retries.  A 100×100 template cut from a CC0
  photograph (camera, brick, gravel, grass in turn; `$JAXPSO_IMAGES`, as
  video.py), the start its corners moved by N(0, 8²), the image that
  photograph: clean; gamma (the image to the power 2^U(−1, 1)); shading
  (× a ramp 0.4–1 across it, random direction); noise (+ N(0, 0.08²),
  clipped); inverted (1 − image: beyond NCC and ECC).  Trial k of each is
  clean's trial k, the image changed.  real_pairs: a second view, the photograph zoomed by 0.7–0.8
  and its plane tilted 20–30° about a random in-plane axis through the
  centre (K·diag(z, z, 1)·R'·K⁻¹, f = 500 px, R' = R with e₃ for its third
  column), blurred (σ 1–2 px), relit (gain 0.6–1.3, bias ±0.1, × a smooth
  field 0.8–1.2) and JPEG'd (quality 20–30); the template from a region
  that stays in view, the start N(0, 4²) off.  ECC, align MI and align NCC
  on every trial in turn, each warmed up once; success: corner RMS ≤ 1 px;
  a table per checkout of the times pooled over the rounds.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import os
import time

import numpy as np

import common

SIGMAS = (2.0, 8.0)
TRIALS = 200
CASES = ("clean", "gamma", "shading", "noise", "inverted", "real_pairs")
FOCAL = 500.0
SQUARE = np.float32([[0, 0], [99, 0], [99, 99], [0, 99]])


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

  rows = []
  for shape, label in (((240, 320), ""), ((480, 640), ", 480×640 frames")):
    sequence = jaxpso.synthetic.make_sequence(0, num_frames=80, jumps=(40,), noise=0.01,
                                              frame_shape=shape)
    for similarity in ("mi", "ncc"):
      config = jaxpso.TrackConfig(similarity=similarity)
      result = []
      seconds = _best_seconds(
          lambda: result.append(jaxpso.track(sequence.frames, sequence.roi, config=config)))
      error = np.sqrt(np.mean(np.sum((result[-1].corners - sequence.corners) ** 2, -1), -1))
      rows.append({"call": f"track {similarity.upper()}, one 100×100 region{label}, ms/frame",
                   "value": seconds / 79 * 1e3,
                   "detail": f"median error {np.median(error):.3f} px"})
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


def _relit(case: str, photo, rng):
  """(H, W) float32 `photo` (H, W) changed as photometric `case` says."""
  if case == "gamma":
    photo = photo ** 2.0 ** rng.uniform(-1, 1)
  elif case == "shading":
    rows, cols = np.mgrid[:photo.shape[0], :photo.shape[1]]
    angle = rng.uniform(0, 2 * np.pi)
    ramp = np.cos(angle) * cols + np.sin(angle) * rows
    photo = photo * (0.4 + 0.6 * (ramp - ramp.min()) / np.ptp(ramp))
  elif case == "noise":
    photo = np.clip(photo + rng.normal(0, 0.08, photo.shape), 0, 1)
  elif case == "inverted":
    photo = 1 - photo
  return photo.astype(np.float32)


def _second_view(photo, rng):
  """(image (H, W) float32, photo pixel → image pixel (3, 3)): `photo` (H, W) zoomed, tilted,
  blurred, relit and JPEG'd."""
  import cv2

  rows, cols = photo.shape
  camera = np.array([[FOCAL, 0, (cols - 1) / 2], [0, FOCAL, (rows - 1) / 2], [0, 0, 1]])
  axis = rng.uniform(0, 2 * np.pi)
  angle = np.deg2rad(rng.uniform(20, 30))
  tilt = cv2.Rodrigues(angle * np.array([np.cos(axis), np.sin(axis), 0]))[0]
  tilt[:, 2] = [0, 0, 1]  # the plane z = 1 turned about its point on the axis
  zoom = rng.uniform(0.7, 0.8)
  view = camera @ np.diag([zoom, zoom, 1]) @ tilt @ np.linalg.inv(camera)
  image = cv2.warpPerspective(photo, view, (cols, rows), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REFLECT)
  image = cv2.GaussianBlur(image, (0, 0), rng.uniform(1, 2))
  field = cv2.resize(rng.uniform(0.8, 1.2, (3, 3)).astype(np.float32), (cols, rows),
                     interpolation=cv2.INTER_CUBIC)
  image = np.clip((image * rng.uniform(0.6, 1.3) + rng.uniform(-0.1, 0.1)) * field, 0, 1)
  jpeg = cv2.imencode(".jpg", np.round(image * 255).astype(np.uint8),
                      [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(20, 31))])[1]
  return cv2.imdecode(jpeg, cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255, view / view[2, 2]


def case_trials(case: str, photos, count: int, seed: int = 0):
  """`count` (image (H, W), template (100, 100), start (3, 3), truth (3, 3)) trials of `case`."""
  import cv2

  for k in range(count):
    rng = np.random.default_rng([seed, k])
    photo = photos[k % len(photos)]
    image, view, sigma = photo, np.eye(3), 8.0
    if case == "real_pairs":
      (image, view), sigma = _second_view(photo, rng), 4.0
    while True:  # a template that stays in view
      x, y = rng.integers(60, 512 - 160, 2)
      truth = view @ np.array([[1, 0, x], [0, 1, y], [0, 0, 1.0]])
      corners = cv2.perspectiveTransform(SQUARE[None].astype(np.float64), truth)[0]
      if np.all((corners >= 8) & (corners <= np.array(photo.shape[::-1]) - 9)):
        break
    moved = corners + rng.normal(0, sigma, (4, 2))
    start = cv2.getPerspectiveTransform(SQUARE, moved.astype(np.float32))
    if case != "real_pairs":
      image = _relit(case, photo, rng)
    yield image, photo[y:y + 100, x:x + 100], start, truth


def _corner_rms(h, truth) -> float:
  """RMS distance (px) of the 100×100 template's corners mapped by h from truth's (3, 3) each."""
  import cv2

  source = SQUARE[None].astype(np.float64)
  mapped = [cv2.perspectiveTransform(source, np.asarray(m, np.float64))[0] for m in (h, truth)]
  return float(np.sqrt(np.mean(np.sum((mapped[0] - mapped[1]) ** 2, -1))))


def _cases_rows(cases: list, count: int, budgets: list):
  """Per case and method a row: the median ms, and each trial's seconds and success; align with
  each of `budgets` (`TrackConfig.max_evaluations`: "default", "none" or an int)."""
  import jaxpso

  photos = [common.photo(name) for name in common.PHOTOS]
  methods = {"ECC": ecc}
  for similarity, budget in itertools.product(("mi", "ncc"), budgets):
    config = jaxpso.TrackConfig(similarity=similarity)
    if budget != "default":
      config = dataclasses.replace(config, max_evaluations=None if budget == "none" else budget)
    name = f"align {similarity.upper()}" + ("" if budget == "default" else f", budget {budget}")
    methods[name] = lambda *a, config=config: np.asarray(jaxpso.align(*a, config=config).homography)
  warmup = next(case_trials("clean", photos, 1))[:3]
  for method in methods.values():
    method(*warmup)
  rows = []
  for case in cases:
    seconds, ok = {name: [] for name in methods}, {name: [] for name in methods}
    for image, template, start, truth in case_trials(case, photos, count):
      for name, method in methods.items():
        begin = time.perf_counter()
        found = method(image, template, start)
        seconds[name].append(time.perf_counter() - begin)
        ok[name].append(_corner_rms(found, truth) <= 1.0)
    rows += [{"call": f"cases {case}: {name}, median ms",
              "value": float(np.median(seconds[name]) * 1e3),
              "detail": f"{np.mean(ok[name]):.0%} within 1 px", "case": case, "method": name,
              "seconds": seconds[name], "ok": [bool(o) for o in ok[name]]} for name in methods]
  return rows


def _cases_lines(rows: list, rounds: int) -> list:
  """The markdown table of the cases part's `rows` of every round, their times pooled."""
  pooled = {}
  for row in rows:
    seconds, ok = pooled.setdefault((row["case"], row["method"]), ([], []))
    seconds += row["seconds"]
    ok += row["ok"]
  lines = ["| case | method | trials | success | median ms | p90 ms | p99 ms | max ms"
           " | median / ECC's | p99 / ECC's |", "|---" * 10 + "|"]
  for (case, name), (seconds, ok) in pooled.items():
    ms, ecc_ms = np.array(seconds) * 1e3, np.array(pooled[case, "ECC"][0]) * 1e3
    median, p90, p99 = np.percentile(ms, [50, 90, 99])
    lines.append(f"| {case} | {name} | {len(ok) // rounds} | {np.mean(ok):.0%} | {median:.2f}"
                 f" | {p90:.2f} | {p99:.2f} | {ms.max():.2f} | {median / np.median(ecc_ms):.2f}"
                 f" | {p99 / np.percentile(ecc_ms, 99):.2f} |")
  return lines


def _align_batch_rows(cases: list, count: int):
  """align MI on `count` trials of each of `cases` as one batch against the same calls one by
  one: best of 3 each, seconds, and their ratio."""
  import jaxpso

  photos = [common.photo(name) for name in common.PHOTOS]
  trials = [t[:3] for case in cases for t in case_trials(case, photos, count)]
  images, templates, starts = (np.stack(a) for a in zip(*trials))
  config = jaxpso.TrackConfig(similarity="mi")
  keys = np.arange(len(trials))

  def batched():
    np.asarray(jaxpso.align(images, templates, starts, config=config, key=keys).homography)

  def alone():
    for k, trial in enumerate(trials):
      np.asarray(jaxpso.align(*trial, config=config, key=int(k)).homography)

  batch_s, alone_s = _best_seconds(batched), _best_seconds(alone)
  label = f"align MI, {len(trials)} of {'/'.join(cases)}"
  return [{"call": f"{label} as one batch, ms", "value": batch_s * 1e3, "detail": ""},
          {"call": f"{label} one by one, ms", "value": alone_s * 1e3, "detail": ""},
          {"call": f"{label}: batch / one by one", "value": batch_s / alone_s, "detail": ""}]


PARTS = {"align": lambda options: _align_rows(), "track": lambda options: _track_rows(),
         "batch": lambda options: _batch_rows(),
         "batch_devices": lambda options: _batch_rows(cpu_devices=os.cpu_count()),
         "cases": lambda options: _cases_rows(options.cases.split(","), options.trials,
                                              _budgets(options.budgets)),
         "align_batch": lambda options: _align_batch_rows(options.cases.split(","),
                                                          options.trials)}


def _budgets(text: str) -> list:
  """`--budgets`: "default", "none" (no cap) or an int each."""
  return [b if b in ("default", "none") else int(b) for b in text.split(",")]


def _probe(checkout: str, part: str, options) -> list:
  """`part`'s rows measured in a fresh process importing jaxpso from `checkout`."""
  return common.in_checkout(__file__, checkout, [
      "--probe", part, "--trials", str(options.trials), "--cases", options.cases,
      "--budgets", options.budgets])


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--reference", help="an earlier checkout to measure alongside")
  parser.add_argument("--rounds", type=int, default=2)
  parser.add_argument("--parts", default="align,track,batch", help=",".join(PARTS))
  parser.add_argument("--name", default="runtime", help="results/NAME.{json,md}")
  parser.add_argument("--trials", type=int, default=40, help="cases: trials per case")
  parser.add_argument("--cases", default=",".join(CASES), help="cases: " + ",".join(CASES))
  parser.add_argument("--budgets", default="default",
                      help="cases: align's max_evaluations, 'default' or ints, e.g. default,8000")
  parser.add_argument("--probe", choices=sorted(PARTS), help=argparse.SUPPRESS)
  args = parser.parse_args()
  if set(args.cases.split(",")) - set(CASES):
    parser.error(f"--cases: each of {','.join(CASES)}")
  if args.probe:
    print(json.dumps(PARTS[args.probe](args)))
    return
  trees = {"now": common.ROOT}
  if args.reference:
    trees = {"reference": os.path.abspath(args.reference), "now": common.ROOT}
  measured = {name: [] for name in trees}
  for round_ in range(args.rounds):
    for part in args.parts.split(","):
      for name, checkout in trees.items():
        measured[name].append(_probe(checkout, part, args))
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
  for name in trees:
    rows = [row for rounds in measured[name] for row in rounds if "case" in row]
    if rows:
      lines += ["", f"Cases, {name}: {args.trials} trials per case, each timed once a round, the"
                f" {args.rounds} rounds pooled; success: corner RMS ≤ 1 px.", "",
                *_cases_lines(rows, args.rounds)]
  common.write(args.name, {"machine": info, "calls": calls}, "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
