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
  report = (f"{case}: status {''.join('TRLD'[s] for s in status)}, quality"
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


def _look_alike_sequence(replaced: float):
  """(12, 240, 320) frames: a camera picture with the region (30, 60, 80, 80) and, at (200, 100),
  its copy with its right `replaced` share of columns from another picture; frames 3-6 hide
  the region under a patch of that other picture."""
  import cv2

  picture = cv2.resize(np.asarray(jaxpso.data.load_image("camera"), np.float32), None,
                       fx=0.75, fy=0.75, interpolation=cv2.INTER_AREA)[40:280, 40:360]
  other = np.asarray(jaxpso.data.load_image("brick"), np.float32)
  x, y, w, h = LOOK_ALIKE_ROI
  copy = picture[y:y + h, x:x + w].copy()
  cut = int(round(w * (1 - replaced)))
  copy[:, cut:] = other[:h, cut:w]
  picture[100:100 + h, 200:200 + w] = copy
  frames = np.repeat(picture[None], 12, axis=0)
  frames[3:7, y - 10:y + h + 10, x - 10:x + w + 10] = other[100:120 + h, 100:120 + w]
  noise = np.random.default_rng(0).normal(0, 0.01, frames.shape)
  return np.clip(frames + noise, 0, 1).astype(np.float32)


LOOK_ALIKE_ROI = (30, 60, 80, 80)


@pytest.mark.parametrize("similarity, replaced", [("ncc", 0.15), ("mi", 0.1)])
def test_a_look_alike_detected_in_doubt_gives_way_to_the_target(similarity, replaced):
  # While the region is hidden (frames 3-6) `detect` finds its look-alike
  # (NCC 0.88, MI 0.72-0.85 against 0.98-1.0 for the region), which is
  # tracked there; the region back in view at frame 7, the detection in
  # doubt (`track._margin`) runs again and finds it.  Without it the
  # estimate stayed on the look-alike, 174 px off, to the end.  While on
  # the look-alike the frames are DOUBTFUL, never TRACKED or RECOVERED.
  frames = _look_alike_sequence(replaced)
  result = jaxpso.track(frames, LOOK_ALIKE_ROI, config=jaxpso.TrackConfig(similarity=similarity))
  x, y, w, h = LOOK_ALIKE_ROI
  box = np.array([[x, y], [x + w - 1, y], [x + w - 1, y + h - 1], [x, y + h - 1]], np.float64)
  errors = _corner_rms(result.corners, box)
  report = f"status {result.status.tolist()}, errors {np.round(errors, 1).tolist()}"
  assert errors[:3].max() < 0.1 and errors[3] > 100, report  # the look-alike found at frame 3
  assert (result.status[3:7] == jaxpso.TrackStatus.DOUBTFUL).all(), report
  assert result.status[7] == jaxpso.TrackStatus.RECOVERED and errors[7:].max() < 0.1, report
  assert (result.status[8:] == jaxpso.TrackStatus.TRACKED).all(), report


def test_a_lost_frame_counts_the_alignments_run_on_the_host(monkeypatch):
  # The first hidden frame of the smooth case: the frame step, the same
  # with `redetect` off, then on the host the visible part and `detect`,
  # none of them adopted (LOST).  The frame's counts are the step's plus
  # every one of those alignments'.
  from jaxpso._src import align as aligning
  from jaxpso._src import detect as detection

  sequence = jaxpso.synthetic.make_sequence(0, num_frames=NUM_FRAMES, frame_shape=FRAME_SHAPE,
                                            roi_size=ROI_SIZE, occlusion=HIDDEN)
  frames = sequence.frames[:HIDDEN[0] + 1]
  alone = jaxpso.track(frames, sequence.roi, key=0, config=jaxpso.TrackConfig(redetect=False))
  ran = []
  original = aligning.align

  def recorded(*args, **kwargs):
    ran.append(original(*args, **kwargs))
    return ran[-1]

  monkeypatch.setattr(aligning, "align", recorded)
  monkeypatch.setattr(detection, "align", recorded)
  result = jaxpso.track(frames, sequence.roi, config=CONFIG, key=0)
  assert result.status[-1] == alone.status[-1] == jaxpso.TrackStatus.LOST
  assert len(ran) >= 2, len(ran)
  for field in ("num_iterations", "num_evaluations"):
    host = sum(int(getattr(found, field)) for found in ran)
    assert getattr(result, field)[-1] == getattr(alone, field)[-1] + host, (field, host)
