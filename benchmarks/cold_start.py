"""The cost of the first answer: compilation, in fresh processes, with an empty and a warm cache.

Every measurement runs in a new Python process (`--child WHAT ...`), timed
from the process's start (imports included) to the first result, with the
compilation cache (`JAXPSO_CACHE_DIR`) in a directory of this run's own:
empty for the cold rows, filled by the cold run for the warm rows.

* align (MI, NCC, SSD): a 100×100 template of the 512×512 camera image,
  4 px off;
* track: the first frame (a 2-frame clip) and a whole 120-frame clip of the
  demo's kind;
* `jaxpso demo` end to end (the command, its video and plots included);
* where the compile time goes: trace, lowering and XLA (CPU seconds, HLO
  size) of the align and track programs;
* the shape mix: 5 image sizes × 4 template sizes (24 to 400 px) × 3 random
  starts, align with each similarity in one process: programs compiled;
* the sweep: 60 `TrackConfig`s (swarm sizes 8–512, variants, topologies,
  similarities, runtime settings) aligned in one process: programs compiled,
  peak memory, wall time.

With `--reference DIR` (a checkout of an earlier jaxpso, e.g. a git
worktree) its cold align, track and demo rows are measured in the same run,
for comparison.  Writes results/cold_start.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

START = time.perf_counter()
HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

IMAGE_SIZES = ((480, 640), (512, 512), (600, 800), (768, 1024), (1080, 1920))
TEMPLATE_SIZES = (24, 64, 160, 400)


# ------------------------------------------------------------------ children
def _camera_case():
  import numpy as np
  import jaxpso
  image = jaxpso.data.load_image("camera")
  template = image[156:256, 206:306]
  start = np.array([[1, 0, 210], [0, 1, 152], [0, 0, 1]], np.float32)
  return image, template, start


def _counts():
  try:
    from jaxpso._src import programs
    return programs.counts()
  except ImportError:  # an earlier jaxpso
    return {}


def child_align(similarity: str) -> dict:
  import jax
  import jaxpso
  image, template, start = _camera_case()
  result = jaxpso.align(image, template, start, config=jaxpso.TrackConfig(similarity=similarity))
  jax.block_until_ready(result)
  return dict(seconds=time.perf_counter() - START, score=float(result.score), **_counts())


def child_track(frames: int) -> dict:
  import numpy as np
  import jaxpso
  rendering = time.perf_counter()
  jumps = tuple(j for j in (40, 80) if j < frames)
  sequence = jaxpso.synthetic.make_sequence(0, num_frames=frames, jumps=jumps, noise=0.01)
  rendering = time.perf_counter() - rendering  # the test clip's rendering, not counted
  result = jaxpso.track(sequence.frames, sequence.roi)
  error = np.sqrt(np.mean(np.sum((result.corners - sequence.corners) ** 2, -1), -1))
  return dict(seconds=time.perf_counter() - START - rendering, rendering=rendering,
              median_error=float(np.median(error)), **_counts())


def child_phases() -> dict:
  """Trace, lowering and XLA seconds (process CPU time) and HLO size of the align and track programs."""
  import jax
  import jaxpso
  from jaxpso._src import align, track

  rows = {}

  def spy(module, name, label):
    program = getattr(module, name)

    def measured(*args, **static):
      jitted = jax.jit(program._fun, static_argnames=tuple(static))
      t0 = time.process_time()
      traced = jitted.trace(*args, **static)
      t1 = time.process_time()
      lowered = traced.lower()
      t2 = time.process_time()
      compiled = lowered.compile()
      t3 = time.process_time()
      text = compiled.as_text()
      rows[label] = dict(trace=t1 - t0, lower=t2 - t1, compile=t3 - t2,
                         hlo_lines=text.count("\n"), fusions=text.count(" fusion("))
      setattr(module, name, program)
      return compiled(*args)
    setattr(module, name, measured)

  spy(align, "_align", "align (MI)")
  image, template, start = _camera_case()
  jax.block_until_ready(jaxpso.align(image, template, start))
  spy(track, "_frame_step", "track frame step (MI)")
  sequence = jaxpso.synthetic.make_sequence(0, num_frames=3)
  jaxpso.track(sequence.frames, sequence.roi)
  return rows


def child_mix(similarity: str) -> dict:
  """Programs compiled for 5 image sizes × 4 template sizes × 3 random starts (align)."""
  import cv2
  import jax
  import numpy as np
  import jaxpso
  rng = np.random.default_rng(0)
  texture = jaxpso.data.load_image("camera")
  config = jaxpso.TrackConfig(similarity=similarity)
  errors = []
  for rows, cols in IMAGE_SIZES:
    image = cv2.resize(texture, (cols, rows), interpolation=cv2.INTER_LINEAR)
    for size in TEMPLATE_SIZES:
      for _ in range(3):
        x = int(rng.integers(0, cols - size))
        y = int(rng.integers(0, rows - size))
        template = image[y:y + size, x:x + size]
        if np.std(template) < 0.05:  # nothing to align on
          continue
        source = np.float32([[0, 0], [size - 1, 0], [size - 1, size - 1], [0, size - 1]])
        truth = source + np.float32([x, y])
        start = cv2.getPerspectiveTransform(
            source, truth + rng.normal(0, 3.0, (4, 2)).astype(np.float32))
        result = jaxpso.align(image, template, start, config=config)
        jax.block_until_ready(result)
        mapped = cv2.perspectiveTransform(source[None], np.float64(result.homography))[0]
        errors.append(float(np.sqrt(np.mean(np.sum((mapped - truth) ** 2, -1)))))
  return dict(alignments=len(errors), within_1px=int(np.sum(np.array(errors) <= 1.0)),
              seconds=time.perf_counter() - START, **_counts())


def sweep_configs() -> list:
  """60 `TrackConfig`s of the kind a swarm-size or variant study runs."""
  import itertools
  import jaxpso
  configs = []
  for size, similarity in itertools.product((8, 32, 128, 512), ("mi", "ncc", "ssd")):
    configs.append(jaxpso.TrackConfig(similarity=similarity, swarm_size=size, accept_quality=None))
  for variant, topology in itertools.product(jaxpso.pso.VARIANTS[:4], jaxpso.pso.TOPOLOGIES[:6]):
    configs.append(jaxpso.TrackConfig(variant=variant, topology=topology, swarm_size=16,
                                      accept_quality=None))
  for i in range(60 - len(configs)):  # runtime settings only: no new program
    configs.append(jaxpso.TrackConfig(swarm_size=32, max_iterations=10 + 5 * i,
                                      search_radius=8.0 + i, patience=None if i % 2 else 5,
                                      accept_quality=None, retry_quality=0.5 + 0.01 * i))
  return configs


def child_sweep() -> dict:
  import jax
  import numpy as np
  import jaxpso
  image, template, start = _camera_case()
  configs = sweep_configs()
  scores = []
  for config in configs:
    result = jaxpso.align(image, template, start, config=config, key=len(scores))
    scores.append(float(jax.block_until_ready(result.score)))
  return dict(configs=len(configs), statics=len({c.statics() for c in configs}),
              finite=bool(np.all(np.isfinite(scores))), seconds=time.perf_counter() - START,
              peak_rss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, **_counts())


CHILDREN = {"align": child_align, "track": child_track, "phases": child_phases,
            "mix": child_mix, "sweep": child_sweep}


# -------------------------------------------------------------------- parent
def run_child(what: str, *args, cache: str | None, path: str = ROOT, timeout: int = 1800) -> dict:
  env = dict(os.environ, PYTHONPATH=path)
  env["JAXPSO_CACHE_DIR"] = cache if cache else "off"
  command = [sys.executable, os.path.abspath(__file__), "--child", what, *map(str, args)]
  started = time.perf_counter()
  done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout,
                        cwd=path)
  wall = time.perf_counter() - started
  lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
  if done.returncode or not lines:
    raise RuntimeError(f"child {what} {args} failed:\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}")
  return dict(json.loads(lines[-1][len("RESULT "):]), wall=wall)


def run_demo(cache: str | None, path: str = ROOT) -> float:
  env = dict(os.environ, PYTHONPATH=path, JAXPSO_CACHE_DIR=cache if cache else "off")
  with tempfile.TemporaryDirectory() as out:
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "jaxpso", "demo", "--out", out], env=env, check=True,
                   capture_output=True, cwd=path, timeout=1800)
    return time.perf_counter() - started


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
  parser.add_argument("--reference", help="a checkout of an earlier jaxpso to measure alongside")
  parser.add_argument("--skip", default="", help="comma-separated parts to skip: mix,sweep")
  args = parser.parse_args()
  if args.child:
    what, *rest = args.child
    result = CHILDREN[what](*[int(a) if a.isdigit() else a for a in rest])
    print("RESULT " + json.dumps(result), flush=True)
    return

  sys.path.insert(0, HERE)
  import common

  skip = set(filter(None, args.skip.split(",")))
  info = common.machine()
  results = dict(machine=info, align={}, track={}, demo={}, reference={})
  with tempfile.TemporaryDirectory() as cache:
    for similarity in ("mi", "ncc", "ssd"):
      cold = run_child("align", similarity, cache=cache)
      warm = run_child("align", similarity, cache=cache)
      results["align"][similarity] = dict(cold=cold, warm=warm)
      print(similarity, "align cold", round(cold["seconds"], 2), "warm", round(warm["seconds"], 2),
            flush=True)
    for frames, name in ((2, "first frame"), (120, "120-frame clip")):
      with tempfile.TemporaryDirectory() as own:
        cold = run_child("track", frames, cache=own)
        warm = run_child("track", frames, cache=own)
      results["track"][name] = dict(cold=cold, warm=warm)
      print("track", name, round(cold["seconds"], 2), round(warm["seconds"], 2), flush=True)
  with tempfile.TemporaryDirectory() as cache:
    results["demo"] = dict(cold=run_demo(cache), warm=run_demo(cache))
  print("demo", results["demo"], flush=True)
  results["phases"] = run_child("phases", cache=None)
  if "mix" not in skip:
    results["mix"] = {}
    with tempfile.TemporaryDirectory() as cache:
      for similarity in ("mi", "ncc", "ssd"):
        results["mix"][similarity] = run_child("mix", similarity, cache=cache)
        print("mix", similarity, results["mix"][similarity], flush=True)
  if "sweep" not in skip:
    with tempfile.TemporaryDirectory() as cache:
      results["sweep"] = run_child("sweep", cache=cache, timeout=3600)
    print("sweep", results["sweep"], flush=True)
  if args.reference:
    reference = results["reference"]
    for similarity in ("mi", "ncc", "ssd"):
      reference[f"align {similarity}"] = run_child("align", similarity, cache=None,
                                                   path=args.reference)
    reference["track first frame"] = run_child("track", 2, cache=None, path=args.reference)
    reference["demo"] = run_demo(None, path=args.reference)
    print("reference", reference, flush=True)
  common.write("cold_start", results, markdown(results))


def markdown(r: dict) -> str:
  import common
  ref = r.get("reference", {})

  def before(key):
    value = ref.get(key)
    if value is None:
      return "–"
    return f"{value:.1f} s" if isinstance(value, float) else f"{value['seconds']:.1f} s"

  lines = ["# Cold start: the first answer, in fresh processes", "",
           common.machine_line(r["machine"]), "",
           "Seconds from the process's start (imports included) to the first result; the"
           " compilation cache empty (cold) or filled by the cold run (warm).  `before`: the"
           " reference checkout (no persistent cache) in the same run.", "",
           "| first call | cold | warm | before (cold) |", "|---|---|---|---|"]
  for similarity, row in r["align"].items():
    lines.append(f"| align {similarity.upper()}, 100×100 template, 512×512 image |"
                 f" {row['cold']['seconds']:.2f} s | {row['warm']['seconds']:.2f} s |"
                 f" {before('align ' + similarity)} |")
  for name, row in r["track"].items():
    lines.append(f"| track, {name} (320×240, 100×100 region) | {row['cold']['seconds']:.2f} s |"
                 f" {row['warm']['seconds']:.2f} s |"
                 f" {before('track first frame') if name == 'first frame' else '–'} |")
  lines.append(f"| `jaxpso demo` end to end (process wall) | {r['demo']['cold']:.1f} s |"
               f" {r['demo']['warm']:.1f} s | {before('demo')} |")
  lines += ["", "## Where the compile time goes (process CPU seconds; XLA uses both cores)", "",
            "| program | trace | lower | XLA | HLO lines | fusions |", "|---|---|---|---|---|---|"]
  for name, row in r["phases"].items():
    if isinstance(row, dict):
      lines.append(f"| {name} | {row['trace']:.2f} | {row['lower']:.2f} | {row['compile']:.2f} |"
                   f" {row['hlo_lines']} | {row['fusions']} |")
  if "mix" in r:
    lines += ["", "## Programs for a mix of shapes (one process per similarity)", "",
              f"Images {', '.join(f'{w}×{h}' for h, w in IMAGE_SIZES)}; templates"
              f" {', '.join(f'{s}×{s}' for s in TEMPLATE_SIZES)}; 3 random starts each"
              " (corners 3 px off).", "",
              "| similarity | alignments | within 1 px | programs compiled | loaded from cache | wall |",
              "|---|---|---|---|---|---|"]
    for similarity, row in r["mix"].items():
      lines.append(f"| {similarity.upper()} | {row['alignments']} | {row['within_1px']} |"
                   f" {row['compiled']} | {row['loaded']} | {row['seconds']:.0f} s |")
  if "sweep" in r:
    s = r["sweep"]
    lines += ["", "## A 60-configuration sweep in one process", "",
              f"{s['configs']} `TrackConfig`s (swarm sizes 8–512 × similarities, 4 variants × 6"
              f" topologies, runtime settings), {s['statics']} distinct programs' worth: "
              f"{s['compiled']} compiled, {s['loaded']} loaded, {s['reused']} calls reused one;"
              f" peak RSS {s['peak_rss_mib']:.0f} MiB; {s['seconds']:.0f} s; every score finite:"
              f" {s['finite']}."]
  return "\n".join(lines) + "\n"


if __name__ == "__main__":
  main()
