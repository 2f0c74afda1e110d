"""Shared test set-up: one compilation cache for the run, and each module's programs dropped after it.

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

