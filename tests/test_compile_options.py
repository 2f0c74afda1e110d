"""The tracker's compiled programs: `compile_options.jit` equals `jax.jit` and drops YNNPACK dots."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import compile_options


def _histograms(a, b):  # (R, k, n) × (R, n, k): the batched product shape of MI's histograms
  return jnp.einsum("rkn,rnl->rkl", a, b)


def test_jit_equals_jax_jit_and_exposes_the_jitted_function():
  a = jax.random.uniform(jax.random.key(0), (4, 16, 64))
  b = jax.random.uniform(jax.random.key(1), (4, 64, 16))
  wrapped = compile_options.jit(_histograms)
  np.testing.assert_allclose(wrapped(a, b), jax.jit(_histograms)(a, b), rtol=1e-5)
  assert wrapped.__name__ == "_histograms"
  before = wrapped._cache_size()
  wrapped(a + 1.0, b)  # new data, same shapes: no new program
  assert wrapped._cache_size() == before == 1


def test_options_turn_off_ynnpack_fusions_where_supported():
  options = compile_options.options()
  assert options in (None, {"xla_cpu_experimental_ynn_fusion_type": ""})
  a = jnp.zeros((4, 16, 64))
  b = jnp.zeros((4, 64, 16))
  text = compile_options.jit(_histograms).lower(a, b).compile().as_text()
  if options is not None:
    assert "__ynn_fusion" not in text
