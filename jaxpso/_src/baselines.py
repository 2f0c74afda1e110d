"""Classic gradient-based image alignment, the baselines the swarm is compared with.

`register(method, ...)` aligns a template coarse to fine from u = 0 (the
start) with one of

* "fa": Lucas–Kanade forward additive, Gauss–Newton on the motion
  parameters u themselves (any motion model);
* "fc": forward compositional (Baker & Matthews, 2004): the Jacobian of an
  incremental warp at the identity times the gradient of the warped image,
  H ← H·ΔH;
* "ic": inverse compositional (Baker & Matthews, 2004): the template's
  gradient, steepest-descent images and Hessian computed once per level,
  H ← H·ΔH⁻¹;
* "esm": efficient second-order minimisation (Benhimane & Malis, 2004): the
  mean of the template's and the warped image's gradients, with the increment
  on the Lie algebra sl(3), H ← H·exp(A(δ));
* "ha": hyperplane approximation (Jurie & Dhome, 2002): linear predictors
  from intensity differences to corner offsets, learned per level from random
  perturbations of the template itself over ranges that halve from one
  iteration to the next, H ← H·ΔH⁻¹;
* "adam", "lbfgs": optax's Adam and L-BFGS (zoom line search) on the
  registration loss itself, differentiated through the bilinear sampling and,
  for "mi", the soft-binned histogram;
* "ecc": OpenCV's `findTransformECC` (Evangelidis & Psarakis, 2008) through a
  host callback.

The Gauss–Newton methods minimise the sum of squared differences over the
pixels that land in the frame (the others are masked out).  A method aligns
on the pyramid levels whose template is large enough for it
(`pyramid_levels`), coarsest first, and iterates a `lax.while_loop` per
level, at most `iterations` times,
stopping once an update moves no parameter by more than 1/1000 of a level
pixel.  The compositional methods compose level homographies and convert the
result back to u through the template's corners, so all of them hand on the
same u as the swarm does.

This module holds the method table (`METHODS`, `SUPPORTED`), the levels a
method aligns on, the coarse-to-fine driver (`register`) and OpenCV's ECC;
one level's problem and each method's update rule are in
`jaxpso._src.gradient_solvers`, which knows nothing of the levels' order,
the stopping rule or the method checks.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import atlas
from jaxpso._src import problem as problems
from jaxpso._src.gradient_solvers import _SOLVERS
from jaxpso._src.gradient_solvers import _Level
from jaxpso._src.gradient_solvers import _corners

METHODS = ("pso", "fa", "fc", "ic", "esm", "ha", "adam", "lbfgs", "ecc")
"""Names of the alignment methods; every one but "pso" is in this module."""

_ANY_MOTION = ("homography", "plane")
_HOMOGRAPHY = ("homography",)
SUPPORTED = {
    "fa": (_ANY_MOTION, ("ssd",)),
    "fc": (_HOMOGRAPHY, ("ssd",)),
    "ic": (_HOMOGRAPHY, ("ssd",)),
    "esm": (_HOMOGRAPHY, ("ssd",)),
    "ha": (_HOMOGRAPHY, ("ssd",)),
    "adam": (_ANY_MOTION, ("mi", "ncc", "ssd")),
    "lbfgs": (_ANY_MOTION, ("mi", "ncc", "ssd")),
    "ecc": (_HOMOGRAPHY, ("ncc",)),
}
"""method → (motions, similarities) it supports, for every method but "pso"."""

# A level stops once an update moves no parameter by more than this many
# pixels of that level.
_TOLERANCE = 1e-3
# The coarsest level a method aligns on keeps at least this many template
# pixels on its smaller side (_MIN_SIDE[method], else _MIN_SIDE_DEFAULT);
# coarser levels of `levels` are skipped.  A template's pyramid is decimated
# at its own phase and the image's is interpolated between samples 2^l
# apart, so at a coarse level the two differ along every sharp edge and the
# level's SSD optimum moves: on a 25 px level of a 100 px template one
# Gauss–Newton step from the true warp went 5–9 px (full resolution) away.
# Forward methods recover on the finer levels, IC (whose steps use the
# template's gradient, not the image's) drifts away instead, so IC's coarsest
# level keeps a larger side (benchmarks/README.md, implementation choices).
_MIN_SIDE = {"ic": 64}
_MIN_SIDE_DEFAULT = 20


def check_supported(method: str, motion: str, similarity: str) -> None:
  """Raises ValueError unless `method` can align with `motion` and `similarity`.

  "pso" supports every motion and similarity.

  Args:
    method: one of `METHODS`.
    motion: motion model name ("homography" or "plane").
    similarity: similarity name ("mi", "ncc" or "ssd").
  """
  if method not in METHODS:
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")
  if method == "pso":
    return
  motions, similarities = SUPPORTED[method]
  if motion not in motions or similarity not in similarities:
    raise ValueError(
        f"method {method!r} supports motions {motions} and similarities {similarities},"
        f" got motion {motion!r} and similarity {similarity!r}")


def pyramid_levels(method: str, shape, levels: int) -> int:
  """How many of `levels` pyramid levels `method` aligns a template of `shape` on.

  The finest ones down to the last whose template keeps at least
  `_MIN_SIDE` pixels on its smaller side (the full resolution always);
  "ecc" works at full resolution only.

  Args:
    method: one of `SUPPORTED`.
    shape: the full-resolution template's (h, w).
    levels: the pyramid's levels (`TrackConfig.levels`).
  """
  if method == "ecc":
    return 1
  side, used = min(shape), 1
  while used < levels:
    side = (side + 1) // 2  # the size `sampling.pyr_down` gives
    if side < _MIN_SIDE.get(method, _MIN_SIDE_DEFAULT):
      break
    used += 1
  return used


def template_pyramids(templates_: list, levels: int) -> list:
  """The baselines' dense template levels: `levels` arrays (N, h_l, w_l) of equally shaped templates."""
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  pyramids = []
  for t in templates_:
    pyramid = [np.ascontiguousarray(t, np.float32)]
    for _ in range(levels - 1):
      pyramid.append(cv2.pyrDown(pyramid[-1]))
    pyramids.append(pyramid)
  return [np.stack(level) for level in zip(*pyramids)]


def _iterate(update, u, state, iterations: int, tolerance: float):
  """Runs u, state ← update(u, state) until `iterations` or a change below `tolerance`.

  A non-finite update is discarded and ends the loop.

  Returns:
    ((D,) u, () int32 iterations, () int32 evaluations).
  """
  def body(carry):
    count, u, state, _, evaluations = carry
    new_u, state, spent = update(u, state)
    new_u = jnp.where(jnp.all(jnp.isfinite(new_u)), new_u, u)
    return count + 1, new_u, state, jnp.max(jnp.abs(new_u - u)), evaluations + spent

  def running(carry):
    count, _, _, change, _ = carry
    return (count < iterations) & (change >= tolerance)

  zero = jnp.zeros([], jnp.int32)
  carry = (zero, u, state, jnp.asarray(jnp.inf, u.dtype), zero)
  count, u, _, _, evaluations = jax.lax.while_loop(running, body, carry)
  return u, count, evaluations


def register(method: str, image: atlas.Atlas, template_pyramid: list, to_h, dim: int,
             loss_at, *, similarity: str, levels: int, iterations: int):
  """Coarse-to-fine gradient alignment from u = 0, traceable inside `jax.jit`.

  Static: method, similarity, levels, iterations, the template's shape.

  Args:
    method: one of `SUPPORTED`.
    image: the image's pyramid (`atlas.Atlas`, unbatched), at least `levels` levels.
    template_pyramid: `levels` (h_l, w_l) template levels (the template's
      Gaussian pyramid).
    to_h: u (dim,) → (3, 3) template → image homography at full resolution.
    dim: number of motion parameters: 8 is motion "homography", fewer
      "plane" (which only "fa", "adam" and "lbfgs" support).
    loss_at: (level, h (3, 3) level homography, patch (h_l, w_l), mask)
      → the loss to minimise at that level (+inf where the warp is not
      admissible).
    similarity: the similarity `loss_at` measures (checked against `SUPPORTED`).
    levels: number of pyramid levels; `pyramid_levels` of them are aligned,
      the coarsest first.
    iterations: iterations at most per level ("ecc" works at full
      resolution only: its iteration cap).

  Returns:
    ((dim,) u, () loss_at(0, …) at u, () int32 iterations summed over the
    levels, () int32 evaluations: image warps or loss evaluations, line
    searches' included, and the final loss).
  """
  if method not in SUPPORTED:
    raise ValueError(f"register takes a method of {tuple(SUPPORTED)}, got {method!r}")
  check_supported(method, "homography" if dim == 8 else "plane", similarity)
  full_shape = template_pyramid[0].shape
  start = to_h(jnp.zeros(dim, jnp.float32))
  start_corners = _corners(start, full_shape)
  finest = _Level(0, atlas.level(image, 0), template_pyramid[0], to_h, full_shape,
                  start_corners, loss_at)
  if method == "ecc":
    u, count = _register_ecc(image, finest, start, iterations)
    return u, finest.loss(u), count, count
  u = jnp.zeros(dim, jnp.float32)
  total_iterations = total_evaluations = jnp.zeros([], jnp.int32)
  used = pyramid_levels(method, full_shape, levels)
  for index in reversed(range(used)):
    level = _Level(index, atlas.level(image, index), template_pyramid[index], to_h,
                   full_shape, start_corners, loss_at, coarsest=index == used - 1)
    update, state = _SOLVERS[method](level, u, iterations)
    u, count, evaluations = _iterate(update, u, state, iterations, _TOLERANCE * 2.0 ** index)
    total_iterations += count
    total_evaluations += evaluations
  return u, finest.loss(u), total_iterations, total_evaluations + 1


def _register_ecc(image: atlas.Atlas, finest: _Level, start, iterations: int):
  """`ecc` as a host callback on the full-resolution image and template → (u (8,), count)."""
  shapes = (jax.ShapeDtypeStruct((3, 3), jnp.float32), jax.ShapeDtypeStruct((), jnp.bool_),
            jax.ShapeDtypeStruct((), jnp.int32))
  h, _, count = jax.pure_callback(
      functools.partial(_ecc_host, iterations=iterations), shapes, image.pixels, image.levels[0],
      finest.template, problems.normalized(start), vmap_method="sequential")
  return finest.parameters(h), count


def _ecc_host(pixels, geometry, template, start, *, iterations: int):
  """`ecc` of the atlas's full-resolution level, with the callback's result types.

  The arguments may arrive as JAX arrays: iterating one would dispatch a JAX
  computation from inside the running program's callback, which deadlocked
  `track` with `method="ecc"` (benchmarks/sequence.py, 150 frames), so each
  is read into NumPy first.
  """
  offset, width, height = (int(v) for v in np.asarray(geometry))
  image = np.asarray(pixels)[offset:offset + width * height].reshape(height, width)
  h, converged, count = ecc(image, template, start, iterations=iterations)
  return h, np.bool_(converged), np.int32(count)


def ecc(image, template, init_homography, *, iterations: int = 100, eps: float = 1e-6,
        gauss_filt_size: int = 5):
  """OpenCV's enhanced-correlation-coefficient alignment on host arrays.

  `cv2.findTransformECC(template, image, init_homography, MOTION_HOMOGRAPHY,
  (COUNT | EPS, iterations, eps), None, gauss_filt_size)`.  OpenCV does not
  report how many iterations it ran; `iterations` is returned in their place.

  Args:
    image: (H, W) float32 image.
    template: (h, w) float32 template.
    init_homography: (3, 3) template → image start.
    iterations: iteration cap.  eps: stop once the update's norm is below it.
    gauss_filt_size: Gaussian blur applied by OpenCV first.

  Returns:
    ((3, 3) float32 homography with h[2, 2] = 1, whether OpenCV finished
    without an error, the iteration cap).  When OpenCV raises (it did not
    converge) or returns a non-finite matrix: the start, False.
  """
  import cv2  # lazily: `import jaxpso` stays free of OpenCV

  start = np.array(init_homography, np.float32)
  criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(iterations), float(eps))
  try:
    _, h = cv2.findTransformECC(np.ascontiguousarray(template, np.float32),
                                np.ascontiguousarray(image, np.float32), start.copy(),
                                cv2.MOTION_HOMOGRAPHY, criteria, None, int(gauss_filt_size))
  except cv2.error:
    h = None
  converged = h is not None and bool(np.all(np.isfinite(h)))
  h = np.asarray(h if converged else start, np.float32)
  return (h / h[2, 2]).astype(np.float32), converged, int(iterations)
