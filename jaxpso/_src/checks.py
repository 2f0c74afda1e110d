"""Input validation shared by the public functions.

Every check runs on static information (shapes, dtypes) or on concrete host
values, so it raises before anything is traced.  Messages name the argument and
the offending shape, dtype or value.

The checks of `align`'s and `track`'s images, templates and start
homographies are here too (`to_gray`, `check_texture`, `check_template_size`,
`check_image_size`, `check_start`), with the limits they enforce
(`MIN_TEXTURE`, `TEMPLATE_SIDES`), so that both entry points refuse the same
inputs with the same messages.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import atlas


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


def to_gray(image, name: str):
  """(H, W) or (H, W, 3) uint8 or float image → (H, W) float32 grey in [0, 1].

  NumPy in, NumPy out (no device work before the compiled call); a JAX array
  stays a JAX array.
  """
  xp = jnp if isinstance(image, jax.Array) else np
  array = image if xp is jnp else np.asarray(image)
  if array.dtype != np.uint8 and not np.issubdtype(array.dtype, np.floating):
    raise TypeError(f"{name} must be uint8 or float, got dtype {array.dtype}")
  if not (array.ndim == 2 or (array.ndim == 3 and array.shape[-1] == 3)):
    raise ValueError(f"{name} must be (H, W) grey or (H, W, 3) colour, got shape {array.shape}")
  grey = array.astype(xp.float32) if xp is jnp else array.astype(np.float32, copy=False)
  if array.dtype == np.uint8:
    grey = grey * xp.float32(1 / 255)
  if grey.ndim == 3:
    grey = grey @ xp.asarray([0.299, 0.587, 0.114], xp.float32)
  if min(grey.shape) < 2:
    raise ValueError(f"{name} must be at least 2×2 pixels, got shape {grey.shape}")
  check_finite_if_concrete(grey, name)
  return grey


# A template whose intensity standard deviation (intensities in [0, 1]) is
# below this is textureless: 2.5 grey levels of 8-bit video, what
# quantisation and sensor noise alone give a flat surface.  Such templates
# (std 0.008) had passed a 1e-3 threshold and then drifted while reported tracked.
MIN_TEXTURE = 0.01


def check_texture(spreads, describe: Callable[[int], str]) -> None:
  """ValueError naming `describe(i)` for the first template whose std in `spreads` (N,) is too low."""
  for i in np.flatnonzero(~(np.asarray(spreads) >= MIN_TEXTURE)):
    raise ValueError(f"{describe(int(i))} is textureless (intensity std {spreads[i]:.2g}"
                     f" < {MIN_TEXTURE}): nothing to align")


# Supported template sides (pixels): the coarsest level needs a few pixels,
# and beyond the largest the template's pyramid would need more levels.
TEMPLATE_SIDES = (8, 4096)


def check_template_size(shape, levels: int, resolution: int | None, name: str) -> None:
  """ValueError naming `name` when a side is outside `TEMPLATE_SIDES`, the coarsest of
  `levels` is under 4 px or `resolution` (`TrackConfig`'s) exceeds its pixels."""
  low, high = TEMPLATE_SIDES
  if not low <= min(shape) or not max(shape) <= high:
    raise ValueError(f"{name} of shape {tuple(shape)} is outside the supported sizes: every side"
                     f" must be {low} to {high} pixels")
  if resolution is not None and resolution > shape[0] * shape[1]:
    raise ValueError(f"TrackConfig.resolution={resolution} is larger than {name} of shape"
                     f" {tuple(shape)} ({shape[0] * shape[1]} pixels)")
  if min(shape) / 2 ** (levels - 1) < 4:
    raise ValueError(
        f"{name} of shape {tuple(shape)} is too small for levels={levels}:"
        " the coarsest level would be under 4 px")


def check_image_size(shape, levels: int, name: str) -> None:
  """ValueError naming `name` when the image's coarsest of `levels` would be under 2×2 pixels."""
  coarsest = atlas.level_shapes(shape, levels)[-1]
  if min(coarsest) < 2:
    raise ValueError(f"levels={levels} is too many for {name} of shape {tuple(shape)}:"
                     " its coarsest level would be smaller than 2×2")


def check_start(start, template_shape, name: str) -> np.ndarray:
  """A validated (3, 3) float64 start homography (ValueError naming `name`)."""
  start = np.asarray(start)
  if not np.issubdtype(start.dtype, np.number) or start.shape != (3, 3):
    raise ValueError(f"{name} must be a (3, 3) real matrix, got {start.dtype}{start.shape}")
  start = start.astype(np.float64)
  problem = _start_problem(start, template_shape)
  if problem is not None:
    raise ValueError(f"{name} must {problem}")
  return start


def is_start(h, template_shape) -> bool:
  """Whether the (3, 3) homography h passes `check_start` for a template of `template_shape`."""
  return _start_problem(np.asarray(h, np.float64), template_shape) is None


def _start_problem(h: np.ndarray, template_shape) -> str | None:
  """What a (3, 3) float64 homography h lacks as a start (after "must"), or None."""
  if not np.all(np.isfinite(h)) or abs(np.linalg.det(h)) < 1e-12:
    return f"be finite and invertible, got {h.tolist()!r}"
  # w of one sign at the corners: the template is not cut by the horizon (-H is H).
  rows, cols = template_shape
  corners = np.array([[0, 0], [cols - 1, 0], [cols - 1, rows - 1], [0, rows - 1]])
  depth = corners @ h[2, :2] + h[2, 2]
  if not (np.all(depth > 0) or np.all(depth < 0)):
    return (f"map every template corner to a finite point (w of one sign), got w ="
            f" {depth.tolist()} for {h.tolist()!r}")
  return None
