"""Wild cases: photographs under occlusion, blur, leaving the frame or a change of light.

Each case moves a 50–130 px crop of a CC0 photograph (translation N(0, 2²)
px a frame per axis, rotation N(0, 0.01²) rad and scale N(0, 0.005²) a
frame) over a resized second photograph for 10 frames of 320×240, with read
noise 0.01 and one event: a flat occluder over 30–70 % of the region's box
in frames 3–6, horizontal blur of 5–15 px in frames 3–5, a drift of 6 px a
frame to the right (leaving), a gamma and gain change growing each frame
(light), or none.  Exact truth.  Tracked with `TrackConfig` defaults, MI,
NCC and SSD in turn.  Per event and similarity: frames, frames reported
tracked (TRACKED or RECOVERED), those more than 5 px off (corner RMS), and
DOUBTFUL frames.  The cases are drawn from `--seed`; the defaults were
tuned on seed 0, seed 1 is held out.

Usage: python benchmarks/wild.py [--cases 240] [--seed 1]
"""

from __future__ import annotations

import argparse
import collections
import time

import numpy as np

import common
import jaxpso

EVENTS = ("occlude", "blur", "leave", "light", "none")
SIMILARITIES = ("mi", "ncc", "ssd")
SHAPE, FRAMES, TOLERANCE_PX = (240, 320), 10, 5.0


def case(index: int, seed: int, photos: dict):
  """(frames (10, 240, 320), truth corners (10, 4, 2), event, similarity) of case `index`."""
  import cv2

  rng = np.random.default_rng([seed, index])
  names = common.PHOTOS
  texture, other = photos[names[index % 4]], photos[names[(index + 1) % 4]]
  rows, cols = SHAPE
  size = int(rng.integers(50, 130))
  centre = np.array([rng.uniform(100, 220), rng.uniform(80, 160)])
  step, turn, zoom = rng.normal(0, 2.0, 2), rng.normal(0, 0.01), rng.normal(0, 0.005)
  similarity = SIMILARITIES[index % 3]
  event = EVENTS[int(rng.integers(0, len(EVENTS)))]
  y, x = rng.integers(0, 512 - 2 * size, 2)
  patch = texture[y:y + size, x:x + size]
  source = np.float32([[0, 0], [size - 1, 0], [size - 1, size - 1], [0, size - 1]])
  background = cv2.resize(other, (cols, rows))
  frames, truth = [], []
  for t in range(FRAMES):
    c, s = np.cos(turn * t) * (1 + zoom * t), np.sin(turn * t) * (1 + zoom * t)
    at = centre + step * t + (np.array([6.0 * t, 0.0]) if event == "leave" else 0.0)
    corners = (source - size / 2) @ np.array([[c, -s], [s, c]]).T + at
    h = cv2.getPerspectiveTransform(source, corners.astype(np.float32))
    mask = cv2.warpPerspective(np.ones_like(patch), h, (cols, rows))
    frame = background * (1 - mask) + cv2.warpPerspective(patch, h, (cols, rows)) * mask
    if event == "occlude" and 3 <= t <= 6:
      (x0, y0), (x1, y1) = corners.min(0).astype(int), corners.max(0).astype(int)
      frame[max(y0, 0):y1, max(x0, 0):x0 + int(rng.uniform(0.3, 0.7) * (x1 - x0))] = rng.random()
    if event == "blur" and 3 <= t <= 5:
      frame = cv2.blur(frame, (int(rng.integers(5, 15)), 1))
    if event == "light":
      frame = np.clip(frame ** (1 + 0.15 * t) * (1 - 0.03 * t), 0, 1)
    frames.append(np.clip(frame + rng.normal(0, 0.01, frame.shape), 0, 1).astype(np.float32))
    truth.append(corners)
  return np.stack(frames), np.array(truth), event, similarity


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--cases", type=int, default=240)
  parser.add_argument("--seed", type=int, default=1)
  args = parser.parse_args()
  photos = {name: common.photo(name) for name in common.PHOTOS}
  counts = collections.defaultdict(lambda: np.zeros(4, int))
  start = time.perf_counter()
  for index in range(args.cases):
    frames, truth, event, similarity = case(index, args.seed, photos)
    result = jaxpso.track(frames, truth[0], config=jaxpso.TrackConfig(similarity=similarity),
                          key=index)
    errors = np.sqrt(np.mean(np.sum((result.corners - truth) ** 2, -1), -1))[1:]
    status = result.status[1:]
    reported = common.tracked(status)
    counts[event, similarity] += [errors.size, reported.sum(),
                                  (reported & (errors > TOLERANCE_PX)).sum(),
                                  (status == jaxpso.TrackStatus.DOUBTFUL).sum()]
  seconds = time.perf_counter() - start
  rows = [dict(event=e, similarity=s, frames=int(v[0]), reported=int(v[1]), off=int(v[2]),
               doubtful=int(v[3])) for (e, s), v in sorted(counts.items())]
  total = np.sum([v for v in counts.values()], axis=0)

  info = common.machine()
  lines = [
      "# Wild cases: photographs under occlusion, blur, leaving the frame, a change of light", "",
      common.machine_line(info), "",
      f"{args.cases} cases (seed {args.seed}), {FRAMES} frames of 320×240 each; see the script's"
      " docstring.  reported = TRACKED or RECOVERED; off = reported and more than 5 px off (corner"
      f" RMS).  {seconds:.0f} s in all.  Script: benchmarks/wild.py.", "",
      "| event | similarity | frames | reported | off | DOUBTFUL |",
      "|---|---|---:|---:|---:|---:|",
  ]
  lines += [f"| {r['event']} | {r['similarity']} | {r['frames']} | {r['reported']} | {r['off']} |"
            f" {r['doubtful']} |" for r in rows]
  lines += ["", f"All: {total[0]} frames, {total[1]} reported, {total[2]} of them more than 5 px"
            f" off, {total[3]} DOUBTFUL."]
  common.write("wild", dict(machine=info, args=vars(args), rows=rows, seconds=seconds),
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
