"""Tests of the public surface: `jaxpso`, `jaxpso.warp`, `jaxpso.similarity`, `jaxpso.pso`."""

from __future__ import annotations

import ast
import inspect
import pathlib
import subprocess
import sys
import types

import numpy as np
import pytest

import jaxpso
from jaxpso import data
from jaxpso import pso
from jaxpso import similarity
from jaxpso import synthetic
from jaxpso import warp

_MODULES = (warp, similarity, pso, synthetic, data, jaxpso.io, jaxpso.baselines, jaxpso.datasets)
_SRC = pathlib.Path(jaxpso.__file__).parent / "_src"


def _attribute_docstrings():
  """{name: docstring} of module-level constants documented by a string after them."""
  docs = {}
  for path in sorted(_SRC.glob("*.py")):
    body = ast.parse(path.read_text()).body
    for node, following in zip(body, body[1:]):
      if (isinstance(node, ast.Assign) and isinstance(following, ast.Expr)
          and isinstance(following.value, ast.Constant)
          and isinstance(following.value.value, str)):
        for target in node.targets:
          if isinstance(target, ast.Name):
            docs[target.id] = following.value.value
  return docs


def test_package_surface():
  assert jaxpso.__doc__
  assert set(jaxpso.__all__) == {"METHODS", "AlignResult", "AlignStatus", "TrackConfig",
                                 "TrackResult", "TrackStatus", "align", "baselines", "cache_dir",
                                 "data", "datasets", "detect", "evaluate", "io", "pso",
                                 "set_cache_dir", "set_max_programs", "similarity",
                                 "synthetic", "track", "warp", "__version__"}
  for name in ("AlignResult", "AlignStatus", "TrackConfig", "TrackResult", "TrackStatus",
               "align", "cache_dir", "detect", "set_cache_dir", "set_max_programs", "track"):
    assert getattr(jaxpso, name).__doc__
  assert jaxpso.warp is warp and jaxpso.similarity is similarity and jaxpso.pso is pso
  assert isinstance(jaxpso.__version__, str) and jaxpso.__version__.count(".") >= 1


@pytest.mark.parametrize("module", _MODULES, ids=lambda m: m.__name__)
def test_all_names_exist_and_are_documented(module):
  assert module.__doc__
  assert len(module.__all__) == len(set(module.__all__))
  constant_docs = None
  for name in module.__all__:
    assert hasattr(module, name), name
    obj = getattr(module, name)
    if inspect.isfunction(obj):
      assert obj.__doc__ and obj.__doc__.strip(), name
    elif isinstance(obj, type):
      doc = vars(obj).get("__doc__") or ""
      assert doc.strip(), name
      if hasattr(obj, "_fields"):  # not the docstring namedtuple generates
        assert doc != f"{name}({', '.join(obj._fields)})", name
    else:
      if constant_docs is None:
        constant_docs = _attribute_docstrings()
      assert constant_docs.get(name, "").strip(), f"{name} has no attribute docstring"


@pytest.mark.parametrize("module", _MODULES, ids=lambda m: m.__name__)
def test_all_lists_every_public_name(module):
  public = {name for name, obj in vars(module).items()
            if not name.startswith("_") and not isinstance(obj, types.ModuleType)
            and name != "annotations"}
  assert public == set(module.__all__)


_MEASURES = ("ssd", "ncc", "mi", "nmi", "joint_histogram", "entropy", "soft_bins")
_KEYWORD_ONLY = {
    "ssd": {"min_valid"},
    "ncc": {"min_valid"},
    "mi": {"bins", "value_range", "min_valid"},
    "nmi": {"bins", "value_range", "min_valid"},
    "joint_histogram": {"bins", "value_range"},
    "entropy": {"bins", "value_range"},
    "soft_bins": {"bins", "value_range"},
}


@pytest.mark.parametrize("name", _MEASURES)
def test_similarity_options_are_keyword_only(name):
  params = inspect.signature(getattr(similarity, name)).parameters
  keyword_only = {p.name for p in params.values() if p.kind is inspect.Parameter.KEYWORD_ONLY}
  assert keyword_only == _KEYWORD_ONLY[name]
  positional = [p.name for p in params.values()
                if p.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD]
  if name in ("entropy", "soft_bins"):
    assert positional[0] == "a"
  else:
    assert positional[:2] == ["a", "b"]
  if name != "soft_bins":
    assert "mask" in positional and params["mask"].default is None
  for option in keyword_only:
    assert params[option].default is not inspect.Parameter.empty, option


def test_options_cannot_be_passed_positionally():
  a = np.zeros((4, 4), np.float32)
  with pytest.raises(TypeError):
    similarity.mi(a, a, None, 8)
  with pytest.raises(TypeError):
    similarity.ssd(a, a, None, 0.5)
  with pytest.raises(TypeError):
    similarity.soft_bins(a, 8)


def test_no_public_function_takes_a_histogram_option_positionally():
  for module in _MODULES:
    for name in module.__all__:
      obj = getattr(module, name)
      if not inspect.isfunction(obj):
        continue
      for param in inspect.signature(obj).parameters.values():
        if param.name in ("bins", "value_range", "min_valid"):
          assert param.kind is inspect.Parameter.KEYWORD_ONLY, (module.__name__, name)


@pytest.mark.parametrize("modules", ["jaxpso", "jaxpso.io, jaxpso.cli"])
def test_import_does_not_pull_in_opencv_or_matplotlib(modules):
  root = pathlib.Path(jaxpso.__file__).parent.parent
  code = (f"import {modules}, sys; "
          "assert 'cv2' not in sys.modules and 'matplotlib' not in sys.modules, "
          "sorted(m for m in ('cv2', 'matplotlib') if m in sys.modules)")
  result = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True,
                          text=True, timeout=120, check=False)
  assert result.returncode == 0, result.stderr


def _import_graph():
  """{module: modules of jaxpso it imports}, every import statement counted (also those under
  `if TYPE_CHECKING:` or inside functions)."""
  package = pathlib.Path(jaxpso.__file__).parent
  files = {}
  for path in package.rglob("*.py"):
    parts = path.relative_to(package.parent).with_suffix("").parts
    files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
  graph = {}
  for module, path in files.items():
    here = module if path.name == "__init__.py" else module.rpartition(".")[0]
    targets = set()
    for node in ast.walk(ast.parse(path.read_text())):
      if isinstance(node, ast.Import):
        targets |= {a.name for a in node.names}
      elif isinstance(node, ast.ImportFrom):
        base = node.module or ""
        if node.level:
          base = ".".join(here.split(".")[:len(here.split(".")) - node.level + 1] + [base]).strip(".")
        targets |= {f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names}
    graph[module] = {t for t in targets if t in files and t != module}
  return graph


def _circles(graph):
  """The strongly connected components of more than one module (Tarjan)."""
  index, low, stack, found = {}, {}, [], []

  def visit(node):
    index[node] = low[node] = len(index)
    stack.append(node)
    for target in graph[node]:
      if target not in index:
        visit(target)
        low[node] = min(low[node], low[target])
      elif target in stack:
        low[node] = min(low[node], index[target])
    if low[node] == index[node]:
      component = []
      while not component or component[-1] != node:
        component.append(stack.pop())
      if len(component) > 1:
        found.append(sorted(component))

  for node in sorted(graph):
    if node not in index:
      visit(node)
  return found


def test_import_graph_has_no_circle():
  graph = _import_graph()
  assert len(graph) > 30 and "jaxpso._src.atlas" in graph["jaxpso._src.checks"]
  assert _circles(graph) == []


def test_circle_finder_sees_a_circle():
  assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
