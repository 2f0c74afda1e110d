"""The `jaxpso` command and the README's commands."""

import csv
import json
import pathlib
import re

import numpy as np
import pytest

from jaxpso import cli
from jaxpso import io
from jaxpso import synthetic

ROOT = pathlib.Path(__file__).resolve().parents[1]


# One small tracker config for every tracking test: compiled once per test run.
_FAST = ["--levels", "1"]


def test_demo_tracks_the_synthetic_sequence_and_writes_its_outputs(tmp_path, capsys):
  out = tmp_path / "demo"
  assert cli.main(["demo", "--frames", "12", "--out", str(out), *_FAST]) == 0
  printed = capsys.readouterr().out
  assert sorted(p.name for p in out.iterdir()) == ["errors.png", "overlay.mp4", "results.csv",
                                                   "results.json"]
  within = re.search(r"within 5 px\s+([\d.]+) % of frames", printed)
  assert within and float(within.group(1)) >= 90.0, printed
  assert re.search(r"corner error\s+median [\d.]+ px, max [\d.]+ px", printed), printed
  assert re.search(r"\d+ ms per frame", printed), printed
  summary = json.loads((out / "results.json").read_text())["summary"]
  assert summary["frames"] == 12 and summary["within_5px"] >= 0.9
  assert len((out / "results.csv").read_text().splitlines()) == 1 + 12
  assert len(list(io.read_frames(out / "overlay.mp4"))) == 12


def test_track_a_video_written_from_a_synthetic_sequence(tmp_path, capsys):
  sequence = synthetic.make_sequence(3, num_frames=10, noise=0.01)  # smooth: tests the plumbing
  video = tmp_path / "sequence.avi"
  io.write_video(video, sequence.frames)
  out = tmp_path / "track"
  roi = ",".join(map(str, sequence.roi))
  assert cli.main(["track", str(video), "--roi", roi, "--max-frames", "8", "--out", str(out),
                   *_FAST]) == 0
  printed = capsys.readouterr().out
  assert "frames        8" in printed
  assert sorted(p.name for p in out.iterdir()) == ["overlay.mp4", "results.csv", "results.json",
                                                   "scores.png"]
  with open(out / "results.csv", newline="") as f:
    rows = list(csv.DictReader(f))
  assert len(rows) == 8 and "error_px" not in rows[0]
  columns = ("tl_x", "tl_y", "tr_x", "tr_y", "br_x", "br_y", "bl_x", "bl_y")
  corners = np.array([[float(row[c]) for c in columns] for row in rows]).reshape(8, 4, 2)
  assert np.all(io.corner_errors(corners, sequence.corners[:8]) < 2.0)
  assert len(list(io.read_frames(out / "overlay.mp4"))) == 8


@pytest.mark.parametrize("argv, needle", [
    (["track", "VIDEO", "--roi", "1,2,3", "--out", "OUT"], "--roi"),
    (["track", "VIDEO", "--roi", "a,b,c,d", "--out", "OUT"], "--roi"),
    (["track", "VIDEO", "--roi", "1,2,0,5", "--out", "OUT"], "--roi"),
    (["track", "VIDEO", "--roi", "300,200,100,100", "--out", "OUT", *_FAST], "roi"),
    (["track", "VIDEO", "--roi", "-5,2,20,20", "--out", "OUT", *_FAST], "roi"),
    (["track", "VIDEO", "--roi", "--out", "OUT"], "--roi: expected one argument"),
    (["track", "VIDEO", "--out", "OUT"], "--roi"),
    (["track", "MISSING", "--roi", "1,2,3,4", "--out", "OUT"], "missing.avi"),
    (["demo", "--similarity", "foo"], "--similarity"),
    (["demo", "--frames", "1"], "--frames"),
    (["demo", "--swarm-size", "0"], "swarm_size"),
    (["bogus"], "bogus"),
])
def test_bad_input_is_one_line_and_exit_1(tmp_path, capsys, argv, needle):
  video = tmp_path / "tiny.avi"
  io.write_video(video, np.zeros((3, 48, 64), np.float32))
  argv = [{"VIDEO": str(video), "MISSING": str(tmp_path / "missing.avi"),
           "OUT": str(tmp_path / "out")}.get(a, a) for a in argv]
  assert cli.main(argv) == 1
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and err[0].startswith("jaxpso: error: ") and needle in err[0], err


def test_ci_runs_the_readme_test_command():
  readme = (ROOT / "README.md").read_text()
  commands = re.findall(r"```bash\n(.*?)\n```", readme, re.S)
  assert len(commands) == 2
  ci = (ROOT / ".ci" / "run").read_text()
  assert commands[1] in ci


def test_readme_python_examples_run(capsys):
  readme = (ROOT / "README.md").read_text()
  blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
  assert len(blocks) == 4
  for block in blocks:
    exec(compile(block, "README.md", "exec"), {})
  printed = capsys.readouterr().out
  assert "STAGNATED" in printed or "MAX_ITERATIONS" in printed
  median = float(re.search(r"median corner error ([0-9.]+) px", printed).group(1))
  assert median < 1.0 and "'TRACKED'" in printed
  assert "(3, 10, 4, 2) [0 0 0]" in printed  # the batch: three regions, all TRACKED
