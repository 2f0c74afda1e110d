"""Occlusion and recovery: a region hidden for 10 frames is reported lost, then re-acquired.

30-frame synthetic sequences of 160×120 with a 48×48 region (the setting of
tests/test_recovery.py), hidden behind an occluder of noise in frames 10–19
(`jaxpso.synthetic.make_sequence(occlusion=(10, 20))`), smooth 6-DOF motion
and a camera jump at frame 15 of 0, 1 or 2 times the motion's amplitudes, so
that the region moves further while it is hidden.  Tracked with
`TrackConfig()` for motion "homography" and for motion "plane" with 6 DOF,
the true camera and the true normal.  Per case and jump: the region's motion
while hidden (corner RMS between frames 9 and 20), the hidden frames
reported LOST, the sequences re-acquired within 5 frames of the occlusion's
end (a frame TRACKED or RECOVERED within 5 px of the true corners, and every
frame from there to the end), the delay, and the time per hidden and per visible frame
(each frame step timed to completion; frame 1, which compiles, left out).

Usage: python benchmarks/occlusion.py [--seeds 16] [--jumps 0,1,2] [--cases homography,plane]
"""

from __future__ import annotations

import argparse

import numpy as np

import common
import jaxpso

FRAME_SHAPE, ROI_SIZE, NUM_FRAMES, HIDDEN, WITHIN, TOLERANCE_PX = (120, 160), (48, 48), 30, (10, 20), 5, 5.0
CASES = {"homography": dict(motion="homography"), "plane": dict(motion="plane", dof=6)}


def run(case: str, seed: int, jump: float) -> dict:
  """One sequence tracked: the per-sequence figures."""
  start, stop = HIDDEN
  sequence = jaxpso.synthetic.make_sequence(
      seed, num_frames=NUM_FRAMES, frame_shape=FRAME_SHAPE, roi_size=ROI_SIZE, occlusion=HIDDEN,
      **(dict(jumps=((start + stop) // 2,), jump_size=jump) if jump else {}))
  config = jaxpso.TrackConfig(**CASES[case])
  extra = (dict(camera=sequence.camera, plane_normal=sequence.normal) if case == "plane" else {})
  with common.timed_frame_steps() as seconds:
    result = jaxpso.track(sequence.frames, sequence.roi, config=config, key=0, **extra)
  error = np.sqrt(np.mean(np.sum((result.corners - sequence.corners) ** 2, -1), -1))
  lost = result.status == jaxpso.TrackStatus.LOST
  found = common.tracked(result.status) & (error <= TOLERANCE_PX)
  first = stop + int(np.argmax(found[stop:])) if found[stop:].any() else None
  delay = None if first is None or not found[first:].all() else first - stop
  ms = 1e3 * np.concatenate([[np.nan, np.nan], seconds[1:]])  # frame k took seconds[k - 1]
  return dict(
      seed=seed, jump=jump,
      motion_px=float(np.sqrt(np.mean(np.sum((sequence.corners[stop] - sequence.corners[start - 1])
                                              ** 2, -1)))),
      hidden_lost=int(lost[start:stop].sum()),
      status="".join("TRLD"[s] for s in result.status), delay=delay,
      max_error_after_px=None if delay is None else float(error[first:].max()),
      ms_hidden=ms[start:stop].tolist(), ms_visible=ms[sequence.visible].tolist())


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--seeds", type=int, default=16)
  parser.add_argument("--jumps", default="0,1,2")
  parser.add_argument("--cases", default="homography,plane")
  args = parser.parse_args()
  rows, summary = [], []
  for case in args.cases.split(","):
    for jump in (float(j) for j in args.jumps.split(",")):
      runs = [run(case, seed, jump) for seed in range(args.seeds)]
      rows += [dict(case=case, **r) for r in runs]
      delays = [r["delay"] for r in runs]
      reacquired = [d for d in delays if d is not None and d < WITHIN]
      summary.append(dict(
          case=case, jump=jump, sequences=len(runs),
          motion_px=float(np.mean([r["motion_px"] for r in runs])),
          motion_max_px=float(np.max([r["motion_px"] for r in runs])),
          hidden_lost=sum(r["hidden_lost"] for r in runs),
          hidden=len(runs) * (HIDDEN[1] - HIDDEN[0]),
          reacquired=len(reacquired), immediately=sum(d == 0 for d in reacquired),
          max_delay=max(reacquired) if reacquired else None,
          max_error_after_px=max((r["max_error_after_px"] for r in runs
                                  if r["max_error_after_px"] is not None), default=None),
          ms_hidden=float(np.nanmedian(sum((r["ms_hidden"] for r in runs), []))),
          ms_visible=float(np.nanmedian(sum((r["ms_visible"] for r in runs), [])))))
      print(summary[-1], flush=True)

  info = common.machine()
  lines = [
      "# Occlusion and recovery (jaxpso.track)",
      "",
      common.machine_line(info),
      "",
      f"{args.seeds} seeds per row; {NUM_FRAMES} frames of 160×120, 48×48 region hidden in frames"
      f" {HIDDEN[0]}–{HIDDEN[1] - 1}, a camera jump at frame {sum(HIDDEN) // 2} of the given size"
      " (× the motion's amplitudes); `TrackConfig()` defaults (\"plane\": 6 DOF, true camera and"
      " normal).  Re-acquired = within 5 frames of the occlusion's end, TRACKED or RECOVERED"
      " and within 5 px from then to the end.  Times are medians per frame, frame steps timed to completion.",
      "",
      "| motion | jump | motion while hidden, mean / max (px) | hidden frames LOST |"
      " re-acquired (immediately) | max delay | max error after (px) | ms per hidden frame |"
      " ms per visible frame |",
      "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
  ]
  for s in summary:
    lines.append(
        f"| {s['case']} | {s['jump']:g} | {s['motion_px']:.1f} / {s['motion_max_px']:.1f} |"
        f" {s['hidden_lost']} / {s['hidden']} | {s['reacquired']} / {s['sequences']}"
        f" ({s['immediately']}) | {s['max_delay']} |"
        f" {'–' if s['max_error_after_px'] is None else format(s['max_error_after_px'], '.1f')} |"
        f" {s['ms_hidden']:.0f} | {s['ms_visible']:.0f} |")
  misses = [r for r in rows if r["delay"] is None or r["delay"] >= WITHIN or r["hidden_lost"] < 10]
  if misses:
    lines += ["", "Sequences not re-acquired within 5 frames or with a hidden frame not LOST"
              " (status per frame: T tracked, R recovered, L lost, D doubtful):", ""]
    lines += [f"- {r['case']}, jump {r['jump']:g}, seed {r['seed']}: motion {r['motion_px']:.1f} px,"
              f" {r['status']}, delay {r['delay']}" for r in misses]
  common.write("occlusion", {"machine": info, "summary": summary, "rows": rows},
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
