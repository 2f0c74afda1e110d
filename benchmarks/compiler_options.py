"""XLA:CPU option sets compared on the same workloads, in one process, paired round by round.

`python benchmarks/compiler_options.py --variants '{"xla_cpu_use_fusion_emitters": true};{}'
[--rounds 12] [--parts track,batch,video,align] [--name compiler_options]` compiles every
workload's programs once per variant (each variant's options laid over
`programs.CPU_COMPILER_OPTIONS`, the persistent cache off), keeps each
variant's program table, and then times every workload under each variant in
turn, the variants' order rotated from round to round.  A machine whose speed
drifts over minutes (a shared host) moves both sides of a round alike, where
runs in separate processes minutes apart compared its drift; the ratio is
taken per round and the table gives its median and range over the rounds,
each variant against the first.

Workloads (`--parts`):
* track: `TrackConfig(similarity=…)` defaults, MI and NCC, one 100×100 region
  over an 80-frame synthetic sequence of 240×320 and of 480×640 frames (a jump
  at frame 40), as runtime.py's track part;
* batch: 64 regions of 48×48 over 20 frames of 240×320 (runtime.py's batch);
* video: MI and NCC on 60 frames of video.py's camera and brick clips (240
  and 280 px regions, 360×480 frames);
* align: MI and NCC on 30 trials of each of runtime.py's cases noise,
  shading, clean and real_pairs, the trials of a case one after another.

Compilation time per variant (every workload's programs, process seconds) is
reported too.  Writes results/NAME.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ["JAXPSO_CACHE_DIR"] = "off"  # each variant's programs compiled, not loaded

import numpy as np

import batch
import common
import jaxpso
import runtime
import video
from jaxpso._src import programs


def workloads(parts: list) -> dict:
  """{name: a call running the workload} for `parts` (see the module's docstring)."""
  calls = {}
  if "track" in parts:
    for shape in ((240, 320), (480, 640)):
      sequence = jaxpso.synthetic.make_sequence(0, num_frames=80, jumps=(40,), noise=0.01,
                                                frame_shape=shape)
      for similarity in ("mi", "ncc"):
        config = jaxpso.TrackConfig(similarity=similarity)
        calls[f"track {similarity.upper()}, {shape[0]}×{shape[1]}"] = (
            lambda s=sequence, c=config: jaxpso.track(s.frames, s.roi, config=c))
  if "batch" in parts:
    sequence = jaxpso.synthetic.make_sequence(0, num_frames=20, frame_shape=(240, 320),
                                              roi_size=(100, 100))
    boxes = batch.regions(sequence, 64)
    calls["track 64 regions of 48×48"] = lambda: jaxpso.track(sequence.frames, boxes)
  if "video" in parts:
    for seed, name in enumerate(("camera", "brick")):
      video_, _, box = video.make_clip(name, 60, seed)
      for similarity in ("mi", "ncc"):
        config = jaxpso.TrackConfig(similarity=similarity)
        calls[f"track {similarity.upper()}, video.py's {name}"] = (
            lambda v=video_, b=box, c=config: jaxpso.track(v, b, config=c))
  if "align" in parts:
    photos = [common.photo(name) for name in common.PHOTOS]
    for case in ("noise", "shading", "clean", "real_pairs"):
      trials = [trial[:3] for trial in runtime.case_trials(case, photos, 30)]
      for similarity in ("mi", "ncc"):
        config = jaxpso.TrackConfig(similarity=similarity)
        calls[f"align {similarity.upper()}, 30 {case}"] = (
            lambda t=trials, c=config: [np.asarray(jaxpso.align(*a, config=c).homography)
                                        for a in t])
  return calls


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--variants", required=True,
                      help="';'-separated JSON objects of options, the first the reference")
  parser.add_argument("--rounds", type=int, default=12)
  parser.add_argument("--parts", default="track,batch,video,align")
  parser.add_argument("--name", default="compiler_options")
  args = parser.parse_args()
  variants = [json.loads(text) for text in args.variants.split(";")]
  calls = workloads(args.parts.split(","))
  base = dict(programs.CPU_COMPILER_OPTIONS)
  programs.set_max_programs(None)  # every variant's table kept whole
  tables, compile_seconds = [], []
  for options in variants:
    programs.CPU_COMPILER_OPTIONS.clear()
    programs.CPU_COMPILER_OPTIONS.update({**base, **options})
    programs.clear()
    begin = time.process_time()
    for call in calls.values():
      call()
    compile_seconds.append(time.process_time() - begin)
    tables.append(dict(programs._table))
  seconds = {name: [[] for _ in variants] for name in calls}
  for round_ in range(args.rounds):
    for name, call in calls.items():
      for k in range(len(variants)):
        index = (k + round_) % len(variants)
        programs._table.clear()
        programs._table.update(tables[index])
        begin = time.perf_counter()
        call()
        seconds[name][index].append(time.perf_counter() - begin)
  programs.CPU_COMPILER_OPTIONS.clear()
  programs.CPU_COMPILER_OPTIONS.update(base)

  info = common.machine()
  labels = [json.dumps(options) for options in variants]
  lines = ["# XLA:CPU option sets on the same workloads, paired round by round", "",
           common.machine_line(info), "",
           f"Variants over `programs.CPU_COMPILER_OPTIONS` ({json.dumps(base)}): "
           + "; ".join(f"{k}: `{label}`" for k, label in enumerate(labels))
           + f".  {args.rounds} rounds, the variants' order rotated each round; per workload the"
           " first variant's median seconds and each other's time over the first's, median"
           " (range) over the rounds.  Script: benchmarks/compiler_options.py.", "",
           "| workload | variant 0, median ms | " + " | ".join(
               f"variant {k} / variant 0" for k in range(1, len(variants))) + " |",
           "|---" * (len(variants) + 1) + "|"]
  for name, per in seconds.items():
    per = np.array(per)
    ratios = per[1:] / per[0]
    lines.append(f"| {name} | {np.median(per[0]) * 1e3:.1f} | " + " | ".join(
        f"{np.median(r):.3f} ({r.min():.2f}–{r.max():.2f})" for r in ratios) + " |")
  lines += ["", "Compiling every workload's programs, process CPU seconds: " + ", ".join(
      f"variant {k} {s:.1f}" for k, s in enumerate(compile_seconds)) + "."]
  common.write(args.name, dict(machine=info, args=vars(args), variants=variants,
                               compile_seconds=compile_seconds, seconds=seconds),
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
