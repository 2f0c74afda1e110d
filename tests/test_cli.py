"""The `jaxpso` command and the README's commands."""

import pathlib
import re

from jaxpso import cli

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_demo_finds_the_shift_with_mi_only(tmp_path, capsys):
  assert cli.main(["demo", "--radius", "8", "--out", str(tmp_path)]) == 0
  lines = capsys.readouterr().out.splitlines()
  errors = {line.split()[0]: float(line.split()[-2]) for line in lines
            if line.split() and line.split()[0] in ("ssd", "ncc", "mi")}
  assert errors["mi"] == 0.0
  assert errors["ssd"] > 2.0 and errors["ncc"] > 2.0
  rows = (tmp_path / "surfaces.csv").read_text().splitlines()
  assert rows[0] == "dx,dy,ssd,ncc,mi" and len(rows) == 1 + 17 * 17


def test_bad_option_is_one_line_and_nonzero(capsys):
  assert cli.main(["demo", "--radius", "0"]) == 1
  err = capsys.readouterr().err.strip().splitlines()
  assert len(err) == 1 and "--radius" in err[0]


def test_ci_runs_the_readme_test_command():
  readme = (ROOT / "README.md").read_text()
  commands = re.findall(r"```bash\n(.*?)\n```", readme, re.S)
  assert len(commands) == 2
  ci = (ROOT / ".ci" / "run").read_text()
  assert commands[1] in ci


def test_readme_python_examples_run(capsys):
  readme = (ROOT / "README.md").read_text()
  blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
  assert len(blocks) == 2
  for block in blocks:
    exec(compile(block, "README.md", "exec"), {})
  printed = capsys.readouterr().out
  assert "STAGNATED" in printed or "MAX_ITERATIONS" in printed
