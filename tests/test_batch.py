"""Batches: `track` over R regions of one video or R sequences, `align` over N triples.

A batch is one compiled program; on a CPU every element comes out bit for
bit as it does alone (`batching.each`).  One small config (SSD, one pyramid level)
keeps the compile count and time down.
"""

import dataclasses
import functools

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpso
from jaxpso.data import load_image
from jaxpso._src import batching
from jaxpso._src import programs


def programs_made() -> int:
  """Programs compiled or loaded from the cache so far (`programs.counts`)."""
  return programs.counts()["compiled"] + programs.counts()["loaded"]

# Re-detection off: these tests are of the frame step's own stages in a batch
# (a 40×40 SSD template over a frame of noise is LOST there; `detect`, whose
# SSD threshold is quality 0.5, finds a false match in that noise).
CONFIG = jaxpso.TrackConfig(similarity="ssd", levels=1, swarm_size=16, max_iterations=15,
                            search_radius=8.0, redetect=False)


@functools.cache
def _sequence(seed: int) -> jaxpso.synthetic.Sequence:
  return jaxpso.synthetic.make_sequence(seed, num_frames=6, frame_shape=(120, 160),
                                        roi_size=(48, 48))


def _box_corners(box):
  x, y, w, h = box
  return np.float32([[x, y], [x + w - 1, y], [x + w - 1, y + h - 1], [x, y + h - 1]])


def _true_corners(sequence, corners0):
  """(T, 4, 2) where the plane carries frame-0 points `corners0` (4, 2) in every frame."""
  out = []
  for truth in sequence.corners:
    h = cv2.getPerspectiveTransform(np.float32(sequence.corners[0]), np.float32(truth))
    out.append(cv2.perspectiveTransform(np.float32(corners0)[None], h)[0])
  return np.stack(out)


def _alone(sequence, roi, **kwargs):
  return jaxpso.track(sequence.frames, roi, config=CONFIG, **kwargs)


def test_regions_of_one_video_track_as_they_do_alone():
  sequence = _sequence(0)
  x, y, w, h = sequence.roi
  # Three regions: the program of `test_regions_of_different_sizes_given_as_corners`.
  rois = np.array([sequence.roi, (x + 6, y - 4, w, h), (x - 5, y + 3, w, h)])
  batch = jaxpso.track(sequence.frames, rois, config=CONFIG, key=0)
  assert batch.homographies.shape == (3, 6, 3, 3) and batch.status.shape == (3, 6)
  assert batch.corners.shape == (3, 6, 4, 2) and batch.poses is None
  alone = _alone(sequence, rois[0], key=0)  # region 0 has the key's own stream
  np.testing.assert_array_equal(batch.homographies[0], alone.homographies)
  np.testing.assert_array_equal(batch.status[0], alone.status)
  for r, roi in enumerate(rois):
    truth = _true_corners(sequence, _box_corners(roi))
    error = np.sqrt(np.mean(np.sum((batch.corners[r] - truth) ** 2, axis=-1), axis=-1))
    assert error.max() < 1.0, (r, error)
  assert np.all(batch.status == jaxpso.TrackStatus.TRACKED)


def test_regions_of_different_sizes_given_as_corners():
  # Templates of 48×48, 30×40 and a skewed quad are sampled on one 48×48
  # grid; each homography maps the region's own template pixels.
  sequence = _sequence(0)
  x, y, w, h = sequence.roi
  quads = np.stack([_box_corners(sequence.roi), _box_corners((x + 8, y + 4, 30, 40)),
                    np.float32([[x + 2, y + 1], [x + 40, y + 5], [x + 44, y + 46], [x, y + 40]])])
  batch = jaxpso.track(sequence.frames, quads, config=CONFIG, key=0)
  np.testing.assert_allclose(batch.corners[:, 0], quads, atol=1e-3)
  small = batch.homographies[1, 0] @ np.array([29.0, 39.0, 1.0])  # its own BR corner
  np.testing.assert_allclose(small[:2] / small[2], quads[1, 2], atol=1e-3)
  for r in range(3):
    truth = _true_corners(sequence, quads[r])
    error = np.sqrt(np.mean(np.sum((batch.corners[r] - truth) ** 2, axis=-1), axis=-1))
    assert error.max() < 1.0, (r, error)


def test_a_batch_of_sequences_tracks_each_as_alone():
  first, second = _sequence(0), _sequence(3)
  frames = np.stack([first.frames, second.frames])
  batch = jaxpso.track(frames, np.array([first.roi, second.roi]), config=CONFIG, key=0,
                       sequences=True)
  listed = jaxpso.track([list(first.frames), iter(second.frames)],
                        np.array([first.roi, second.roi]), config=CONFIG, key=0, sequences=True)
  np.testing.assert_array_equal(listed.homographies, batch.homographies)
  np.testing.assert_array_equal(batch.homographies[0], _alone(first, first.roi, key=0).homographies)
  for r, sequence in enumerate((first, second)):
    error = np.sqrt(np.mean(np.sum((batch.corners[r] - sequence.corners) ** 2, axis=-1), axis=-1))
    assert error.max() < 1.0, (r, error)


def test_a_repeated_batch_adds_no_compiled_program():
  sequence = _sequence(0)
  x, y, w, h = sequence.roi
  rois = np.array([sequence.roi, (x + 6, y - 4, w, h), (x - 5, y + 3, w, h)])
  jaxpso.track(sequence.frames[:3], rois, config=CONFIG, key=1)
  size = programs_made()
  jaxpso.track(sequence.frames[2:], rois - np.array([2, 2, 0, 0]), config=CONFIG, key=2)
  assert programs_made() == size


def test_costly_searches_run_for_the_batch_only_when_a_region_needs_them():
  # Gauss–Newton alone is accepted on these small motions: no swarm runs, so
  # no frame of the batch costs a swarm's evaluations.  Three regions, as in
  # the other batch tests here: one program for all of them.
  sequence = _sequence(0)
  batch = jaxpso.track(sequence.frames, np.array([sequence.roi] * 3), config=CONFIG)
  assert batch.num_evaluations[:, 1:].max() < CONFIG.swarm_size
  # A region over a frame of noise needs the recovery; the other region keeps its own result.
  noisy = sequence.frames.copy()
  x, y, w, h = sequence.roi
  noisy[3, :, 80:] = np.random.default_rng(0).uniform(size=noisy[3, :, 80:].shape)
  left = (4, 30, 40, 40)
  mixed = jaxpso.track(noisy, np.array([left, (110, 30, 40, 40), (20, 40, 40, 40)]), config=CONFIG)
  alone = jaxpso.track(noisy, left, config=CONFIG)
  assert mixed.status[1, 3] == jaxpso.TrackStatus.LOST
  np.testing.assert_array_equal(mixed.homographies[0], alone.homographies)
  np.testing.assert_array_equal(mixed.num_evaluations[0], alone.num_evaluations)


@pytest.mark.parametrize("size", [1, 5, 17, 70])
def test_where_needed_computes_exactly_the_needing_elements(size):
  # compute() marks what it was asked for; every needing element is
  # computed once, no other element is written, in rounds of
  # `batching._capacity(R)` elements, the last padded.
  values = jnp.arange(size, dtype=jnp.float32)

  @jax.jit
  def run(mask):
    def compute(indices):
      return (values[indices] + 100.0, jnp.ones_like(indices))
    return batching.where_needed(mask, compute, (values, jnp.zeros(size, jnp.int32)))

  for mask in [np.zeros(size, bool), np.ones(size, bool),
               np.random.default_rng(size).uniform(size=size) < 0.3]:
    result, computed = run(mask)
    np.testing.assert_array_equal(result, np.where(mask, np.arange(size) + 100.0, np.arange(size)))
    np.testing.assert_array_equal(computed, mask)


def test_each_runs_every_element_as_it_runs_alone():
  # A per-element loop of data-dependent length and a sum of 640 floats: on
  # a CPU every element's result is bit-identical to the function's alone
  # (under `vmap` XLA sums a batch of 16 in another order, 2e-6 apart).
  def fn(values, steps):
    total = jnp.sum(values * values)
    return jax.lax.while_loop(lambda c: c[0] < steps, lambda c: (c[0] + 1, c[1] * 0.5 + total),
                              (0, 0.0))[1]

  rng = np.random.default_rng(0)
  values = rng.normal(size=(16, 640)).astype(np.float32)
  steps = np.arange(16, dtype=np.int32) % 5
  batch = jax.jit(lambda v, s: batching.each(fn, v, s))(values, steps)
  alone = jax.jit(fn)
  np.testing.assert_array_equal(batch, [alone(v, s) for v, s in zip(values, steps)])


def test_every_region_of_a_wide_batch_tracks_bit_identically_as_alone():
  # 17 regions with one key each: region r's track is the one alone with key[r].
  sequence = _sequence(0)
  x, y, w, h = sequence.roi
  shifts = [(dx, dy) for dx in (-4, 0, 4) for dy in (-3, 0, 3)]
  rois = np.array([(x + dx, y + dy, w, h) for dx, dy in (shifts * 2)[:17]])
  keys = list(range(10, 27))
  batch = jaxpso.track(sequence.frames, rois, config=CONFIG, key=keys)
  for r, roi in enumerate(rois):
    alone = _alone(sequence, roi, key=keys[r])
    np.testing.assert_array_equal(batch.homographies[r], alone.homographies)
    np.testing.assert_array_equal(batch.num_evaluations[r], alone.num_evaluations)
    truth = _true_corners(sequence, _box_corners(roi))
    error = np.sqrt(np.mean(np.sum((batch.corners[r] - truth) ** 2, axis=-1), axis=-1))
    assert error.max() < 1.0, (r, error)
  assert np.all(batch.status == jaxpso.TrackStatus.TRACKED)


@pytest.fixture
def accelerator_path(monkeypatch):
  """A call that switches to the batch as on an accelerator (`vmap`, `where_needed`), run on
  the CPU, in programs of its own."""
  def switch():
    for name in ("_dir_setting", "_dir", "_dir_checked"):
      monkeypatch.setattr(programs, name, getattr(programs, name))
    programs.set_cache_dir(None)
    programs.clear()
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")

  yield switch
  programs.clear()


def test_the_accelerator_path_tracks_and_aligns_each_element_as_alone(accelerator_path):
  # Vectorised, a batch rounds otherwise than one element alone on the CPU's
  # path: equal within 1e-3 px, not bit for bit.  A region over a frame of
  # noise runs the recovery, gathered by `where_needed`; the others keep
  # their results.
  sequence = _sequence(0)
  noisy = sequence.frames.copy()
  noisy[3, :, 80:] = np.random.default_rng(0).uniform(size=noisy[3, :, 80:].shape)
  rois = np.array([(4, 30, 40, 40), (110, 30, 40, 40), (20, 40, 40, 40)])
  alone = {r: jaxpso.track(noisy, rois[r], config=CONFIG, key=r + 1) for r in (0, 2)}
  accelerator_path()
  batch = jaxpso.track(noisy, rois, config=CONFIG, key=[1, 2, 3])
  assert batch.status[1, 3] == jaxpso.TrackStatus.LOST
  for r in (0, 2):
    np.testing.assert_allclose(batch.corners[r], alone[r].corners, atol=1e-3)
    np.testing.assert_array_equal(batch.status[r], alone[r].status)
  triples = [_triple(seed) for seed in range(3)]
  templates, starts, truths = (np.stack(a) for a in zip(*triples))
  aligned = jaxpso.align(np.stack([IMAGE] * 3), templates, starts, config=ALIGN, key=[4, 5, 6])
  for i in range(3):
    mapped = cv2.perspectiveTransform(SOURCE[None], np.float64(aligned.homography[i]))[0]
    assert np.abs(mapped - truths[i]).max() < 0.5, i


# --- align ------------------------------------------------------------------------------------

IMAGE = load_image("camera")
SIZE = 64
SOURCE = np.float32([[0, 0], [SIZE - 1, 0], [SIZE - 1, SIZE - 1], [0, SIZE - 1]])
ALIGN = dataclasses.replace(CONFIG, levels=2, search_radius=12.0)


def _triple(seed):
  rng = np.random.default_rng(seed)
  x, y = rng.integers(60, 380, 2)
  template = IMAGE[y:y + SIZE, x:x + SIZE].copy()
  corners = SOURCE + np.float32([x, y]) + rng.normal(0, 2.0, (4, 2)).astype(np.float32)
  truth = SOURCE + np.float32([x, y])
  return template, cv2.getPerspectiveTransform(SOURCE, corners), truth


def test_a_batch_of_alignments_equals_them_one_by_one():
  triples = [_triple(seed) for seed in range(3)]
  templates, starts, truths = (np.stack(a) for a in zip(*triples))
  batch = jaxpso.align(np.stack([IMAGE] * 3), templates, starts, config=ALIGN, key=4)
  assert batch.homography.shape == (3, 3, 3) and batch.status.shape == (3,)
  alone = jaxpso.align(IMAGE, templates[0], starts[0], config=ALIGN, key=4)
  np.testing.assert_array_equal(batch.homography[0], alone.homography)
  for i in range(3):
    mapped = cv2.perspectiveTransform(SOURCE[None], np.float64(batch.homography[i]))[0]
    assert np.abs(mapped - truths[i]).max() < 0.5, i
  compiled = programs_made()
  jaxpso.align(np.stack([IMAGE] * 3), templates[::-1], starts[::-1], config=ALIGN, key=5)
  assert programs_made() == compiled


# --- bad input --------------------------------------------------------------------------------


def test_an_align_batch_mixes_image_and_template_sizes_in_one_program():
  # Templates of 40×56, 64×64 and 48×48 px in images of two sizes: one
  # program (three elements: `test_a_batch_of_alignments_equals_them_one_by_one`'s),
  # and every element registers as it does alone.
  rng = np.random.default_rng(7)
  images = [IMAGE, np.ascontiguousarray(IMAGE[:300, :420]), IMAGE]
  boxes = [(120, 90, 56, 40), (200, 150, 64, 64), (250, 250, 48, 48)]
  templates, starts, truths = [], [], []
  for (x, y, w, h) in boxes:
    source = np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])
    templates.append(IMAGE[y:y + h, x:x + w].copy())
    truths.append(source + np.float32([x, y]))
    corners = truths[-1] + rng.normal(0, 2.0, (4, 2)).astype(np.float32)
    starts.append(cv2.getPerspectiveTransform(source, corners))
  before = programs_made()
  batch = jaxpso.align(images, templates, np.stack(starts), config=ALIGN, key=2)
  assert programs_made() - before <= 1
  for i, (image, template, start, truth) in enumerate(zip(images, templates, starts, truths)):
    h, w = template.shape
    source = np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])
    mapped = cv2.perspectiveTransform(source[None], np.float64(batch.homography[i]))[0]
    assert np.abs(mapped - truth).max() < 0.5, i
  # Element 0 (the key's own stream) as alone, bit for bit (0.011 px apart
  # under `vmap`, benchmarks/results/invariance.md).
  alone = jaxpso.align(images[0], templates[0], starts[0], config=ALIGN, key=2)
  np.testing.assert_array_equal(batch.homography[0], alone.homography)


def test_one_key_per_element_gives_each_the_result_it_has_alone():
  # The swarm runs for every element (no start is accepted, and the retry
  # follows a poor match), so each result hangs on its element's stream.
  config = dataclasses.replace(ALIGN, accept_quality=None)
  triples = [_triple(seed) for seed in range(3)]
  templates, starts, _ = (np.stack(a) for a in zip(*triples))
  keys = [7, 123, 5]
  for key in (keys, np.array(keys), jax.random.split(jax.random.key(3), 3)):
    batch = jaxpso.align(np.stack([IMAGE] * 3), templates, starts, config=config, key=key)
    for i in range(3):
      alone = jaxpso.align(IMAGE, templates[i], starts[i], config=config, key=key[i])
      assert alone.num_evaluations > config.swarm_size
      np.testing.assert_array_equal(batch.homography[i], alone.homography)
      np.testing.assert_array_equal(batch.num_evaluations[i], alone.num_evaluations)


@pytest.mark.parametrize("call, match", [
    (lambda s: jaxpso.track(s.frames, np.zeros((0, 4))), "at least one region"),
    (lambda s: jaxpso.track(np.stack([s.frames] * 2), np.array([s.roi] * 3), sequences=True),
     "one sequence per region: 3 regions, 2 sequences"),
    (lambda s: jaxpso.track([s.frames, s.frames[:4]], np.array([s.roi] * 2), sequences=True),
     "one length"),
    (lambda s: jaxpso.track(s.frames[0], np.array([s.roi] * 2), sequences=True),
     r"\(R, T, H, W\)"),
    (lambda s: jaxpso.track(s.frames, np.array([s.roi, (150, 0, 48, 48)])), r"roi\[1\]"),
    (lambda s: jaxpso.track(s.frames, np.array([s.roi, (0, 0, 48, 48)]), devices=[]),
     "at least one device"),
    (lambda s: jaxpso.track(s.frames, np.array([s.roi] * 2), devices="cpu"), "jax.Device"),
    (lambda s: jaxpso.track(s.frames, np.array([s.roi] * 2), key=[1, 2, 3]),
     "one per element of the batch: 3 keys for a batch of 2"),
    (lambda s: jaxpso.align(np.stack([IMAGE] * 2), np.stack([IMAGE[:64, :64]] * 2),
                            np.stack([np.eye(3)] * 2), key=np.zeros((3, 2), np.uint32)),
     "3 keys for a batch of 2"),
    (lambda s: jaxpso.align(np.stack([IMAGE] * 2), np.stack([IMAGE[:64, :64]] * 3),
                            np.stack([np.eye(3)] * 2)), "as many images, templates"),
    (lambda s: jaxpso.align(np.stack([IMAGE] * 2), [IMAGE[:64, :64], IMAGE[:64, :60]],
                            np.stack([np.eye(3)] * 2), config=jaxpso.TrackConfig(method="ic",
                                                                               similarity="ssd")),
     "every template of a batch aligned by 'ic'"),
    (lambda s: jaxpso.align(np.stack([IMAGE] * 2), np.stack([IMAGE[:64, :64]] * 2),
                            np.stack([np.eye(3), np.zeros((3, 3))])),
     r"init_homography\[1\] must be finite and invertible"),
])
def test_bad_batches_name_the_problem(call, match):
  with pytest.raises((ValueError, TypeError), match=match):
    call(_sequence(0))


def test_sequences_of_different_lengths_are_refused_before_anything_is_compiled():
  # Known lengths: refused at once (a frame step compiles for 15-25 s).  An
  # iterator's length is unknown: refused where the shorter sequence ends.
  s = _sequence(0)
  before = programs_made()
  with pytest.raises(ValueError, match=r"one length: their lengths are \[6, 4\]"):
    jaxpso.track([s.frames, s.frames[:4]], np.array([s.roi] * 2), sequences=True)
  assert programs_made() == before
  with pytest.raises(ValueError, match="some end after 4 frames"):
    jaxpso.track([s.frames, iter(s.frames[:4])], np.array([s.roi] * 2), sequences=True,
                 config=CONFIG)
