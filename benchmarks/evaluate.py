"""`jaxpso evaluate` on generated datasets in every layout: completion, resume, memory, overhead.

For each layout of `jaxpso.datasets.LAYOUTS` a dataset of --sequences sequences of --frames
frames (jaxpso.synthetic, 240×320, a 100×100 region, frame 2 unannotated and frame 4 flagged
where the layout allows) is written to a temporary folder, then `jaxpso evaluate` runs on it in
a fresh process with --methods.  Per layout: the process's wall time, the time inside the
trackers (frame decoding included: frames stream from disk), the evaluation loop's overhead
(the rest, over the whole), peak memory (ru_maxrss of the process) against a process
evaluating only the first 2 sequences, and the table.  The pot dataset is also evaluated
with the process interrupted (SIGINT) about half way and run again: the
second run must run only the remaining (sequence, method) pairs and give the same table.

  python evaluate.py [--sequences 20] [--frames 100] [--methods pso,ic,ecc]

The attributes in the tables are those the sequences' names carry in each layout (POT-210's
suffix _1 ... _7), not challenges the synthetic frames show.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import signal
import subprocess
import sys
import tempfile

import numpy as np

import common
from jaxpso import datasets
from jaxpso import synthetic

_CHILD = """
import json, resource, sys, time
import jaxpso
start = time.perf_counter()
report = jaxpso.evaluate(sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4],
                         sequences=None if sys.argv[5] == "all" else sys.argv[5].split(","),
                         progress=False)
print(json.dumps({"seconds": time.perf_counter() - start, "tracker_seconds": report.tracker_seconds,
                  "report_seconds": report.report_seconds,
                  "ran": report.ran, "resumed": report.resumed,
                  "max_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def _names(layout: str, count: int) -> list[str]:
  if layout == "pot":
    return [f"V{i // 7 + 1:02d}_{i % 7 + 1}" for i in range(count)]
  if layout == "ucsb":
    return [f"tex{i:02d}_{('motion', 'zoom', 'rotation', 'panning')[i % 4]}{i}" for i in range(count)]
  return [f"seq{i:03d}" for i in range(count)]


def make(root: str, layout: str, count: int, frames: int) -> None:
  for seed, name in enumerate(_names(layout, count)):
    sequence = synthetic.make_sequence(seed, num_frames=frames, lazy=True)
    corners = sequence.corners.copy()
    excluded = np.zeros(frames, bool)
    if layout in ("pot", "planartrack", "plain"):
      corners[2] = np.nan
    if layout in ("pot", "planartrack"):
      excluded[4] = True
    datasets.write(root, layout, name, sequence.frames, corners, excluded=excluded,
                   attributes=("occlusion",) if seed % 2 else ())


def child(root: str, layout: str, methods: str, out: str, sequences: str = "all",
          interrupt_after: float | None = None) -> dict | None:
  """Runs one evaluation in a fresh process; None when it was interrupted."""
  process = subprocess.Popen([sys.executable, "-c", _CHILD, root, layout, methods, out, sequences],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
  if interrupt_after is not None:
    try:
      process.wait(interrupt_after)
    except subprocess.TimeoutExpired:
      process.send_signal(signal.SIGINT)
      process.communicate()
      return None
  stdout, stderr = process.communicate()
  if process.returncode:
    raise RuntimeError(stderr)
  return json.loads(stdout.strip().splitlines()[-1])


def _table(out: str) -> list:
  with open(os.path.join(out, "summary.csv")) as handle:
    return [{k: v for k, v in row.items() if k != "ms_per_frame"} for row in csv.DictReader(handle)]


def main() -> None:
  parser = argparse.ArgumentParser()
  parser.add_argument("--sequences", type=int, default=20)
  parser.add_argument("--frames", type=int, default=100)
  parser.add_argument("--methods", default="pso,ic,ecc")
  args = parser.parse_args()
  info = common.machine()
  rows, tables = [], {}
  with tempfile.TemporaryDirectory() as scratch:
    make(os.path.join(scratch, "warm"), "plain", 2, args.frames)  # fills the compilation cache
    child(os.path.join(scratch, "warm"), "plain", args.methods, os.path.join(scratch, "warm-out"))
    for layout in datasets.LAYOUTS:
      data = os.path.join(scratch, layout)
      make(data, layout, args.sequences, args.frames)
      run = child(data, layout, args.methods, os.path.join(scratch, layout + "-out"))
      small = child(data, layout, args.methods, os.path.join(scratch, layout + "-small"),
                    ",".join(_names(layout, args.sequences)[:2]))
      files = sum(len(f) for _, _, f in os.walk(os.path.join(scratch, layout + "-out", "results")))
      rows.append({"layout": layout, **run, "small_max_rss_mib": small["max_rss_mib"],
                   "result_files": files,
                   "loop_overhead": (run["seconds"] - run["tracker_seconds"]
                                     - run["report_seconds"]) / run["seconds"]})
      tables[layout] = _table(os.path.join(scratch, layout + "-out"))
      print(rows[-1], flush=True)
    data = os.path.join(scratch, "pot")
    out = os.path.join(scratch, "pot-resumed")
    interrupt_after = 3.0 + rows[0]["seconds"] / 2  # about half way through the runs
    first = child(data, "pot", args.methods, out, interrupt_after=interrupt_after)
    done_first = sum(len(f) for _, _, f in os.walk(os.path.join(out, "errors")))
    second = child(data, "pot", args.methods, out)
    resume = {"interrupted": first is None, "interrupt_after_s": interrupt_after, "after_interrupt_done": done_first,
              "second_ran": second["ran"], "second_resumed": second["resumed"],
              "same_table": _table(out) == tables["pot"]}
  print(resume)
  pairs = args.sequences * len(args.methods.split(","))
  lines = [
      "# jaxpso evaluate on generated datasets in every layout", "",
      common.machine_line(info), "",
      f"Each layout: {args.sequences} sequences of {args.frames} frames (jaxpso.synthetic, 240×320"
      " PNG frames, a 100×100 region), evaluated by `jaxpso.evaluate` in a fresh process with"
      f" methods {args.methods} ({pairs} runs).  Wall: the process's evaluation call; trackers:"
      " the time inside the methods' runs (frames are decoded from disk there, as they stream);"
      " report: writing the table and the curves at the end; loop overhead: the rest (reading"
      " annotations, scoring, result files) over the wall time.  Every process loads the"
      " compiled programs from the persistent cache, filled by a run before.  Peak RSS: the process's ru_maxrss, against the same evaluation on the"
      " first 2 sequences.  Attributes: those the sequences' names carry (POT-210's suffix),"
      " not challenges the synthetic frames show.", "",
      "| layout | runs | wall s | trackers s | report s | loop overhead | peak RSS MiB"
      " (2 sequences) | result files |",
      "|---|---:|---:|---:|---:|---:|---|---:|"]
  lines += [f"| {r['layout']} | {r['ran']} | {r['seconds']:.1f} | {r['tracker_seconds']:.1f} |"
            f" {r['report_seconds']:.1f} | {100 * r['loop_overhead']:.1f} % | {r['max_rss_mib']:.0f} ({r['small_max_rss_mib']:.0f})"
            f" | {r['result_files']} |" for r in rows]
  lines += ["", f"pot, interrupted with SIGINT {resume['interrupt_after_s']:.0f} s after the"
            " process started"
            f" ({resume['after_interrupt_done']} of {pairs} runs done), run again: it ran"
            f" {resume['second_ran']} and read {resume['second_resumed']} back; same table as the"
            f" uninterrupted run: {resume['same_table']}.", "",
            "## The pot table (precision: alignment error ≤ 5 px; success: discrepancy ≤ 30)", "",
            "| method | attribute | sequences | scored frames | precision | success |",
            "|---|---|---:|---:|---:|---:|"]
  lines += [f"| {r['method']} | {r['attribute']} | {r['sequences']} | {r['frames']} |"
            f" {float(r['precision']):.3f} | {float(r['success']):.3f} |" for r in tables["pot"]]
  common.write("evaluate", {"machine": info, "args": vars(args), "layouts": rows,
                            "resume": resume, "tables": tables}, "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
