"""The visible part of a region (`jaxpso._src.visible`): blocks, their rectangle, registration."""

import cv2
import numpy as np
import pytest

import jaxpso
from jaxpso._src import detect
from jaxpso._src import visible


def test_largest_rectangle_allows_a_hole_but_not_a_missing_column():
  grid = np.zeros((visible.GRID, visible.GRID), bool)
  grid[2:8, 0:4] = True
  grid[4, 2] = False  # one hole in 24 blocks: within _FILLED
  assert visible.largest_rectangle(grid) == (2, 8, 0, 4)
  assert visible.largest_rectangle(np.zeros_like(grid)) is None


def _half_out():
  """A (200, 240) frame showing the left half of a brick region whose template is (120, 120),
  placed with its top-left corner at (-60, 40), and that template."""
  texture = cv2.resize(np.asarray(jaxpso.data.load_image("brick"), np.float32), None, fx=0.5,
                       fy=0.5, interpolation=cv2.INTER_AREA)
  template = texture[60:180, 40:160].copy()
  frame = texture[20:220, 100:340].copy()  # the template's (x, y) = frame's (x - 60, y + 40)
  noise = np.random.default_rng(0).normal(0, 0.01, frame.shape)
  return np.clip(frame + noise, 0, 1).astype(np.float32), template


@pytest.mark.parametrize("similarity", ["mi", "ncc"])
def test_a_start_a_few_pixels_off_is_recentred_before_the_blocks_are_judged(similarity):
  # Half of a fine brick region out of the frame, the start 3.5 px off (a
  # pan that stopped, coasted on): at the start no block of the visible half
  # correlates at _BLOCK_NCC; moved by the best shift first, the half is
  # seen and registered (measured 0.1 px off).
  frame, template = _half_out()
  truth = np.array([[1.0, 0, -60], [0, 1, 40], [0, 0, 1]])
  start = truth @ np.array([[1.0, 0, 3.0], [0, 1, -2.0], [0, 0, 1]])
  either_sign = similarity == "mi"
  assert visible.blocks(frame, template, start, either_sign).sum() == 0  # 27 of 64 at the truth
  moved = visible.recentred(frame, template, start, either_sign)
  np.testing.assert_allclose(moved, truth, atol=1e-9)
  config = detect.bounded(jaxpso.TrackConfig(similarity=similarity))
  part, share = visible.register_part(frame, template, start, config, 0, either_sign)
  assert 0.4 <= share <= 0.5, share  # the half inside the frame, less its rim
  corners = np.c_[[[0, 0], [119, 0], [119, 119], [0, 119]], np.ones(4)]
  found = corners @ np.asarray(part.homography, np.float64).T
  true = corners @ truth.T[:, :2]
  error = np.sqrt(np.mean(np.sum((found[:, :2] / found[:, 2:] - true) ** 2, -1)))
  assert error < 0.2, error
  assert float(part.quality) >= jaxpso.TrackConfig(similarity=similarity).lost_threshold


@pytest.mark.parametrize("similarity", ["mi", "ncc"])
def test_followed_moves_a_region_mostly_outside_with_its_part_inside(similarity):
  # A quarter of a brick region inside the frame: too little for its own
  # homography (`register_part` needs MIN_VISIBLE of the blocks matching at
  # the estimate), enough to move the estimate by the shift of that quarter.
  texture = cv2.resize(np.asarray(jaxpso.data.load_image("brick"), np.float32), None, fx=0.5,
                       fy=0.5, interpolation=cv2.INTER_AREA)
  template = texture[60:180, 130:250].copy()
  frame = texture[20:220, 0:160].copy()  # the template's (x, y) = frame's (x + 130, y + 40)
  truth = np.array([[1.0, 0, 130], [0, 1, 40], [0, 0, 1]])
  either_sign = similarity == "mi"
  for shift in ((-14.0, 12.0), (20.0, -6.0), (0.0, 0.0)):
    start = truth @ np.array([[1.0, 0, shift[0]], [0, 1, shift[1]], [0, 0, 1]])
    moved, score = visible.followed(frame, template, start, either_sign)
    np.testing.assert_allclose(moved, truth, atol=1e-9)
    assert score >= visible.FOLLOW_NCC, score
  # Every shift within reach leaves less than FOLLOW_SHARE inside: no answer.
  away = truth @ np.array([[1.0, 0, 64.0], [0, 1, 0], [0, 0, 1]])
  moved, score = visible.followed(frame, template, away, either_sign)
  assert score == -1.0 and np.array_equal(moved, away)


def test_a_part_s_match_that_folds_the_whole_template_is_no_match(monkeypatch):
  # Found by fuzzing: a visible part's match, admissible for the part, can put
  # the rest of the template across the horizon; `track` reported such a
  # whole homography TRACKED.  A match of the left half bent so that w
  # stays positive over the half and turns negative at the template's far edge.
  frame, template = _half_out()
  truth = np.array([[1.0, 0, -60], [0, 1, 40], [0, 0, 1]])
  config = detect.bounded(jaxpso.TrackConfig(similarity="ncc"))
  part, share = visible.register_part(frame, template, truth, config, 0, False)
  assert part is not None and share > 0.4
  align = visible.aligning.align
  bend = np.array([[1.0, 0, 0], [0, 1, 0], [0.02, 0, 1]])  # w = 1 + 0.02 x in the part's pixels
  monkeypatch.setattr(visible.aligning, "align", lambda *a, **k: (lambda found: found._replace(
      homography=np.asarray(found.homography, np.float64) @ bend))(align(*a, **k)))
  assert visible.register_part(frame, template, truth, config, 0, False) == (None, share)


def test_masked_correlation_of_either_sign_counts_a_perfect_anticorrelation():
  # An exact inverse correlates at -1, the value that also marks a place
  # with too little inside: taken as that mark, it was never the best.
  rng = np.random.default_rng(3)
  image = rng.random((40, 50)).astype(np.float32)
  patch = 1.0 - image[10:30, 20:40]
  inside = np.ones_like(image)
  inside[:, :5] = 0.0
  scores = visible.masked_correlation(image, inside, patch, 0.9, either_sign=True)
  assert np.unravel_index(np.argmax(scores), scores.shape) == (10, 20)
  assert scores[10, 20] == pytest.approx(1.0, abs=1e-5)
  signed = visible.masked_correlation(image, inside, patch, 0.9)
  assert signed[10, 20] == pytest.approx(-1.0, abs=1e-5)
  assert np.all(scores[:, :2] == -1.0)  # under 0.9 of the patch inside
