"""`jaxpso.detect` (a template found with no start) and `track`'s re-detection of a lost region."""

import dataclasses

import cv2
import numpy as np
import pytest

import jaxpso
from jaxpso._src import detect as detection

FRAME = (240, 320)  # rows, columns


def _rect(side):
  """(4, 2) corners TL, TR, BR, BL of a side×side template, or of a (rows, cols) one."""
  rows, cols = (side, side) if np.isscalar(side) else side
  return np.array([[0, 0], [cols - 1, 0], [cols - 1, rows - 1], [0, rows - 1]], np.float64)


def _placed(side, centre, scale, angle_deg, tilt=None):
  """(3, 3) homography putting a side×side (or (rows, cols)) template at `centre`, rotated,
  scaled, tilted."""
  a = np.radians(angle_deg)
  rotation = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
  rect = _rect(side)
  corners = (rect - rect.mean(axis=0)) * scale @ rotation.T + centre
  if tilt is not None:
    corners = corners + tilt
  return cv2.getPerspectiveTransform(rect.astype(np.float32), corners.astype(np.float32))


def _frame(template, truth, background, hidden=False):
  """float32 of background's shape: `template` warped by `truth` over `background` (or hidden:
  background only)."""
  if hidden:
    return background.copy()
  size = background.shape[::-1]
  warped = cv2.warpPerspective(template, truth, size, flags=cv2.INTER_LINEAR)
  mask = cv2.warpPerspective(np.ones_like(template), truth, size, flags=cv2.INTER_LINEAR)
  return (warped + (1 - mask) * background).astype(np.float32)


def _error(h, truth, side):
  a = cv2.perspectiveTransform(_rect(side)[None], np.asarray(h, np.float64))[0]
  b = cv2.perspectiveTransform(_rect(side)[None], np.asarray(truth, np.float64))[0]
  return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


@pytest.fixture(scope="module")
def scene():
  camera = jaxpso.data.load_image("camera")
  brick = jaxpso.data.load_image("brick")
  background = cv2.GaussianBlur(cv2.resize(brick, None, fx=0.8, fy=0.8), (0, 0), 1.0)
  return camera[130:210, 200:280].copy(), background[:FRAME[0], :FRAME[1]].copy()


@pytest.mark.parametrize("scale, angle", [(1.5, 150.0), (0.6, -70.0), (1.0, 10.0)])
def test_detect_finds_a_template_anywhere(scene, scale, angle):
  template, background = scene
  truth = _placed(80, np.array([200.0, 110.0]), scale, angle, tilt=[[4, -3], [0, 5], [-5, 0], [3, 2]])
  found = jaxpso.detect(_frame(template, truth, background), template)
  assert found.status == jaxpso.AlignStatus.SUCCESS
  assert _error(found.homography, truth, 80) < 0.3
  assert float(found.quality) > 0.85


def test_detect_under_inversion_with_mi(scene):
  template, background = scene
  truth = _placed(80, np.array([120.0, 130.0]), 1.2, -135.0)
  found = jaxpso.detect(1.0 - _frame(template, truth, background), template)
  assert _error(found.homography, truth, 80) < 0.3


@pytest.mark.parametrize("similarity", ["mi", "ncc"])
def test_detect_correlates_the_whole_template_where_its_middle_is_flat(scene, similarity):
  """A grey, finely grained patch of the camera photograph whose dark edges lie near its rim:
  at the coarse level its inner square is flat, so the whole template is correlated over its
  rotated footprint.  Correlating the inner square alone put it 70-74 px off."""
  _, background = scene
  template = jaxpso.data.load_image("camera")[302:386, 182:266].copy()
  truth = _placed(84, np.array([160.0, 120.0]), 1.6, -30.0,
                  tilt=[[3, -2], [0, 4], [-4, 0], [2, 1]])
  found = jaxpso.detect(_frame(template, truth, background), template,
                        config=jaxpso.TrackConfig(similarity=similarity))
  assert _error(found.homography, truth, 84) < 0.5  # measured 0.33


def test_detect_judges_the_inner_square_of_an_elongated_template(scene):
  """A 24×110 strip whose middle is plain (a sign's blank centre): the inner square correlated
  is the 16 px one at its centre, flat, so the whole strip is correlated.  Judged over the
  strip less its rim instead (which is textured), every map of the flat square was skipped
  and `detect` found no place at all (a ValueError)."""
  _, background = scene
  template = jaxpso.data.load_image("camera")[150:174, 180:290].copy()
  template[:, 40:70] = template.mean()
  truth = _placed(template.shape, np.array([170.0, 115.0]), 1.3, 35.0)
  found = jaxpso.detect(_frame(template, truth, background), template)
  assert _error(found.homography, truth, template.shape) < 0.5


@pytest.mark.parametrize("window, scale, angle", [
    ((60, 200, 180, 30), 1.2, -52.0), ((300, 120, 24, 144), 1.1, 142.0)])
def test_detect_fits_the_rotation_and_scale_of_an_elongated_template(scene, window, scale,
                                                                      angle):
  """A 6:1 strip, tilted: its inner square places it, but the rotation and scale read from that
  square were too far off for `align` to converge from them (70-184 px off at quality
  0.38-0.53, b921201); the variants around them scored by the whole template are close enough
  (measured 0.23 and 0.28 px)."""
  _, background = scene
  y, x, rows, cols = window
  template = jaxpso.data.load_image("camera")[y:y + rows, x:x + cols].copy()
  truth = _placed(template.shape, np.array([160.0, 120.0]), scale, angle,
                  tilt=[[4, -3], [0, 5], [-5, 0], [3, 2]])
  found = jaxpso.detect(_frame(template, truth, background), template)
  assert _error(found.homography, truth, template.shape) < 0.5


@pytest.mark.parametrize("window, scale, angle, tilt", [
    ((267, 316, 194, 30), 1.1, 115.0, [[-1, 3], [4.5, -5], [4, -1], [0, -4]]),
    ((183, 340, 183, 35), 1.15, -17.5, [[2, 2], [-2, 2], [1, 2.5], [0, -2]])])
def test_detect_refines_an_elongated_template_on_a_deeper_pyramid(scene, window, scale, angle,
                                                                   tilt):
  """A 6:1 strip under perspective: with the default pyramid (its 30-35 px short side kept at
  12 px or more: 2 levels) `detect` ended 7.2 and 22.7 px off; one level deeper
  (`detect._ELONGATED_COARSEST_PX`) 0.18 and 0.15 px."""
  _, background = scene
  y, x, rows, cols = window
  template = jaxpso.data.load_image("camera")[y:y + rows, x:x + cols].copy()
  truth = _placed(template.shape, np.array([160.0, 120.0]), scale, angle, tilt=tilt)
  found = jaxpso.detect(_frame(template, truth, background), template)
  assert _error(found.homography, truth, template.shape) < 0.5


def test_detect_keeps_the_levels_a_user_sets(scene, monkeypatch):
  """The deeper pyramid replaces automatic levels only: `TrackConfig(levels=1)` reaches `align`
  as it is, and without it an elongated template's refinement gets more levels than its
  default (a 30×180 strip: 2 by default, 3 with its short side down to 6 px)."""
  _, background = scene
  template = jaxpso.data.load_image("camera")[100:130, 150:330].copy()
  truth = _placed(template.shape, np.array([160.0, 120.0]), 1.0, 20.0)
  frame = _frame(template, truth, background)
  seen = []
  real = detection.align
  monkeypatch.setattr(detection, "align", lambda *a, config, **k: (
      seen.append(config.levels), real(*a, config=config, **k))[1])
  jaxpso.detect(frame, template, config=jaxpso.TrackConfig(levels=1))
  assert seen and set(seen) == {1}
  seen.clear()
  jaxpso.detect(frame, template)
  default = jaxpso.TrackConfig().for_template(template.shape, template).levels
  assert default == 2 and set(seen) == {3}


def test_detect_aligns_a_best_short_of_acceptance_again_with_the_full_search(scene, monkeypatch):
  """A candidate 14 px and 20° off: its bounded alignment (one quick swarm, no retries) stops
  25 px off at NCC 0.72; `align` with the caller's config from there finds the truth.  The
  result counts the evaluations of both."""
  template, background = scene
  truth = _placed(80, np.array([200.0, 110.0]), 1.5, 150.0, tilt=[[4, -3], [0, 5], [-5, 0], [3, 2]])
  start = _placed(80, np.array([214.0, 103.0]), 1.5, 170.0)
  frame = _frame(template, truth, background)
  monkeypatch.setattr(detection, "candidates",  # none at the second look (`_SECOND_LOOK_PX`)
                      lambda *a, patch_px=detection._PATCH_PX, **k:
                      ([[start]] if patch_px == detection._PATCH_PX else [], []))
  ran, real = [], detection.align
  monkeypatch.setattr(detection, "align", lambda *a, **k: ran.append(real(*a, **k)) or ran[-1])
  config = jaxpso.TrackConfig(similarity="ncc")
  found = jaxpso.detect(frame, template, config=config)
  assert _error(found.homography, truth, 80) < 0.3 and float(found.quality) > 0.95
  assert len(ran) == 2 and int(found.num_evaluations) == sum(int(r.num_evaluations) for r in ran)
  assert int(found.num_iterations) == sum(int(r.num_iterations) for r in ran)
  bounded = detection.search(frame, template, config, 0, detection.SCALES, detection.ANGLES, 1,
                             None)
  assert _error(bounded.homography, truth, 80) > 10.0 and float(bounded.quality) < 0.8


def test_places_inside_are_left_once_the_best_is_clear_ahead(scene, monkeypatch):
  """With acceptance out of reach, the places inside are aligned until the best is twice
  another's and at least half the lost threshold; the places partly outside are aligned
  whatever.  The right place first (MI 0.97): it and the next (0.20) are aligned.  Two wrong
  places first (0.20 and 0.15: neither clear ahead): the right third one ends it."""
  template, background = scene
  truth = _placed(80, np.array([200.0, 110.0]), 1.5, 150.0)
  frame = _frame(template, truth, background)
  near = _placed(80, np.array([203.0, 108.0]), 1.5, 155.0)
  far = [_placed(80, np.array(c), 1.0, a) for c, a in (((80, 70), 0), ((250, 190), 90),
                                                        ((70, 180), -60))]
  ran, real = [], detection.align
  monkeypatch.setattr(detection, "align", lambda *a, **k: ran.append(real(*a, **k)) or ran[-1])
  quick = detection.bounded(jaxpso.TrackConfig())
  for inside, aligned in (([near] + far, 2), (far[:2] + [near, far[2]], 3)):
    ran.clear()
    best, sure = detection._best_of(frame, template, [[h] for h in inside], [[far[2]]], quick,
                                    0, None, np.inf, True)
    assert _error(best.homography, truth, 80) < 0.3 and sure
    qualities = sorted(float(r.quality) for r in ran[:aligned])
    assert len(ran) == aligned + 1 and qualities[-1] >= 2 * qualities[-2], qualities


def test_detect_says_why_it_finds_no_place(scene):
  """A template textured only at the finest scale (a 1 px checkerboard, std 0.02) is flat once
  low-passed to be shrunk: no map can be correlated, and the error says why."""
  _, background = scene
  template = (0.5 + 0.02 * (-1.0) ** np.add.outer(np.arange(40), np.arange(40))).astype(np.float32)
  with pytest.raises(ValueError, match="no place to be matched.*flat"):
    jaxpso.detect(background, template, scales=(0.5, 0.6))


def test_detect_reports_a_missing_template_by_its_quality(scene):
  template, background = scene
  found = jaxpso.detect(background, template)
  assert float(found.quality) < jaxpso.TrackConfig().lost_threshold
  assert np.all(np.isfinite(np.asarray(found.homography)))


@pytest.mark.parametrize("kwargs, message", [
    (dict(scales=(2.0, 0.5)), "scales must be finite with low <= high"),
    (dict(scales=(0.0, 2.0)), "scales must be > 0"),
    (dict(scales=(0.5, np.inf)), "scales must be finite"),
    (dict(scales=(1.0,)), "scales must be two numbers"),
    (dict(angles=(-np.nan, 10.0)), "angles must be finite"),
    (dict(angles=(-270.0, 180.0)), "angles must span at most 360 degrees"),
    (dict(candidates_tried=0), "candidates_tried"),
])
def test_detect_bad_ranges(scene, kwargs, message):
  template, background = scene
  with pytest.raises(ValueError, match=message):
    jaxpso.detect(background, template, **kwargs)


def test_detect_bad_templates(scene):
  template, background = scene
  with pytest.raises(ValueError, match="larger than image"):
    jaxpso.detect(template, background)
  with pytest.raises(ValueError, match="textureless"):
    jaxpso.detect(background, np.full((40, 40), 0.5, np.float32))
  with pytest.raises(TypeError, match="TrackConfig"):
    jaxpso.detect(background, template, config={"similarity": "mi"})


def _jump_sequence(scene):
  """12 frames: the template drifts slowly, is hidden in frames 5–6, and reappears 150 px away,
  rotated by 90° and scaled 1.3 (out of reach of any search around its last place)."""
  template, background = scene
  truths, frames = [], []
  for k in range(12):
    if k < 7:
      truth = _placed(80, np.array([79.5 + k, 69.5 + 0.5 * k]), 1.0, 2.0 * k)
    else:
      truth = _placed(80, np.array([230.0 - k, 160.0]), 1.3, 90.0 + k)
    truths.append(truth)
    frames.append(_frame(template, truth, background, hidden=k in (5, 6)))
  return np.stack(frames), truths


def test_track_redetects_a_region_that_reappears_far_away(scene):
  frames, truths = _jump_sequence(scene)
  roi = (40, 30, 80, 80)  # the template's box in frame 0
  result = jaxpso.track(frames, roi)
  errors = np.array([_error(h, t, 80) for h, t in zip(result.homographies, truths)])
  status = result.status
  assert np.all(status[5:7] == jaxpso.TrackStatus.LOST)
  assert status[7] == jaxpso.TrackStatus.RECOVERED  # the first visible frame
  assert np.all(errors[:5] < 0.3) and np.all(errors[7:] < 0.3)
  assert np.all(status[8:] == jaxpso.TrackStatus.TRACKED)
  assert np.all(np.isfinite(result.quality[5:7])) or np.all(result.quality[5:7] < 0.65)

  without = jaxpso.track(frames, roi, config=jaxpso.TrackConfig(redetect=False))
  assert np.all(without.status[7:] == jaxpso.TrackStatus.LOST)  # out of the recovery's reach


def test_track_keeps_a_region_lost_where_detect_finds_no_place(scene, monkeypatch):
  """Where `detect` can correlate no map (a template flat at every scale it is matched at:
  `test_detect_says_why_it_finds_no_place`), its search finds nothing and the region stays
  LOST; `track` raised `detect`'s ValueError instead."""
  frames, _ = _jump_sequence(scene)
  searched = []
  monkeypatch.setattr(detection, "search", lambda *args: searched.append(args[3]))
  result = jaxpso.track(frames, (40, 30, 80, 80))
  assert np.all(result.status[5:] == jaxpso.TrackStatus.LOST)
  assert searched == list(range(5, 12))  # detect ran on every LOST frame
  assert np.all(np.isfinite(result.homographies))


def test_redetect_must_be_a_bool():
  with pytest.raises(TypeError, match="TrackConfig.redetect must be a bool"):
    jaxpso.TrackConfig(redetect=1)


def _covered_sequence(scene, covered):
  """14 frames of a 96 px template drifting 1.5 px/frame; in frames 4–9 an occluder cut from the
  background hides the right `covered` share of it.  (frames, truths, occluded frames)."""
  camera = jaxpso.data.load_image("camera")
  template = camera[120:216, 190:286].copy()
  _, background = scene
  occluder = 1.0 - np.ascontiguousarray(np.rot90(jaxpso.data.load_image("brick"))[:FRAME[0], :FRAME[1]])
  truths, frames = [], []
  for k in range(14):
    truth = _placed(96, np.array([119.5 + 1.5 * k, 109.5 + 0.5 * k]), 1.0, 0.5 * k)
    frame = _frame(template, truth, background)
    if 4 <= k < 10:
      right = truth[0, 2] + 96  # the template's right edge in the frame
      left = int(round(right - covered * 96))
      frame[:, left:] = occluder[:, left:]
    truths.append(truth)
    frames.append(frame)
  return np.stack(frames), truths, np.arange(4, 10)


@pytest.mark.parametrize("similarity", ["mi", "ncc"])
def test_track_follows_the_visible_part_of_a_half_covered_region(scene, similarity):
  frames, truths, covered = _covered_sequence(scene, 0.6)
  roi = (72, 62, 96, 96)  # the template's box in frame 0
  config = jaxpso.TrackConfig(similarity=similarity)
  result = jaxpso.track(frames, roi, config=config)
  errors = np.array([_error(h, t, 96) for h, t in zip(result.homographies, truths)])
  assert np.all(result.status == jaxpso.TrackStatus.TRACKED), result.status
  assert errors.max() < 0.5, errors.round(2)
  # The 40 % left uncovered, judged in blocks: a rectangle of them is registered.
  assert np.all((result.visible[covered] >= 0.25) & (result.visible[covered] <= 0.45)), result.visible
  assert np.all(result.visible[:4] == 1.0)

  frozen = jaxpso.track(frames, roi, config=dataclasses.replace(config, redetect=False))
  assert np.all(frozen.status[covered] == jaxpso.TrackStatus.LOST)  # the whole template fails
  assert np.all(frozen.visible[covered] == 0.0)


def _leaving(scene, speed, last, blur_px, similarity, back_dy=0.0):
  """The region slides out over the right edge at `speed` px/frame for `last` + 1 frames and
  back (`back_dy` px lower), each frame smeared along the motion over `blur_px` px (1: sharp),
  tracked.  (result, errors (T,), share of the region inside the frame (T,), frames on the
  way out (T,) bool)."""
  camera = jaxpso.data.load_image("camera")
  template = camera[120:216, 190:286].copy()
  _, background = scene
  steps = np.r_[np.arange(0, last + 1), np.arange(last, -1, -1)]
  dy = np.r_[np.zeros(last + 1), np.full(last + 1, back_dy)]
  truths = [_placed(96, np.array([149.5 + speed * s, 119.5 + y]), 1.0, 0.0)
            for s, y in zip(steps, dy)]
  smear = np.full((1, blur_px), 1.0 / blur_px, np.float32)
  frames = np.stack([cv2.filter2D(_frame(template, t, background), -1, smear,
                                  borderType=cv2.BORDER_REFLECT) for t in truths])
  result = jaxpso.track(frames, (102, 72, 96, 96), config=jaxpso.TrackConfig(similarity=similarity))
  errors = np.array([_error(h, t, 96) for h, t in zip(result.homographies, truths)])
  inside = np.clip((FRAME[1] - 0.5 - (102 + speed * steps)) / 96, 0, 1)
  return result, errors, inside, np.arange(len(steps)) <= last


@pytest.mark.parametrize("similarity", ["mi", "ncc"])
def test_a_region_leaving_the_frame_is_never_tracked_off_target(scene, similarity):
  """Out at 6 px/frame down to a twelfth inside, and back.  Under half inside, the whole
  template's registration squeezes half of it into the frame: NCC's frame step matched it
  9-17 px off at 0.87-0.91, so its visible part is also registered from the motion's
  prediction.  Once LOST, it leaves at its last speed."""
  result, errors, inside, out = _leaving(scene, 6.0, 35, 1, similarity)
  tracked = result.status != jaxpso.TrackStatus.LOST
  report = f"errors {errors.round(1)}, status {result.status}, inside {inside.round(2)}"
  assert np.all(errors[tracked] < 0.5), report  # never TRACKED off the target
  assert np.all(tracked[out & (inside >= 0.33)]), report  # its visible part is enough
  assert np.all(tracked[inside >= 0.5]), report  # and found again coming back
  leaving = ~tracked & out
  assert np.any(leaving) and np.all(errors[leaving] < 0.5), report  # coasting at its speed
  np.testing.assert_allclose(result.visible[tracked & (inside > 0.75)],
                             inside[tracked & (inside > 0.75)], atol=1 / 16)  # 16 columns
  assert np.all(result.visible[tracked & (inside < 0.75)] < 0.75)
  assert np.all(np.isfinite(result.homographies)) and np.all(np.isfinite(result.visible))


@pytest.mark.parametrize("speed, blur_px", [(8.0, 8), (10.0, 12)])
def test_a_blurred_region_leaving_the_frame_is_never_tracked_off_target(scene, speed, blur_px):
  """Out down to a tenth inside and back, blurred along the motion (NCC).  At 8 px/frame and 8
  px of blur, registered only from the squeezed step's match, the frame at 43 % inside was
  TRACKED 10.2 px off.  At 10 px/frame and 12 px, the frame step matched the region at 39 %
  inside 42.5 px off, wholly inside the frame, at NCC 0.8: only a region the last step
  matched partly outside is checked again (`track`'s `edge`).  Once LOST on the way out, it
  coasts on by its last shift alone: moved by the whole last motion, whose match was squeezed
  into the frame, it lay 4.0-6.4 px off at 27-18 % inside (8 px/frame, 8 px of blur)."""
  result, errors, inside, out = _leaving(scene, speed, 27, blur_px, "ncc")
  tracked = result.status != jaxpso.TrackStatus.LOST
  report = f"errors {errors.round(1)}, status {result.status}, inside {inside.round(2)}"
  assert np.all(errors[tracked] < 3.0), report  # measured 2.2 and 1.7 px at most
  assert np.all(tracked[inside >= 0.5]), report
  assert not np.any(tracked[out & (inside < 0.25)]), report
  coasting = ~tracked & out & (inside >= 0.1)
  assert np.any(coasting) and np.all(errors[coasting] < 4.0), report  # measured 3.2 at most


@pytest.mark.parametrize("similarity", ["mi", "ncc"])
def test_a_region_coming_back_elsewhere_is_followed_from_a_quarter_inside(scene, similarity):
  """Wholly out at 8 px/frame under 8 px of blur, back 16 px lower.  From about a quarter
  inside the LOST estimate moves with the part inside (`visible.followed`); held where the
  region left, it lay 17-40 px off until half of it was inside."""
  result, errors, inside, out = _leaving(scene, 8.0, 30, 8, similarity, back_dy=16.0)
  tracked = result.status != jaxpso.TrackStatus.LOST
  report = f"errors {errors.round(1)}, status {result.status}, inside {inside.round(2)}"
  assert np.all(errors[tracked] < 2.5), report  # measured 2.1 at most
  assert np.all(tracked[inside >= 0.55]), report
  followed = ~tracked & ~out & (inside >= 0.25)
  assert np.sum(followed) >= 3 and np.all(errors[followed] < 3.0), report  # 2.0-2.4 measured


def test_detect_ranks_its_candidates_on_a_finer_level():
  """A small template (49 px at 0.66×) over a textured background: four background places
  outscore it on the coarse level, and only ranking the coarse peaks again on the next finer
  level (`detect._RERANK`) keeps it among the candidates tried."""
  camera = jaxpso.data.load_image("camera")
  brick = jaxpso.data.load_image("brick")
  background = cv2.GaussianBlur(cv2.resize(brick, None, fx=0.73, fy=0.73), (0, 0), 1.0)
  background = background[3:3 + FRAME[0], 52:52 + FRAME[1]]
  template = camera[145:194, 145:194].copy()
  tilt = [[-1.9, -0.8], [-2.5, -0.4], [-2.0, 0.4], [0.9, 1.1]]
  truth = _placed(49, np.array([233.8, 193.8]), 0.66, -172.0, tilt=tilt)
  found = jaxpso.detect(_frame(template, truth, background), template)
  assert _error(found.homography, truth, 49) < 1.0


@pytest.mark.parametrize("similarity", ["mi", "ncc"])
def test_detect_tries_the_half_turn_of_a_place_that_looks_alike_turned(similarity, monkeypatch):
  """Bricks look alike turned half a turn: at their place the coarse map of the half turn
  outscores the right rotation, which as one place with it would be merged away
  (detection.py's seed 1, trial 85, at half its size).  Its twin (`detect._TWIN`) is tried as
  a place of its own: measured 0.21 (MI) and 0.22 px (NCC); with no twins 86-89 px off."""
  camera = jaxpso.data.load_image("camera")
  background = cv2.GaussianBlur(cv2.resize(camera, None, fx=0.85, fy=0.85), (0, 0), 1.0)
  template = jaxpso.data.load_image("brick")[262:398, 311:447].copy()
  corners = np.array([[219.5, 120.6], [179.1, 164.2], [130.2, 116.3], [187.7, 74.0]])
  truth = cv2.getPerspectiveTransform(_rect(136).astype(np.float32),
                                      corners.astype(np.float32))
  frame = _frame(template, truth, background[:FRAME[0], :FRAME[1]])
  config = jaxpso.TrackConfig(similarity=similarity)
  found = jaxpso.detect(frame, template, config=config)
  assert _error(found.homography, truth, 136) < 0.3
  monkeypatch.setattr(detection, "_TWIN", np.inf)
  assert _error(jaxpso.detect(frame, template, config=config).homography, truth, 136) > 50.0


@pytest.mark.parametrize("similarity", ["mi", "ncc"])
def test_detect_looks_again_closer_where_its_best_is_in_doubt(similarity, monkeypatch):
  """A camera crop at 1.5× on bricks in a 480×640 frame (detection.py's seed 2, trial 6): where
  the inner disc spans 12 px, smaller scales' peaks outscore it (every candidate at 0.42-0.75×)
  and no place is clear ahead of another.  The second look (`detect._SECOND_LOOK_PX`) finds
  it: measured 0.40 (MI) and 0.43 px (NCC); looking again at 12 px, 111-113 px off."""
  template = jaxpso.data.load_image("camera")[305:451, 142:288].copy()
  background = cv2.resize(jaxpso.data.load_image("brick"), None, fx=1.7, fy=1.7)
  background = np.tile(cv2.GaussianBlur(background, (0, 0), 1.0), (2, 2))[:480, :640]
  corners = np.array([[590.6, 294.8], [487.8, 471.1], [321.1, 338.7], [432.8, 154.2]])
  truth = cv2.getPerspectiveTransform(_rect(146).astype(np.float32), corners.astype(np.float32))
  frame = _frame(template, truth, background)
  config = jaxpso.TrackConfig(similarity=similarity)
  assert _error(jaxpso.detect(frame, template, config=config).homography, truth, 146) < 0.5
  monkeypatch.setattr(detection, "_SECOND_LOOK_PX", detection._PATCH_PX)
  assert _error(jaxpso.detect(frame, template, config=config).homography, truth, 146) > 50.0


def test_only_a_template_that_looks_alike_turned_keeps_twins(scene):
  """Bricks look alike turned (the crop above: 0.87, `detect._ALIKE` 0.6); the camera crop
  of the other tests does not (0.30), nor does a flat square."""
  template, _ = scene
  bricks = jaxpso.data.load_image("brick")[262:398, 311:447].copy()
  assert detection._looks_alike_turned(bricks)
  assert not detection._looks_alike_turned(template)
  flat = np.full((40, 40), 0.5, np.float32)
  assert not detection._looks_alike_turned(flat)


@pytest.mark.parametrize("similarity", ["mi", "ncc"])
def test_detect_partial_finds_a_template_partly_outside_the_image(scene, similarity):
  """Two fifths of the template lie beyond the right edge: the candidates wholly inside the
  image have no place for it, the partial ones correlate the part inside
  (`detect._masked_correlation`).  The corners outside rest on the pixels inside: measured
  0.8 (MI) and 1.4 px (NCC) RMS."""
  template, background = scene
  truth = _placed(80, np.array([310.0, 120.0]), 1.1, 15.0)
  frame = _frame(template, truth, background)
  config = jaxpso.TrackConfig(similarity=similarity)
  whole = detection.search(frame, template, config, 0, detection.SCALES, detection.ANGLES,
                           detection.CANDIDATES, None)
  found = jaxpso.detect(frame, template, config=config, partial=True)
  assert _error(whole.homography, truth, 80) > 20.0
  assert _error(found.homography, truth, 80) < 2.0, _error(found.homography, truth, 80)
  assert float(found.quality) > config.lost_threshold + 0.1, float(found.quality)
  with pytest.raises(ValueError, match="partial must be a bool"):
    jaxpso.detect(frame, template, partial=1)


def test_masked_correlation_is_opencv_s_inside_the_image():
  from jaxpso._src import detect

  rng = np.random.default_rng(0)
  picture = cv2.GaussianBlur(rng.random((60, 80)).astype(np.float32), (0, 0), 1.5)
  patch = picture[20:36, 30:46].copy()
  inside = detect._masked_correlation(picture, patch, (0, 0), (64, 44), 0.5)
  np.testing.assert_allclose(inside, cv2.matchTemplate(picture, patch, cv2.TM_CCOEFF_NORMED),
                             atol=1e-4)
  # The patch's left half at the picture's left edge: found over that half alone.
  cut = np.ascontiguousarray(picture[:, 38:])
  scores = detect._masked_correlation(cut, patch, (-8, -8), (cut.shape[1] - 8, 52), 0.5)
  y, x = np.unravel_index(np.argmax(scores), scores.shape)
  assert (x - 8, y - 8) == (30 - 38, 20) and scores[y, x] > 0.999
  assert scores[0, 0] == -1.0  # a quarter of the patch inside: under the least share
