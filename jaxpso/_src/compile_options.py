"""XLA compiler options of the tracker's compiled programs, and `jit` that applies them.

XLA's CPU backend hands dot products to YNNPACK fusions by default (jaxlib
0.10).  The tracker's dots are batches of small products (the soft joint
histograms of MI, (bins, h·w) × (h·w, bins) per region or particle, and
Gauss–Newton's Gram matrices), and there the YNNPACK fusions ran several
times slower than XLA's own code: one (64, 16, 2304) × (64, 2304, 16)
histogram product inside the 64-region frame step took 18 ms per call in a
profile, against 1.5 ms for the same product compiled alone.  With them
off (benchmarks/batch.py's regions, 40 frames, one run): one region 2.71 →
2.04 ms per frame, 64 regions 1.54 → 1.42 ms per region-frame; no change
measured for `align` (30 alignments at σ = 8 px: medians 1.7–2.5 ms either
way).  The option is set per compiled
program (`jax.jit(compiler_options=...)`), so a user's other programs keep
XLA's defaults.  It is an XLA:CPU option (not tried on a GPU backend; a
backend or jaxlib that rejects it compiles without it, `options`).
"""

from __future__ import annotations

import functools

import jax

_NO_YNN = {"xla_cpu_experimental_ynn_fusion_type": ""}


@functools.cache
def options() -> dict | None:
  """The compiler options of `jit`: YNNPACK fusions off where this jaxlib knows the option, else None."""
  try:
    jax.jit(lambda x: x + 1, compiler_options=_NO_YNN).lower(0.0).compile()
  except Exception:  # an older or newer jaxlib without the option: XLA's defaults
    return None
  return _NO_YNN


class jit:  # noqa: N801 (used like jax.jit)
  """`jax.jit(fun, **kwargs)` with `options()`, decided at the first call (not at import).

  Attribute access (`lower`, `_cache_size`, ...) goes to the jitted function.
  """

  def __init__(self, fun, **kwargs):
    self._fun, self._kwargs, self._jitted = fun, kwargs, None
    functools.update_wrapper(self, fun)

  def _get(self):
    if self._jitted is None:
      self._jitted = jax.jit(self._fun, compiler_options=options(), **self._kwargs)
    return self._jitted

  def __call__(self, *args, **kwargs):
    return self._get()(*args, **kwargs)

  def __getattr__(self, name):
    if name.startswith("__"):
      raise AttributeError(name)
    return getattr(self._get(), name)
