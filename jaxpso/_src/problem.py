"""One template's registration in one image: its loss, Gauss–Newton, the swarm and the check.

`Problem` (unbatched) refines a start with Levenberg–Marquardt steps down
the pyramid (`Problem.descend`), searches with the swarm at a coarse level
(`Problem.swarm`), and judges a candidate by the full-resolution loss and
its `quality` (`Problem.finish`).  It reads a `Context` (the image, the
template, the bases) and the `Knobs` (`TrackConfig`'s runtime settings as
arrays) and returns a `Candidate`.

Shapes: u (…, D) motion parameters relative to base 0 or 1 of the context
(D = `motion.dimension`); homographies (…, 3, 3), template → image at full
resolution (`atlas.to_level` for a level's).  Every loss scores one of the
template's point sets (one per pyramid level, and `template.FULL` for the
check) a fixed-size chunk at a time (`measures.over_chunks`).

Why a module of its own: what one registration computes does not depend on
the order the stages ask for it (`jaxpso._src.register`) nor on how a batch
maps it (`jaxpso._src.batching`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import atlas
from jaxpso._src import measures
from jaxpso._src import motion
from jaxpso._src import pso
from jaxpso._src import refine
from jaxpso._src import template as templates

# Gauss–Newton stops once a step moves the corners by under this many pixels
# of the level being refined: full resolution, coarser levels (the finer
# ones refine further: a quarter pixel there is well inside their basin;
# 0.05 spent 1–8 more steps per alignment at equal success and error,
# convergence.py with pso-mi, every condition and σ).
_TOLERANCE, _COARSE_TOLERANCE = 0.01, 0.25
# Points scored per chunk by Gauss–Newton and the swarm (the full-resolution
# check scores its set, at most `TrackConfig.resolution` points, in one).
# A set costs whole chunks (under vmap, the largest element's), so the
# chunks are sized to the sets: a coarse level has 144–576 points, a 48×48
# template's level 1 has 576 (benchmarks/README.md, implementation choices).
_GN_CHUNK, _SWARM_CHUNK = 640, 160


class Knobs(NamedTuple):
  """`TrackConfig`'s runtime settings as arrays: changing them never recompiles.

  Every field is a () array: search_radius, max_iterations, quick_iterations, patience (a
  huge value when off), refine_steps, accept_quality (+inf when off),
  retry_quality, hopeless_quality (-inf when off), retries, lost_quality, min_valid,
  recovery_scale, retry_scale, predict (bool), max_evaluations (a huge value when off).
  """
  search_radius: jax.Array
  max_iterations: jax.Array
  quick_iterations: jax.Array
  patience: jax.Array
  refine_steps: jax.Array
  accept_quality: jax.Array
  retry_quality: jax.Array
  hopeless_quality: jax.Array
  retries: jax.Array
  lost_quality: jax.Array
  min_valid: jax.Array
  recovery_scale: jax.Array
  retry_scale: jax.Array
  predict: jax.Array
  max_evaluations: jax.Array


class Context(NamedTuple):
  """One registration's data (a pytree; leading batch axis in a batch).

  Attributes:
    image: the image's `atlas.Atlas`.
    template: its `template.Template`.
    bases: (2, 3, 3) start homographies, or (2, 4, 4) base poses for motion
      "plane": the start and, for `track`'s recovery, the last good estimate.
    geometry: `motion.Plane` for motion "plane", else None.
    quads: (2, 4, 2) motion "homography": where each base puts the
      template's corners (else zeros).
    template_range: (2,) MI's binning range of the template (`Template.value_range`).
    image_ranges: (2, 2) MI's binning range of the image at each base (the
      second computed only where a stage starts from it, `register.with_range`).
    self_loss: () the template's loss against itself, `quality`'s scale.
    seed: (2,) uint32 swarm seed.
    reference: () the quality a match reaches in these images (1 unless
      `track` measured it): a start is accepted at `accept_quality` × it.
  """
  image: atlas.Atlas
  template: templates.Template
  bases: jax.Array
  geometry: motion.Plane | None
  quads: jax.Array
  template_range: jax.Array
  image_ranges: jax.Array
  self_loss: jax.Array
  seed: jax.Array
  reference: jax.Array


class Candidate(NamedTuple):
  """A registration's result (all arrays; leading batch axis in a batch).

  Attributes:
    u: (D,) motion parameters relative to the base.
    homography: (3, 3) template → image, h[2, 2] = 1.
    loss: () the full-resolution loss (+inf if too few pixels are valid).
    quality: () its `quality`, about 1 for a match.
    confirmed: () bool: accepted from the start, or the swarm's result and
      the start's refinement agree (within `register._AGREE_PX` at every corner).
    base: () int32 index of the base u is relative to (`Context.bases`).
    num_iterations: () int32 swarm iterations plus refinement steps.
    num_evaluations: () int32 particle evaluations plus refinement steps.
  """
  u: jax.Array
  homography: jax.Array
  loss: jax.Array
  quality: jax.Array
  confirmed: jax.Array
  base: jax.Array
  num_iterations: jax.Array
  num_evaluations: jax.Array


def measure_of(config) -> measures.Measure:
  return measures.Measure(config.similarity, config.bins)


def normalized(h) -> jax.Array:
  """(3, 3) h / h[2, 2] with h[2, 2] exactly 1, rounded alike in every program (`batching.each`)."""
  return (h * (1.0 / h[2, 2])).at[2, 2].set(1.0)


class Problem:
  """One template's registration in one image (unbatched): what the stages are made of.

  Args:
    context: one `Context`.  knobs: `Knobs`.  config: the static `TrackConfig`.
  """

  def __init__(self, context: Context, knobs: Knobs, config):
    self.context, self.knobs, self.config = context, knobs, config
    self.measure = measure_of(config)
    self.template = context.template
    self.size = context.template.size
    self.dim = motion.dimension(config.motion, config.dof)

  def _corners(self, u, base):
    """Motion "homography": (…, 4, 2) template corners for parameters u (…, 8) (`motion.moved_corners`)."""
    return self.context.quads[base] + u.reshape(u.shape[:-1] + (4, 2))

  def homography(self, u, base):
    """(…, D) parameters relative to base index `base` → (…, 3, 3) full-resolution homographies."""
    if self.config.motion == "homography":
      return motion.rect_to_quad(self._corners(u, base), self.size)
    return motion.to_homography(u, base=self.context.bases[base], geometry=self.context.geometry,
                                shape=self.size, motion=self.config.motion, dof=self.config.dof)

  def ranges(self, base) -> measures.Ranges:
    return measures.Ranges(self.context.template_range, self.context.image_ranges[base])

  def _chunk(self, index, start, size: int):
    """(size, 2) points and (size,) values of set `index` from `start`, and which are in the set."""
    offset, count = self.template.sets[index]
    points = jax.lax.dynamic_slice(self.template.points, (offset + start, 0), (size, 2))
    values = jax.lax.dynamic_slice(self.template.values, (offset + start,), (size,))
    return points, values, start + jnp.arange(size) < count

  def admissible(self, u, base):
    """(…) whether parameters u (…, D) keep the template a convex quad of sensible size (`motion.admissible`)."""
    if self.config.motion == "homography":
      return motion.admissible_quad(self._corners(u, base), self.size)
    return motion.admissible(self.homography(u, base), self.size)

  def _loss(self, stats, index, u, base):
    """The loss of the statistics of set `index`, +inf where parameters u (…, D) are not admissible."""
    count = self.template.sets[index, 1]
    value = measures.loss(self.measure, stats, count, self.knobs.min_valid)
    return jnp.where(self.admissible(u, base), value, jnp.inf)

  def _template_bins(self, index):
    """MI: (n, bins) `measures.bin_weights` of set `index`'s values (n its `template.slot`), once per search; else None."""
    if self.config.similarity != "mi":
      return None
    values = jax.lax.dynamic_slice(self.template.values, (self.template.sets[index, 0],),
                                   (templates.slot(self.config.resolution),))
    return measures.bin_weights(values, self.config.bins, self.context.template_range, True)

  def _scores(self, h, level, index, chunk: int, lead: tuple, ranges, bins):
    """Similarity statistics of set `index` sampled at `level` through (lead…, 3, 3) level homographies h.

    `bins`: the set's `_template_bins`, or None to bin each chunk's template
    values as it is scored (cheaper for one pass).  The set is scored `chunk` points at
    a time (in one piece when the resolution fits in one).
    """
    image = atlas.level(self.context.image, level)
    count = self.template.sets[index, 1]

    def body(start, stats):
      points, template, inside = self._chunk(index, start, chunk)
      patch, valid = materialized(image.sample(h, points), self.knobs)
      weights = None if bins is None else jax.lax.dynamic_slice_in_dim(bins, start, chunk, axis=0)
      return measures.add(self.measure, stats, template, patch, valid & inside, ranges, weights)

    empty = self._empty(h, level, index, lead)
    return measures.over_chunks(count, chunk, body, empty, self.config.resolution)

  def _empty(self, h, level, index, lead: tuple):
    """Zero statistics; for "ncc" shifted by the set's first value and the image at the template's centre."""
    if self.config.similarity != "ncc":
      return measures.empty(self.measure, lead)
    first = self.template.values[self.template.sets[index, 0]]
    centre = (jnp.stack([self.size[1], self.size[0]]) - 1.0) / (2.0 * jnp.exp2(level))
    reference, _ = atlas.level(self.context.image, level).sample(h, centre[None])
    return measures.empty(self.measure, lead, first, reference[..., 0])

  # ------------------------------------------------------------ Gauss–Newton
  def _linearise(self, u, base, level, bins, first):
    """(loss, JᵀJ, Jᵀr) of the adapted SSD at u over level `level`'s set, in one chunk pass.

    J = B·M: B = ∂I(W(p))/∂h per point in closed form, M = ∂h/∂u, over
    h's first 8 entries (h[2, 2] = 1 does not move).  T̃ is linear in its
    coefficients (a B-spline remap for "mi",
    gain and bias for "ncc"), so Bᵀr = BᵀI − (BᵀX)·coefficients with X the
    template's bin weights (or [T, 1]): one pass sums BᵀB, BᵀI, BᵀX and the
    similarity's statistics, in one matrix product per chunk, and T̃ comes
    after.  `bins`: the set's `_template_bins`; `first` () bool: MI's first
    phase, T̃ a gain and bias (`refine`).
    """
    name = self.config.similarity
    ranges = self.ranges(base)

    def to_level(u):  # with h[2, 2] = 1, the homography's free scale stays out of J
      h = atlas.to_level(self.homography(u, base), level)
      # × the reciprocal, not ÷: one rounding in every program (batching.each)
      return h * (1.0 / h[2, 2])

    h = to_level(u)
    count = self.template.sets[level, 1]
    image = atlas.level(self.context.image, level)

    def sums(start, carry):
      products, stats = carry
      points, values, inside = self._chunk(level, start, _GN_CHUNK)
      value, gx, gy, valid, (x, y, w) = image.sample_with_gradient(h, points)
      valid = valid & inside
      w = jnp.where(valid, w, jnp.inf)  # zero slopes past the set's end too
      value, gx, gy, x, y = materialized((value, gx / w, gy / w, x, y), self.knobs)
      px, py = points[:, 0], points[:, 1]
      across = -(gx * x + gy * y)
      # B as rows (8, c) on the left and as columns (c, 8) on the right: the
      # CPU's products of (k, c) by (c, k') are several times faster than by
      # (k', c) transposed, most of all batched (benchmarks/README.md,
      # implementation choices).
      # Its terms (gx, gy, across) ⊗ (px, py, 1) as one outer product: one
      # kernel each side, where the 8 products stacked were 8.
      m = valid.astype(value.dtype)
      slopes = jnp.stack([gx, gy, across])
      coords = jnp.stack([px, py, jnp.ones_like(px)])
      b_rows = (slopes[:, None] * coords[None]).reshape(9, -1)[:8]
      b_columns = (slopes.T[:, :, None] * coords.T[:, None, :]).reshape(-1, 9)[:, :8]
      left = jnp.concatenate([b_rows, (m * value)[None]])
      if name != "mi":
        right = jnp.concatenate([b_columns, jnp.stack([values, jnp.ones_like(values)], axis=-1)],
                                -1)
        stats = measures.add(self.measure, stats, values, value, valid)
        return products + left @ right, stats
      # One product [B; m·I; m; β(I)·m]·[B, X]: the rows past B's give the
      # histogram with T̃'s sums (one call beats two smaller ones, batched).
      template = jax.lax.dynamic_slice_in_dim(bins, start, _GN_CHUNK, 0)  # X (c, bins)
      patch = measures.bin_weights(value, self.config.bins, ranges.image) * m
      left = jnp.concatenate([left, m[None], patch])
      return products + left @ jnp.concatenate([b_columns, template], -1), stats

    bins_count = self.config.bins
    rows, columns = (10 + bins_count, 8 + bins_count) if name == "mi" else (9, 10)
    products, stats = measures.over_chunks(
        count, _GN_CHUNK, sums,
        (jnp.zeros((rows, columns), jnp.float32), self._empty(h, level, level, ())))
    per_bin = None
    if name == "mi":
      stats = products[10:, 8:].T  # the joint histogram, template bins along the rows
      per_bin = (products[8, 8:], products[9, 8:], self.template.remap, count)
    normal, slopes_image = products[:8, :8], products[8, :8]
    slopes_template = products[:8, 8:] @ refine.adapted_coefficients(name, stats, per_bin, first)
    by_motion = jax.jacfwd(to_level)(u).reshape(9, -1)[:8]  # h[2, 2] = 1 stays put
    loss = self._loss(stats, level, u, base)
    return (loss, by_motion.T @ normal @ by_motion,
            by_motion.T @ (slopes_image - slopes_template))

  def _level_loss(self, u, base, level, bins):
    h = atlas.to_level(self.homography(u, base), level)
    stats = self._scores(h, level, level, _GN_CHUNK, (), self.ranges(base), bins)
    return self._loss(stats, level, u, base)

  def descend(self, u, base, top, settle=None):
    """u refined by Gauss–Newton from level `top` down to full resolution → (u, steps, settled).

    `settle`: ((3, 3) homography, () float32 pixels) or None: Gauss–Newton
    ends above full resolution once a level's estimate is within that many
    pixels of the homography (`motion.corner_gap`; 0: never), and
    `settled` () bool says so: that estimate, refined at full resolution,
    then stands for this one (two estimates of one basin share its finer
    levels).
    """
    mi = self.config.similarity == "mi"  # a gain and bias first, the remap at level 0 (`refine`)

    def body(carry):
      u, level, steps, _ = carry
      bins = self._template_bins(level)
      u, taken = refine.levenberg_marquardt(
          u, lambda v, first: self._linearise(v, base, level, bins, first),
          lambda v: self._level_loss(v, base, level, bins), self.knobs.refine_steps,
          jnp.where(level > 0, _COARSE_TOLERANCE, _TOLERANCE)
          * jnp.exp2(level.astype(jnp.float32)), first=mi, second=level == 0, polish=not mi)
      done = jnp.asarray(False)
      if settle is not None:
        gap = motion.corner_gap(self.homography(u, base), settle[0], self.size)
        done = (level >= 1) & (settle[1] > 0) & (gap <= settle[1])
      return u, level - 1, steps + taken, done

    u, _, steps, settled = jax.lax.while_loop(
        lambda c: (c[1] >= 0) & ~c[3], body,
        (u, jnp.asarray(top, jnp.int32), jnp.zeros([], jnp.int32), jnp.asarray(False)))
    return u, steps, settled

  # --------------------------------------------------------------- the swarm
  def _lift(self, translation):
    """(D, D) map from the swarm's position to u: the identity, or the 2-D image translation."""
    if self.config.motion == "homography":
      shift = np.tile(np.eye(2), (4, 1))
    else:
      shift = np.eye(self.dim, 2)
    moves = np.concatenate([shift, np.zeros((self.dim, self.dim - 2))], axis=1)
    return jnp.where(translation, jnp.asarray(moves, jnp.float32),
                     jnp.eye(self.dim, dtype=jnp.float32))

  def swarm(self, base, seed, level, radius, iterations, restarts, translation):
    """The best of `restarts` swarms over ±radius at `level` → ((D,) u, iterations, evaluations).

    Each swarm runs at most `iterations` iterations; with `translation` it
    searches the template's image translation only (every corner alike for
    "homography", (tx, ty) for "plane"), the refinement later the rest.
    """
    lift = self._lift(translation)
    ranges = self.ranges(base)
    bins = self._template_bins(level)

    def loss_fn(x, _):  # x (n, D)
      u = x @ lift.T
      h = atlas.to_level(self.homography(u, base), level)
      stats = self._scores(h, level, level, _SWARM_CHUNK, (x.shape[0],), ranges, bins)
      return self._loss(stats, level, u, base)

    box = jnp.full(self.dim, radius, jnp.float32)
    limits = pso.PSOLimits(max_iterations=iterations, patience=self.knobs.patience,
                           tolerance=jnp.float32(pso.PSOConfig.tolerance),
                           target_loss=jnp.float32(-jnp.inf), stop_weights=jnp.zeros(3, jnp.float32))
    config = self.config.pso_config().static()

    def run(k, best):
      x, loss, spent_iterations, spent_evaluations = best
      found = pso._run_impl(seed ^ (k * jnp.uint32(0x9E3779B9)).astype(jnp.uint32), -box, box,
                            None, pso.default_hparams(self.config.variant), None, None,
                            jnp.zeros(self.dim, jnp.float32), box, loss_fn=loss_fn,
                            config=config, limits=limits)
      better = found.loss < loss
      return (jnp.where(better, found.x, x), jnp.where(better, found.loss, loss),
              spent_iterations + found.num_iterations, spent_evaluations + found.num_evaluations)

    zero = jnp.zeros([], jnp.int32)
    x, _, spent_iterations, spent_evaluations = jax.lax.fori_loop(
        0, restarts, run, (jnp.zeros(self.dim, jnp.float32), jnp.float32(jnp.inf), zero, zero))
    return lift @ x, spent_iterations, spent_evaluations

  # ------------------------------------------------------------- the check
  def finish(self, u, base, iterations, evaluations) -> Candidate:
    """The candidate at u: its loss over the `FULL` set (full resolution) and its `quality`."""
    h = self.homography(u, base)
    ranges = self.ranges(base)
    mi = self.config.similarity == "mi"

    image = atlas.level(self.context.image, 0)
    count = self.template.sets[templates.FULL, 1]

    def body(start, carry):
      stats, own = carry
      points, template, inside = self._chunk(templates.FULL, start, self.config.resolution)
      patch, valid = materialized(image.sample(h, points), self.knobs)
      valid = valid & inside
      if not mi:
        return measures.add(self.measure, stats, template, patch, valid), own
      # The patch against itself too, both sides binned over the image's range.
      # The template's bins per chunk: only the chunks in use (a small
      # template fills a fraction of the set's capacity).
      weights = measures.bin_weights(template, self.config.bins, ranges.template, True)
      return measures.add_with_own(stats, own, weights, patch, valid, self.measure, ranges.image)

    empty = self._empty(h, 0, templates.FULL, ())
    stats, own = measures.over_chunks(count, self.config.resolution, body,
                                      (empty, measures.empty(self.measure, ()) if mi else None),
                                      self.config.resolution)
    loss = self._loss(stats, templates.FULL, u, base)
    own_loss = None
    if mi:
      own_loss = measures.loss(self.measure, own, self.template.sets[templates.FULL, 1],
                               self.knobs.min_valid)
    return Candidate(u=u, homography=normalized(h), loss=loss,
                     quality=quality(loss, own_loss, self.context.self_loss, self.config),
                     confirmed=jnp.asarray(False), base=jnp.asarray(base, jnp.int32),
                     num_iterations=iterations, num_evaluations=evaluations + 1)


def materialized(tree, knobs: Knobs):
  """`tree` (arrays), computed once: the branch of a conditional on data that always holds.

  XLA's CPU fusion otherwise duplicates cheap producers into every consumer:
  fused into the bins' (bins, n) weights, the image sampling that made the
  values was recomputed for each bin (the loss took 3–4× as long).  The
  condition reads a knob (shared by a batch), so that under `vmap` it stays
  a conditional instead of becoming a select of both branches.
  """
  return jax.lax.cond(knobs.min_valid > -1.0, lambda t: t,
                      lambda t: jax.tree.map(jnp.zeros_like, t), tree)


def quality(loss, own_loss, self_loss, config):
  """() quality of a loss, about 1 for a match.

  "ssd": 1 − SSD / the template's variance; "ncc": NCC over the template's
  own; "mi": MI(T, I) / √(MI(T, T) · MI(I, I)), I the patch binned over the
  image's range (`own_loss` = −MI(I, I)), so that a correct alignment scores
  near 1 under a monotone intensity change of the image too.  0 for a flat
  template or patch; -inf where the loss is (too few valid pixels).  It can
  exceed 1 slightly (soft binning).
  """
  if config.similarity == "ssd":
    informative = self_loss > 0
    value = 1.0 - loss / jnp.where(informative, self_loss, 1.0)
  else:
    scale = self_loss  # −MI(T, T) or −NCC(T, T)
    if config.similarity == "mi":
      scale = -jnp.sqrt(jnp.maximum(scale * own_loss, 0.0))
    informative = scale < 0
    value = loss / jnp.where(informative, scale, -1.0)
  return jnp.where(jnp.isfinite(loss), jnp.where(informative, value, 0.0), -jnp.inf)
