"""`programs`: jaxpso's programs compiled once, kept in memory (LRU) and on disk across processes."""

import collections
import dataclasses
import functools
import gc
import hashlib
import json
import os
import pickle
import subprocess
import sys
import threading
import warnings
import weakref

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxpso
from jaxpso import pso
from jaxpso._src import programs


@functools.partial(programs.Program, static_argnames=("scale",))
def _affine(x, pair, *, scale=2.0):
  """x (n,), pair (a (n,), b (n,) or None) → a·x·scale (+ b)."""
  a, b = pair
  y = a * x * scale
  return y if b is None else y + b


def _histograms(a, b):  # (R, k, n) × (R, n, k): the batched product shape of MI's histograms
  return jnp.einsum("rkn,rnl->rkl", a, b)


_histograms_program = programs.Program(_histograms)

# A program in its own process: __main__'s file is part of its disk key.
_SCRIPT = """
import functools, json, sys
import jax, jax.numpy as jnp, numpy as np
from jaxpso._src import programs

@functools.partial(programs.Program, static_argnames=("ridge",))
def solve(x, *, ridge):  # LAPACK: its kernels must be bound in a process that only loads
  return jnp.linalg.solve(x @ x.T + ridge * jnp.eye(x.shape[0]), x)

x = np.arange(16, dtype=np.float32).reshape(4, 4) / 16
if len(sys.argv) > 1:  # split over every device
  mesh = jax.sharding.Mesh(np.array(jax.devices()), ("b",))
  x = jax.device_put(x, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("b")))
out = solve(x, ridge=0.5)
print(json.dumps(dict(out=np.asarray(out).tolist(), counts=programs.counts(), devices=len(out.devices()))))
"""


def _data(n=5, seed=0):
  rng = np.random.default_rng(seed)
  return rng.normal(size=n).astype(np.float32), (rng.normal(size=n).astype(np.float32), None)


def _delta(before):
  return {name: value - before[name] for name, value in programs.counts().items()}


def _entries(directory):
  return sorted(directory.glob("*.program")) if directory.exists() else []


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
  """Each test: an empty table of at most 16 programs, the disk cache in tmp_path/"cache" (restored after)."""
  for name in ("_dir_setting", "_dir", "_dir_checked", "_max_programs"):
    monkeypatch.setattr(programs, name, getattr(programs, name))
  programs.clear()
  programs.set_max_programs(programs.MAX_PROGRAMS)
  programs.set_cache_dir(tmp_path / "cache")
  yield tmp_path / "cache"
  programs.clear()


def _run(script, cache_dir, *args, flags=""):
  env = dict(os.environ, JAXPSO_CACHE_DIR=str(cache_dir), XLA_FLAGS=flags)
  result = subprocess.run([sys.executable, str(script), *args], env=env, capture_output=True,
                          text=True, timeout=120, check=False)
  assert result.returncode == 0, result.stderr
  return json.loads(result.stdout.splitlines()[-1])


def test_equals_jax_jit_and_new_data_does_not_compile():
  x, pair = _data()
  reference = jax.jit(_affine.__wrapped__, static_argnames="scale")
  before = programs.counts()
  np.testing.assert_array_equal(_affine(x, pair, scale=3.0), reference(x, pair, scale=3.0))
  assert _delta(before) == dict(compiled=1, loaded=0, reused=0)
  x2, pair2 = _data(seed=1)
  np.testing.assert_array_equal(_affine(x2, pair2, scale=3.0), reference(x2, pair2, scale=3.0))
  assert _delta(before) == dict(compiled=1, loaded=0, reused=1)


def _recorded_options(monkeypatch) -> list:
  """The `compiler_options` of every `Lowered.compile` from now on."""
  given = []
  compile_ = jax.stages.Lowered.compile

  def recorded(self, compiler_options=None):
    given.append(compiler_options)
    return compile_(self, compiler_options=compiler_options)

  monkeypatch.setattr(jax.stages.Lowered, "compile", recorded)
  return given


def test_programs_on_a_cpu_compile_with_the_cpu_options(monkeypatch):
  # LLVM's level 1 ran align's and the frame step's code 8-11 % faster than
  # XLA's default, without YNNPACK's fusions pso.run ran up to 1.4x as fast, and
  # without the MLIR fusion emitters align NCC 1.1-1.3x as fast
  # (benchmarks/README.md, implementation choices).
  for name in programs.CPU_COMPILER_OPTIONS:
    assert programs._known_option(name), name  # the installed XLA takes each
  given = _recorded_options(monkeypatch)
  x, pair = _data(n=11)
  _affine(x, pair, scale=5.0)
  assert given == [programs.CPU_COMPILER_OPTIONS]
  assert programs.CPU_COMPILER_OPTIONS == {"xla_backend_optimization_level": 1,
                                           "xla_cpu_experimental_ynn_fusion_type": "",
                                           "xla_cpu_use_fusion_emitters": False}


def test_an_option_the_installed_xla_does_not_know_is_left_out(monkeypatch):
  monkeypatch.setattr(programs, "CPU_COMPILER_OPTIONS",
                      {**programs.CPU_COMPILER_OPTIONS, "xla_cpu_no_such_option": "1"})
  programs._known_option.cache_clear()
  try:
    given = _recorded_options(monkeypatch)
    x, pair = _data(n=13)
    _affine(x, pair, scale=5.0)
    known = {name: value for name, value in programs.CPU_COMPILER_OPTIONS.items()
             if name != "xla_cpu_no_such_option"}
    assert given[-1] == known and len(given) == len(programs.CPU_COMPILER_OPTIONS) + 1  # probes
  finally:
    programs._known_option.cache_clear()


def test_a_new_shape_static_value_or_structure_compiles_once_each():
  x, pair = _data()
  _affine(x, pair)
  before = programs.counts()
  _affine(x, pair, scale=2.0)  # the default spelled out: the same program
  assert _delta(before)["compiled"] == 0
  _affine(*_data(n=7))
  _affine(*_data(n=7))
  _affine(x, pair, scale=4.0)
  _affine(x, (pair[0], x))  # b given: another pytree structure
  assert _delta(before)["compiled"] == 3


def test_numpy_then_jax_arrays_share_one_program():
  x, (a, _) = _data()
  before = programs.counts()
  first = _affine(x, (a, None))
  second = _affine(jnp.asarray(x), (jax.device_put(a, jax.devices()[0]), None))
  np.testing.assert_array_equal(first, second)
  assert _delta(before) == dict(compiled=1, loaded=0, reused=1)


def test_unknown_keywords_are_a_type_error_naming_them():
  with pytest.raises(TypeError, match="'offset'"):
    _affine(*_data(), offset=1.0)


def test_under_transformations_it_is_traced_like_jax_jit():
  x, (a, _) = _data()
  batched = jax.vmap(lambda x: _affine(x, (a, None)))(np.stack([x, 2 * x]))
  np.testing.assert_allclose(batched, np.stack([2 * a * x, 4 * a * x]), rtol=1e-6)
  np.testing.assert_allclose(jax.jit(lambda x: _affine(x, (a, None)))(x), 2 * a * x, rtol=1e-6)


@pytest.mark.parametrize("setting", [None, "bfloat16", "tensorfloat32"])
def test_matrix_products_are_float32_whatever_the_default_precision(setting):
  """An accelerator's default (TensorFloat-32 on an H100) left homographies 0.5 px off."""
  a = np.ones((2, 4, 4), np.float32)
  with jax.default_matmul_precision(setting):
    text = _histograms_program.compiled(a, a).as_text()
    outer = jax.jit(lambda a: _histograms_program(a, a)).lower(a).as_text()
  dots = [line for line in text.splitlines() if " dot(" in line]
  assert dots and all("operand_precision={highest,highest}" in line for line in dots)
  assert "precision = [HIGHEST, HIGHEST]" in outer and "DEFAULT" not in outer


def test_programs_survive_jax_clear_caches():
  x, pair = _data()
  first = _affine(x, pair)
  jax.clear_caches()
  before = programs.counts()
  np.testing.assert_array_equal(_affine(x, pair), first)
  assert _delta(before) == dict(compiled=0, loaded=0, reused=1)


def test_threads_asking_for_one_new_program_compile_it_once():
  x, pair = _data(n=9)
  start = threading.Barrier(4)
  results = [None] * 4

  def call(i):
    start.wait()
    results[i] = np.asarray(_affine(x, pair))

  before = programs.counts()
  threads = [threading.Thread(target=call, args=(i,)) for i in range(4)]
  for thread in threads:
    thread.start()
  for thread in threads:
    thread.join()
  assert _delta(before) == dict(compiled=1, loaded=0, reused=3)
  for result in results:
    np.testing.assert_array_equal(result, results[0])


@pytest.mark.filterwarnings("ignore:jaxpso. compiled")
def test_evicted_programs_are_released():
  programs.set_cache_dir(None)
  programs.set_max_programs(1)
  x, pair = _data()
  compiled = _affine.compiled(x, pair)
  compiled(x, pair)  # the C++ fast path holds the executable too
  alive = weakref.ref(compiled), weakref.ref(compiled._executable)
  del compiled
  _affine(*_data(n=6))  # evicts the first
  gc.collect()
  assert alive[0]() is None and alive[1]() is None
  before = programs.counts()
  _affine(x, pair)
  assert _delta(before)["compiled"] == 1


def test_a_program_is_loaded_from_disk_once_dropped_from_memory(cache):
  x, pair = _data()
  first = np.asarray(_affine(x, pair))
  assert len(_entries(cache)) == 1
  assert cache.stat().st_mode & 0o777 == 0o700
  programs.clear()
  before = programs.counts()
  np.testing.assert_array_equal(_affine(x, pair), first)
  assert _delta(before) == dict(compiled=0, loaded=1, reused=0)


def test_a_new_process_loads_instead_of_compiling(tmp_path, cache):
  script = tmp_path / "solve.py"
  script.write_text(_SCRIPT)
  first = _run(script, cache)
  assert first["counts"] == dict(compiled=1, loaded=0, reused=0)
  assert len(_entries(cache)) == 1
  second = _run(script, cache)
  assert second["counts"] == dict(compiled=0, loaded=1, reused=0)
  assert second["out"] == first["out"]


def test_a_program_sharded_over_two_devices_stays_in_memory(tmp_path, cache):
  script = tmp_path / "solve.py"
  script.write_text(_SCRIPT)
  result = _run(script, cache, "sharded", flags="--xla_force_host_platform_device_count=2")
  assert result["devices"] == 2 and result["counts"]["compiled"] == 1
  x = np.arange(16, dtype=np.float32).reshape(4, 4) / 16
  np.testing.assert_allclose(result["out"], np.linalg.solve(x @ x.T + 0.5 * np.eye(4), x),
                             rtol=1e-4, atol=1e-5)
  assert not _entries(cache)


def _corrupt(path, how):
  data = path.read_bytes()
  magic, version, digest, payload = data.split(b"\n", 3)
  if how == "truncated":
    path.write_bytes(data[:len(data) // 2])
  elif how == "bad magic":
    path.write_bytes(b"something else\n" + data)
  elif how == "hash mismatch":
    path.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
  else:  # a valid checksum over a payload that does not unpickle or deserialize
    _, in_tree, out_tree = pickle.loads(payload)
    payload = b"not a pickle" if how == "unpickling" else pickle.dumps((b"junk", in_tree, out_tree))
    path.write_bytes(b"\n".join((magic, version, hashlib.sha256(payload).hexdigest().encode(), payload)))


@pytest.mark.parametrize("how", ["truncated", "bad magic", "hash mismatch", "unpickling", "deserialize"])
def test_a_corrupt_entry_is_a_warning_and_compiled_again(cache, how):
  x, pair = _data()
  first = np.asarray(_affine(x, pair))
  entry, = _entries(cache)
  _corrupt(entry, how)
  programs.clear()
  before = programs.counts()
  with pytest.warns(RuntimeWarning, match="unusable cached program"):
    np.testing.assert_array_equal(_affine(x, pair), first)
  assert _delta(before) == dict(compiled=1, loaded=0, reused=0)
  programs.clear()  # rewritten: loads again
  _affine(x, pair)
  assert _delta(before)["loaded"] == 1


def test_a_group_writable_directory_is_refused(cache):
  cache.mkdir(mode=0o700)
  cache.chmod(0o770)
  x, pair = _data()
  with pytest.warns(RuntimeWarning, match="owned by you and not writable by group or others"):
    np.testing.assert_array_equal(_affine(x, pair), 2 * pair[0] * x)
  assert programs.cache_dir() is None and not _entries(cache)


def test_an_unwritable_directory_is_one_warning(cache):
  cache.mkdir(mode=0o500)
  if os.access(cache, os.W_OK):
    pytest.skip("chmod does not stop this user (root) from writing")
  x, pair = _data()
  with pytest.warns(RuntimeWarning, match="cannot write"):
    _affine(x, pair)
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    np.testing.assert_array_equal(_affine(*_data(n=6)), _affine.__wrapped__(*_data(n=6)))


def test_an_uncreatable_directory_is_one_warning(tmp_path):
  (tmp_path / "file").write_text("")
  programs.set_cache_dir(tmp_path / "file" / "cache")
  with pytest.warns(RuntimeWarning, match="cannot create"):
    _affine(*_data())
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    _affine(*_data(n=6))


def test_a_failed_write_is_one_warning_then_no_disk_cache(cache, monkeypatch):
  def refuse(**kwargs):
    raise PermissionError("refused")

  monkeypatch.setattr(programs.tempfile, "mkstemp", refuse)
  x, pair = _data()
  with pytest.warns(RuntimeWarning, match="cannot write"):
    np.testing.assert_array_equal(_affine(x, pair), 2 * pair[0] * x)
  assert programs.cache_dir() is None
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    _affine(*_data(n=6))


def test_none_writes_nothing(cache):
  programs.set_cache_dir(None)
  _affine(*_data())
  assert programs.cache_dir() is None and not cache.exists()


@pytest.mark.parametrize("value", ["off", "OFF", "0", "none", ""])
def test_the_environment_switches_it_off(monkeypatch, value):
  monkeypatch.setenv("JAXPSO_CACHE_DIR", value)
  monkeypatch.setattr(programs, "_dir_setting", programs._UNSET)
  monkeypatch.setattr(programs, "_dir_checked", False)
  assert programs.cache_dir() is None


def test_the_environment_places_it(tmp_path, monkeypatch):
  monkeypatch.setattr(programs, "_dir_setting", programs._UNSET)
  monkeypatch.delenv("JAXPSO_CACHE_DIR", raising=False)
  monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
  monkeypatch.setattr(programs, "_dir_checked", False)
  assert programs.cache_dir() == tmp_path / "xdg" / "jaxpso"
  monkeypatch.setenv("JAXPSO_CACHE_DIR", str(tmp_path / "moved"))
  monkeypatch.setattr(programs, "_dir_checked", False)
  assert programs.cache_dir() == tmp_path / "moved" and (tmp_path / "moved").is_dir()


def test_the_least_recently_used_entries_go_beyond_the_size_bound(cache, monkeypatch):
  _affine(*_data())
  first, = _entries(cache)
  _affine(*_data(n=6))
  second, = set(_entries(cache)) - {first}
  os.utime(first, (1e9 - 10, 1e9 - 10))
  os.utime(second, (1e9, 1e9))
  programs.clear()
  _affine(*_data())  # loaded: `first` is now the most recently used, `second` the least
  monkeypatch.setenv("JAXPSO_CACHE_MAX_BYTES", str(int(2.5 * max(first.stat().st_size,
                                                                    second.stat().st_size))))
  _affine(*_data(n=8))
  remaining = _entries(cache)
  assert len(remaining) == 2 and first in remaining and second not in remaining


@dataclasses.dataclass(frozen=True)
class _Shifted:
  """A loss whose `repr` names no address: its code could change under the same `repr`."""
  shift: float

  def __call__(self, x, args):
    return jnp.sum((x - self.shift) ** 2)


def test_compiling_a_dropped_program_again_is_one_warning(monkeypatch):
  monkeypatch.setattr(programs, "_evicted", collections.OrderedDict())
  monkeypatch.setattr(programs, "_thrash_warned", False)
  programs.set_cache_dir(None)
  programs.set_max_programs(1)
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    _affine(*_data())
    _affine(*_data(n=6))  # drops the first
    assert not caught
    for _ in range(3):  # a loop over two configurations with room for one
      _affine(*_data())
      _affine(*_data(n=6))
  assert len(caught) == 1 and "set_max_programs" in str(caught[0].message)
  assert "_affine" in str(caught[0].message)


@pytest.mark.parametrize("bad", [0, -1, 2.5, True, "16"])
def test_a_bad_bound_is_a_value_error(bad):
  with pytest.raises(ValueError, match="max programs"):
    jaxpso.set_max_programs(bad)


def test_swarm_programs_are_bounded_and_stay_in_memory(cache):
  programs.set_max_programs(2)
  config = pso.PSOConfig(swarm_size=8, max_iterations=5, patience=None)
  loss = _Shifted(0.5)
  before = programs.counts()
  for d in (1, 2, 3):
    pso.run(0, loss, -jnp.ones(d), jnp.ones(d), config=config)
  pso.trace(0, loss, -jnp.ones(1), jnp.ones(1), config=config)
  assert _delta(before)["compiled"] == 4 and len(programs._table) == 2
  result = pso.run(0, loss, -jnp.ones(1), jnp.ones(1), config=config)  # evicted: compiled again
  assert _delta(before)["compiled"] == 5
  assert abs(float(result.x[0]) - 0.5) < 0.5
  assert _entries(cache) == []  # the user's function is not part of a disk key
