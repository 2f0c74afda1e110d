"""`evaluate`: trackers over a dataset of `datasets.LAYOUTS`, with the benchmarks' metrics.

The metrics are those of the POT-210 and PlanarTrack toolkits: on the frames that are
annotated and not flagged, less the first such frame (the one the tracker starts from),
  alignment error  √(Σ‖cᵢ − ĉᵢ‖² / 4) over the 4 corners, in pixels;
  homography discrepancy  (1/4) Σ ‖pⱼ − π(H·pⱼ)‖, H = H_true · pinv(H_est) of the frame 0 → t
      homographies, pⱼ the corners (±1, ±1);
a sequence's precision (success) curve is the share of its frames with an error at most each
of `PRECISION_PX` (`SUCCESS_THRESHOLDS`), and a method's curve the mean over sequences; the
toolkits rank methods by the curve at `PRECISION_RANK_PX` and `SUCCESS_RANK`.

Every (sequence, method) run writes its tracker output in the layout the benchmark's toolkit
reads, then its per-frame errors as JSON; a run whose JSON exists is not run again, so an
interrupted evaluation resumes where it stopped.  At the end the table (Markdown and CSV) and
the curves (PNG, with matplotlib) are written from every JSON of the methods asked for.
"""

from __future__ import annotations

import csv
import dataclasses
import itertools
import json
import math
import os
import sys
import time
from collections.abc import Iterable
from typing import NamedTuple

import numpy as np

from jaxpso._src import baselines
from jaxpso._src import datasets
from jaxpso._src import results
from jaxpso._src.config import TrackConfig

PRECISION_PX = tuple(range(21))
"""Alignment-error thresholds (px) of the precision curve."""
PRECISION_RANK_PX = 5
"""The threshold the toolkits rank precision at."""
SUCCESS_THRESHOLDS = tuple(range(0, 201, 10))
"""Homography-discrepancy thresholds of the success curve."""
SUCCESS_RANK = 30
"""The threshold the PlanarTrack toolkit ranks success at (its 4th)."""

FEATURE_PEER = "sift"
"""The method name of `track_features` (SIFT + RANSAC against frame 0's region)."""
SIFT_RATIO, SIFT_RANSAC_PX, SIFT_MIN = 0.75, 5.0, 8

_UNIT_SQUARE = np.array([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]])


@dataclasses.dataclass(frozen=True)
class Method:
  """A method to evaluate: a `TrackConfig` run by `jaxpso.track`, or the feature peer (config
  None).  name: its name in the output files, e.g. "pso-mi", "ic-ssd", "sift"."""
  name: str
  config: TrackConfig | None


def method(spec) -> Method:
  """A `Method` from "NAME" or "NAME:SIMILARITY" (NAME one of `jaxpso.METHODS` or
  `FEATURE_PEER`; the similarity defaults to the method's first supported one, MI for "pso"),
  or from a (name, TrackConfig) pair.  ValueError naming an unknown method."""
  if isinstance(spec, Method):
    return spec
  if isinstance(spec, tuple) and len(spec) == 2 and isinstance(spec[1], TrackConfig):
    name, config = spec
    if not isinstance(name, str) or not name or os.sep in name:
      raise ValueError(f"a method's name must be a plain file name, got {name!r}")
    return Method(name, config)
  if not isinstance(spec, str):
    raise TypeError(f"a method must be a name or a (name, TrackConfig) pair, got {spec!r}")
  name, _, similarity = spec.strip().partition(":")
  if name == FEATURE_PEER and not similarity:
    return Method(name, None)
  if name not in baselines.METHODS:
    raise ValueError(f"unknown method {spec!r}: use one of"
                     f" {baselines.METHODS + (FEATURE_PEER,)}, optionally NAME:SIMILARITY")
  if not similarity:
    similarity = "mi" if name == "pso" else baselines.SUPPORTED[name][1][0]
  return Method(f"{name}-{similarity}", TrackConfig(method=name, similarity=similarity))


def alignment_errors(truth: np.ndarray, estimate: np.ndarray) -> np.ndarray:
  """(T,) √(Σ‖cᵢ − ĉᵢ‖² / 4) of (T, 4, 2) true and estimated corners, +inf where one is not
  finite (`results.corner_errors`)."""
  return results.corner_errors(estimate, truth)


def homography_discrepancies(truth: np.ndarray, estimate: np.ndarray) -> np.ndarray:
  """(T,) mean over the corners p of [-1, 1]² of ‖p − π(H_true pinv(H_est) p)‖; (T, 3, 3) each."""
  out = np.full(len(truth), math.inf)
  points = np.c_[_UNIT_SQUARE, np.ones(4)].T
  for t, (h_true, h_est) in enumerate(zip(truth, estimate)):
    if not (np.all(np.isfinite(h_true)) and np.all(np.isfinite(h_est))):
      continue
    mapped = h_true @ np.linalg.pinv(h_est) @ points
    with np.errstate(divide="ignore", invalid="ignore"):
      mapped = mapped[:2] / mapped[2]
    distance = np.mean(np.linalg.norm(_UNIT_SQUARE.T - mapped, axis=0))
    out[t] = distance if np.isfinite(distance) else math.inf
  return out


def used_frames(sequence: datasets.Sequence) -> np.ndarray:
  """(T,) bool: the frames the toolkits score (not excluded, less the first such frame)."""
  used = ~sequence.excluded
  used[np.argmax(used)] = False
  return used


def curve(errors: np.ndarray, thresholds) -> np.ndarray:
  """(len(thresholds),) share of `errors` at most each threshold (0 for no frame)."""
  errors = np.asarray(errors, np.float64)
  return np.array([np.sum(errors <= t) / max(len(errors), 1) for t in thresholds])


def track_features(frames: Iterable, corners) -> tuple[np.ndarray, np.ndarray]:
  """The feature peer: SIFT keypoints of frame 0's region matched in each whole frame (ratio
  `SIFT_RATIO`), homography by RANSAC (`SIFT_RANSAC_PX`) from at least `SIFT_MIN` matches
  with as many inliers, else the previous estimate.

  Args:
    frames: iterable of (H, W) uint8 grey frames, frame 0 first.
    corners: (4, 2) the region in frame 0, TL, TR, BR, BL.

  Returns:
    (T, 4, 2) corners and (T,) bool, whether each frame's homography was found.
  """
  import cv2

  frames = iter(frames)
  first = next(frames)
  quad = np.asarray(corners, np.float64).reshape(1, 4, 2)
  sift = cv2.SIFT_create()
  mask = np.zeros(first.shape[:2], np.uint8)
  cv2.fillConvexPoly(mask, np.round(quad[0]).astype(np.int32), 255)
  keys, template = sift.detectAndCompute(first, mask)
  source = np.float32([k.pt for k in keys]).reshape(-1, 2)
  matcher = cv2.BFMatcher(cv2.NORM_L2)
  homography = np.eye(3)
  out, found = [quad[0]], [True]
  for frame in frames:
    ok = False
    frame_keys, descriptors = sift.detectAndCompute(frame, None)
    if template is not None and descriptors is not None and len(descriptors) >= 2:
      pairs = matcher.knnMatch(template, descriptors, k=2)
      good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < SIFT_RATIO * p[1].distance]
      if len(good) >= SIFT_MIN:
        src = source[[m.queryIdx for m in good]]
        dst = np.float32([frame_keys[m.trainIdx].pt for m in good])
        estimate, inliers = cv2.findHomography(src, dst, cv2.RANSAC, SIFT_RANSAC_PX)
        if (estimate is not None and np.all(np.isfinite(estimate))
            and int(np.sum(inliers)) >= SIFT_MIN):
          homography, ok = estimate, True
    out.append(cv2.perspectiveTransform(quad, homography)[0])
    found.append(ok)
  return np.stack(out), np.array(found)


def _run(entry: Method, sequence: datasets.Sequence, key: int) -> dict:
  """One method on one sequence: its (T, 4, 2) corners (NaN before the first annotated frame),
  (T,) statuses (-1 there; the feature peer: 0 found, 2 not) and seconds."""
  from jaxpso._src.track import track  # track imports most of the package: load it on use

  first = sequence.first
  frames = itertools.islice(sequence.frames(gray=True), first, None)
  start = time.perf_counter()
  try:
    if entry.config is None:
      corners, found = track_features(frames, sequence.corners[first])
      status = np.where(found, 0, 2)
    else:
      result = track(frames, sequence.corners[first], config=entry.config, key=key)
      corners, status = result.corners, result.status
  except ValueError as error:
    raise ValueError(f"sequence {sequence.name}, method {entry.name}: {error}") from None
  seconds = time.perf_counter() - start
  pad = np.full((first, 4, 2), math.nan)
  return {"corners": np.concatenate([pad, corners]),
          "status": np.concatenate([np.full(first, -1), status]), "seconds": seconds}


def _write_output(folder: str, layout: str, sequence: datasets.Sequence, name: str,
                  corners: np.ndarray, homographies: np.ndarray) -> None:
  """The tracker's corners in the files the benchmark's toolkit reads."""
  os.makedirs(folder, exist_ok=True)
  if layout in ("pot", "planartrack"):
    stem = os.path.join(folder, f"{sequence.name}_{name}")
    datasets.write_points(stem + ".txt", corners)
    datasets.write_homographies(stem + "_homography.txt", homographies)
  elif layout in ("ucsb", "tmt"):
    datasets.write_mtf(os.path.join(folder, sequence.name + ".txt"), corners)
  else:
    datasets.write_csv(os.path.join(folder, sequence.name + ".csv"), corners)


def _json_errors(values: np.ndarray, used: np.ndarray) -> list:
  return [(float(v) if math.isfinite(v) else "inf") if u else None for v, u in zip(values, used)]


def _from_json(values: list) -> np.ndarray:
  return np.array([math.inf if v == "inf" else v for v in values if v is not None], np.float64)


def _scored(entry: Method, sequence: datasets.Sequence, run: dict, key: int) -> dict:
  """The per-frame record written as JSON: errors on the used frames (None elsewhere).  run:
  `_run`'s, with the (T, 3, 3) `datasets.frame_homographies` of its corners."""
  corners = run["corners"]
  used = used_frames(sequence)
  align = alignment_errors(sequence.corners, corners)
  return {"sequence": sequence.name, "method": entry.name, "config": _setup(entry, key),
          "frames": len(sequence),
          "attributes": list(sequence.attributes), "seconds": run["seconds"],
          "ms_per_frame": 1000 * run["seconds"] / max(len(sequence) - sequence.first - 1, 1),
          "alignment_error": _json_errors(align, used),
          "homography_discrepancy": _json_errors(
              homography_discrepancies(sequence.homographies, run["homographies"]), used),
          "status": [int(s) for s in run["status"]]}


class Report(NamedTuple):
  """What `evaluate` measured.

  Attributes:
    rows: one dict per (method, attribute) with keys method, attribute ("all" or a name),
      sequences, frames, precision (at `PRECISION_RANK_PX`), success (at `SUCCESS_RANK`),
      ms_per_frame.
    curves: {(method, attribute): (precision (21,), success (21,))}.
    ran: (sequence, method) runs done by this call; resumed: those read back from disk.
    seconds: this call's time; tracker_seconds: the part spent inside the trackers' runs
      (decoding the frames included: they stream from disk); report_seconds: the part spent
      writing the table and the curves at the end.
  """
  rows: list
  curves: dict
  ran: int
  resumed: int
  seconds: float
  tracker_seconds: float
  report_seconds: float


def _summarise(records: dict, methods: list, sequences: list) -> tuple[list, dict]:
  attributes = sorted({a for s in sequences for a in s.attributes})
  rows, curves = [], {}
  for entry in methods:
    for attribute in ["all"] + attributes:
      chosen = [s for s in sequences if attribute == "all" or attribute in s.attributes]
      found = [records[(s.name, entry.name)] for s in chosen]
      precision = np.mean([curve(_from_json(r["alignment_error"]), PRECISION_PX)
                           for r in found], axis=0)
      success = np.mean([curve(_from_json(r["homography_discrepancy"]), SUCCESS_THRESHOLDS)
                         for r in found], axis=0)
      curves[(entry.name, attribute)] = (precision, success)
      seconds = sum(r["seconds"] for r in found)
      frames = sum(r["frames"] for r in found)
      rows.append({"method": entry.name, "attribute": attribute, "sequences": len(found),
                   "frames": sum(len(_from_json(r["alignment_error"])) for r in found),
                   "precision": float(precision[PRECISION_PX.index(PRECISION_RANK_PX)]),
                   "success": float(success[SUCCESS_THRESHOLDS.index(SUCCESS_RANK)]),
                   "ms_per_frame": 1000 * seconds / max(frames - len(found), 1)})
  return rows, curves


def _write_tables(out: str, rows: list, dataset: str, layout: str) -> None:
  with open(os.path.join(out, "summary.csv"), "w", newline="") as handle:
    writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
  lines = [f"# {os.path.basename(os.path.abspath(dataset))} ({layout})", "",
           f"Precision: share of scored frames with an alignment error ≤ {PRECISION_RANK_PX} px;"
           f" success: homography discrepancy ≤ {SUCCESS_RANK}; each the mean over sequences"
           " (the POT-210 / PlanarTrack toolkits' ranking).  Curves: precision.png,"
           " success.png; per-frame errors: errors/METHOD/SEQUENCE.json.", "",
           "| method | attribute | sequences | scored frames | precision | success | ms/frame |",
           "|---|---|---:|---:|---:|---:|---:|"]
  lines += [f"| {r['method']} | {r['attribute']} | {r['sequences']} | {r['frames']} |"
            f" {r['precision']:.3f} | {r['success']:.3f} | {r['ms_per_frame']:.1f} |"
            for r in rows]
  with open(os.path.join(out, "summary.md"), "w") as handle:
    handle.write("\n".join(lines) + "\n")


def _plot(out: str, curves: dict, methods: list) -> list:
  """precision.png and success.png, a panel per attribute; [] without matplotlib."""
  try:
    import matplotlib
  except ImportError:
    return []
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  attributes = list(dict.fromkeys(a for _, a in curves))
  columns = min(len(attributes), 4)
  rows_ = math.ceil(len(attributes) / columns)
  written = []
  for index, (file, thresholds, label, rank) in enumerate((
      ("precision.png", PRECISION_PX, "alignment error threshold (px)", PRECISION_RANK_PX),
      ("success.png", SUCCESS_THRESHOLDS, "homography discrepancy threshold", SUCCESS_RANK))):
    figure, axes = plt.subplots(rows_, columns, figsize=(4 * columns, 3.2 * rows_),
                                squeeze=False)
    for axis, attribute in zip(axes.flat, attributes):
      for entry in methods:
        values = curves[(entry.name, attribute)][index]
        axis.plot(thresholds, values,
                  label=f"{entry.name} [{values[list(thresholds).index(rank)]:.3f}]")
      axis.set(title=attribute, xlabel=label, ylim=(0, 1.02))
      axis.grid(alpha=0.3)
      axis.legend(fontsize=7, loc="lower right")
    for axis in list(axes.flat)[len(attributes):]:
      axis.axis("off")
    figure.tight_layout()
    figure.savefig(os.path.join(out, file), dpi=100)
    plt.close(figure)
    written.append(os.path.join(out, file))
  return written


def _claim(out: str, dataset: str, layout: str) -> None:
  """Creates out/run.json, or checks that it names this dataset and layout."""
  path = os.path.join(out, "run.json")
  mine = {"dataset": os.path.abspath(dataset), "layout": layout}
  if os.path.exists(path):
    with open(path) as handle:
      theirs = json.load(handle)
    if {k: theirs.get(k) for k in mine} != mine:
      raise ValueError(f"{out} holds the evaluation of {theirs.get('dataset')!r}"
                       f" ({theirs.get('layout')}); choose another --out")
    return
  os.makedirs(out, exist_ok=True)
  with open(path, "w") as handle:
    json.dump(mine, handle, indent=1)


def _progress(done: int, total: int, seconds: float, frames_done: int, frames_left: int,
              text: str) -> None:
  eta = seconds / frames_done * frames_left if frames_done else math.nan
  eta_text = "?" if math.isnan(eta) else time.strftime("%H:%M:%S", time.gmtime(eta))
  print(f"[{done}/{total}] {text}  ETA {eta_text}", file=sys.stderr, flush=True)


def _setup(entry: Method, key: int) -> str:
  """What a run's result depends on besides the data: the config and the seed."""
  return f"{entry.config!r}, key={key}"


def evaluate(dataset, layout: str, methods, out, *, sequences=None, key: int = 0,
             progress: bool = True) -> Report:
  """Runs `methods` over the dataset and writes results, errors, table and curves to `out`.

  Args:
    dataset: the dataset folder.
    layout: one of `datasets.LAYOUTS`.
    methods: specs for `method` ("pso", "pso:ncc", "ic", "ecc", "sift", (name, TrackConfig)).
    out: the output folder; a folder of an earlier run on the same dataset is resumed.
    sequences: names of the sequences to evaluate (default all).
    key: the trackers' int seed (the same for every sequence).
    progress: a line per run on stderr with the estimated time left.

  Returns:
    `Report`.  Writes out/results/METHOD/ (the toolkit's files), out/errors/METHOD/SEQ.json,
    out/summary.md, out/summary.csv, out/precision.png and out/success.png.

  Raises:
    ValueError: an unknown method or sequence, a dataset in another layout or with malformed
    files, an `out` holding another dataset's evaluation; all checked before anything is run.
  """
  started = time.perf_counter()
  entries = [method(m) for m in (methods.split(",") if isinstance(methods, str) else methods)]
  if not entries:
    raise ValueError("methods is empty")
  names = [e.name for e in entries]
  if len(set(names)) != len(names):
    raise ValueError(f"methods name one method twice: {names}")
  found = datasets.read(dataset, layout)
  if sequences is not None:
    unknown = sorted(set(sequences) - {s.name for s in found})
    if unknown:
      raise ValueError(f"no sequence {unknown} in {dataset}")
    found = [s for s in found if s.name in set(sequences)]
    if not found:
      raise ValueError("sequences is empty")
  out = os.fspath(out)
  _claim(out, dataset, layout)
  records, todo = {}, []
  for sequence in found:
    for entry in entries:
      path = os.path.join(out, "errors", entry.name, sequence.name + ".json")
      if os.path.exists(path):
        with open(path) as handle:
          record = json.load(handle)
        if record.get("config") != _setup(entry, key):
          raise ValueError(f"{path} was made with another configuration of {entry.name}"
                           f" ({record.get('config')}); choose another --out or method name")
        records[(sequence.name, entry.name)] = record
      else:
        todo.append((sequence, entry, path))
  resumed = len(records)
  tracker_seconds, frames_done = 0.0, 0
  frames_left = sum(len(s) for s, _, _ in todo)
  for done, (sequence, entry, path) in enumerate(todo, start=1):
    run = _run(entry, sequence, key)
    tracker_seconds += run["seconds"]
    run["homographies"] = datasets.frame_homographies(run["corners"])
    _write_output(os.path.join(out, "results", entry.name), layout, sequence, entry.name,
                  run["corners"], run["homographies"])
    record = _scored(entry, sequence, run, key)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path + ".part", "w") as handle:
      json.dump(record, handle)
    os.replace(path + ".part", path)  # last: a run is done once its JSON exists
    records[(sequence.name, entry.name)] = record
    frames_done += len(sequence)
    frames_left -= len(sequence)
    if progress:
      precision = curve(_from_json(record["alignment_error"]), [PRECISION_RANK_PX])[0]
      _progress(done + resumed, len(todo) + resumed, tracker_seconds, frames_done, frames_left,
                f"{sequence.name} {entry.name}: {record['ms_per_frame']:.1f} ms/frame,"
                f" precision {precision:.3f}")
  reporting = time.perf_counter()
  rows, curves = _summarise(records, entries, found)
  _write_tables(out, rows, dataset, layout)
  _plot(out, curves, entries)
  end = time.perf_counter()
  return Report(rows, curves, len(todo), resumed, end - started, tracker_seconds,
                end - reporting)
