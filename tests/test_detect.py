"""`jaxpso.detect` (a template found with no start) and `track`'s re-detection of a lost region."""

import cv2
import numpy as np
import pytest

import jaxpso

FRAME = (240, 320)  # rows, columns


def _rect(side):
  return np.array([[0, 0], [side - 1, 0], [side - 1, side - 1], [0, side - 1]], np.float64)


def _placed(side, centre, scale, angle_deg, tilt=None):
  """(3, 3) homography putting a side×side template at `centre`, rotated, scaled, tilted."""
  a = np.radians(angle_deg)
  rotation = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
  corners = (_rect(side) - (side - 1) / 2) * scale @ rotation.T + centre
  if tilt is not None:
    corners = corners + tilt
  return cv2.getPerspectiveTransform(_rect(side).astype(np.float32), corners.astype(np.float32))


def _frame(template, truth, background, hidden=False):
  """(240, 320) float32: `template` warped by `truth` over `background` (or hidden: background only)."""
  if hidden:
    return background.copy()
  warped = cv2.warpPerspective(template, truth, FRAME[::-1], flags=cv2.INTER_LINEAR)
  mask = cv2.warpPerspective(np.ones_like(template), truth, FRAME[::-1], flags=cv2.INTER_LINEAR)
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


def test_redetect_must_be_a_bool():
  with pytest.raises(TypeError, match="TrackConfig.redetect must be a bool"):
    jaxpso.TrackConfig(redetect=1)
