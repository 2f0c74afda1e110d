"""`jaxpso.datasets`: the benchmark layouts, their metrics and `evaluate` (resume, bad input)."""

import csv
import json
import math
import os
import shutil

import numpy as np
import pytest

import jaxpso
from jaxpso import cli
from jaxpso import datasets
from jaxpso import synthetic
from jaxpso._src import evaluation

_NAMES = {"pot": ("V01_3", "V02_5", "V03_2"), "ucsb": ("bricks_motion1", "paris_zoom"),
          "planartrack": ("Seq_00001", "Seq_00002"), "tmt": ("nl_bookI_s1", "nl_cerealII_s2"),
          "plain": ("desk", "poster")}
_FRAMES = 8
# One small swarm for every tracking test here: compiled once per test run.
_PSO = ("pso-fast", jaxpso.TrackConfig(levels=2, swarm_size=16, max_iterations=10))


def _truth(seed: int, layout: str):
  """A rendered sequence, its corners with frame 2 not annotated where the layout allows,
  and frame 4 flagged where it has flags."""
  sequence = synthetic.make_sequence(seed, num_frames=_FRAMES, frame_shape=(120, 160),
                                     roi_size=(60, 60))
  corners = sequence.corners.copy()
  excluded = np.zeros(_FRAMES, bool)
  if layout in ("pot", "planartrack", "plain"):
    corners[2] = np.nan
  if layout in ("pot", "planartrack"):
    excluded[4] = True
  return sequence, corners, excluded


def _dataset(root, layout: str, count: int = 2):
  truths = {}
  for seed, name in enumerate(_NAMES[layout][:count]):
    sequence, corners, excluded = _truth(seed, layout)
    datasets.write(root, layout, name, sequence.frames, corners, excluded=excluded,
                   attributes=("occlusion",))
    truths[name] = (sequence, corners, excluded)
  return truths


@pytest.mark.parametrize("layout", datasets.LAYOUTS)
def test_each_layout_round_trips_its_ground_truth_exactly(tmp_path, layout):
  truths = _dataset(tmp_path, layout)
  found = datasets.read(tmp_path, layout)
  assert [s.name for s in found] == sorted(truths)
  for sequence in found:
    rendered, corners, excluded = truths[sequence.name]
    np.testing.assert_array_equal(sequence.corners, corners)  # bit for bit, NaN where missing
    np.testing.assert_array_equal(sequence.excluded, excluded | np.isnan(corners[:, 0, 0]))
    frames = list(sequence.frames())
    assert len(frames) == _FRAMES and frames[0].shape == (120, 160)
    assert np.abs(frames[3].astype(float) - 255 * np.asarray(rendered.frames[3])).max() <= 0.5
    annotated = ~np.isnan(corners[:, 0, 0])
    mapped = np.einsum("tij,kj->tki", sequence.homographies[annotated],
                       np.c_[corners[0], np.ones(4)])
    np.testing.assert_allclose(mapped[..., :2] / mapped[..., 2:], corners[annotated], atol=1e-6)
  expected = {"pot": {"V01_3": ("perspective distortion",), "V02_5": ("occlusion",)},
              "planartrack": {n: ("occlusion",) for n in _NAMES["planartrack"]},
              "plain": {n: ("occlusion",) for n in _NAMES["plain"]},
              "ucsb": {"bricks_motion1": ("motion",), "paris_zoom": ("zoom",)},
              "tmt": {n: () for n in _NAMES["tmt"]}}[layout]
  assert {s.name: s.attributes for s in found} == expected


def test_frames_stream_from_disk(tmp_path):
  _dataset(tmp_path, "plain", count=1)
  frames = datasets.read(tmp_path, "plain")[0].frames()
  assert not isinstance(frames, (list, tuple, np.ndarray))
  first = next(frames)
  assert first.shape == (120, 160) and first.dtype == np.uint8


def test_metrics_match_a_hand_computed_case():
  truth = np.array([[[0, 0], [10, 0], [10, 10], [0, 10]]] * 3, float)
  estimate = truth + np.array([[0, 0], [3, 4], [6, 8]], float)[:, None, :]
  np.testing.assert_allclose(datasets.alignment_errors(truth, estimate), [0, 5, 10])
  one_corner = truth.copy()
  one_corner[0, 2] += [2, 0]  # √(2² / 4) = 1
  np.testing.assert_allclose(datasets.alignment_errors(truth[:1], one_corner[:1]), [1])
  # H_true = I, H_est a shift by (t, 0): H_true pinv(H_est) moves every point by −t.
  shifts = [0.0, 3.0, 25.0]
  estimated = np.stack([np.array([[1, 0, t], [0, 1, 0], [0, 0, 1]], float) for t in shifts])
  np.testing.assert_allclose(
      datasets.homography_discrepancies(np.stack([np.eye(3)] * 3), estimated), shifts)
  # H_est = 2·I: H_true pinv(H_est) halves (±1, ±1), √0.5 from each corner.
  doubled = np.diag([2.0, 2.0, 1.0])[None]
  np.testing.assert_allclose(datasets.homography_discrepancies(np.eye(3)[None], doubled),
                             [math.sqrt(0.5)])
  errors = [0.0, 1.0, 5.0, 5.5, math.inf]
  np.testing.assert_allclose(datasets.curve(errors, [0, 1, 5, 20]), [0.2, 0.4, 0.6, 0.8])
  sequence = datasets.Sequence("s", "", truth, np.stack([np.eye(3)] * 3),
                               np.array([True, False, False]), (), "")
  np.testing.assert_array_equal(datasets.used_frames(sequence), [False, False, True])


def test_method_names():
  assert datasets.method("pso").name == "pso-mi"
  assert datasets.method("pso:ncc").config.similarity == "ncc"
  assert datasets.method("ic").name == "ic-ssd" and datasets.method("ecc").name == "ecc-ncc"
  assert datasets.method("sift").config is None
  with pytest.raises(ValueError, match="unknown method 'orb'"):
    datasets.method("orb")
  with pytest.raises(ValueError, match="ic"):
    datasets.method("ic:mi")


def _table(out) -> list:
  """summary.csv without its timing column."""
  with open(os.path.join(out, "summary.csv")) as handle:
    return [{k: v for k, v in row.items() if k != "ms_per_frame"} for row in csv.DictReader(handle)]


def test_a_resumed_run_runs_only_what_is_left_and_gives_the_same_table(tmp_path, monkeypatch):
  _dataset(tmp_path / "data", "pot", count=3)
  methods = [_PSO, "sift"]
  whole = jaxpso.evaluate(tmp_path / "data", "pot", methods, tmp_path / "whole", progress=False)
  assert (whole.ran, whole.resumed) == (6, 0)
  row = next(r for r in whole.rows if r["method"] == "pso-fast" and r["attribute"] == "all")
  # 8 frames less the initial, the unannotated and the flagged one: 5 scored per sequence.
  assert row["sequences"] == 3 and row["frames"] == 15 and row["precision"] == 1.0
  assert {r["attribute"] for r in whole.rows} == {"all", "perspective distortion", "occlusion",
                                                  "rotation"}

  real, calls = evaluation._run, []

  def interrupted(entry, sequence, key):
    calls.append((sequence.name, entry.name))
    if len(calls) == 4:
      raise KeyboardInterrupt
    return real(entry, sequence, key)

  monkeypatch.setattr(evaluation, "_run", interrupted)
  with pytest.raises(KeyboardInterrupt):
    jaxpso.evaluate(tmp_path / "data", "pot", methods, tmp_path / "part", progress=False)
  assert not (tmp_path / "part" / "summary.csv").exists()
  calls.clear()
  monkeypatch.setattr(evaluation, "_run", real)
  resumed = jaxpso.evaluate(tmp_path / "data", "pot", methods, tmp_path / "part",
                            progress=False)
  assert (resumed.ran, resumed.resumed) == (3, 3)
  assert _table(tmp_path / "part") == _table(tmp_path / "whole")
  again = jaxpso.evaluate(tmp_path / "data", "pot", methods, tmp_path / "part", progress=False)
  assert (again.ran, again.resumed) == (0, 6)

  results = tmp_path / "whole" / "results" / "pso-fast"
  assert sorted(os.listdir(results)) == sorted(
      f"{n}_pso-fast{s}.txt" for n in ("V01_3", "V02_5", "V03_2") for s in ("", "_homography"))
  points = np.loadtxt(results / "V01_3_pso-fast.txt")
  assert points.shape == (_FRAMES, 8)
  record = json.loads((tmp_path / "whole" / "errors" / "pso-fast" / "V01_3.json").read_text())
  assert record["alignment_error"][0] is None and record["alignment_error"][2] is None
  assert max(e for e in record["alignment_error"] if e is not None) < 1.0
  assert {"precision.png", "success.png", "summary.md"} <= set(os.listdir(tmp_path / "whole"))


def test_the_command_evaluates_a_dataset(tmp_path, capsys):
  _dataset(tmp_path / "data", "tmt")
  out = tmp_path / "out"
  assert cli.main(["evaluate", str(tmp_path / "data"), "--format", "tmt", "--methods", "sift",
                   "--out", str(out)]) == 0
  printed = capsys.readouterr()
  assert "| sift | all | 2 | 14 | 1.000 |" in printed.out
  assert "[2/2] nl_cerealII_s2 sift" in printed.err and "ETA" in printed.err
  assert sorted(os.listdir(out / "results" / "sift")) == ["nl_bookI_s1.txt", "nl_cerealII_s2.txt"]
  assert (out / "results" / "sift" / "nl_bookI_s1.txt").read_text().startswith("frame ulx")


def test_the_command_passes_tracker_options_and_seed_to_every_tracker(tmp_path, capsys):
  _dataset(tmp_path / "data", "tmt", count=1)
  out = tmp_path / "out"
  assert cli.main(["evaluate", str(tmp_path / "data"), "--format", "tmt", "--methods", "pso,sift",
                   "--out", str(out), "--levels", "2", "--swarm-size", "16",
                   "--max-iterations", "10", "--seed", "3"]) == 0
  record = json.loads((out / "errors" / "pso-mi" / "nl_bookI_s1.json").read_text())
  assert "swarm_size=16" in record["config"] and record["config"].endswith("key=3")
  assert json.loads((out / "errors" / "sift" / "nl_bookI_s1.json").read_text())["config"] == (
      "None, key=3")
  capsys.readouterr()
  assert "give each method's as NAME:SIMILARITY" in _error(
      capsys, str(tmp_path / "data"), "--format", "tmt", "--out", str(out), "--similarity", "ncc")
  assert "another configuration of pso-mi" in _error(
      capsys, str(tmp_path / "data"), "--format", "tmt", "--out", str(out), "--methods", "pso",
      "--levels", "2", "--swarm-size", "16", "--max-iterations", "10")  # seed 0 now


def _error(capsys, *argv) -> str:
  assert cli.main(["evaluate", *argv]) == 1
  return capsys.readouterr().err


def test_bad_datasets_and_methods_are_named(tmp_path, capsys):
  data = tmp_path / "data"
  _dataset(data, "plain", count=1)
  out = str(tmp_path / "out")
  assert "is not in the pot layout" in _error(capsys, str(data), "--format", "pot", "--out", out)
  assert "sequences is empty" in str(pytest.raises(ValueError, jaxpso.evaluate, data, "plain",
                                                  "sift", out, sequences=[]).value)
  assert "unknown method 'nope'" in _error(capsys, str(data), "--format", "plain", "--out", out,
                                           "--methods", "sift,nope")
  assert not os.path.exists(out)
  path = data / "desk" / "corners.csv"
  lines = path.read_text().splitlines()
  path.write_text("\n".join(lines[:4] + [lines[4].rsplit(",", 1)[0]] + lines[5:]) + "\n")
  assert f"{path}, line 5: expected 8 values, got 7" in _error(
      capsys, str(data), "--format", "plain", "--out", out)
  path.write_text("\n".join(lines[:4] + [lines[4].replace(lines[4].split(",")[2], "x7")]
                            + lines[5:]) + "\n")
  assert f"{path}, line 5: 'x7' is not a number" in _error(
      capsys, str(data), "--format", "plain", "--out", out)
  path.write_text("\n".join(lines[:-2]) + "\n")
  assert f"{path}: 6 lines, but" in _error(capsys, str(data), "--format", "plain", "--out", out)
  assert not os.path.exists(out)


def test_an_unreadable_video_is_named(tmp_path):
  sequence, corners, _ = _truth(0, "plain")
  frames = datasets.write(tmp_path, "plain", "clip", sequence.frames, corners)
  folder = tmp_path / "clip"
  shutil.rmtree(frames)
  (folder / "clip.mp4").write_bytes(b"not a video")
  with pytest.raises(ValueError, match="clip.mp4"):
    datasets.read(folder, "plain")


def test_an_out_folder_of_another_dataset_is_left_alone(tmp_path):
  _dataset(tmp_path / "a", "ucsb", count=1)
  _dataset(tmp_path / "b", "ucsb", count=1)
  jaxpso.evaluate(tmp_path / "a", "ucsb", "sift", tmp_path / "out", progress=False)
  before = {p: p.read_bytes() for p in (tmp_path / "out").rglob("*") if p.is_file()}
  with pytest.raises(ValueError, match="holds the evaluation of"):
    jaxpso.evaluate(tmp_path / "b", "ucsb", "sift", tmp_path / "out", progress=False)
  with pytest.raises(ValueError, match="another configuration of pso-fast"):
    os.makedirs(tmp_path / "out" / "errors" / "pso-fast")
    name = "bricks_motion1.json"
    (tmp_path / "out" / "errors" / "pso-fast" / name).write_text(json.dumps({"config": "x"}))
    jaxpso.evaluate(tmp_path / "a", "ucsb", [_PSO], tmp_path / "out", progress=False)
  after = {p: p.read_bytes() for p in before}
  assert after == before
