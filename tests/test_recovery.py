"""Occlusion and recovery: a region hidden for 10 frames is LOST, then re-acquired.

Requirement (issue 6): on a synthetic sequence where the region is hidden for
10 frames, the tracker reports the loss during the occlusion and re-acquires
within 5 frames after it ends (within 5 px).  The tracker runs with the
default `TrackConfig()` (4 pyramid levels: the 48 px template is 6 px at the
coarsest), so the test covers the recovery search users get; its one
compilation is most of the test's time.
"""

import numpy as np
import pytest

import jaxpso

FRAME_SHAPE = (120, 160)
ROI_SIZE = (48, 48)
NUM_FRAMES = 30
HIDDEN = (10, 20)  # frames 10..19 are occluded
REACQUIRE_WITHIN = 5  # frames after the occlusion ends
TOLERANCE_PX = 5.0
CONFIG = jaxpso.TrackConfig()

# Seed 0: the smooth motion moves the region 10.7 px (corner RMS) while it is
# hidden.  Seed 1 with a camera jump at frame 15 (twice the motion's
# amplitudes): 38.8 px, more than the normal search's 32 px radius, so only
# the recovery search can find it (the one before, a swarm over all 8 corner
# offsets, never did).
CASES = {"smooth": dict(seed=0), "jump-while-hidden": dict(seed=1, jumps=(15,), jump_size=2.0)}


def _corner_rms(corners, truth) -> np.ndarray:
  """(T,) root-mean-square distance between the estimated and the true 4 corners."""
  return np.sqrt(np.mean(np.sum((np.asarray(corners) - truth) ** 2, axis=-1), axis=-1))


@pytest.mark.parametrize("case", list(CASES))
def test_occluded_region_is_lost_then_reacquired(case):
  settings = dict(CASES[case])
  sequence = jaxpso.synthetic.make_sequence(settings.pop("seed"), num_frames=NUM_FRAMES,
                                            frame_shape=FRAME_SHAPE, roi_size=ROI_SIZE,
                                            occlusion=HIDDEN, **settings)
  start, stop = HIDDEN
  np.testing.assert_array_equal(np.flatnonzero(~sequence.visible), np.arange(start, stop))
  result = jaxpso.track(sequence.frames, sequence.roi, config=CONFIG, key=0)
  errors = _corner_rms(result.corners, sequence.corners)
  status = result.status
  lost = status == jaxpso.TrackStatus.LOST
  report = (f"{case}: status {''.join('TRL'[s] for s in status)}, quality"
            f" {np.round(result.quality, 2).tolist()}, corner error {np.round(errors, 1).tolist()} px")

  # Before the occlusion: followed closely.
  np.testing.assert_array_equal(status[:start], jaxpso.TrackStatus.TRACKED, err_msg=report)
  assert errors[:start].max() < 1.0, report

  # During the occlusion the loss is reported: every hidden frame is LOST.
  # A wide search can in principle find a chance match above lost_quality
  # (0.5), such as a quad half outside the frame (with the recovery swarm
  # one pyramid level finer, 27 of 960 hidden frames were RECOVERED that
  # way); with the library's recovery none of the 960 hidden frames of
  # benchmarks/occlusion.py was, so a hidden frame not LOST is a regression.
  np.testing.assert_array_equal(status[start:stop], jaxpso.TrackStatus.LOST, err_msg=report)
  # A LOST frame's estimate is finite (a NaN would be kept forever) and
  # coasts: each lost frame moves it less than the one before, starting from
  # the last tracked frame's motion.
  assert np.all(np.isfinite(result.homographies)) and np.all(np.isfinite(result.corners)), report
  moves = _corner_rms(result.corners[1:], result.corners[:-1])  # moves[k]: frame k → k + 1
  for frame in np.flatnonzero(lost):
    assert moves[frame - 1] <= 1.05 * moves[frame - 2] + 0.02, (frame, moves.round(2), report)

  # After it: re-acquired (TRACKED or RECOVERED within 5 px) in one of the 5
  # frames after the occlusion, and followed from there to the end.
  found = ~lost & (errors <= TOLERANCE_PX)
  reacquired = stop + int(np.argmax(found[stop:]))
  assert found[stop:].any() and reacquired < stop + REACQUIRE_WITHIN, report
  assert found[reacquired:].all(), report
