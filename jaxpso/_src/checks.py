"""Input validation shared by the public functions.

Every check runs on static information (shapes, dtypes) or on concrete host
values, so it raises before anything is traced.  Messages name the argument and
the offending shape, dtype or value.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np


def as_float_array(value, name: str) -> jax.Array:
  """Returns `value` as a JAX array, refusing non-float and empty inputs.

  Raises:
    TypeError: if the dtype is not floating point.
    ValueError: if the array has a zero-size dimension.
  """
  try:
    array = jnp.asarray(value)
  except TypeError:  # strings, objects: JAX names neither the argument nor the value
    raise TypeError(f"{name} must be a floating-point array, got {value!r}") from None
  if not jnp.issubdtype(array.dtype, jnp.floating):
    raise TypeError(
        f"{name} must be a floating-point array, got dtype {array.dtype}"
        f" with shape {array.shape}")
  if array.size == 0:
    raise ValueError(f"{name} must not be empty, got shape {array.shape}")
  return array


def check_min_rank(array, rank: int, name: str, layout: str) -> None:
  """Raises ValueError unless `array.ndim >= rank`; `layout` describes the shape."""
  if array.ndim < rank:
    raise ValueError(
        f"{name} must have shape {layout}, got shape {array.shape}")


def check_trailing(array, trailing: Sequence[int], name: str, layout: str) -> None:
  """Raises ValueError unless the last dimensions of `array` equal `trailing`."""
  trailing = tuple(trailing)
  if array.ndim < len(trailing) or array.shape[array.ndim - len(trailing):] != trailing:
    raise ValueError(
        f"{name} must have shape {layout}, got shape {array.shape}")


def check_int(value, name: str, minimum: int) -> int:
  """Returns `value` if it is an int (not a bool) >= `minimum`, else raises ValueError."""
  if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
    raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")
  return value


def check_real(value, name: str) -> float:
  """Returns `value` as a float if it is a real number (not a bool), else raises TypeError."""
  if isinstance(value, bool) or not isinstance(value, numbers.Real):
    raise TypeError(f"{name} must be a real number, got {value!r}")
  return float(value)


def check_shape2d(shape, name: str) -> tuple[int, int]:
  """Returns `shape` as a pair of positive ints `(h, w)`, or raises ValueError."""
  try:
    h, w = (int(s) for s in shape)
  except (TypeError, ValueError):
    raise ValueError(f"{name} must be a pair (h, w) of ints, got {shape!r}") from None
  if h < 1 or w < 1 or (h, w) != tuple(shape):
    raise ValueError(f"{name} must be a pair of positive ints (h, w), got {shape!r}")
  return h, w


def check_finite_if_concrete(array, name: str) -> None:
  """Raises ValueError for non-finite entries when `array` holds concrete values.

  Traced values are left alone: inside `jit` the data-dependent failure is
  reported through masks and scores instead.
  """
  if isinstance(array, jax.core.Tracer):
    return
  values = np.asarray(array)
  if not np.all(np.isfinite(values)):
    bad = tuple(int(i) for i in np.argwhere(~np.isfinite(values))[0])  # not np.int64(…) reprs
    raise ValueError(
        f"{name} must be finite, got {values[bad]} at index {bad} of shape {values.shape}")


def as_checked(value, trailing: Sequence[int], name: str, layout: str) -> jax.Array:
  """Returns `value` as a finite float array whose last axes are `trailing`.

  `layout` describes the expected shape for the error message, e.g. "(..., 3, 3)".
  """
  array = as_float_array(value, name)
  check_trailing(array, trailing, name, layout)
  check_finite_if_concrete(array, name)
  return array
