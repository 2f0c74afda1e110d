"""jaxpso on an accelerator: compilation, align, track, batches and the bare swarm, in one run.

Written for a lent GPU and a short lease: every part is timed, its rows are
written to results/NAME.{json,md} as soon as it ends, and a part that fails
leaves its traceback in the table and the run goes on.  OpenCV's ECC runs on
the same machine's CPU, on the same trials, in the same process.

* cold: the first `align` (MI) and the first 120-frame `track` in fresh
  processes, with an empty and then a warm compilation cache
  (`cold_start.run_child`): seconds from the process's start to the result.
* align: `runtime.align_trials` (100×100 templates of the camera image, 4
  corners moved by N(0, σ²), σ 2 and 8 px), one template per call: median
  ms, 90th percentile over the median, share > 1 px off; `runtime.ecc` on
  the same.
* align batches: N such templates (σ 8) in one call: alignments per second.
* video: `video.py`'s hand-held clips (200–280 px regions), every frame and
  every 8th: `track` MI and NCC against chained ECC, ms per frame and P@5.
* track batches: `batch.py`'s R regions of 48×48 over 20 frames in one
  call: templates × frames per second, the status's precision.
* swarm: `pso.run` on 6-D Rastrigin, evaluations per second against the
  swarm size, on the accelerator and on this machine's CPU.

Usage: python benchmarks/gpu.py [--name gpu] [--parts cold,align,video,...] [--quick]
(video.py's photographs from `$JAXPSO_IMAGES` where ../shared is not beside the checkout)
"""

from __future__ import annotations

import argparse
import tempfile
import time
import traceback

import jax
import numpy as np

import batch
import cold_start
import common
import jaxpso
import pso_throughput
import runtime
import video
from jaxpso import pso


def part_cold(quick: bool) -> list[dict]:
  rows = []
  with tempfile.TemporaryDirectory() as cache:
    for state in ("empty", "warm"):
      for what, args in (("align", ("mi",)), ("track", (120,))):
        child = cold_start.run_child(what, *args, cache=cache)
        rows.append({"part": "cold", "case": f"first {what} {' '.join(map(str, args))},"
                     f" {state} cache", "seconds": child["seconds"]})
  return rows


def part_align(quick: bool) -> list[dict]:
  image = np.asarray(jaxpso.data.load_image("camera"), np.float32)
  config = jaxpso.TrackConfig(similarity="mi")
  rows = []
  for sigma in (2.0, 8.0):
    ours, ecc, off, ecc_off = [], [], [], []
    for template, start, origin in runtime.align_trials(image, sigma, 20 if quick else 200):
      begin = time.perf_counter()
      found = np.asarray(jaxpso.align(image, template, start, config=config).homography)
      ours.append(time.perf_counter() - begin)
      begin = time.perf_counter()
      warp = runtime.ecc(image, template, start)
      ecc.append(time.perf_counter() - begin)
      off.append(common.corner_error(found, origin) > 1.0)
      ecc_off.append(common.corner_error(warp, origin) > 1.0)
    first = ours.pop(0)  # the compiling call (σ 2) or a warm one (σ 8)
    rows.append({"part": "align", "case": f"MI σ {sigma:g} px, one per call",
                 "ms_median": 1e3 * np.median(ours), "ecc_ms_median": 1e3 * np.median(ecc),
                 "x_ecc": np.median(ours) / np.median(ecc),
                 "p90_over_median": np.percentile(ours, 90) / np.median(ours),
                 "off_1px": float(np.mean(off)), "ecc_off_1px": float(np.mean(ecc_off)),
                 "first_call_s": first})
  return rows


def part_align_batches(quick: bool) -> list[dict]:
  image = np.asarray(jaxpso.data.load_image("camera"), np.float32)
  config = jaxpso.TrackConfig(similarity="mi")
  rows = []
  for count in (16, 64) if quick else (16, 256, 1024):
    trials = list(runtime.align_trials(image, 8.0, count, seed=1))
    templates = np.stack([t for t, _, _ in trials])
    starts = np.stack([s for _, s, _ in trials])
    images = np.broadcast_to(image, (count,) + image.shape)
    begin = time.perf_counter()
    result = jax.block_until_ready(jaxpso.align(images, templates, starts, config=config))
    compile_s = time.perf_counter() - begin
    seconds = np.inf
    for _ in range(2):
      begin = time.perf_counter()
      result = jax.block_until_ready(jaxpso.align(images, templates, starts, config=config))
      seconds = min(seconds, time.perf_counter() - begin)
    off = [common.corner_error(h, origin) > 1.0
           for h, (_, _, origin) in zip(np.asarray(result.homography), trials)]
    rows.append({"part": "align batches", "case": f"{count} templates, MI σ 8 px",
                 "aligns_per_s": count / seconds, "off_1px": float(np.mean(off)),
                 "first_call_s": compile_s})
  return rows


def part_video(quick: bool) -> list[dict]:
  rows = []
  for seed, name in enumerate(("camera", "brick")):
    clip, truth, box = video.make_clip(name, 40 if quick else 120, seed)
    for stride in (1, 8):
      kept, kept_truth = clip[::stride], truth[::stride]
      begin = time.perf_counter()
      ecc = video.track_ecc(kept, box)
      ecc_ms = 1e3 * (time.perf_counter() - begin) / (len(kept) - 1)
      for similarity in ("mi", "ncc"):
        config = jaxpso.TrackConfig(similarity=similarity)
        jaxpso.track(kept, box, config=config)
        begin = time.perf_counter()
        result = jaxpso.track(kept, box, config=config)
        ms = 1e3 * (time.perf_counter() - begin) / (len(kept) - 1)
        errors = jaxpso.io.corner_errors(result.corners, kept_truth)
        rows.append({"part": "video", "case": f"{name} {box[2]} px, every {stride}"
                     f" frame{'s' if stride > 1 else ''}, {similarity.upper()}",
                     "ms_per_frame": ms, "ecc_ms_per_frame": ecc_ms, "x_ecc": ms / ecc_ms,
                     "p_at_5": float(np.mean(errors <= video.GOOD_PX)),
                     "ecc_p_at_5": float(np.mean(jaxpso.io.corner_errors(ecc, kept_truth)
                                                 <= video.GOOD_PX)),
                     **common.status_precision(result.status, errors, video.GOOD_PX)})
  return rows


def part_track_batches(quick: bool) -> list[dict]:
  frames = 20
  sequence = jaxpso.synthetic.make_sequence(0, num_frames=frames, frame_shape=(240, 320),
                                            roi_size=(100, 100))
  rows = []
  for count in (1, 16) if quick else (1, 16, 256, 1024):
    boxes = batch.regions(sequence, count)
    compile_s, seconds, result = batch.timed_batch(sequence, boxes, jaxpso.TrackConfig(), 2)
    errors = batch.errors(sequence, boxes, result.corners)
    rows.append({"part": "track batches", "case": f"{count} regions of 48×48, 20 frames",
                 "templates_frames_per_s": count * (frames - 1) / seconds,
                 "within_2px": float(np.mean(errors <= 2.0)), "first_call_s": compile_s,
                 **common.status_precision(result.status, errors)})
  return rows


def part_swarm(quick: bool) -> list[dict]:
  sizes = {256: 2000, 4096: 200} if quick else {256: 2000, 4096: 200, 65536: 100, 1048576: 20}
  rows = []
  for platform in ("accelerator", "cpu"):
    device = jax.devices()[0] if platform == "accelerator" else jax.devices("cpu")[0]
    for n, iterations in sizes.items():
      if platform == "cpu" and n > 65536:
        continue
      with jax.default_device(device):
        runner = pso_throughput.jaxpso_runner(n, iterations, pso.PSOConfig().rng)
        seconds = common.median_seconds(runner, 0, repeats=3, warmup=1)
      rows.append({"part": "swarm", "case": f"{platform} ({device.platform}), swarm {n},"
                   f" {iterations} iterations", "evals_per_s": n * (iterations + 1) / seconds})
  return rows


PARTS = {"cold": part_cold, "align": part_align, "video": part_video,
         "track_batches": part_track_batches, "align_batches": part_align_batches,
         "swarm": part_swarm}
COLUMNS = ("ms_median", "ecc_ms_median", "x_ecc", "p90_over_median", "off_1px", "ecc_off_1px",
           "ms_per_frame", "ecc_ms_per_frame", "p_at_5", "ecc_p_at_5", "aligns_per_s",
           "templates_frames_per_s", "within_2px", "evals_per_s", "seconds", "first_call_s")


def _cell(row: dict) -> str:
  cells = [f"{k} {row[k]:.3g}" for k in COLUMNS if k in row]
  if "tracked" in row:
    cells.append(f"tracked but > 5 px off {row['tracked_but_off']}/{row['tracked']},"
                 f" good but LOST {row['good_but_lost']}/{row['good']}")
  return "; ".join(cells)


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--name", default="gpu")
  parser.add_argument("--parts", default=",".join(PARTS))
  parser.add_argument("--quick", action="store_true", help="fewer trials, sizes and frames")
  args = parser.parse_args()
  info = common.machine()
  rows, failures = [], []
  for part in args.parts.split(","):
    begin = time.perf_counter()
    try:
      rows += PARTS[part](args.quick)
    except Exception:  # noqa: BLE001 (a short lease: report the failure, measure the rest)
      failures.append(f"{part}: {traceback.format_exc()}")
      print(failures[-1], flush=True)
    print(f"{part}: {time.perf_counter() - begin:.0f} s", flush=True)
    lines = ["# jaxpso on an accelerator", "", common.machine_line(info), "",
             f"Devices: {jax.devices()}.  OpenCV ECC on this machine's CPU ({info['cores']} cores),"
             " same trials, same process.  Script: benchmarks/gpu.py.", "",
             "| part | case | figures |", "|---|---|---|"]
    lines += [f"| {r['part']} | {r['case']} | {_cell(r)} |" for r in rows]
    lines += [f"\nFailed: {f}" for f in failures]
    common.write(args.name, {"machine": info, "devices": str(jax.devices()), "rows": rows,
                             "failures": failures}, "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
