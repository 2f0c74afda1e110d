"""Shared test set-up: each test module's compiled programs are dropped after it.

The whole suite compiles a few hundred XLA programs in one process; kept to
the end, their machine code exhausted LLVM's JIT memory on the 2-core CI
machine (a segmentation fault inside `backend_compile_and_load`, three
quarters through).  Modules share no compiled programs with each other.
"""

import jax
import pytest


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs():
  yield
  jax.clear_caches()
