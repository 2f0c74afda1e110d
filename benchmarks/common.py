"""Shared helpers for the benchmark scripts: timing, machine description, output."""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import platform
import subprocess
import sys
import time

import jax
import numpy as np

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
"""The checkout these benchmarks belong to."""
IMAGES = os.environ.get("JAXPSO_IMAGES", os.path.join(
    os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data", "images"))
"""The CC0 photographs (`../shared/data/images`, or `$JAXPSO_IMAGES`)."""
PHOTOS = ("camera", "brick", "gravel", "grass")


def photo(name: str) -> np.ndarray:
  """(H, W) float32 grey in [0, 1]: the photograph `name` of `IMAGES`."""
  import cv2

  image = cv2.imread(os.path.join(IMAGES, name + ".png"), cv2.IMREAD_GRAYSCALE)
  if image is None:
    raise FileNotFoundError(f"{name}.png not in {IMAGES} (set JAXPSO_IMAGES)")
  return image.astype(np.float32) / 255.0


def machine() -> dict:
  """The machine, software versions, date and command line of this run."""
  cpu = platform.processor() or "unknown"
  try:
    with open("/proc/cpuinfo") as f:
      cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
  except (OSError, StopIteration):
    pass
  return {
      "cpu": cpu,
      "cores": os.cpu_count(),
      "device": str(jax.devices()[0]),
      "jax": jax.__version__,
      "python": platform.python_version(),
      "date": datetime.date.today().isoformat(),
      "command": "python " + " ".join(sys.argv),
  }


def machine_line(info: dict) -> str:
  """The results tables' line naming the machine, software, date and command of `info`."""
  return (f"Machine: {info['cpu']}, {info['cores']} cores, {info['device']}; jax {info['jax']};"
          f" date {info['date']}.  Command: `{info['command']}`.")


def median_seconds(fn, *args, repeats: int = 7, warmup: int = 2) -> float:
  """Median wall time of `fn(*args)` after warm-up, blocking on the result."""
  for _ in range(warmup):
    jax.block_until_ready(fn(*args))
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - start)
  return float(np.median(times))


@contextlib.contextmanager
def timed_frame_steps(after_step=None):
  """Times every call of `jaxpso.track`'s compiled frame step to completion.

  Yields the list that each call's seconds are appended to (blocking on its
  outputs, so asynchronous dispatch cannot run ahead); `after_step(count)`,
  if given, runs after each call.  Frame 1's call includes the compilation.
  """
  from jaxpso._src import track  # the private step: track() looks it up per call

  step = track._frame_step
  seconds = []

  def timed(*args, **kwargs):
    start = time.perf_counter()
    out = jax.block_until_ready(step(*args, **kwargs))
    seconds.append(time.perf_counter() - start)
    if after_step is not None:
      after_step(len(seconds))
    return out

  track._frame_step = timed
  try:
    yield seconds
  finally:
    track._frame_step = step


def frame_seconds(run) -> np.ndarray:
  """(steps − 1,) seconds from the end of each `jaxpso.track` frame step to the next one's.

  `run()` calls `jaxpso.track` once; each gap holds the host's work after a
  step (its re-detection too) and the next frame's step, which is blocked
  on (`timed_frame_steps`), so a frame's cost cannot hide behind the next.
  """
  ends = []
  with timed_frame_steps(lambda _: ends.append(time.perf_counter())):
    run()
  return np.diff(ends)


def write(name: str, payload: dict, markdown: str) -> None:
  """Writes results/NAME.json and results/NAME.md."""
  os.makedirs(RESULTS, exist_ok=True)
  with open(os.path.join(RESULTS, name + ".json"), "w") as f:
    json.dump(payload, f, indent=1)
  with open(os.path.join(RESULTS, name + ".md"), "w") as f:
    f.write(markdown)
  print(markdown)


def in_checkout(script: str, checkout: str, arguments: list):
  """The JSON last line `script` (a benchmark's path) prints when run with `arguments` in a fresh
  process importing jaxpso from `checkout`: a reference measured beside the current code."""
  out = subprocess.run([sys.executable, os.path.abspath(script), *arguments],
                       env=dict(os.environ, PYTHONPATH=checkout), cwd=checkout, check=True,
                       capture_output=True, text=True).stdout
  return json.loads(out.strip().splitlines()[-1])


def corner_error(h, origin, size: int = 100) -> float:
  """RMS distance (px) of a size×size template's corners mapped by h (3, 3) from them moved to origin (x, y)."""
  import cv2
  source = np.float32([[0, 0], [size - 1, 0], [size - 1, size - 1], [0, size - 1]])
  mapped = cv2.perspectiveTransform(source[None], np.asarray(h, np.float64))[0]
  return float(np.sqrt(np.mean(np.sum((mapped - (source + origin)) ** 2, axis=1))))


def status_precision(status: np.ndarray, errors: np.ndarray, good_px: float = 5.0) -> dict:
  """Counts for the status's precision: frames reported tracked (TRACKED or RECOVERED) but more
  than `good_px` off, good ones LOST, and DOUBTFUL ones (all, and more than `good_px` off).

  status, errors: (…) per frame (`jaxpso.TrackStatus`, corner RMS px).
  """
  import jaxpso

  reported, good = tracked(status), errors <= good_px
  doubtful = status == jaxpso.TrackStatus.DOUBTFUL
  return {"tracked_but_off": int(np.sum(reported & ~good)), "tracked": int(np.sum(reported)),
          "good_but_lost": int(np.sum((status == jaxpso.TrackStatus.LOST) & good)),
          "good": int(np.sum(good)), "doubtful": int(np.sum(doubtful)),
          "doubtful_but_off": int(np.sum(doubtful & ~good))}


def tracked(status: np.ndarray) -> np.ndarray:
  """(…) bool: frames `jaxpso.track` reports as tracked, TRACKED or RECOVERED (not LOST, not
  DOUBTFUL); status (…) `jaxpso.TrackStatus`."""
  import jaxpso

  return (status == jaxpso.TrackStatus.TRACKED) | (status == jaxpso.TrackStatus.RECOVERED)
