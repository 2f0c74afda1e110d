"""One pyramid level of a gradient baseline's registration, and the methods' solvers.

`_Level` is one level's alignment problem: the image's `atlas.Level`, the
template at that level, the warp of parameters u (D,) to a (3, 3) level
homography, the sampled patch and its gradient, the Jacobian of the warped
points and the composition of the level homography with an increment
(turned back into u through the template's corners, `_corners`).
`_SOLVERS[method]` builds one method's iteration at a level:
`solver(level, u, iterations) → (update, state)`, with
`update(u, state) → (u (D,), state, () evaluations spent)`; the
Gauss–Newton methods ("fa", "fc", "ic", "esm"), the hyperplane predictors
("ha") and optax's Adam and L-BFGS ("adam", "lbfgs") are described in
`jaxpso._src.baselines`.  Shapes: template and patch (h_l, w_l), grid
(h_l·w_l, 2), Jacobians (h_l·w_l, D), corner offsets δ (8,) in pixels of
the level.

Why a module of its own: the update rules are the mathematics of each
method, one level at a time; which method may run on which motion and
similarity, the coarse-to-fine loop over the levels with its stopping rule
and OpenCV's ECC are `jaxpso._src.baselines`, which imports this module
(never the other way round).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxpso._src import atlas
from jaxpso._src import homography
from jaxpso._src import sampling

# Adam's step size at level l is _ADAM_RATE · 2^l units of u (about that
# many level pixels of corner motion per step), decayed exponentially to
# _ADAM_DECAY times that over the level's iterations.
_ADAM_RATE, _ADAM_DECAY = 0.5, 0.01
# Hyperplane approximation: at every level a cascade of predictors trained on
# corner motions uniform in ±r level pixels, r halving from the level's reach
# while it stays >= _HA_FINEST; iteration i applies the i-th (the last from
# then on).  The coarsest level's reach is _HA_RANGE of its template's
# smaller side (the start's error), a finer level's _HA_FINE level pixels
# (what the coarser level leaves: a level pixel there is two here).  The
# sample points keep the reach (plus one pixel) from the template's border,
# at most _HA_POINTS per side; _HA_TRAINING perturbations per sample point;
# ridge term relative to the mean squared intensity difference.  With one
# predictor per level trained on _HA_RANGE = 1/8 of every level's side
# (±12 px of full-resolution motion at each level) the iterations at the
# finer levels wandered by pixels, hence a cascade of predictors
# (benchmarks/README.md, implementation choices; the cascade's figures are in
# benchmarks/results/convergence.md).
_HA_RANGE, _HA_FINE, _HA_FINEST = 0.25, 2.0, 0.5
_HA_POINTS, _HA_TRAINING, _HA_RIDGE = 16, 4, 1e-3

# Generators of sl(3) (Benhimane & Malis, 2004): translations, shears, scalings
# and the two projective terms.
_SL3 = np.array([
    [[0, 0, 1], [0, 0, 0], [0, 0, 0]],
    [[0, 0, 0], [0, 0, 1], [0, 0, 0]],
    [[0, 1, 0], [0, 0, 0], [0, 0, 0]],
    [[0, 0, 0], [1, 0, 0], [0, 0, 0]],
    [[1, 0, 0], [0, -1, 0], [0, 0, 0]],
    [[0, 0, 0], [0, -1, 0], [0, 0, 1]],
    [[0, 0, 0], [0, 0, 0], [1, 0, 0]],
    [[0, 0, 0], [0, 0, 0], [0, 1, 0]],
], np.float32)


def _corners(h, shape) -> jax.Array:
  """(3, 3) homography → (8,) its images of the template's corners TL, TR, BR, BL."""
  mapped, _ = homography.apply_to_points(h, homography.rect_corners(shape))
  return mapped.reshape(8)


class _Level:
  """One pyramid level of a registration: warps, Jacobians, composition.

  Attributes:
    index: the level (0 = full resolution).
    image: the image's `atlas.Level`.
    template: (h_l, w_l) template at this level.
    grid: (h_l·w_l, 2) template pixel centres.
    coarsest: whether the registration starts at this level.
  """

  def __init__(self, index, image: atlas.Level, template, to_h, full_shape, start, loss_at,
               coarsest=False):
    self.index = index
    self.coarsest = coarsest
    self.image = image
    self.template = template
    self.grid = sampling.template_grid(template.shape).reshape(-1, 2)
    self._to_h = to_h
    self._full_shape = full_shape  # the full-resolution template's (h, w)
    self._start = start  # (8,) corners of to_h(0), full resolution
    self._loss_at = loss_at

  def loss(self, u) -> jax.Array:
    """() the registration loss at this level for parameters u (D,)."""
    h = self.h(u)
    return self._loss_at(self.index, h, *self.sample(h))

  def sample(self, h, points=None, shape=None):
    """The image (shape (h_l, w_l) by default) at `points` (the level's grid) mapped by h, and the mask."""
    shape = self.template.shape if shape is None else shape
    patch, mask = self.image.sample(h, self.grid if points is None else points)
    return patch.reshape(shape), mask.reshape(shape)

  def h(self, u) -> jax.Array:
    """(D,) parameters → (3, 3) template → image homography at this level."""
    return homography.homography_to_level(self._to_h(u), self.index)

  def warp(self, h):
    """The image and its gradient at the grid mapped by h: (h_l, w_l) each, and the mask."""
    *sampled, _ = self.image.sample_with_gradient(h, self.grid)
    return tuple(a.reshape(self.template.shape) for a in sampled)

  def point_jacobian(self, h, increment) -> jax.Array:
    """(N, 2, 8) derivative of the points h·increment(δ)·x at δ = 0."""
    def points(delta):
      return homography.apply_to_points(h @ increment(delta), self.grid)[0]
    return jax.jacfwd(points)(jnp.zeros(8, self.grid.dtype))

  def parameters(self, h) -> jax.Array:
    """(8,) parameters u of motion "homography" of a full-resolution homography h (3, 3).

    u are the offsets of the template's corners under h from those under
    to_h(0), which is the homography motion's definition of u.
    """
    return _corners(h, self._full_shape) - self._start

  def compose(self, u, increment) -> jax.Array:
    """(8,) parameters of the level homography h(u)·increment (3, 3) (motion "homography")."""
    return self.parameters(homography.homography_from_level(self.h(u) @ increment, self.index))


def _steepest_descent(gx, gy, point_jacobian) -> jax.Array:
  """(N, D) image gradients (h, w each) times the (N, 2, D) Jacobian of the points."""
  return gx.reshape(-1, 1) * point_jacobian[:, 0] + gy.reshape(-1, 1) * point_jacobian[:, 1]


def _solve(hessian, gradient) -> jax.Array:
  """hessian⁻¹ gradient with a relative Tikhonov term; 0 where that is not finite.

  A flat patch (hessian 0) or one with no valid pixel gives a zero step.
  """
  d = hessian.shape[0]
  ridge = 1e-6 * jnp.trace(hessian) / d + 1e-12
  step = jnp.linalg.solve(hessian + ridge * jnp.eye(d, dtype=hessian.dtype), gradient)
  return jnp.where(jnp.all(jnp.isfinite(step)), step, 0.0)


def _gauss_newton_step(jacobian, residual, mask) -> jax.Array:
  """(D,) step −(JᵀJ)⁻¹Jᵀr over the valid pixels; jacobian (N, D), residual, mask (h, w)."""
  m = mask.reshape(-1).astype(jacobian.dtype)
  weighted = jacobian * m[:, None]
  return -_solve(weighted.T @ jacobian, weighted.T @ residual.reshape(-1))


def _forward_additive(level: _Level, u, iterations):
  """Lucas–Kanade: u ← u + Δu with the Jacobian of the warped points w.r.t. u."""
  del u, iterations

  def points(params):
    return homography.apply_to_points(level.h(params), level.grid)[0]

  def update(u, state):
    values, gx, gy, mask = level.warp(level.h(u))
    jacobian = _steepest_descent(gx, gy, jax.jacfwd(points)(u))
    return u + _gauss_newton_step(jacobian, values - level.template, mask), state, 1

  return update, ()


def _corner_increment(shape):
  """δ (8,) → (3, 3) homography moving the level template's corners by δ pixels (C(0) = I)."""
  return functools.partial(homography.corner_offsets_to_homography, shape=shape)


def _lie_increment(shape):
  """The ESM increment on sl(3), about one pixel of corner motion per unit of δ.

  G(δ) = N⁻¹ exp(Σ δᵢ Aᵢ / s) N with N centring the template's coordinates
  and dividing them by its half-size s, so that a unit of every δᵢ moves the
  template's corners by about one pixel.

  Returns:
    (G, its tangent N⁻¹ (I + Σ δᵢ Aᵢ / s) N, which has G's derivative at δ = 0
    and is cheaper to differentiate), each δ (8,) → (3, 3).
  """
  h, w = shape
  s = max(h - 1, w - 1) / 2.0
  to_unit = np.array([[1 / s, 0, -(w - 1) / (2 * s)], [0, 1 / s, -(h - 1) / (2 * s)], [0, 0, 1]])
  from_unit = jnp.asarray(np.linalg.inv(to_unit), jnp.float32)
  to_unit = jnp.asarray(to_unit, jnp.float32)

  def algebra(delta):
    return jnp.tensordot(delta / s, jnp.asarray(_SL3), axes=1)

  def increment(delta):
    return from_unit @ jax.scipy.linalg.expm(algebra(delta)) @ to_unit

  def tangent(delta):
    return from_unit @ (jnp.eye(3, dtype=delta.dtype) + algebra(delta)) @ to_unit

  return increment, tangent


def _template_gradient(template):
  """Central-difference gradient (h, w) × 2 of a template (one-sided at its border)."""
  _, gx, gy, _ = sampling.sample_with_gradient(sampling.pack_quads(template), template.shape,
                                               jnp.eye(3, dtype=template.dtype),
                                               sampling.template_grid(template.shape))
  return gx, gy


def _forward_compositional(level: _Level, u, iterations):
  """Forward compositional: ∇(I∘W)·∂C/∂δ at δ = 0, H ← H·C(δ), C the corner increment.

  The gradient of the warped image is taken by the chain rule, the image's
  gradient at the warped points times the derivative of the warp.
  """
  del u, iterations
  increment = _corner_increment(level.template.shape)

  def update(u, state):
    h = level.h(u)
    values, gx, gy, mask = level.warp(h)
    jacobian = _steepest_descent(gx, gy, level.point_jacobian(h, increment))
    delta = _gauss_newton_step(jacobian, values - level.template, mask)
    return level.compose(u, increment(delta)), state, 1

  return update, ()


def _inverse_compositional(level: _Level, u, iterations):
  """Inverse compositional: ∇T·∂C/∂δ and its Hessian once, H ← H·C(δ)⁻¹.

  Pixels that leave the frame drop out of the residual only; the Hessian
  stays the precomputed one (a smaller step while part of the template is
  outside, never a singular system).
  """
  del u, iterations
  increment = _corner_increment(level.template.shape)
  jacobian = _steepest_descent(*_template_gradient(level.template),
                               level.point_jacobian(jnp.eye(3, dtype=level.template.dtype),
                                                    increment))
  hessian = jacobian.T @ jacobian

  def update(u, state):
    patch, mask = level.sample(level.h(u))
    residual = jnp.where(mask, patch - level.template, 0.0).reshape(-1)
    delta = _solve(hessian, jacobian.T @ residual)
    return level.compose(u, homography.inverse(increment(delta))), state, 1

  return update, ()


def _esm(level: _Level, u, iterations):
  """ESM: Gauss–Newton with ½(∇T + ∇(I∘W))·∂G/∂δ at δ = 0, H ← H·G(δ), G on sl(3)."""
  del u, iterations
  increment, tangent = _lie_increment(level.template.shape)
  template_jacobian = _steepest_descent(
      *_template_gradient(level.template),
      level.point_jacobian(jnp.eye(3, dtype=level.template.dtype), tangent))

  def update(u, state):
    h = level.h(u)
    values, gx, gy, mask = level.warp(h)
    image_jacobian = _steepest_descent(gx, gy, level.point_jacobian(h, tangent))
    delta = _gauss_newton_step(0.5 * (image_jacobian + template_jacobian),
                               values - level.template, mask)
    return level.compose(u, increment(delta)), state, 1

  return update, ()


def _hyperplane(level: _Level, u, iterations):
  """Jurie–Dhome: δ = Aₖ·(I(W(xₛ)) − T(xₛ)) on sample points xₛ, H ← H·C(δ)⁻¹.

  Aₖ (8 × points, kept transposed) is the ridge least-squares fit of corner
  offsets δ to the intensity differences they cause on the template itself,
  T(C(δ)·xₛ) − T(xₛ), over random δ (fixed PRNG keys) uniform in ±rₖ level
  pixels, rₖ = reach·2⁻ᵏ; iteration k of the level applies Aₖ (the last
  from then on).  δ is in pixels of the level, C the corner increment.
  While some sample points are outside the frame, the predictor is refitted
  on the others (a zero difference at a missing point would read as "no
  motion there" and bias the prediction).
  """
  del u, iterations
  template = level.template
  rows, cols = template.shape
  reach = _HA_RANGE * (min(rows, cols) - 1) if level.coarsest else _HA_FINE
  ranges = [reach]
  while ranges[-1] / 2 >= _HA_FINEST:
    ranges.append(ranges[-1] / 2)
  margin = reach + 1.0
  side = [min(_HA_POINTS, int(n - 1 - 2 * margin) + 1) for n in (rows, cols)]
  # Sample-grid index (j, i) → template point (margin + j·step_x, margin + i·step_y).
  to_points = jnp.asarray(
      [[(cols - 1 - 2 * margin) / max(side[1] - 1, 1), 0, margin],
       [0, (rows - 1 - 2 * margin) / max(side[0] - 1, 1), margin], [0, 0, 1]], template.dtype)
  increment = _corner_increment(template.shape)
  quads = sampling.pack_quads(template)
  reference, _ = sampling.sample_quads(quads, template.shape, to_points, side)
  count = _HA_TRAINING * side[0] * side[1]
  grams, correlations = [], []
  for k, r in enumerate(ranges):
    deltas = jax.random.uniform(jax.random.key(k), (count, 8), template.dtype, -r, r)
    moved, _ = sampling.sample_quads(quads, template.shape, increment(deltas) @ to_points, side)
    differences = (moved - reference).reshape(count, -1)
    grams.append(differences.T @ differences)
    correlations.append(differences.T @ deltas)
  points = side[0] * side[1]
  sample_grid = sampling.template_grid(side).reshape(-1, 2)
  eye = jnp.eye(points, dtype=template.dtype)

  def fit(gram, correlation, valid):
    """(points, 8) Aᵀ from the sample points where valid (points,) is 1; 0 rows elsewhere."""
    ridge = _HA_RIDGE * jnp.trace(gram) / points + 1e-12
    predictor = jnp.linalg.solve(gram * valid[:, None] * valid + ridge * eye,
                                 correlation * valid[:, None])
    return jnp.where(jnp.all(jnp.isfinite(predictor)), predictor, 0.0)

  # One solve per range (not vmapped: a batched solve inside the loop hung XLA's CPU runtime).
  everywhere = jnp.ones(points, template.dtype)
  predictors = jnp.stack([fit(g, c, everywhere) for g, c in zip(grams, correlations)])
  grams, correlations = jnp.stack(grams), jnp.stack(correlations)

  def update(u, k):
    patch, mask = level.sample(level.h(u) @ to_points, sample_grid, side)
    valid = mask.reshape(-1)
    current = jax.lax.cond(jnp.all(valid), lambda: predictors[k],
                           lambda: fit(grams[k], correlations[k], valid.astype(template.dtype)))
    delta = jnp.where(valid, (patch - reference).reshape(-1), 0.0) @ current
    return (level.compose(u, homography.inverse(increment(delta))),
            jnp.minimum(k + 1, len(ranges) - 1), 1)

  return update, jnp.zeros([], jnp.int32)


def _finite(tree):
  """The tree with non-finite entries set to 0."""
  return jax.tree.map(lambda g: jnp.where(jnp.isfinite(g), g, 0.0), tree)


def _adam(level: _Level, u, iterations):
  """optax.adam on the loss, step size _ADAM_RATE · 2^level decaying to _ADAM_DECAY of it."""
  schedule = optax.exponential_decay(_ADAM_RATE * 2.0 ** level.index, iterations, _ADAM_DECAY)
  optimizer = optax.adam(schedule)

  def update(u, state):
    gradient = _finite(jax.grad(level.loss)(u))
    step, state = optimizer.update(gradient, state)
    return u + step, state, 1

  return update, optimizer.init(u)


def _lbfgs(level: _Level, u, iterations):
  """optax.lbfgs with its zoom line search, no learning rate.

  The first direction is the negative gradient, cut to unit length if longer
  (one unit of u, about one full-resolution pixel of corner motion); the
  zoom line search starts every step at 1 and doubles or shrinks it.  Each
  evaluation is one loss and gradient: the line search's, plus the initial
  one (and a fresh one whenever the line search ended on a non-finite loss).
  """
  del iterations
  optimizer = optax.lbfgs()
  value_and_grad = optax.value_and_grad_from_state(level.loss)

  def update(u, state):
    stored = optax.tree.get(state, "value")
    value, gradient = value_and_grad(u, state=state)
    gradient = _finite(gradient)
    step, state = optimizer.update(gradient, state, u, value=value, grad=gradient,
                                   value_fn=level.loss)
    searched = optax.tree.get(state, "num_linesearch_steps")
    return u + step, state, (~jnp.isfinite(stored)).astype(jnp.int32) + searched

  return update, optimizer.init(u)


_SOLVERS = {"fa": _forward_additive, "fc": _forward_compositional, "ic": _inverse_compositional,
            "esm": _esm, "ha": _hyperplane, "adam": _adam, "lbfgs": _lbfgs}
