"""Periodic templates (`jaxpso._src.periodic`): which alias themselves, and the best shift."""

import numpy as np
import pytest

import jaxpso
from jaxpso._src import periodic


def _stripes(rows: int, cols: int, period: int = 2) -> np.ndarray:
  """(rows, cols) float32 diagonal stripes: x + y modulo `period` makes a stripe."""
  yy, xx = np.mgrid[:rows, :cols]
  return np.where((yy + xx) % period < period / 2, 0.7, 0.3).astype(np.float32)


@pytest.mark.parametrize("period", [2, 3, 5])
def test_stripes_and_checkerboards_alias_themselves(period):
  assert periodic.aliased(_stripes(100, 50, period))
  yy, xx = np.mgrid[:60, :80]
  checker = ((yy // period + xx // period) % 2).astype(np.float32)
  assert periodic.aliased(checker)


def test_photographs_and_noise_do_not_alias_themselves():
  rng = np.random.default_rng(0)
  assert not periodic.aliased(rng.random((80, 90)).astype(np.float32))
  for name in ("camera", "brick"):
    image = np.asarray(jaxpso.data.load_image(name), np.float32)
    for _ in range(40):
      rows, cols = rng.integers(24, 200, 2)
      y, x = rng.integers(0, 512 - rows), rng.integers(0, 512 - cols)
      assert not periodic.aliased(image[y:y + rows, x:x + cols]), (name, y, x, rows, cols)


def test_a_template_smaller_than_eight_pixels_is_never_aliased():
  assert periodic.reach((7, 100)) == 1
  assert not periodic.aliased(_stripes(7, 100))


@pytest.mark.parametrize("either_sign", [False, True])
def test_best_shift_finds_the_truth_along_the_stripes(either_sign):
  # The stripes are pasted on a photograph: only their border tells the
  # truth from a place slid along them, and that border is enough.
  frame = np.asarray(jaxpso.data.load_image("camera"), np.float32)[200:360, 100:300].copy()
  template = _stripes(100, 50)
  frame[30:130, 70:120] = 1.0 - template if either_sign else template
  off = np.array([[1.0, 0, 73], [0, 1, 27], [0, 0, 1]])  # 3 px along the stripes
  shift, scores = periodic.best_shift(frame, template, off, either_sign)
  np.testing.assert_array_equal(shift, [-3, 3])
  reach = periodic.reach(template.shape)
  assert scores.shape == (2 * reach + 1,) * 2
  assert scores.max() > 0.999
  assert 0.8 < scores[reach, reach] < 0.9  # measured 0.84: the stripes match, their border not


def test_best_shift_counts_only_shifts_mostly_inside_the_frame():
  frame = np.random.default_rng(1).random((120, 160)).astype(np.float32)
  template = frame[0:60, 40:100].copy()
  start = np.array([[1.0, 0, 40], [0, 1, 0], [0, 0, 1]])
  shift, scores = periodic.best_shift(frame, template, start, either_sign=False)
  np.testing.assert_array_equal(shift, [0, 0])
  reach = periodic.reach(template.shape)
  assert np.all(scores[:reach - 6] == -1.0)  # shifted up by 7 px or more: too little inside
  assert np.all(np.isfinite(scores))


def test_best_shift_of_a_template_mostly_outside_the_frame_is_none():
  frame = _stripes(100, 120)
  template = _stripes(60, 60)
  start = np.array([[1.0, 0, 90], [0, 1, 20], [0, 0, 1]])  # half of it past the right edge
  shift, scores = periodic.best_shift(frame, template, start, either_sign=False)
  np.testing.assert_array_equal(shift, [0, 0])
  assert np.all(scores == -1.0)
