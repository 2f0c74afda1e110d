"""Per-frame time of `jaxpso.track`: median, tail and slowest frame of each sequence.

The sequences of tracking.py (seed 0: 200 frames, jumps at 1/3 and 2/3, gain drift, noise;
its five cases) and of video.py (its four hand-held clips at strides 1, 4 and 8, MI and NCC).
A frame's time is the interval between `track` taking it and taking the next one from a
generator (everything `track` does for it: the compiled step, the host's checks, the
visible-part registration, re-detection), after a warm-up call on the same frames.

  python frame_times.py [--frames 200] [--video-frames 120]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import common
import jaxpso
import tracking
import video


def frame_seconds(frames, roi, config, **extra) -> tuple[np.ndarray, float]:
  """(T − 2,) seconds between `track` taking frame t and frame t + 1 (t = 1 ... T − 2), and the
  seconds from its taking frame T − 1 to its return (that frame and gathering the result)."""
  jaxpso.track(frames, roi, config=config, **extra)  # compiles (or loads) and warms up
  pulled = []

  def timed():
    for frame in frames:
      pulled.append(time.perf_counter())
      yield frame

  jaxpso.track(timed(), roi, config=config, **extra)
  pulled.append(time.perf_counter())
  intervals = np.diff(pulled)
  return intervals[1:-1], float(intervals[-1])


def _row(source: str, case: str, timed: tuple[np.ndarray, float]) -> dict:
  seconds, last = timed
  median = float(np.median(seconds))
  row = {"source": source, "case": case, "frames": len(seconds) + 2, "last_ms": 1e3 * last,
         "median_ms": 1e3 * median, "p99_ms": 1e3 * float(np.percentile(seconds, 99)),
         "max_ms": 1e3 * float(seconds.max()), "max_over_median": float(seconds.max()) / median,
         "slowest_frame": int(np.argmax(seconds)) + 1,
         "over_10x": int(np.sum(seconds > 10 * median))}
  print(row, flush=True)
  return row


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--frames", type=int, default=200)
  parser.add_argument("--video-frames", type=int, default=120, dest="video_frames")
  args = parser.parse_args()
  rows = []
  n = args.frames
  seq = tracking.sequence(0, n)
  for name, (fields, tilt) in tracking.CASES.items():
    rows.append(_row("tracking.py", name, frame_seconds(
        np.asarray(seq.frames), seq.roi, jaxpso.TrackConfig(**fields),
        **tracking.plane_arguments(seq, tilt))))
  for seed, clip in enumerate(video.SIDES):
    frames, _, box = video.make_clip(clip, args.video_frames, seed)
    for stride in video.STRIDES:
      for tracker, fields in video.TRACKERS.items():
        rows.append(_row("video.py", f"{clip}, every {stride}, {tracker}",
                         frame_seconds(frames[::stride], box, jaxpso.TrackConfig(**fields))))
  info = common.machine()
  worst = max(rows, key=lambda r: r["max_over_median"])
  lines = [
      "# Per-frame time of jaxpso.track: median, tail, slowest frame", "",
      common.machine_line(info), "",
      "A frame's time: from `track` taking it from a generator to taking the next (the compiled"
      " step, the host's checks, visible-part registration, re-detection), after a warm-up call"
      f" on the same frames.  tracking.py: seed 0, {n} frames, its cases.  video.py: its clips"
      f" ({args.video_frames} frames) at strides {', '.join(map(str, video.STRIDES))}.", "",
      f"Largest slowest/median: {worst['max_over_median']:.1f}× ({worst['source']},"
      f" {worst['case']}, frame {worst['slowest_frame']}); frames over 10× their sequence's"
      f" median: {sum(r['over_10x'] for r in rows)} of {sum(r['frames'] - 2 for r in rows)}."
      "  Frames 1 to T − 2; the last frame's interval also holds gathering the result"
      " (last + finish).", "",
      "| source | case | frames | median ms | p99 ms | max ms | max / median | slowest frame |"
      " frames > 10× median | last + finish ms |",
      "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
  lines += [f"| {r['source']} | {r['case']} | {r['frames']} | {r['median_ms']:.2f} |"
            f" {r['p99_ms']:.1f} | {r['max_ms']:.1f} | {r['max_over_median']:.1f} |"
            f" {r['slowest_frame']} | {r['over_10x']} | {r['last_ms']:.1f} |" for r in rows]
  common.write("frame_times", {"machine": info, "args": vars(args), "rows": rows},
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
