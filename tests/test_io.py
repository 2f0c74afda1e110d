"""Tests of `jaxpso.io`: reading videos and image folders, overlays, result files, plots."""

from __future__ import annotations

import csv
import inspect
import json
from typing import NamedTuple

import cv2
import numpy as np
import pytest

import jaxpso
from jaxpso import io


def _frames(count=5, shape=(48, 64)):
  """Colour RGB uint8 frames, each a different flat colour plus a gradient."""
  frames = []
  for t in range(count):
    frame = np.zeros(shape + (3,), np.uint8)
    frame[..., 0] = 40 * t + 20  # R changes with t
    frame[..., 1] = np.linspace(0, 200, shape[1]).astype(np.uint8)[None, :]
    frame[..., 2] = 30
    frames.append(frame)
  return frames


# --- read_frames / write_video ----------------------------------------------------------------
@pytest.mark.parametrize("name", ["clip.avi", "clip.mp4"])
def test_video_round_trip_keeps_count_size_and_rgb_order(tmp_path, name):
  frames = _frames()
  path = tmp_path / name
  assert io.write_video(path, frames, fps=10) == len(frames)
  read = list(io.read_frames(path))
  assert len(read) == len(frames)
  for original, back in zip(frames, read):
    assert back.shape == original.shape and back.dtype == np.uint8
    # lossy codecs: the mean of each channel survives within a few levels
    np.testing.assert_allclose(back.reshape(-1, 3).mean(0), original.reshape(-1, 3).mean(0),
                               atol=6)
  grey = list(io.read_frames(path, gray=True))
  assert len(grey) == len(frames) and grey[0].shape == frames[0].shape[:2]


def test_folder_is_read_in_natural_name_order_exactly(tmp_path):
  frames = _frames(count=3)
  order = {"f1.png": 0, "f2.png": 1, "f10.png": 2}
  for name, t in order.items():
    cv2.imwrite(str(tmp_path / name), frames[t][..., ::-1])  # OpenCV writes BGR
  (tmp_path / "notes.txt").write_text("not an image")
  (tmp_path / "sub.png").mkdir()  # a folder with an image's name is skipped
  read = list(io.read_frames(str(tmp_path)))
  assert len(read) == 3
  for t in range(3):
    np.testing.assert_array_equal(read[t], frames[t])  # PNG is lossless: exact RGB
  grey = next(io.read_frames(tmp_path, gray=True))
  np.testing.assert_array_equal(grey, cv2.cvtColor(frames[0], cv2.COLOR_RGB2GRAY))


def test_grey_images_come_out_as_three_equal_channels(tmp_path):
  image = np.arange(48 * 64, dtype=np.uint8).reshape(48, 64)
  cv2.imwrite(str(tmp_path / "a.png"), image)
  frame = next(io.read_frames(tmp_path))
  assert frame.shape == (48, 64, 3)
  for channel in range(3):
    np.testing.assert_array_equal(frame[..., channel], image)


def test_missing_path_raises_file_not_found_naming_it(tmp_path):
  missing = tmp_path / "nope.mp4"
  with pytest.raises(FileNotFoundError, match="nope.mp4"):
    io.read_frames(missing)  # raised at the call, not at the first next()


def test_unreadable_sources_raise_value_error_naming_them(tmp_path):
  garbage = tmp_path / "garbage.mp4"
  garbage.write_bytes(b"this is not a video" * 10)
  with pytest.raises(ValueError, match="garbage.mp4"):
    io.read_frames(garbage)
  no_frames = tmp_path / "no_frames.avi"  # a valid container holding no frame
  writer = cv2.VideoWriter(str(no_frames), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
  writer.release()
  with pytest.raises(ValueError, match="no_frames.avi"):
    io.read_frames(no_frames)
  empty = tmp_path / "empty"
  empty.mkdir()
  (empty / "readme.txt").write_text("no images here")
  with pytest.raises(ValueError, match="empty"):
    io.read_frames(empty)
  broken = tmp_path / "broken"
  broken.mkdir()
  (broken / "0.png").write_bytes(b"not a png")
  with pytest.raises(ValueError, match="0.png"):
    io.read_frames(broken)


def test_folder_with_a_bad_later_image_fails_when_reached(tmp_path):
  frames = _frames(count=2)
  cv2.imwrite(str(tmp_path / "0.png"), frames[0])
  cv2.imwrite(str(tmp_path / "1.png"), cv2.resize(frames[1], (32, 24)))
  reader = io.read_frames(tmp_path)
  next(reader)
  with pytest.raises(ValueError, match="1.png"):
    next(reader)


def test_write_video_errors(tmp_path):
  with pytest.raises(ValueError, match=".mkv"):
    io.write_video(tmp_path / "a.mkv", _frames())
  with pytest.raises(ValueError, match="no frames"):
    io.write_video(tmp_path / "a.avi", [])
  with pytest.raises(ValueError, match=r"frames\[1\]"):
    io.write_video(tmp_path / "b.avi", [np.zeros((48, 64, 3), np.uint8),
                                        np.zeros((40, 64, 3), np.uint8)])
  with pytest.raises(OSError, match="missing"):
    io.write_video(tmp_path / "missing" / "a.avi", _frames())
  with pytest.raises(TypeError, match="int64"):
    io.write_video(tmp_path / "c.avi", [np.zeros((48, 64), np.int64)])


# --- draw_overlay -----------------------------------------------------------------------------
_SQUARE = np.array([[20.0, 10.0], [70.0, 10.0], [70.0, 50.0], [20.0, 50.0]])


@pytest.mark.parametrize("status, color", [(0, (0, 200, 0)), (1, (255, 140, 0)),
                                           (2, (230, 0, 0)), (3, (210, 0, 210))])
def test_overlay_colour_follows_status(status, color):
  frame = np.full((64, 96), 0.5, np.float32)
  out = io.draw_overlay(frame, _SQUARE, status)
  assert out.shape == (64, 96, 3) and out.dtype == np.uint8
  assert io.STATUS_COLORS[status] == color
  np.testing.assert_array_equal(out[10, 45], color)  # the middle of the top edge
  np.testing.assert_array_equal(out[50, 45], color)
  np.testing.assert_array_equal(out[30, 45], (128, 128, 128))  # inside: untouched
  np.testing.assert_array_equal(frame, 0.5)  # the input is not modified


def test_overlay_marks_the_top_left_corner_and_copies_colour_frames():
  frame = np.zeros((64, 96, 3), np.uint8)
  out = io.draw_overlay(frame, _SQUARE, 0)
  assert out is not frame and not frame.any()
  np.testing.assert_array_equal(out[12, 22], io.STATUS_COLORS[0])  # inside the TL disc
  np.testing.assert_array_equal(out[47, 67], 0)  # inside the BR corner: no disc


def test_overlay_draws_truth_and_skips_non_finite_corners():
  frame = np.zeros((64, 96), np.uint8)
  truth = _SQUARE + [0.0, 2.0]
  out = io.draw_overlay(frame, np.full((4, 2), np.nan), 2, truth_corners=truth)
  assert out[12, 45, 2] > 0 and out[12, 45, 0] == 0  # thin blue truth, no red
  assert not (out[..., 0] > 0).any()


def test_overlay_rejects_bad_input():
  frame = np.zeros((8, 8), np.uint8)
  with pytest.raises(ValueError, match="status"):
    io.draw_overlay(frame, _SQUARE, 4)
  with pytest.raises(ValueError, match="corners"):
    io.draw_overlay(frame, _SQUARE[:3], 0)
  with pytest.raises(ValueError, match="frame"):
    io.draw_overlay(np.zeros((8, 8, 4), np.uint8), _SQUARE, 0)


# --- write_results / plot_results ---------------------------------------------------------------
class _Result(NamedTuple):
  """The per-frame fields of a `jaxpso.TrackResult`."""
  corners: np.ndarray
  scores: np.ndarray
  quality: np.ndarray
  status: np.ndarray
  num_iterations: np.ndarray
  num_evaluations: np.ndarray


def _result():
  truth = np.stack([_SQUARE + [t, 0.0] for t in range(4)]).astype(np.float32)
  corners = truth.copy()
  corners[1] += [3.0, 4.0]  # every corner 5 px off: error 5, within 5 px
  corners[2] += [6.0, 8.0]  # 10 px off
  result = _Result(corners=corners, scores=np.array([0.9, 0.8, 0.2, 0.7], np.float32),
                   quality=np.array([1.0, 0.9, 0.1, 0.8], np.float32),
                   status=np.array([0, 0, 2, 1], np.int32),
                   num_iterations=np.array([0, 12, 40, 30]),
                   num_evaluations=np.array([0, 384, 1280, 960]))
  return result, truth


def test_status_names_match_the_tracker():
  assert io.STATUS_COLORS and len(io.STATUS_COLORS) == len(jaxpso.TrackStatus)
  from jaxpso._src import results
  assert results.STATUS_NAMES == tuple(s.name for s in sorted(jaxpso.TrackStatus))


def test_results_csv_and_json_with_truth(tmp_path):
  result, truth = _result()
  summary = io.write_results(tmp_path / "out", result, truth_corners=truth)
  assert summary == {"frames": 4, "status_counts": {"TRACKED": 2, "RECOVERED": 1, "LOST": 1,
                                                     "DOUBTFUL": 0},
                     "median_score": pytest.approx(0.75), "within_5px": 0.75,
                     "median_error_px": pytest.approx(2.5), "mean_error_px": pytest.approx(3.75),
                     "max_error_px": pytest.approx(10.0)}
  with open(tmp_path / "out" / "results.csv", newline="") as f:
    rows = list(csv.DictReader(f))
  assert list(rows[0]) == ["frame", "status", "score", "quality", "tl_x", "tl_y", "tr_x", "tr_y",
                           "br_x", "br_y", "bl_x", "bl_y", "error_px", "iterations",
                           "evaluations"]
  assert [r["status"] for r in rows] == ["TRACKED", "TRACKED", "LOST", "RECOVERED"]
  assert [float(r["error_px"]) for r in rows] == pytest.approx([0.0, 5.0, 10.0, 0.0])
  assert float(rows[1]["tl_x"]) == 24.0 and float(rows[1]["bl_y"]) == 54.0
  assert [int(r["evaluations"]) for r in rows] == [0, 384, 1280, 960]
  data = json.loads((tmp_path / "out" / "results.json").read_text())
  assert data["summary"] == json.loads(json.dumps(summary))
  assert len(data["frames"]) == 4
  assert data["frames"][2]["corners"][0] == [28.0, 18.0]
  assert data["frames"][2]["error_px"] == pytest.approx(10.0)
  assert data["frames"][3]["status"] == "RECOVERED"


def test_results_without_truth_and_non_finite_values(tmp_path):
  result, _ = _result()
  result = result._replace(scores=np.array([0.9, np.nan, np.inf, 0.7], np.float32))
  summary = io.write_results(tmp_path, result)
  assert set(summary) == {"frames", "status_counts", "median_score"}
  assert summary["median_score"] == pytest.approx(0.8)
  header = (tmp_path / "results.csv").read_text().splitlines()[0]
  assert "error_px" not in header
  text = (tmp_path / "results.json").read_text()
  assert "NaN" not in text and "Infinity" not in text  # strict JSON: null instead
  assert json.loads(text)["frames"][1]["score"] is None


def test_results_count_and_name_doubtful_frames(tmp_path):
  result, _ = _result()
  summary = io.write_results(tmp_path, result._replace(status=np.array([0, 3, 2, 3], np.int32)))
  assert summary["status_counts"] == {"TRACKED": 1, "RECOVERED": 0, "LOST": 1, "DOUBTFUL": 2}
  rows = list(csv.DictReader(open(tmp_path / "results.csv")))
  assert [r["status"] for r in rows] == ["TRACKED", "DOUBTFUL", "LOST", "DOUBTFUL"]


def test_results_reject_inconsistent_input(tmp_path):
  result, truth = _result()
  with pytest.raises(ValueError, match="truth_corners"):
    io.write_results(tmp_path, result, truth_corners=truth[:3])
  with pytest.raises(ValueError, match="status"):
    io.write_results(tmp_path, result._replace(status=np.array([0, 0, 5, 1])))
  with pytest.raises(TypeError, match="corners"):
    io.write_results(tmp_path, object())


def test_corner_errors_match_the_homography_error():
  result, truth = _result()
  errors = io.corner_errors(result.corners, truth)
  assert errors == pytest.approx([0.0, 5.0, 10.0, 0.0])
  h_true = np.array([[1.0, 0.1, 20.0], [0.0, 1.1, 10.0], [1e-4, 0.0, 1.0]], np.float32)
  h_est = np.array([[1.02, 0.1, 23.0], [0.01, 1.1, 14.0], [0.0, 2e-4, 1.0]], np.float32)
  shape = (40, 50)
  corners = [np.asarray(jaxpso.warp.apply_to_points(h, jaxpso.warp.rect_corners(shape))[0])
             for h in (h_est, h_true)]
  expected = float(jaxpso.warp.corner_error(h_est, h_true, shape))
  assert io.corner_errors(corners[0][None], corners[1][None])[0] == pytest.approx(expected,
                                                                                   rel=1e-5)
  corners = result.corners.copy()
  corners[0, 0, 0] = np.nan
  assert io.corner_errors(corners, truth)[0] == np.inf


def test_plot_results_writes_pngs(tmp_path):
  pytest.importorskip("matplotlib")
  result, truth = _result()
  for name, kwargs in (("errors.png", {"truth_corners": truth}), ("scores.png", {})):
    io.plot_results(tmp_path / name, result, **kwargs)
    assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --- public surface ---------------------------------------------------------------------------
def test_io_surface_is_documented_and_options_are_keyword_only():
  assert io.__doc__ and len(io.__all__) == len(set(io.__all__))
  for name in io.__all__:
    obj = getattr(io, name)
    if inspect.isfunction(obj):
      assert obj.__doc__ and obj.__doc__.strip(), name
      for param in inspect.signature(obj).parameters.values():
        if param.default is not inspect.Parameter.empty:
          assert param.kind is inspect.Parameter.KEYWORD_ONLY, (name, param.name)
