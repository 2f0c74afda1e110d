"""Shared test set-up: one compilation cache for the run, each module's programs dropped after it,
and the longest modules collected first.

The suite's compiled programs go to a cache directory of its own (unless
`JAXPSO_CACHE_DIR` names one), so that a module compiling a program another
module already compiled loads it instead, and the user's cache is left
alone.  JAX's own compiled functions are dropped after each module: kept to
the end of a few hundred, their machine code once exhausted LLVM's JIT
memory on the 2-core CI machine.
"""

import os
import tempfile

os.environ.setdefault("JAXPSO_CACHE_DIR", tempfile.mkdtemp(prefix="jaxpso-tests-"))

import jax  # noqa: E402
import pytest  # noqa: E402

from jaxpso._src import programs  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs():
  yield
  jax.clear_caches()
  programs.clear()


# The longest modules, first: xdist hands whole modules to its two workers in
# collection order (`--no-loadscope-reorder`; by default it puts the modules
# with most tests first, and the sharding test, one test running a 2.5 min
# subprocess, came last and kept one worker busy 2.3 min after the other had
# finished, 13 min 21 s in all on 2026-11-29).  Measured per module on that
# run: track 298 s, align 228 s, batch 163 s, sharding 147 s.  A worker takes
# its next module once at most 2 of its tests are left, so the first worker
# runs track then align (the `align` programs they share compile once, then
# load from the disk cache), the second sharding, batch and the short modules.
_LONGEST_FIRST = ("tests/test_track.py", "tests/test_sharding.py", "tests/test_batch.py",
                  "tests/test_align.py")


def pytest_collection_modifyitems(items):
  def rank(item):
    module = item.nodeid.split("::")[0]
    return _LONGEST_FIRST.index(module) if module in _LONGEST_FIRST else len(_LONGEST_FIRST)

  items.sort(key=rank)  # stable: the other modules keep their order
