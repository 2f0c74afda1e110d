"""The notebooks in notebooks/ run top to bottom without an exception.

No Jupyter needed: each .ipynb is read as JSON and its code cells are
executed in order in one fresh namespace, with matplotlib's Agg backend and
the working directory a temporary folder.  Compilation dominates: each
notebook takes up to about a minute on a 2-core CPU.
"""

import json
import pathlib

import pytest

NOTEBOOKS = pathlib.Path(__file__).resolve().parent.parent / "notebooks"
EXPECTED = ("01_quickstart.ipynb", "02_similarity_surfaces.ipynb", "03_pso_variants.ipynb",
            "04_versus_gradient_methods.ipynb")
FOUND = sorted(path.name for path in NOTEBOOKS.glob("*.ipynb"))


def code_cells(path: pathlib.Path) -> list[str]:
  """The source of every code cell of a notebook, in order."""
  notebook = json.loads(path.read_text(encoding="utf-8"))
  assert notebook["nbformat"] == 4, f"{path.name}: nbformat {notebook['nbformat']}, expected 4"
  return ["".join(cell["source"]) for cell in notebook["cells"] if cell["cell_type"] == "code"]


def test_the_notebooks_are_there():
  assert set(EXPECTED) <= set(FOUND), f"missing: {sorted(set(EXPECTED) - set(FOUND))}"


@pytest.mark.parametrize("name", FOUND)
def test_committed_without_outputs_or_magics(name):
  notebook = json.loads((NOTEBOOKS / name).read_text(encoding="utf-8"))
  for cell in notebook["cells"]:
    if cell["cell_type"] == "code":
      assert cell["outputs"] == [] and cell["execution_count"] is None, f"{name}: outputs"
      lines = "".join(cell["source"]).splitlines()
      assert not any(line.lstrip().startswith(("%", "!")) for line in lines), f"{name}: magic"


@pytest.mark.slow
@pytest.mark.parametrize("name", FOUND)
def test_runs(name, tmp_path, monkeypatch):
  matplotlib = pytest.importorskip("matplotlib")
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt

  monkeypatch.chdir(tmp_path)
  namespace = {"__name__": "__main__"}
  try:
    for index, source in enumerate(code_cells(NOTEBOOKS / name)):
      exec(compile(source, f"{name}[cell {index}]", "exec"), namespace)
  finally:
    plt.close("all")
