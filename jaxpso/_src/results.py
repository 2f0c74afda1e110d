"""The tracker's result files, summaries and plots.

`write_results` writes a track result as results.csv and results.json,
`summarize` and `corner_errors` reduce it to numbers, `plot_results` draws
it as a PNG.  Everything runs on the host in NumPy.  matplotlib is imported
inside `plot_results` only (and OpenCV inside `video.py` only), so
`import jaxpso` (and `import jaxpso.io`) stays free of both.

Frame input/output and overlays are in `video.py`; this module imports the
status colours from there (for the plot's points), never the reverse.
"""

from __future__ import annotations

import csv
import json
import math
import os

import numpy as np

from jaxpso._src.video import STATUS_COLORS

STATUS_NAMES = ("TRACKED", "RECOVERED", "LOST", "DOUBTFUL")
"""Names of the tracker's status codes 0, 1, 2, 3 (`jaxpso.TrackStatus`)."""

WITHIN_PX = 5.0
"""Corner error (px) under which `write_results` counts a frame as within tolerance."""


def _field(result, name: str, trailing=(), dtype=np.float64) -> np.ndarray:
  try:
    value = getattr(result, name)
  except AttributeError:
    raise TypeError(f"result must be a TrackResult (it has no field {name!r})") from None
  array = np.asarray(value, dtype)
  if array.ndim != 1 + len(trailing) or array.shape[1:] != tuple(trailing):
    layout = "(T" + "".join(f", {n}" for n in trailing) + ")"
    raise ValueError(f"result.{name} must have shape {layout}, got shape {array.shape}")
  return array


def _table(result, truth_corners):
  """Per-frame columns of a track result, checked for consistent lengths."""
  columns = {
      "corners": _field(result, "corners", (4, 2)),
      "scores": _field(result, "scores"),
      "quality": _field(result, "quality"),
      "status": _field(result, "status", dtype=np.int64),
      "num_iterations": _field(result, "num_iterations", dtype=np.int64),
      "num_evaluations": _field(result, "num_evaluations", dtype=np.int64),
  }
  length = len(columns["corners"])
  for name, column in columns.items():
    if len(column) != length:
      raise ValueError(f"result.{name} has {len(column)} frames, result.corners {length}")
  if np.any((columns["status"] < 0) | (columns["status"] >= len(STATUS_NAMES))):
    raise ValueError(f"result.status must hold codes 0, 1, 2 or 3, got"
                     f" {np.unique(columns['status'])}")
  errors = None
  if truth_corners is not None:
    truth = np.asarray(truth_corners, np.float64)
    if truth.shape != (length, 4, 2):
      raise ValueError(f"truth_corners must have shape ({length}, 4, 2) like result.corners,"
                       f" got shape {truth.shape}")
    errors = corner_errors(columns["corners"], truth)
  return columns, errors


def corner_errors(corners, truth_corners) -> np.ndarray:
  """Root-mean-square distance between tracked and true corners, per frame.

  e_t = sqrt(1/4 Σ_i |c_ti − c*_ti|²), the Baker–Matthews alignment error
  (the same as `jaxpso.warp.corner_error` on the homographies); +inf where
  a corner is not finite.

  Args:
    corners: (T, 4, 2) tracked corners.
    truth_corners: (T, 4, 2) true corners.

  Returns:
    (T,) float64 errors in pixels.

  Examples:
    >>> import numpy as np
    >>> square = np.array([[[0.0, 0.0], [9.0, 0.0], [9.0, 9.0], [0.0, 9.0]]])
    >>> corner_errors(square + [3.0, 4.0], square).tolist()
    [5.0]
  """
  corners = np.asarray(corners, np.float64)
  truth = np.asarray(truth_corners, np.float64)
  if corners.ndim != 3 or corners.shape[1:] != (4, 2) or truth.shape != corners.shape:
    raise ValueError(f"corners and truth_corners must both have shape (T, 4, 2), got"
                     f" {corners.shape} and {truth.shape}")
  with np.errstate(invalid="ignore", over="ignore"):
    errors = np.sqrt(np.mean(np.sum((corners - truth) ** 2, axis=-1), axis=-1))
  return np.where(np.isfinite(errors), errors, np.inf)


def _number(value: float):
  """A float for JSON: None where not finite (JSON has no inf or NaN)."""
  value = float(value)
  return value if math.isfinite(value) else None


def summarize(result, *, truth_corners=None) -> dict:
  """Summary of a track result: frames, status counts, and errors if truth is given.

  Args:
    result: a `jaxpso.TrackResult` (any object with its per-frame fields).
    truth_corners: optional (T, 4, 2) true corners.

  Returns:
    dict with "frames" (T), "status_counts" ({"TRACKED": n, "RECOVERED": n,
    "LOST": n, "DOUBTFUL": n}) and "median_score"; with truth also
    "within_5px" (fraction of frames whose corner error is <= `WITHIN_PX`),
    "median_error_px", "mean_error_px" and "max_error_px" (None where not
    finite).
  """
  columns, errors = _table(result, truth_corners)
  return _summary(columns, errors)


def _summary(columns, errors) -> dict:
  status = columns["status"]
  scores = columns["scores"]
  finite_scores = scores[np.isfinite(scores)]
  summary = {
      "frames": len(status),
      "status_counts": {name: int(np.sum(status == code))
                        for code, name in enumerate(STATUS_NAMES)},
      "median_score": _number(np.median(finite_scores)) if finite_scores.size else None,
  }
  if errors is not None:
    summary.update({
        "within_5px": float(np.mean(errors <= WITHIN_PX)) if errors.size else 0.0,
        "median_error_px": _number(np.median(errors)) if errors.size else None,
        "mean_error_px": _number(np.mean(errors)) if errors.size else None,
        "max_error_px": _number(np.max(errors)) if errors.size else None,
    })
  return summary


def _short(value) -> str:
  """The shortest text that reads back as the same float32 ("inf", "nan" where not finite)."""
  return str(np.float32(value))


_CORNER_COLUMNS = tuple(f"{corner}_{axis}" for corner in ("tl", "tr", "br", "bl") for axis in "xy")


def write_results(out_dir, result, *, truth_corners=None) -> dict:
  """Writes results.csv and results.json for a track result; returns the summary.

  results.csv has one row per frame with the columns frame, status (name),
  score, quality, tl_x, tl_y, tr_x, tr_y, br_x, br_y, bl_x, bl_y, error_px
  (only with truth: RMS corner error, `corner_errors`), iterations and
  evaluations.  results.json holds {"summary": `summarize(...)`, "frames":
  [one object per frame with the same values, corners as [[x, y] × 4]]};
  non-finite numbers are written as null.

  Args:
    out_dir: folder to write into (created if missing).
    result: a `jaxpso.TrackResult` (any object with fields corners (T, 4, 2),
      scores, quality, status, num_iterations, num_evaluations (T,)).
    truth_corners: optional (T, 4, 2) true corners.

  Returns:
    The summary dict (see `summarize`).

  Raises:
    TypeError: if `result` lacks a field.
    ValueError: on inconsistent shapes or status codes outside {0, 1, 2, 3}.
  """
  columns, errors = _table(result, truth_corners)
  summary = _summary(columns, errors)
  out_dir = os.fspath(out_dir)
  os.makedirs(out_dir, exist_ok=True)
  header = ["frame", "status", "score", "quality", *_CORNER_COLUMNS]
  if errors is not None:
    header.append("error_px")
  header += ["iterations", "evaluations"]
  rows = []
  with open(os.path.join(out_dir, "results.csv"), "w", newline="") as f:
    writer = csv.writer(f)
    writer.writerow(header)
    for t in range(summary["frames"]):
      corners = columns["corners"][t]
      row = {"frame": t, "status": STATUS_NAMES[columns["status"][t]],
             "score": _number(columns["scores"][t]), "quality": _number(columns["quality"][t]),
             "corners": [[_number(x), _number(y)] for x, y in corners]}
      if errors is not None:
        row["error_px"] = _number(errors[t])
      row["iterations"] = int(columns["num_iterations"][t])
      row["evaluations"] = int(columns["num_evaluations"][t])
      rows.append(row)
      values = [t, row["status"], _short(columns["scores"][t]), _short(columns["quality"][t]),
                *(_short(v) for v in corners.ravel())]
      if errors is not None:
        values.append(_short(errors[t]))
      writer.writerow(values + [row["iterations"], row["evaluations"]])
  with open(os.path.join(out_dir, "results.json"), "w") as f:
    json.dump({"summary": summary, "frames": rows}, f, indent=1, allow_nan=False)
  return summary


def _centres(corners: np.ndarray) -> np.ndarray:
  """(T, 2) images of the template centre: where the quadrilateral's diagonals cross.

  A homography maps the rectangle's centre (its diagonals' crossing) to the
  crossing of the mapped diagonals; the corners' mean is the fallback where
  the diagonals are (nearly) parallel.
  """
  tl, tr, br, bl = (corners[:, i] for i in range(4))
  d1, d2 = br - tl, bl - tr
  denominator = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
  offset = tr - tl
  safe = np.abs(denominator) > 1e-9
  s = np.where(safe, (offset[:, 0] * d2[:, 1] - offset[:, 1] * d2[:, 0])
               / np.where(safe, denominator, 1.0), 0.5)
  crossing = tl + s[:, None] * d1
  return np.where(safe[:, None], crossing, corners.mean(axis=1))


def plot_results(path, result, *, truth_corners=None) -> None:
  """Writes a PNG: the error (or score) per frame and the template centre's path.

  Left: the RMS corner error per frame with the `WITHIN_PX` line if truth is
  given, else the score per frame; points coloured by status.  Right: the
  trajectory of the template centre in image coordinates, tracked and (if
  given) true.  Uses matplotlib's Agg canvas directly (no pyplot, the global
  backend is left alone).

  Args:
    path: the PNG file to write (str or `os.PathLike`); its folder must exist.
    result: a `jaxpso.TrackResult` (fields as in `write_results`).
    truth_corners: optional (T, 4, 2) true corners.

  Raises:
    ImportError: if matplotlib is not installed (pip install jaxpso[plots]).
    TypeError, ValueError: as `write_results`.
  """
  columns, errors = _table(result, truth_corners)
  try:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
  except ImportError as error:
    raise ImportError("plot_results needs matplotlib: pip install 'jaxpso[plots]'") from error

  status = columns["status"]
  frames = np.arange(len(status))
  colors = np.array([np.array(c) / 255.0 for c in STATUS_COLORS])[status]
  figure = Figure(figsize=(10, 4))
  FigureCanvasAgg(figure)
  left, right = figure.subplots(1, 2)
  if errors is not None:
    shown = np.where(np.isfinite(errors), errors, np.nan)
    left.plot(frames, shown, color="0.6", linewidth=1, zorder=1)
    left.scatter(frames, shown, c=colors, s=12, zorder=2)
    left.axhline(WITHIN_PX, color="k", linestyle="--", linewidth=1, label=f"{WITHIN_PX:g} px")
    left.set_ylabel("RMS corner error (px)")
    if np.nanmax(np.append(shown, 0.0)) > 20 * WITHIN_PX:
      left.set_yscale("log")
    left.set_title("corner error per frame")
  else:
    shown = np.where(np.isfinite(columns["scores"]), columns["scores"], np.nan)
    left.plot(frames, shown, color="0.6", linewidth=1, zorder=1)
    left.scatter(frames, shown, c=colors, s=12, zorder=2)
    left.set_ylabel("score")
    left.set_title("score per frame")
  left.set_xlabel("frame")
  for code, name in enumerate(STATUS_NAMES):  # legend entries for the status colours
    left.scatter([], [], color=np.array(STATUS_COLORS[code]) / 255.0, s=12, label=name)
  left.legend(loc="best", fontsize="small")

  tracked = _centres(columns["corners"])
  if truth_corners is not None:
    truth = _centres(np.asarray(truth_corners, np.float64))
    right.plot(truth[:, 0], truth[:, 1], color="k", linewidth=1.5, label="truth")
  right.plot(tracked[:, 0], tracked[:, 1], color="tab:green", linewidth=1, marker=".",
             markersize=3, label="tracked")
  right.invert_yaxis()
  right.set_aspect("equal", adjustable="datalim")
  right.set_xlabel("x (px)")
  right.set_ylabel("y (px)")
  right.set_title("template centre")
  right.legend(loc="best", fontsize="small")
  figure.tight_layout()
  figure.savefig(os.fspath(path), dpi=80, format="png")
