"""The registration of a template in an image: Gauss–Newton, the swarm, Gauss–Newton, in stages.

One registration (`Problem`) refines a start with Levenberg–Marquardt steps
down the pyramid (`Problem.descend`), and, where that falls short, searches
with the swarm at a coarse level and refines its best (`Problem.swarm`); the
full-resolution loss and `quality` judge every candidate (`Problem.finish`).
`align` and `track` chain such stages (`ALIGN`, `TRACK`): a start, a
coarser start, a search, a retry or a recovery search, each run only where
the previous ones fell short.

Why stages in a loop: every stage is one pass of the same loop body (an
optional swarm, then Gauss–Newton from a top level down, then the
full-resolution check), so the compiled program holds one copy of the
swarm, one of Gauss–Newton (the pyramid level is data) and one of the check,
whatever the number of stages or levels.  Unrolled, the same pipeline
compiled 13 copies of Gauss–Newton and 2 of the swarm: 20 s of XLA on the
2-core machine for one `align` program, against a few seconds now
(benchmarks/cold_start.py).  The image (`atlas`) and the template
(`template`) are point sets and buffers of fixed capacity, so neither
image nor template size enters the program either.

In a batch (`run`), the first stage runs for every element at once, and the
others only for the elements still short of it, gathered a few at a time
(`where_needed`): under `vmap` a per-element `lax.cond` would run the swarm
for every element.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import atlas
from jaxpso._src import baselines
from jaxpso._src import homography
from jaxpso._src import measures
from jaxpso._src import motion
from jaxpso._src import pso
from jaxpso._src import refine
from jaxpso._src import similarity
from jaxpso._src import template as templates

# Gauss–Newton stops once a step moves the corners by under this many pixels
# of the level being refined: full resolution, coarser levels (the finer
# ones refine further).
_TOLERANCE, _COARSE_TOLERANCE = 0.01, 0.05
# Two registrations agree when no template corner is further apart than this
# (full-resolution pixels).
_AGREE_PX = 1.0
# Points scored per chunk by Gauss–Newton and the swarm (the full-resolution
# check scores its set, at most `TrackConfig.resolution` points, in one).
# A set costs whole chunks (under vmap, the largest element's), so the
# chunks are sized to the sets: a coarse level has 144–576 points, a 48×48
# template's level 1 has 576 (benchmarks/README.md, batch).
_GN_CHUNK, _SWARM_CHUNK = 640, 160
# `track` also accepts a start within this margin of its last search's
# quality, where that was at least _MIN_REFERENCE (`_advance_track`).
_REFERENCE_MARGIN, _MIN_REFERENCE = 0.02, 0.8
# The wide searches (retry, recovery) draw other swarm streams.
_WIDE_SEED = 0x5BD1E995


class Knobs(NamedTuple):
  """`TrackConfig`'s runtime settings as arrays: changing them never recompiles.

  Every field is a () array: search_radius, max_iterations, patience (a
  huge value when off), refine_steps, accept_quality (+inf when off),
  retry_quality, lost_quality, min_valid, recovery_scale, predict (bool).
  """
  search_radius: jax.Array
  max_iterations: jax.Array
  patience: jax.Array
  refine_steps: jax.Array
  accept_quality: jax.Array
  retry_quality: jax.Array
  lost_quality: jax.Array
  min_valid: jax.Array
  recovery_scale: jax.Array
  predict: jax.Array


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
      second computed only where a stage starts from it, `with_range`).
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
      the start's refinement agree (within `_AGREE_PX` at every corner).
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
  """(3, 3) h / h[2, 2] with h[2, 2] exactly 1 (XLA divides by multiplying)."""
  return (h / h[2, 2]).at[2, 2].set(1.0)


def _full_set(template: templates.Template, resolution: int):
  """(resolution, 2) points, (resolution,) values and mask of the `FULL` set, at once."""
  offset, count = template.sets[templates.FULL]
  points = jax.lax.dynamic_slice(template.points, (offset, 0), (resolution, 2))
  values = jax.lax.dynamic_slice(template.values, (offset,), (resolution,))
  return points, values, jnp.arange(resolution) < count


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
    return measures.bin_weights(values, self.config.bins, self.context.template_range).T

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
  def _linearise(self, u, base, level, bins):
    """(loss, JᵀJ, Jᵀr) of the adapted SSD at u over level `level`'s set, in one chunk pass.

    J = B·M: B = ∂I(W(p))/∂h per point in closed form, M = ∂h/∂u, over
    h's first 8 entries (h[2, 2] = 1 does not move).  T̃ is linear in its
    coefficients (per-bin means for "mi",
    gain and bias for "ncc"), so Bᵀr = BᵀI − (BᵀX)·coefficients with X the
    template's bin weights (or [T, 1]): one pass sums BᵀB, BᵀI, BᵀX and the
    similarity's statistics, in one matrix product per chunk, and T̃ comes
    after.  `bins`: the set's `_template_bins`.
    """
    name = self.config.similarity
    ranges = self.ranges(base)

    def to_level(u):  # with h[2, 2] = 1, the homography's free scale stays out of J
      h = atlas.to_level(self.homography(u, base), level)
      return h / h[2, 2]

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
      # (k', c) transposed, most of all batched (benchmarks/README.md, batch).
      terms = [gx * px, gx * py, gx, gy * px, gy * py, gy, across * px, across * py]
      m = valid.astype(value.dtype)
      left = jnp.stack(terms + [m * value])
      if name != "mi":
        right = jnp.stack(terms + [values, jnp.ones_like(values)], axis=-1)
        stats = measures.add(self.measure, stats, values, value, valid)
        return products + left @ right, stats
      # One product [B; m·I; m; β(I)·m]·[B, X]: the rows past B's give the
      # histogram with T̃'s sums (one call beats two smaller ones, batched).
      template = jax.lax.dynamic_slice_in_dim(bins, start, _GN_CHUNK, 0)  # X (c, bins)
      patch = measures.bin_weights(value, self.config.bins, ranges.image) * m
      left = jnp.concatenate([left, m[None], patch])
      return products + left @ jnp.concatenate([jnp.stack(terms, axis=-1), template], -1), stats

    bins_count = self.config.bins
    rows, columns = (10 + bins_count, 8 + bins_count) if name == "mi" else (9, 10)
    products, stats = measures.over_chunks(
        count, _GN_CHUNK, sums,
        (jnp.zeros((rows, columns), jnp.float32), self._empty(h, level, level, ())))
    per_bin = None
    if name == "mi":
      stats = products[10:, 8:].T  # the joint histogram, template bins along the rows
      per_bin = jnp.stack([products[8, 8:], products[9, 8:]])
    normal, slopes_image = products[:8, :8], products[8, :8]
    slopes_template = products[:8, 8:] @ refine.adapted_coefficients(name, stats, per_bin)
    by_motion = jax.jacfwd(to_level)(u).reshape(9, -1)[:8]  # h[2, 2] = 1 stays put
    loss = self._loss(stats, level, u, base)
    return (loss, by_motion.T @ normal @ by_motion,
            by_motion.T @ (slopes_image - slopes_template))

  def _level_loss(self, u, base, level, bins):
    h = atlas.to_level(self.homography(u, base), level)
    stats = self._scores(h, level, level, _GN_CHUNK, (), self.ranges(base), bins)
    return self._loss(stats, level, u, base)

  def descend(self, u, base, top):
    """u refined by Gauss–Newton from level `top` down to full resolution → (u, steps)."""
    def body(carry):
      u, level, steps = carry
      bins = self._template_bins(level)
      u, _, taken = refine.levenberg_marquardt(
          u, lambda v: self._linearise(v, base, level, bins),
          lambda v: self._level_loss(v, base, level, bins), self.knobs.refine_steps,
          jnp.where(level > 0, _COARSE_TOLERANCE, _TOLERANCE)
          * jnp.exp2(level.astype(jnp.float32)))
      return u, level - 1, steps + taken

    u, _, steps = jax.lax.while_loop(lambda c: c[1] >= 0, body,
                                     (u, jnp.asarray(top, jnp.int32), jnp.zeros([], jnp.int32)))
    return u, steps

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
      weights = measures.bin_weights(template, self.config.bins, ranges.template).T
      own_bins = measures.bin_weights(patch, self.config.bins, ranges.image)
      stats = measures.add(self.measure, stats, template, patch, valid, ranges, weights, own_bins)
      own = measures.add(self.measure, own, patch, patch, valid, None, own_bins.T, own_bins)
      return stats, own

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


def baseline(context: Context, pyramid: list, knobs: Knobs, config) -> Candidate:
  """`config.method`'s gradient registration from the start (unbatched); `pyramid` the template's dense levels."""
  problem = Problem(context, knobs, config)
  ranges = problem.ranges(0)

  def loss_at(level, h, patch, mask):
    template = pyramid[level]
    if config.similarity == "mi":
      weights = jnp.moveaxis(measures.bin_weights(template, config.bins, ranges.template), -2, -1)
      value = -similarity.mi(similarity.SoftBins(weights, ranges.image[0], ranges.image[1]), patch,
                             mask, min_valid=config.min_valid)
    elif config.similarity == "ncc":
      value = -similarity.ncc(template, patch, mask, min_valid=config.min_valid)
    else:
      value = similarity.ssd(template, patch, mask, min_valid=config.min_valid)
    return jnp.where(motion.admissible(h, template.shape), value, jnp.inf)

  u, _, iterations, evaluations = baselines.register(
      config.method, context.image, pyramid, lambda v: problem.homography(v, 0), problem.dim,
      loss_at, similarity=config.similarity, levels=config.levels,
      iterations=config.max_iterations)
  return problem.finish(u, 0, iterations, evaluations - 1)


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


def better(first: Candidate, second: Candidate) -> Candidate:
  """Per element the candidate of lower loss (the first on ties), counting both searches."""
  best = select(first.loss <= second.loss, first, second)
  return best._replace(num_iterations=first.num_iterations + second.num_iterations,
                       num_evaluations=first.num_evaluations + second.num_evaluations)


def select(mask, first, second):
  """Per batch element `first` where the (R,) or () `mask` holds, else `second` (pytrees)."""
  return jax.tree.map(
      lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - mask.ndim)), a, b),
      first, second)


def take(tree, indices):
  """The elements `indices` (C,) of every leaf's leading axis (a shared `atlas.Atlas` as it is)."""
  return _mapped(lambda a: a[indices], tree)


def corner_gap(first, second, size) -> jax.Array:
  """() the largest distance between the template corners two (3, 3) homographies map."""
  rect = motion.corners(size)
  gap = homography.apply_to_points(first, rect)[0] - homography.apply_to_points(second, rect)[0]
  return jnp.max(jnp.linalg.norm(gap, axis=-1))


# ------------------------------------------------------------------- stages
@dataclasses.dataclass(frozen=True)
class Stage:
  """One stage: an optional swarm, then Gauss–Newton from `top` down, then the check.

  Attributes:
    swarm: run the swarm first (else start from u = 0).
    finer: the swarm searches one level finer than the coarsest.
    wide: `recovery_scale` swarms of `recovery_scale` × the iterations,
      other seeds (align's retry, track's recovery).
    widen: the wide search's box is also `recovery_scale` × the radius.
    translation: the swarm searches the 2-D translation only.
    top: Gauss–Newton's first level: 0 level 1 (refining the start alone:
      the coarser levels' optimum can be a wrong one near a start already in
      the right basin), 1 the coarsest, 2 the swarm's.
    base: 0 the start, 1 the last good estimate (`Context.bases`).
  """
  swarm: bool = False
  finer: bool = False
  wide: bool = False
  widen: bool = False
  translation: bool = False
  top: int = 0
  base: int = 0


ALIGN = (Stage(), Stage(top=1), Stage(swarm=True, top=2),
         Stage(swarm=True, finer=True, wide=True, top=2))
"""`align`'s stages: the start, a coarser start, the search, the retry one level finer."""
TRACK = (Stage(), Stage(swarm=True, top=2), Stage(base=1),
         Stage(swarm=True, wide=True, widen=True, translation=True, top=2, base=1))
"""`track`'s stages: the start, the search, then the recovery from the last good estimate."""


class State(NamedTuple):
  """The stage loop's state (leading batch axis C).

  Attributes:
    stage: (C,) int32 the next stage (len(stages): done).
    best: `Candidate` the best so far.
    anchor: `Candidate` align: the start's refinement; track: the recovery's.
    recovered: (C,) bool: track's recovery ran.
    searched: (C,) bool: a swarm ran.
  """
  stage: jax.Array
  best: Candidate
  anchor: Candidate
  recovered: jax.Array
  searched: jax.Array


def _shared(node) -> bool:
  """Whether `node` is an `atlas.Atlas` shared by a batch (1-D pixels)."""
  return isinstance(node, atlas.Atlas) and node.pixels.ndim == 1


def _axes(tree):
  """vmap axes of a batched pytree: 0, but None for a shared `atlas.Atlas`."""
  return jax.tree.map(lambda node: None if _shared(node) else 0, tree, is_leaf=_shared)


def _mapped(fn, tree):
  """`fn` on every leaf of `tree` but a shared `atlas.Atlas`'s."""
  return jax.tree.map(lambda node: node if _shared(node) else fn(node), tree, is_leaf=_shared)


def each(fn: Callable, *args):
  """`jax.vmap(fn)(*args)` over the leading axis, or for a batch of one `fn` on the element itself.

  An `atlas.Atlas` with 1-D pixels is shared by the batch (not mapped).
  Under `vmap`, every `while_loop` with a per-element condition becomes a
  loop of selects over its whole carry (and a `cond` runs both branches):
  for one element that only cost compilation time and run time.
  """
  count = next(a.shape[0] for a in jax.tree.leaves(args, is_leaf=_shared) if not _shared(a))
  if count != 1:
    return jax.vmap(fn, in_axes=_axes(args))(*args)
  return jax.tree.map(lambda a: a[None], fn(*_mapped(lambda a: a[0], args)))


def _column(stages, name: str, index):
  return jnp.asarray([getattr(s, name) for s in stages])[index]


def _pass(contexts: Context, state: State, knobs: Knobs, stages, config, swarm: bool) -> Candidate:
  """One pass of the stage loop's body for every element: its stage's swarm, Gauss–Newton, the check.

  `swarm` (static) False leaves the swarm out of the program (the first stage has none).
  """
  stage = jnp.minimum(state.stage, len(stages) - 1)
  coarsest = contexts.template.levels - 1
  swarm_level = jnp.maximum(coarsest - _column(stages, "finer", stage), 0)
  top = jnp.select([_column(stages, "top", stage) == 0, _column(stages, "top", stage) == 1],
                   [jnp.minimum(1, coarsest), coarsest], swarm_level)
  base = _column(stages, "base", stage)
  if any(s.base for s in stages):
    contexts = with_range(contexts, (state.stage < len(stages)) & (base == 1), config)
  count = state.stage.shape[0]
  dim = motion.dimension(config.motion, config.dof)
  zero = jnp.zeros(count, jnp.int32)
  u, iterations, evaluations = jnp.zeros((count, dim), jnp.float32), zero, zero
  if swarm:
    wide = _column(stages, "wide", stage)
    scale = jnp.where(wide, knobs.recovery_scale, 1)
    radius = knobs.search_radius * jnp.where(wide & _column(stages, "widen", stage), scale, 1)
    seeds = contexts.seed ^ jnp.where(wide, jnp.uint32(_WIDE_SEED), jnp.uint32(0))[:, None]
    needed = (state.stage < len(stages)) & _column(stages, "swarm", stage)

    def search(_):
      def one(context, base, seed, level, radius, scale, translation):
        return Problem(context, knobs, config).swarm(
            base, seed, level, radius, knobs.max_iterations * scale, scale, translation)
      found = each(one, contexts, base, seeds, swarm_level, radius, scale,
                   _column(stages, "translation", stage))
      return jax.tree.map(lambda a, b: jnp.where(needed.reshape((-1,) + (1,) * (a.ndim - 1)),
                                                 a, b), found, (u, zero, zero))

    u, iterations, evaluations = jax.lax.cond(jnp.any(needed), search, lambda _: (u, zero, zero),
                                              None)

  def refine_and_check(context, u, base, top, iterations, evaluations):
    problem = Problem(context, knobs, config)
    u, steps = problem.descend(u, base, top)
    return problem.finish(u, base, iterations + steps, evaluations + steps)

  return each(refine_and_check, contexts, u, base, top, iterations, evaluations)


def _advance_align(state: State, found: Candidate, contexts: Context, knobs: Knobs) -> State:
  """align's transitions: accepted start → done; else coarser start, search, retry."""
  stage, done = state.stage, len(ALIGN)
  starting = stage <= 1
  start = select(stage == 0, found, better(state.best, found))
  accepted = start.quality >= knobs.accept_quality
  coarse_next = jnp.isfinite(knobs.accept_quality) & (contexts.template.levels > 2)
  gap = jax.vmap(corner_gap)(found.homography, state.anchor.homography, contexts.template.size)
  searched = better(found, state.anchor)._replace(confirmed=gap <= _AGREE_PX)
  settled = (searched.quality >= knobs.retry_quality) | searched.confirmed
  best = select(starting, start._replace(confirmed=accepted),
                select(stage == 2, searched, better(state.best, found)))
  following = jnp.select(
      [stage == 0, stage == 1, stage == 2],
      [jnp.where(accepted, done, jnp.where(coarse_next, 1, 2)), jnp.where(accepted, done, 2),
       jnp.where(settled, done, 3)], done)
  return State(following, best, select(starting, start, state.anchor), state.recovered,
               state.searched | (stage >= 2))


def _advance_track(state: State, found: Candidate, contexts: Context, knobs: Knobs) -> State:
  """track's transitions: accepted start → done; else search; short of `lost_quality`: recovery."""
  stage, done = state.stage, len(TRACK)
  # Also accepted: within _REFERENCE_MARGIN of the quality the region's last
  # search reached (noise and blur lower the right alignment's quality too),
  # unless that was under _MIN_REFERENCE (low texture: too uncertain).
  reference = contexts.reference
  accepted = ((found.quality >= knobs.accept_quality)
              | ((reference >= _MIN_REFERENCE) & (found.quality >= reference - _REFERENCE_MARGIN)))
  searched = better(found, state.best)
  recovered = better(found, state.anchor)
  best = select(stage == 0, found, select(stage == 1, searched, select(
      stage == 2, select(accepted, better(state.best, found), state.best),
      better(state.best, recovered))))
  following = jnp.select(
      [stage == 0, stage == 1, stage == 2],
      [jnp.where(accepted, done, 1),
       jnp.where(searched.quality >= knobs.lost_quality, done, 2),
       jnp.where(accepted, done, 3)], done)
  return State(following, best, select(stage == 2, found, state.anchor),
               state.recovered | (stage == 2), state.searched | (stage == 1) | (stage == 3))


PIPELINES = {"align": (ALIGN, _advance_align), "track": (TRACK, _advance_track)}


def _initial(count: int, config) -> State:
  """Stage 0 for `count` elements, with placeholder candidates."""
  dim = motion.dimension(config.motion, config.dof)
  zero = jnp.zeros(count, jnp.int32)
  none = Candidate(u=jnp.zeros((count, dim), jnp.float32),
                   homography=jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32), (count, 3, 3)),
                   loss=jnp.full(count, jnp.inf, jnp.float32),
                   quality=jnp.full(count, -jnp.inf, jnp.float32),
                   confirmed=jnp.zeros(count, bool), base=zero, num_iterations=zero,
                   num_evaluations=zero)
  return State(zero, none, none, jnp.zeros(count, bool), jnp.zeros(count, bool))


def _loop(contexts: Context, state: State, knobs: Knobs, pipeline: str, config) -> State:
  """The stage loop until every element is done."""
  stages, advance = PIPELINES[pipeline]

  def body(state):
    return advance(state, _pass(contexts, state, knobs, stages, config, swarm=True), contexts,
                   knobs)

  return jax.lax.while_loop(lambda s: jnp.any(s.stage < len(stages)), body, state)


def run(contexts: Context, knobs: Knobs, pipeline: str, config) -> State:
  """The stages of `pipeline` ("align" or "track") for a batch of registrations (leading axis R, static).

  A batch of one runs the stage loop alone.  A larger batch runs the first
  stage for every element at once, then the loop only for the elements it
  left short (`where_needed`), a few at a time.
  """
  count = contexts.seed.shape[0]
  state = _initial(count, config)
  if count == 1 or config.method != "pso":
    return _loop(contexts, state, knobs, pipeline, config)
  stages, advance = PIPELINES[pipeline]
  state = advance(state, _pass(contexts, state, knobs, stages, config, swarm=False), contexts,
                  knobs)
  return where_needed(state.stage < len(stages),
                      lambda indices: _loop(take(contexts, indices), take(state, indices), knobs,
                                            pipeline, config), state)


def _share() -> int:
  """A batch of R runs its later stages on ceil(R / _share()) elements at a time (`where_needed`).

  32 on a CPU, where the work is compute-bound and an idle slot of a round
  costs as much as a busy one (benchmarks/README.md, batch).  8 on
  accelerators, whose slots run in parallel (not measured on a GPU).
  """
  return 32 if jax.default_backend() == "cpu" else 8


def where_needed(mask, compute: Callable, otherwise):
  """`otherwise` with the elements where the (R,) `mask` holds replaced by `compute`'s.

  `compute(indices)` gets (C,) element indices and returns those elements'
  results (leading C).  Only the elements that need it are computed, C =
  ceil(R / _share()) at a time in a `lax.while_loop` of as many rounds as
  needed (none when no element does).
  """
  size = mask.shape[0]
  capacity = -(-size // _share())
  padded = -(-size // capacity) * capacity
  needed = jnp.sum(mask)
  # The needing elements first; every other slot is the out-of-range index `size`.
  order = jnp.argsort(~mask, stable=True)
  order = jnp.where(jnp.arange(size) < needed, order, size)
  order = jnp.concatenate([order, jnp.full(padded - size, size, order.dtype)])

  def round_(state):
    done, results = state
    indices = jax.lax.dynamic_slice(order, (done,), (capacity,))
    found = compute(jnp.minimum(indices, size - 1))
    results = jax.tree.map(lambda a, f: a.at[indices].set(f, mode="drop"), results, found)
    return done + capacity, results

  def rounds(_):
    return jax.lax.while_loop(lambda state: state[0] < needed, round_,
                              (jnp.zeros([], needed.dtype), otherwise))[1]

  # The cond keeps batches that need nothing from entering the loop at all.
  return jax.lax.cond(needed > 0, rounds, lambda _: otherwise, None)


# ---------------------------------------------------------------- contexts
def image_range(context: Context, base, config) -> jax.Array:
  """(2,) MI binning range: the template's and the image's where base `base` puts it."""
  points, _, inside = _full_set(context.template, config.resolution)
  problem = Problem(context, None, config)
  h = problem.homography(jnp.zeros(problem.dim, jnp.float32), base)
  values, valid = atlas.level(context.image, 0).sample(h, points)
  lo, hi = measures.intensity_range(values, valid & inside)
  return jnp.stack([jnp.minimum(lo, context.template_range[0]),
                    jnp.maximum(hi, context.template_range[1])])


def context(image: atlas.Atlas, template: templates.Template, bases, geometry, seed,
            config) -> Context:
  """One registration's `Context`."""
  self_loss = template.self_loss[templates.SIMILARITIES.index(config.similarity)]
  template_range = template.value_range
  quads = jnp.zeros((2, 4, 2), jnp.float32)
  if config.motion == "homography":
    quads = homography.apply_to_points(bases, motion.corners(template.size))[0]
  made = Context(image, template, bases, geometry, quads, template_range,
                 jnp.zeros((2, 2), jnp.float32), self_loss, seed, jnp.float32(1.0))
  if config.similarity != "mi":
    return made
  return made._replace(image_ranges=jnp.stack([image_range(made, 0, config)] * 2))


def with_range(contexts: Context, needed, config) -> Context:
  """Batched contexts with the image's MI binning range at base 1 computed where `needed` (C,)."""
  if config.similarity != "mi":
    return contexts

  def compute(contexts):
    ranges = each(lambda c: image_range(c, 1, config), contexts)
    return contexts._replace(image_ranges=contexts.image_ranges.at[:, 1].set(ranges))

  return jax.lax.cond(jnp.any(needed), compute, lambda c: c, contexts)
