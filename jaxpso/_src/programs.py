"""jaxpso's compiled programs: compiled ahead of time once, kept in memory and on disk.

`Program` is `jax.jit` for jaxpso's own programs.  A call looks its
arguments' signature up in a bounded, least recently used table of
`jax.stages.Compiled` programs (`set_max_programs`); on a miss it loads the
program from the disk cache or traces, lowers and compiles it, then writes it
there.  The disk key is computed without tracing (the program's name, the
static arguments' `repr`, the arguments' pytree structure and types, the JAX
and XLA versions and settings, the backend and CPU, the source of jaxpso), so
a later process skips tracing, lowering and XLA altogether (`align`'s
program, 2.7–3.1 MiB: 11–25 s to compile on the 2-core machine, 0.35–0.6 s
to load).  No global JAX setting is touched: a user's other programs keep
JAX's own caches.

Disk cache (`set_cache_dir`, `cache_dir`): `$JAXPSO_CACHE_DIR`, else
`$XDG_CACHE_HOME/jaxpso` or `~/.cache/jaxpso`; `JAXPSO_CACHE_DIR=off` (or
"0", "none", "") switches it off.  Entries are machine code that is
executed, so a directory not owned by the user or writable by group or
others is refused; each entry carries the SHA-256 of its payload, and a
corrupt one is a warning, removed and compiled afresh.  The least recently
used entries go once the entries exceed `$JAXPSO_CACHE_MAX_BYTES` (2 GiB).
Only programs on the default device are written: a program sharded over
several devices, taking a static argument whose `repr` is an address (a
function), defined inside a function or made with `stored=False` (`pso.run`'s,
whose loss is the user's function) stays in memory only.

Matrix products are traced in float32 (`MATMUL_PRECISION`), never in an
accelerator's faster TensorFloat-32 or bfloat16 passes.  Compiler options:
`CPU_COMPILER_OPTIONS` on a CPU, XLA's defaults elsewhere.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import hashlib
import inspect
import os
import pathlib
import pickle
import platform
import re
import tempfile
import threading
import warnings

import jax
import jaxlib
import numpy as np
from jax._src.lax import linalg
from jax.experimental import serialize_executable

MATMUL_PRECISION = "float32"
"""Every matrix product of jaxpso's programs, whatever `jax_default_matmul_precision` says.

An accelerator's default may round a float32 product's operands to
TensorFloat-32 (10 mantissa bits): a homography then maps 500 px
coordinates 0.5 px off, and a Gauss–Newton system loses its last digits.
"""

CPU_COMPILER_OPTIONS = {"xla_backend_optimization_level": 1,
                        "xla_cpu_experimental_ynn_fusion_type": "",
                        "xla_cpu_use_fusion_emitters": False}
"""XLA options of jaxpso's programs on a CPU: LLVM's level 1 (XLA's default is 2), no YNNPACK
fusions (XLA's default hands some dots, element-wise and reduction fusions to YNNPACK), and
fusions emitted as LLVM IR directly rather than through XLA:CPU's MLIR fusion emitters.

Their code ran 8–11 % faster at level 1, and compiled no slower; without YNNPACK's fusions
`pso.run` on 4 096 particles ran 1.4× as fast and `align` MI in 0.90–0.98× the time; without
the fusion emitters everything compiled in 0.58–0.68× the time, `align` NCC ran in 0.76–0.91×
the time, MI 0.93–1.04×, `track` one region 0.73–1.04×, but 64 regions 1.14–1.24×
(benchmarks/README.md, implementation choices).  An option the installed XLA does not know is
left out (`_compiler_options`).
"""

MAX_PROGRAMS = 16
"""Default bound of the in-memory table (`set_max_programs`)."""

MAX_CACHE_BYTES = 2 * 1024**3
"""Default bound of the disk cache's entries, in bytes (`$JAXPSO_CACHE_MAX_BYTES` overrides it)."""

_CONFIG = ("jax_enable_x64", "jax_default_matmul_precision", "jax_numpy_dtype_promotion",
           "jax_default_prng_impl", "jax_threefry_partitionable", "jax_default_device")
_OFF = ("off", "0", "none", "")
_FORMAT = b"1"
_MAGIC = b"jaxpso compiled program"
_SUFFIX = ".program"
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")
_UNSET = object()

_lock = threading.Lock()
_table: collections.OrderedDict = collections.OrderedDict()  # key → jax.stages.Compiled, oldest first
_pending: dict = {}  # key → the lock of the thread compiling or loading it
_counts = {"compiled": 0, "loaded": 0, "reused": 0}
_max_programs: int | None = MAX_PROGRAMS
_EVICTED_KEPT = 4096
_evicted: collections.OrderedDict = collections.OrderedDict()  # hashes of dropped keys, oldest first
_thrash_warned = False
_dir_setting = _UNSET  # set_cache_dir's path or None; _UNSET: the environment's, read at first use
_dir: pathlib.Path | None = None  # the checked directory, None when off
_dir_checked = False


class Program:
  """`jax.jit(fun, static_argnames=...)` whose programs are compiled once and kept in memory and on disk.

  Dynamic arguments are positional pytrees (leaves: arrays, scalars; None is
  an empty subtree); static ones are keyword-only, hashable and with a
  `repr` that is the same in every process (frozen dataclasses).  Under a
  JAX transformation (tracer arguments) the call is `jax.jit`'s, traced into
  the enclosing computation.

  Args:
    fun: the function.
    static_argnames: the names of `fun`'s static keyword arguments.
    stored: whether its programs may go to the disk cache; False where a
      static argument is a user's function, whose `repr` need not change
      when its code does.
  """

  def __init__(self, fun, *, static_argnames: tuple[str, ...] | str = (), stored: bool = True):
    self._fun = fun
    self._stored = stored
    self._static = (static_argnames,) if isinstance(static_argnames, str) else tuple(static_argnames)
    self._static_set = frozenset(self._static)
    parameters = inspect.signature(fun).parameters
    self._defaults = {name: parameters[name].default for name in self._static
                      if name in parameters and parameters[name].default is not inspect.Parameter.empty}
    self._jitted = None
    self._source = _UNSET
    functools.update_wrapper(self, fun)

  def __call__(self, *args, **static):
    """`fun(*args, **static)`, run by the compiled program for these argument types."""
    compiled = self._program(args, static)
    if compiled is None:
      return self._traced()(*args, **static)
    return compiled(*args)

  def compiled(self, *args, **static) -> jax.stages.Compiled:
    """The program for these arguments: from memory, from the disk cache or compiled now."""
    compiled = self._program(args, static)
    if compiled is None:
      raise TypeError(f"{self.__qualname__}: no compiled program for traced arguments")
    return compiled

  def _program(self, args, static) -> jax.stages.Compiled | None:
    """The program of `fun(*args, **static)`; None for traced arguments."""
    unknown = static.keys() - self._static_set
    if unknown:
      raise TypeError(f"{self.__qualname__}() got unexpected keyword arguments {sorted(unknown)}; "
                      f"its static arguments are {list(self._static)}")
    static = {**self._defaults, **static}
    leaves, treedef = jax.tree.flatten(args)
    config = tuple(getattr(jax.config, name) for name in _CONFIG)
    default = _default_sharding(config[-1])
    types = []
    for index, leaf in enumerate(leaves):
      if isinstance(leaf, (np.ndarray, np.generic)):
        types.append((leaf.shape, leaf.dtype, False, None))
      elif isinstance(leaf, jax.core.Tracer):
        return None
      elif isinstance(leaf, jax.Array):  # typed PRNG keys have no weak_type
        placement = leaf.sharding
        types.append((leaf.shape, leaf.dtype, getattr(leaf, "weak_type", False),
                      None if placement == default else placement))
      else:  # Python scalars
        try:
          aval = jax.typeof(leaf)
        except TypeError:
          raise TypeError(self._not_an_array(args, index)) from None
        types.append((aval.shape, aval.dtype, aval.weak_type, None))
    key = (self, tuple(sorted(static.items())), treedef, tuple(types), config)
    with _lock:
      compiled = _reuse(key)
      if compiled is not None:
        return compiled
      pending = _pending.setdefault(key, threading.Lock())
    with pending:  # one thread compiles or loads a key, the others wait for it
      try:
        with _lock:
          compiled = _reuse(key)
        if compiled is None:
          compiled = self._load_or_compile(key, args, static, default)
          with _lock:
            _table[key] = compiled
            _evict()
      finally:
        with _lock:
          _pending.pop(key, None)
    return compiled

  def _not_an_array(self, args, index: int) -> str:
    """The message for leaf `index` of `args`, which is neither an array nor a scalar."""
    path, leaf = jax.tree_util.tree_flatten_with_path(args)[0][index]
    names = list(inspect.signature(self._fun).parameters)
    name = names[path[0].idx] + jax.tree_util.keystr(path[1:])
    return (f"{self.__qualname__}: argument {name} must be an array or a scalar, got {leaf!r}"
            f" of type {type(leaf)}")

  def _load_or_compile(self, key, args, static, default):
    """A missing program: loaded from the disk cache, else compiled (and written there)."""
    path = self._path(key, default)
    if path is not None:
      compiled = _load(path, jax.tree.structure((args, {})), default)
      if compiled is not None:
        _count("loaded")
        return compiled
    _warn_if_evicted(key)
    program = _in_float32(self._fun)  # new per compilation: JAX's caches keyed weakly on it let go with it
    compiled = jax.jit(program, static_argnames=self._static).lower(*args, **static).compile(
        compiler_options=_compiler_options(key[3], default))
    _count("compiled")
    if path is not None:
      _store(path, compiled)
    return compiled

  def _path(self, key, default) -> pathlib.Path | None:
    """The disk cache's file of `key`; None when the program stays in memory."""
    _, static, treedef, types, config = key
    statics = repr(static)
    if (not self._stored or any(placement is not None for *_, placement in types)
        or _ADDRESS.search(statics)
        or "<" in self.__qualname__ or self._source_hash() is None):
      return None
    directory = _directory()
    if directory is None:
      return None
    text = "\n".join((
        f"program {self.__module__}.{self.__qualname__} {self._source_hash()}",
        f"static {statics}", f"tree {treedef}",
        "types " + " ".join(f"{dtype}{list(shape)}{'~' * weak}" for shape, dtype, weak, _ in types),
        f"config {config!r} {default!r}", _environment()))
    name = re.sub(r"[^A-Za-z0-9_]", "_", self.__qualname__)[:64]
    return directory / f"{name}-{hashlib.sha256(text.encode()).hexdigest()}{_SUFFIX}"

  def _source_hash(self) -> str | None:
    """"jaxpso" for jaxpso's programs (hashed in `_environment`), else the SHA-256 of `fun`'s file or None."""
    if self._source is _UNSET:
      if self.__module__.split(".")[0] == "jaxpso":
        self._source = "jaxpso"
      else:
        try:
          self._source = hashlib.sha256(pathlib.Path(inspect.getfile(self._fun)).read_bytes()).hexdigest()
        except (OSError, TypeError):
          self._source = None
    return self._source

  def _traced(self):
    """`jax.jit(fun)` for calls inside a transformation (compiler options are for top-level programs)."""
    if self._jitted is None:
      self._jitted = jax.jit(_in_float32(self._fun), static_argnames=self._static)
    return self._jitted


def _in_float32(fun):
  """`fun` traced with its matrix products in `MATMUL_PRECISION` (a new function each call)."""
  @functools.wraps(fun)
  def program(*args, **static):
    with jax.default_matmul_precision(MATMUL_PRECISION):
      return fun(*args, **static)

  return program


def _reuse(key):
  """The table's program of `key` (now the most recently used) or None; under `_lock`."""
  compiled = _table.get(key)
  if compiled is not None:
    _table.move_to_end(key)
    _counts["reused"] += 1
  return compiled


def _evict():
  """Drops the least recently used programs beyond the bound, remembering their keys' hashes;
  under `_lock`."""
  while _max_programs is not None and len(_table) > _max_programs:
    key, _ = _table.popitem(last=False)
    _evicted[hash(key)] = None
    while len(_evicted) > _EVICTED_KEPT:
      _evicted.popitem(last=False)


def _warn_if_evicted(key):
  """One warning per process where a program dropped from the table is compiled again."""
  global _thrash_warned
  with _lock:
    again = hash(key) in _evicted and not _thrash_warned
    _thrash_warned = _thrash_warned or again
  if again:
    _warn(f"compiled {key[0].__qualname__} again after dropping it from the table of the"
          f" {_max_programs} programs last used: a loop over more configurations than that compiles"
          " on every call; raise the bound with jaxpso.set_max_programs(n)")


def _count(name):
  with _lock:
    _counts[name] += 1


def counts() -> dict[str, int]:
  """Programs since the process started: `compiled` (traced and compiled here), `loaded` (from
  disk) and `reused` (from memory); differences of two calls tell whether a call compiled."""
  with _lock:
    return dict(_counts)


def clear():
  """Drops every program from memory (the disk cache stays)."""
  with _lock:
    _table.clear()


def set_max_programs(n: int | None):
  """Bounds the compiled programs kept in memory (jaxpso's and `pso.run`'s) to `n` (default
  `MAX_PROGRAMS`; None: no bound), dropping the least recently used.

  Each holds about 100 memory mappings and 5 MiB on a CPU
  (benchmarks/results/program_memory.md); Linux stops a process at
  `vm.max_map_count` (65 530) mappings.
  """
  global _max_programs
  if n is not None and (isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1):
    raise ValueError(f"max programs must be a positive int or None, got {n!r}")
  with _lock:
    _max_programs = n
    _evict()


def set_cache_dir(path: str | os.PathLike | None):
  """Moves jaxpso's cache of compiled programs on disk, overriding `$JAXPSO_CACHE_DIR`.

  A new process then loads a program it has seen before instead of compiling
  it again (tens of seconds per new shape for `track`).  The directory is
  created (mode 0o700) at first use; one not owned by you or writable by
  group or others is refused with a warning (it holds machine code).

  Args:
    path: the directory; None switches the disk cache off.
  """
  global _dir_setting, _dir_checked
  with _lock:
    _dir_setting = None if path is None else pathlib.Path(path).expanduser()
    _dir_checked = False


def cache_dir() -> pathlib.Path | None:
  """The directory of jaxpso's compiled programs on disk (created if needed); None when it is off.

  By default `$JAXPSO_CACHE_DIR`, else `$XDG_CACHE_HOME/jaxpso` or
  `~/.cache/jaxpso`; `JAXPSO_CACHE_DIR=off` switches it off, and so does a
  directory that was refused or could not be written.  `set_cache_dir`
  moves it.
  """
  return _directory()


def _directory() -> pathlib.Path | None:
  """The checked cache directory or None; checked once per setting."""
  global _dir, _dir_checked
  with _lock:
    if not _dir_checked:
      setting = _dir_setting if _dir_setting is not _UNSET else _from_environment()
      _dir, _dir_checked = _checked(setting), True
    return _dir


def _from_environment() -> pathlib.Path | None:
  value = os.environ.get("JAXPSO_CACHE_DIR")
  if value is None:
    base = os.environ.get("XDG_CACHE_HOME")
    return (pathlib.Path(base) if base and os.path.isabs(base) else pathlib.Path.home() / ".cache") / "jaxpso"
  return None if value.strip().lower() in _OFF else pathlib.Path(value).expanduser()


def _checked(path: pathlib.Path | None) -> pathlib.Path | None:
  """`path` created (0o700) if missing; None, with a warning, if it cannot be created or trusted."""
  if path is None:
    return None
  try:
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    stat = path.stat()
  except OSError as error:
    return _warn(f"cannot create the compilation cache {path} ({error}); compiling without it")
  if os.name == "posix" and (stat.st_uid != os.getuid() or stat.st_mode & 0o022):
    return _warn(f"not using the compilation cache {path}: it holds machine code to execute, so it must be "
                 "owned by you and not writable by group or others; compiling without it")
  if not os.access(path, os.W_OK | os.X_OK):
    return _warn(f"cannot write to the compilation cache {path}; compiling without it")
  return path


def _warn(message):
  warnings.warn(f"jaxpso: {message}", RuntimeWarning, stacklevel=2)


def _load(path: pathlib.Path, in_tree, placement) -> jax.stages.Compiled | None:
  """The program in `path` on `placement`'s device; None if absent or (warned, removed) unusable."""
  try:
    data = path.read_bytes()
  except FileNotFoundError:
    return None
  except OSError as error:
    _warn(f"cannot read the cached program {path} ({error}); compiling it")
    return None
  try:
    magic, version, digest, payload = data.split(b"\n", 3)
    if magic != _MAGIC or version != _FORMAT or digest != hashlib.sha256(payload).hexdigest().encode():
      raise ValueError("bad header or checksum")
    serialized, stored_tree, out_tree = pickle.loads(payload)
    if stored_tree != in_tree:
      raise ValueError("another argument structure")
    # LAPACK's kernels are bound at lowering, which a loaded program skips: an unbound one
    # crashes the process (jaxlib 0.10; `jax.export` binds them the same way).
    linalg.initialize_lapack()
    device, = placement.device_set
    compiled = serialize_executable.deserialize_and_load(serialized, stored_tree, out_tree,
                                                         backend=device.client, execution_devices=[device])
  except Exception as error:  # truncated, corrupt or from an incompatible build
    _warn(f"removing the unusable cached program {path} ({type(error).__name__}: {error}); compiling it")
    with contextlib.suppress(OSError):
      path.unlink()
    return None
  with contextlib.suppress(OSError):
    os.utime(path)  # recently used: kept longest by `_trim`
  return compiled


def _store(path: pathlib.Path, compiled: jax.stages.Compiled):
  """Writes `compiled` to `path` atomically if it runs on one device and can be serialized."""
  global _dir
  shardings = jax.tree.leaves((compiled.input_shardings, compiled.output_shardings))
  if any(len(sharding.device_set) > 1 for sharding in shardings):
    return
  try:
    serialized, in_tree, out_tree = serialize_executable.serialize(compiled)
    payload = pickle.dumps((serialized, in_tree, out_tree), protocol=pickle.HIGHEST_PROTOCOL)
  except Exception:  # e.g. a program with constants JAX cannot serialize: kept in memory only
    return
  header = b"\n".join((_MAGIC, _FORMAT, hashlib.sha256(payload).hexdigest().encode(), b""))
  try:
    descriptor, temporary = tempfile.mkstemp(dir=path.parent, prefix=".", suffix=".tmp")
    try:
      with os.fdopen(descriptor, "wb") as file:
        file.write(header + payload)
      os.replace(temporary, path)
    except BaseException:
      with contextlib.suppress(OSError):
        os.unlink(temporary)
      raise
    _trim(path.parent)
  except OSError as error:
    with _lock:
      _dir = None
    _warn(f"cannot write to the compilation cache {path.parent} ({error}); compiling without it")


def _trim(directory: pathlib.Path):
  """Removes the least recently used entries until they take at most `$JAXPSO_CACHE_MAX_BYTES`."""
  try:
    limit = int(os.environ.get("JAXPSO_CACHE_MAX_BYTES", MAX_CACHE_BYTES))
  except ValueError:
    limit = MAX_CACHE_BYTES
  entries = []
  with os.scandir(directory) as scan:
    for entry in scan:
      with contextlib.suppress(OSError):  # another process may be trimming too
        if entry.name.endswith(_SUFFIX) and entry.is_file(follow_symlinks=False):
          stat = entry.stat(follow_symlinks=False)
          entries.append((stat.st_mtime, stat.st_size, entry.path))
  total = sum(size for _, size, _ in entries)
  for _, size, name in sorted(entries):
    if total <= limit:
      break
    with contextlib.suppress(OSError):
      os.unlink(name)
    total -= size


def _compiler_options(types, default) -> dict:
  """`CPU_COMPILER_OPTIONS` the installed XLA knows, for a program whose arguments all live on
  CPU devices; else none."""
  shardings = [default] + [placement for *_, placement in types if placement is not None]
  platforms = {device.platform for sharding in shardings for device in sharding.device_set}
  if platforms != {"cpu"}:
    return {}
  return {name: value for name, value in CPU_COMPILER_OPTIONS.items() if _known_option(name)}


@functools.cache
def _known_option(name: str) -> bool:
  """Whether XLA takes the compile option `name` (an older one refuses a newer option's name)."""
  lowered = jax.jit(lambda x: x + 1).lower(np.float32(0))
  try:
    lowered.compile(compiler_options={name: CPU_COMPILER_OPTIONS[name]})
  except Exception as error:  # XlaRuntimeError or JaxRuntimeError, by JAX's version
    if "No such compile option" in str(error):
      return False
    raise
  return True


@functools.cache
def _default_sharding(default_device) -> jax.sharding.SingleDeviceSharding:
  """Where JAX puts a NumPy argument, given `jax_default_device`."""
  if isinstance(default_device, str):
    default_device = jax.local_devices(backend=default_device)[0]
  return jax.sharding.SingleDeviceSharding(default_device or jax.local_devices()[0])


@functools.cache
def _environment() -> str:
  """What else decides the compiled code: versions, backend, CPU, XLA flags and options, jaxpso's source."""
  device = jax.devices()[0]
  cpu = ""
  if device.platform == "cpu":
    try:
      flags = next(line for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines()
                   if line.startswith("flags"))
      cpu = hashlib.sha256(flags.encode()).hexdigest()
    except (OSError, StopIteration):
      cpu = f"{platform.machine()} {platform.processor()}"
  package = pathlib.Path(__file__).resolve().parent.parent
  source = hashlib.sha256()
  for file in sorted(package.rglob("*.py")):
    source.update(f"{file.relative_to(package)}\0".encode() + file.read_bytes() + b"\0")
  return "\n".join((
      f"format {_FORMAT.decode()} jax {jax.__version__} jaxlib {jaxlib.__version__}",
      f"backend {device.client.platform} {device.client.platform_version} {device.device_kind} "
      f"{jax.device_count()} devices {jax.process_count()} processes",
      f"cpu {cpu}", f"XLA_FLAGS {os.environ.get('XLA_FLAGS', '')}",
      f"jaxpso {source.hexdigest()}"))
