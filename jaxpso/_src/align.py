"""One registration of a template in an image: Gauss–Newton, the swarm, Gauss–Newton.

`align(image, template, init_homography)` first refines the start with a few
Levenberg–Marquardt steps per pyramid level (`jaxpso._src.refine`); when that
reaches `TrackConfig.accept_quality` it is the result.  Otherwise the PSO
engine searches the motion parameters (`jaxpso._src.motion`) at the coarsest
level of a Gaussian pyramid, where the similarity's basin is widest and a
swarm evaluation cheapest, the swarm's best is refined level by level down to
full resolution (the hybrid: the swarm finds the basin, Gauss–Newton the last
sub-pixel), and the better of the two is kept.  When that result's
`quality` is low and the swarm and the start's refinement disagree, `align`
searches once more with a larger swarm one level finer.  `register` is that pipeline
on prepared inputs, shared with `track`; `TrackConfig.method` swaps it for a
gradient baseline (`jaxpso._src.baselines`).  `register` works on batches
(`vmap` over the templates; the swarm and the retry run only for the
elements that need them, `where_needed`), and `align` takes a batch of N
alignments.  Everything after input checks is one compiled function per
(shapes, config).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import baselines
from jaxpso._src import checks
from jaxpso._src import compile_options
from jaxpso._src import homography
from jaxpso._src import motion
from jaxpso._src import plane
from jaxpso._src import pso
from jaxpso._src import refine
from jaxpso._src import sampling
from jaxpso._src import sharding
from jaxpso._src import similarity

SIMILARITIES = ("mi", "ncc", "ssd")
"""Names accepted by `TrackConfig.similarity`."""
MOTIONS = ("homography", "plane")
"""Names accepted by `TrackConfig.motion`."""
DOFS = (2, 4, 6)
"""Values accepted by `TrackConfig.dof` (motion "plane")."""


# Gauss–Newton stops once a step moves the corners by under this many pixels
# of the level being refined.
_TOLERANCE = 0.01


class AlignStatus(enum.IntEnum):
  """Outcome of an alignment; 0 is success."""
  SUCCESS = 0
  NO_VALID_WARP = 1


# `TrackConfig.levels=None`: the coarsest level keeps the template's shorter
# side at least COARSEST_PX pixels, with at most AUTO_LEVELS levels.
COARSEST_PX, AUTO_LEVELS = 12, 4


# `TrackConfig.lost_quality=None`: the quality below which a frame is lost.
LOST_QUALITY = {"mi": 0.65, "ncc": 0.8, "ssd": 0.5}


@dataclasses.dataclass(frozen=True)
class TrackConfig:
  """Static settings of `align` and `track`; a change recompiles.

  Attributes:
    method: "pso" (default: the swarm, then Gauss–Newton) or a gradient
      baseline of `jaxpso.baselines` ("fa", "fc", "ic", "esm", "ha", "adam",
      "lbfgs", "ecc"; `jaxpso.METHODS`), which starts from the start alone,
      runs at most `max_iterations` per pyramid level and has no retry or
      recovery search.
    similarity: "mi" (default), "ncc" or "ssd".
    motion: "homography" (8 corner offsets) or "plane" (plane-induced, `dof`).
    dof: pose parameters of motion "plane": 2 (tx, ty), 4 (+ tz, wz) or 6.
    bins: histogram bins of MI (16: 100 % vs 70 % success at σ = 2 with 8;
      benchmarks/convergence.py).
    swarm_size: particles of the swarm.
    max_iterations: PSO iterations at most (a baseline's per level).
    patience: PSO stagnation stop (None disables).
    variant: PSO variant (`jaxpso.pso.VARIANTS`).
    topology: PSO topology (`jaxpso.pso.TOPOLOGIES`).
    search_radius: half-width, in full-resolution pixels of corner motion, of
      the box searched in every motion parameter around the start.
    levels: pyramid levels; the swarm searches the coarsest.  None (the
      default): as many as keep the template's shorter side at least
      `COARSEST_PX` pixels on the coarsest level, at most `AUTO_LEVELS`
      (`for_template`): 4 for a 100×100 template, 3 for 48×48.  With 4
      levels a 48×48 template's coarsest level is 6×6, and on a clip
      translating 5 px a frame 4 of its 12 fully visible frames came out
      10–14 px off (quality 0.41–0.51); with 3, none
      (tests/test_track.py::test_small_templates_get_fewer_levels).
    refine_steps: Gauss–Newton (Levenberg–Marquardt) steps per pyramid level
      after the swarm (0 disables the refinement).
    pixels: fraction of the full-resolution template's pixels the
      refinement uses there, those with the largest gradient magnitude (at
      least 256 or all of them); 1 uses every pixel.  The coarser levels and
      the swarm always use every pixel (selecting at levels 1–3 as well
      made the refinement from the start converge less often: at σ = 8 px
      the swarm had to run in most trials, 15 ms vs 10 ms per alignment).
    accept_quality: the start refined by Gauss–Newton alone is the result,
      and the swarm is skipped, when its `quality` reaches this; None always
      runs the swarm.  `align` refines a start that falls short once more
      from the coarsest level before it runs the swarm: at σ = 12 px
      (benchmarks/convergence.py) the swarm then ran in 38 % of the trials
      instead of 74 %, with success unchanged or higher at every σ.
    min_valid: fraction of template pixels that must land in the image.
    predict: `track` starts each frame from a constant-velocity prediction
      (or the previous estimate, whichever scores better).  Off by default:
      on the synthetic 200-frame sequences it changed nothing for motion
      "homography" and, for "plane", let the pose drift along the
      translation/rotation ambiguity (benchmarks/tracking.py).
    lost_quality: `track` declares a frame lost when its `quality` stays
      below this after the recovery search (`lost_threshold`).  None (the
      default): `LOST_QUALITY` of the similarity, above the wrong matches
      measured and below every correct frame.  Correct frames of three
      60-frame synthetic sequences (jumps, gain drift, noise up to 0.03,
      blur, camera and brick textures) scored at least 0.83 (MI), 0.975
      (NCC) and 0.79 (SSD); wrong ones, reported TRACKED under the former
      single threshold 0.5: NCC 0.69–0.74 (a brick texture locked one
      period off after a jump, a target gone out of the frame), MI 0.50–0.62
      (chance matches of low-texture regions).
    retry_quality: `align` runs a second swarm (another seed,
      `recovery_scale` × the particles and the iterations, same box, one
      pyramid level finer) when the quality of its first result is below
      this and the swarm's result and the start's refinement disagree, and
      keeps the better result.  At σ = 16 / 20 px (50 trials each) the
      retry one level finer raised success from 94 / 92 % (same level) to
      98 / 92 %; the agreement test keeps correct alignments of a noisy
      image (quality 0.7–0.95) from paying for it (σ = 8, noise 0.03:
      111 → 24 ms median).
    recovery_scale: `track`'s recovery search has this many times the radius,
      iterations and particles of the normal search; its swarm searches the
      template's 2-D translation only, and Gauss–Newton the full motion from
      its best.  Over every motion parameter in the wide box the swarm
      seldom found a region that had moved while hidden: on occluded
      160×120 sequences (48 px template, 16 seeds) re-acquired within 5
      frames 11 / 4 of 16 times after 15 / 26 px of mean motion (motion
      "homography"), with the translation search 16 / 14
      (benchmarks/occlusion.py).
  """
  method: str = "pso"
  similarity: str = "mi"
  motion: str = "homography"
  dof: int = 6
  bins: int = 16
  swarm_size: int = 32
  max_iterations: int = 40
  patience: int | None = 10
  variant: str = "constriction"
  topology: str = "von_neumann"
  search_radius: float = 32.0
  levels: int | None = None
  refine_steps: int = 10
  pixels: float = 0.25
  accept_quality: float | None = 0.95
  min_valid: float = 0.5
  predict: bool = False
  lost_quality: float | None = None
  retry_quality: float = 0.95
  recovery_scale: int = 3

  def __post_init__(self):
    if self.similarity not in SIMILARITIES:
      raise ValueError(f"TrackConfig.similarity must be one of {SIMILARITIES}, got {self.similarity!r}")
    if self.motion not in MOTIONS:
      raise ValueError(f"TrackConfig.motion must be one of {MOTIONS}, got {self.motion!r}")
    if self.method not in baselines.METHODS:
      raise ValueError(f"TrackConfig.method must be one of {baselines.METHODS}, got {self.method!r}")
    baselines.check_supported(self.method, self.motion, self.similarity)
    if self.dof not in DOFS or isinstance(self.dof, bool):
      raise ValueError(f"TrackConfig.dof must be one of {DOFS}, got {self.dof!r}")
    for name in ("swarm_size", "max_iterations", "recovery_scale"):
      checks.check_int(getattr(self, name), f"TrackConfig.{name}", 1)
    if self.levels is not None:
      checks.check_int(self.levels, "TrackConfig.levels", 1)
    checks.check_int(self.bins, "TrackConfig.bins", 4)  # the B-spline kernel spans 4 bins
    checks.check_int(self.refine_steps, "TrackConfig.refine_steps", 0)
    if not 0 < checks.check_real(self.search_radius, "TrackConfig.search_radius") < math.inf:
      raise ValueError(
          f"TrackConfig.search_radius must be finite and > 0, got {self.search_radius!r}")
    if not 0.0 < checks.check_real(self.pixels, "TrackConfig.pixels") <= 1.0:
      raise ValueError(f"TrackConfig.pixels must be in (0, 1], got {self.pixels!r}")
    if not 0.0 < checks.check_real(self.min_valid, "TrackConfig.min_valid") <= 1.0:
      raise ValueError(f"TrackConfig.min_valid must be in (0, 1], got {self.min_valid!r}")
    for name in ("lost_quality", "retry_quality", "accept_quality"):
      value = getattr(self, name)
      if value is not None and not checks.check_real(value, f"TrackConfig.{name}") <= 1.0:
        raise ValueError(f"TrackConfig.{name} must be <= 1, got {value!r}")
    if not isinstance(self.predict, bool):
      raise TypeError(f"TrackConfig.predict must be a bool, got {self.predict!r}")
    self.pso_config()  # validates the PSO settings

  @property
  def lost_threshold(self) -> float:
    """`lost_quality`, or the similarity's `LOST_QUALITY` when it is None."""
    return LOST_QUALITY[self.similarity] if self.lost_quality is None else self.lost_quality

  def for_template(self, shape) -> "TrackConfig":
    """This config with `levels` chosen for a template of `shape` (h, w) when it is None."""
    return self if self.levels is not None else _with_levels(self, tuple(shape))

  def pso_config(self) -> pso.PSOConfig:
    """The swarm's settings (batched loss over the whole swarm)."""
    return pso.PSOConfig(swarm_size=self.swarm_size, variant=self.variant,
                         topology=self.topology, max_iterations=self.max_iterations,
                         patience=self.patience, batched=True)


@functools.lru_cache(maxsize=64)
def _with_levels(config: TrackConfig, shape: tuple) -> TrackConfig:
  """`TrackConfig.for_template`, cached (replace re-validates the config: 0.1 ms per call)."""
  levels = 1
  while levels < AUTO_LEVELS and min(shape) / 2 ** levels >= COARSEST_PX:
    levels += 1
  return dataclasses.replace(config, levels=levels)


class AlignResult(NamedTuple):
  """Outcome of `align`.

  Attributes:
    homography: (3, 3) template → image homography, h[2, 2] = 1.
    score: () the similarity at it (an error for "ssd", else higher is better).
    quality: () the score relative to the template's own (`quality`): about 1
      for a match, lower the worse.
    status: () int32 `AlignStatus`.
    num_iterations: () int32 PSO iterations plus refinement steps.
    num_evaluations: () int32 swarm evaluations (particles × iterations) plus
      refinement steps (each one similarity and its gradient).
    pose: (4, 4) camera motion from the view of `init_homography` to the
      image's for motion "plane" (translation in units of the plane's
      distance), else None.
  """
  homography: jax.Array
  score: jax.Array
  quality: jax.Array
  status: jax.Array
  num_iterations: jax.Array
  num_evaluations: jax.Array
  pose: jax.Array | None = None


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
  grey = array.astype(xp.float32)
  if array.dtype == np.uint8:
    grey = grey * xp.float32(1 / 255)
  if grey.ndim == 3:
    grey = grey @ xp.asarray([0.299, 0.587, 0.114], xp.float32)
  if min(grey.shape) < 2:
    raise ValueError(f"{name} must be at least 2×2 pixels, got shape {grey.shape}")
  checks.check_finite_if_concrete(grey, name)
  return grey


def _measure(config: TrackConfig):
  """loss(template or SoftBins, patches, mask) -> (...) to minimise, and the score's sign."""
  if config.similarity == "mi":
    return lambda a, b, m: -similarity.mi(a, b, m, min_valid=config.min_valid), -1.0
  if config.similarity == "ncc":
    return lambda a, b, m: -similarity.ncc(a, b, m, min_valid=config.min_valid), -1.0
  return lambda a, b, m: similarity.ssd(a, b, m, min_valid=config.min_valid), 1.0


class Template(NamedTuple):
  """A template prepared once for every registration against it (a pytree).

  Attributes:
    pyramid: `levels` arrays (h_l, w_l), full resolution first.
    bins: their soft-bin weights (h_l, w_l, bins) for "mi", binned over
      `value_range`, else the pyramid.
    selected: per level, the refinement's pixels (`TrackConfig.pixels`): a
      tuple (grid (h', w', 2) template points, their values (h', w'), their
      soft bins (h', w', bins) or values); the whole level when pixels = 1.
    value_range: (2,) the intensity range the template is binned over
      (`intensity_range`).
    self_loss: () the loss of the template against itself (for "ssd" its
      variance), the scale of `quality`.
  """
  pyramid: list
  bins: list
  selected: list
  value_range: jax.Array
  self_loss: jax.Array

  def reference(self, level: int, image_range=None, selected: bool = False):
    """What `_measure`'s loss takes as the template at `level` (or its selection).

    For "mi", soft bins against patches binned over `image_range` (2,)
    (default: the template's own range).
    """
    bins = self.selected[level][2] if selected else self.bins[level]
    if bins.ndim == 2:
      return bins
    lo, hi = self.value_range if image_range is None else image_range
    return similarity.SoftBins(bins, lo, hi)


# MI bins intensities over the range between these quantiles of the template
# (and, for the image, the union of that and the same range of the image where
# the start puts the template), widened by _RANGE_MARGIN of its span each way
# and at least _MIN_SPAN wide, so that a low-contrast template fills the bins
# instead of two or three of them: some failures of benchmarks/convergence.py
# with the fixed range [0, 1] were templates of intensity std 0.06–0.11.
# Measured on its 50 trials (successes at σ = 8 / 16): fixed range 47 / 46,
# image range alone 46 / 47, union 46 / 48.
# The quantiles are read off a histogram of _RANGE_HISTOGRAM bins between the
# extremes (to 1/1000 of the span): XLA's CPU sort of 10⁴ values, which
# jnp.quantile uses, took 1.6 ms, a third of a whole accepted alignment.
_RANGE_QUANTILES, _RANGE_MARGIN, _MIN_SPAN = (0.01, 0.99), 0.1, 0.05
_RANGE_HISTOGRAM = 1024


def intensity_range(values, mask) -> jax.Array:
  """(2,) the binning range of the (h, w) `values` where `mask`; (0, 1) if none is valid."""
  valid = mask & jnp.isfinite(values)
  least = jnp.min(jnp.where(valid, values, jnp.inf))
  span = jnp.max(jnp.where(valid, values, -jnp.inf)) - least
  span = jnp.where(span > 0, span, 1.0)
  index = jnp.clip(((values - least) / span * _RANGE_HISTOGRAM).astype(jnp.int32), 0,
                   _RANGE_HISTOGRAM - 1)
  counts = jnp.zeros(_RANGE_HISTOGRAM, jnp.float32).at[
      jnp.where(valid, index, _RANGE_HISTOGRAM).reshape(-1)].add(1.0, mode="drop")
  cumulative = jnp.cumsum(counts)
  bins = jnp.searchsorted(cumulative, jnp.asarray(_RANGE_QUANTILES) * cumulative[-1])
  lo, hi = least + (bins + 0.5) * (span / _RANGE_HISTOGRAM)
  centre = 0.5 * (lo + hi)
  half = jnp.maximum(hi - lo, _MIN_SPAN) * (0.5 + _RANGE_MARGIN)
  both = jnp.stack([centre - half, centre + half])
  return jnp.where(jnp.any(mask) & jnp.all(jnp.isfinite(both)), both, jnp.asarray([0.0, 1.0]))


# The pixel selection keeps at least this many pixels per level.
_MIN_PIXELS = 256


def _select(template, bins, fraction: float):
  """`Template.selected` entry: the pixels of largest gradient magnitude."""
  grid = sampling.template_grid(template.shape)
  count = max(_MIN_PIXELS, math.ceil(fraction * template.size))
  if count >= template.size:
    return grid, template, bins
  gy, gx = jnp.gradient(template)
  _, chosen = jax.lax.top_k((gx * gx + gy * gy).reshape(-1), count)

  def pick(a):
    return a.reshape((template.size,) + a.shape[2:])[chosen][None]

  return pick(grid), pick(template), pick(bins)


def prepare_template(template, config: TrackConfig) -> Template:
  """(h, w) grey template → `Template` (its pyramid, soft bins and selection)."""
  pyramid = sampling.gaussian_pyramid(template, config.levels)
  value_range = intensity_range(template, jnp.ones(template.shape, bool))
  bins = ([similarity.soft_bins(t, bins=config.bins, value_range=tuple(value_range)).weights
           for t in pyramid] if config.similarity == "mi" else pyramid)
  selected = [_select(t, b, config.pixels if level == 0 else 1.0)
              for level, (t, b) in enumerate(zip(pyramid, bins))]
  prepared = Template(pyramid, bins, selected, value_range, jnp.var(template))
  if config.similarity != "ssd":
    loss_of, _ = _measure(config)
    prepared = prepared._replace(
        self_loss=loss_of(prepared.reference(0), template, jnp.ones(template.shape, bool)))
  return prepared


def prepare_frame(image, config: TrackConfig) -> tuple[list, list]:
  """(H, W) grey image, or (R, H, W) images → each pyramid level packed by `sampling.pack_quads`
  (((H_l−1)·(W_l−1), 4), with the leading R if batched), and the levels' (H_l, W_l)."""
  def packed(image):
    return [sampling.pack_quads(level) for level in sampling.gaussian_pyramid(image, config.levels)]

  shapes = [tuple(image.shape[-2:])]
  for _ in range(config.levels - 1):
    shapes.append(tuple((size + 1) // 2 for size in shapes[-1]))  # what pyr_down gives
  return (jax.vmap(packed)(image) if image.ndim == 3 else packed(image)), shapes


def quality(loss, template: Template, patch, mask, image_range, config: TrackConfig):
  """The loss of the (h, w) `patch` (valid where `mask`) → () quality, about 1 for a match.

  "ssd": 1 − SSD / the template's variance; "ncc": NCC over the template's
  own; "mi": MI(T, I) / √(MI(T, T) · MI(I, I)), I the patch binned over
  `image_range`, so that a correct alignment scores near 1 under a monotone
  intensity change of the image too (on benchmarks/convergence.py's trials
  under gamma 0.5, correct alignments scored 0.82–0.99 against MI(T, T)
  alone, 0.94–0.98 with this normalisation; failures 0.04–0.86 either way).
  0 for a flat template or patch; -inf where the loss is (too few valid
  pixels).  It can exceed 1 slightly (soft binning).
  """
  if config.similarity == "ssd":
    scale, informative = template.self_loss, template.self_loss > 0
    ratio = loss / jnp.where(informative, scale, 1.0)
    value = 1.0 - ratio
  else:
    scale = template.self_loss  # −MI(T, T) or −NCC(T, T)
    if config.similarity == "mi":
      bins = similarity.soft_bins(patch, bins=config.bins, value_range=tuple(image_range))
      loss_of, _ = _measure(config)
      scale = -jnp.sqrt(jnp.maximum(scale * loss_of(bins, patch, mask), 0.0))
    informative = scale < 0
    value = loss / jnp.where(informative, scale, -1.0)
  return jnp.where(jnp.isfinite(loss), jnp.where(informative, value, 0.0), -jnp.inf)


class Registration(NamedTuple):
  """What `register` found (all arrays).

  Attributes:
    u: (D,) motion parameters relative to the base.
    homography: (3, 3) template → frame, h[2, 2] = 1.
    loss: () the loss at full resolution (+inf if too few pixels are valid).
    quality: () its `quality`.
    confirmed: () bool: accepted from the start alone, or the swarm's result
      and the start's refinement agree (within `_AGREE_PX` at every corner).
    num_iterations: () PSO iterations plus refinement steps (of both candidates).
    num_evaluations: () particle evaluations plus refinement steps.
  """
  u: jax.Array
  homography: jax.Array
  loss: jax.Array
  quality: jax.Array
  confirmed: jax.Array
  num_iterations: jax.Array
  num_evaluations: jax.Array


# Two registrations agree when no template corner is further apart than this
# (full-resolution pixels).
_AGREE_PX = 1.0


def _corner_gap(first, second, shape) -> jax.Array:
  """() the largest distance between the template corners that two (3, 3) homographies map."""
  gap = (homography.homography_to_corner_offsets(first, shape)
         - homography.homography_to_corner_offsets(second, shape))
  return jnp.max(jnp.linalg.norm(gap.reshape(4, 2), axis=-1))


class _Registrar:
  """One template's registration in one frame (unbatched): the pieces `register` maps over a batch.

  Args:
    frame: `prepare_frame` levels of one image.  frame_shapes: their (H, W).
    template: one `Template`.  base: the motion's base ((3, 3) start
    homography or (4, 4) base pose).  geometry: `motion.Plane` or None.
    image_range: (2,) the MI binning range of the image (`image_range`), else None.
  """

  def __init__(self, frame, frame_shapes, template: Template, base, geometry, image_range,
               config: TrackConfig):
    self.frame, self.frame_shapes, self.template = frame, frame_shapes, template
    self.image_range, self.config = image_range, config
    self.loss_of, _ = _measure(config)
    self.shape = template.pyramid[0].shape
    self.dim = motion.dimension(config.motion, config.dof)
    self.to_h = functools.partial(motion.to_homography, base=base, geometry=geometry,
                                  shape=self.shape, motion=config.motion, dof=config.dof)

  def at_level(self, u, level):
    return homography.homography_to_level(self.to_h(u), level)

  def warp_loss(self, level, reference, h, patches, mask):
    """The loss of warps h (…, 3, 3) at `level`; +inf where not admissible."""
    loss = self.loss_of(reference, patches, mask)
    return jnp.where(motion.admissible(h, self.template.pyramid[level].shape), loss, jnp.inf)

  def finish(self, u, iterations, evaluations, loss=None) -> Registration:
    """The registration at u, its loss over every pixel computed unless given."""
    h = self.at_level(u, 0)
    patch, mask = sampling.sample_quads(self.frame[0], self.frame_shapes[0], h, self.shape)
    if loss is None:
      loss = self.warp_loss(0, self.template.reference(0, self.image_range), h, patch, mask)
      evaluations += 1
    return Registration(u=u, homography=normalized(self.to_h(u)), loss=loss,
                        quality=quality(loss, self.template, patch, mask, self.image_range,
                                        self.config),
                        confirmed=jnp.asarray(False), num_iterations=iterations,
                        num_evaluations=evaluations)

  def baseline(self, max_iterations: int) -> Registration:
    """`TrackConfig.method`'s gradient registration from the base."""
    config, template = self.config, self.template
    u, loss, iterations, evaluations = baselines.register(
        config.method, self.frame, self.frame_shapes, template.pyramid, self.to_h, self.dim,
        lambda level, h, patches, mask: self.warp_loss(
            level, template.reference(level, self.image_range), h, patches, mask),
        similarity=config.similarity, levels=config.levels, iterations=max_iterations)
    return self.finish(u, iterations, evaluations, loss)

  def descend(self, u, top: int, iterations, evaluations) -> Registration:
    """u refined by Gauss–Newton from level `top` down to full resolution."""
    config = self.config
    for level in reversed(range(top + 1)):
      grid, values, bins = self.template.selected[level]
      reference = self.template.reference(level, self.image_range, selected=True)
      u, _, taken = refine.gauss_newton(
          u, self.frame[level], self.frame_shapes[level], grid, values,
          bins if config.similarity == "mi" else None,
          functools.partial(self.warp_loss, level, reference),
          functools.partial(self.at_level, level=level), config.refine_steps, config.similarity,
          _TOLERANCE * 2.0 ** level)
      iterations, evaluations = iterations + taken, evaluations + taken
    return self.finish(u, iterations, evaluations)  # the loss over every pixel

  def start(self, top: int = 1) -> Registration:
    """The start refined from level `top` (at most the coarsest) down."""
    zero = jnp.zeros([], jnp.int32)
    return self.descend(jnp.zeros(self.dim, jnp.float32), min(top, self.config.levels - 1), zero,
                        zero)

  def search(self, seed, radius, *, max_iterations: int, swarm_size: int, level: int,
             translation: bool) -> Registration:
    """The swarm at pyramid `level` over ±radius, its best refined down (see `register`)."""
    config, dim = self.config, self.dim
    reference = self.template.reference(level, self.image_range)

    def swarm_loss(u, _):  # u: (n, D)
      h = self.at_level(u, level)
      patches, mask = sampling.sample_quads(self.frame[level], self.frame_shapes[level], h,
                                            self.template.pyramid[level].shape)
      return self.warp_loss(level, reference, h, patches, mask)

    def lift(v):  # (…, 2) image translation → (…, D) parameters
      if config.motion == "homography":
        return jnp.tile(v, 4)
      return jnp.concatenate([v, jnp.zeros(v.shape[:-1] + (dim - 2,), v.dtype)], axis=-1)

    width = 2 if translation else dim  # the swarm's dimension
    to_u = lift if translation else (lambda v: v)
    box = jnp.full(width, radius, jnp.float32)
    pso_config = dataclasses.replace(config.pso_config(), max_iterations=max_iterations,
                                     swarm_size=swarm_size)
    found = pso._run(seed, -box, box, None, pso.default_hparams(config.variant), None, None,
                     jnp.zeros(width, jnp.float32), box,
                     loss_fn=lambda v, args: swarm_loss(to_u(v), args), config=pso_config)
    return self.descend(to_u(found.x), level, found.num_iterations, found.num_evaluations)


def image_range(frame, template: Template, base, geometry, *, frame_shapes, config: TrackConfig):
  """(2,) MI binning range: the template's and the image's where the base puts it (None unless MI)."""
  if config.similarity != "mi":
    return None
  shape = template.pyramid[0].shape
  h = motion.to_homography(jnp.zeros(motion.dimension(config.motion, config.dof), jnp.float32),
                           base=base, geometry=geometry, shape=shape, motion=config.motion,
                           dof=config.dof)
  lo, hi = intensity_range(*sampling.sample_quads(frame[0], frame_shapes[0], h, shape))
  return jnp.stack([jnp.minimum(lo, template.value_range[0]),
                    jnp.maximum(hi, template.value_range[1])])


def select(mask, first, second):
  """Per batch element, `first` where the (R,) `mask` holds, else `second` (pytrees, leading R)."""
  return jax.tree.map(
      lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - mask.ndim)), a, b),
      first, second)


def take(tree, indices):
  """The elements `indices` (C,) of every leaf's leading axis."""
  return jax.tree.map(lambda a: a[indices], tree)


def _share() -> int:
  """A batch of R runs its costly searches on ceil(R / _share()) elements at a time (`where_needed`).

  32 on a CPU, where the work is compute-bound and an idle slot of a round
  costs as much as a busy one: at R = 64 (about 4.5 regions needing the
  swarm per frame) a region-frame took 1.7 ms with 32, 2.3 ms with 8
  (benchmarks/batch.py's regions, 20 frames, with an unrolled Cholesky
  solve since reverted).  8 on accelerators, whose slots run in parallel
  (not measured on a GPU).
  """
  return 32 if jax.default_backend() == "cpu" else 8


def where_needed(mask, compute: Callable, otherwise):
  """`otherwise` with the elements where the (R,) `mask` holds replaced by `compute`'s.

  `compute(indices)` gets (C,) element indices and returns those elements'
  results (leading C).  Only the elements that need it are computed, C =
  ceil(R / _share()) at a time in a `lax.while_loop` of as many rounds as
  needed (none when no element does).  Under `vmap` a per-element
  `lax.cond` would run the costly branch (the swarm, the retry, the recovery
  search) for every element on every frame.
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

  # The cond keeps frames that need nothing from entering the loop at all:
  # with zero rounds it still cost a 1-region track 16 ms per frame (4 ms).
  return jax.lax.cond(needed > 0, rounds, lambda _: otherwise, None)


def register(frame: list, frame_shapes: list, template: Template, base, geometry, seed,
             radius, *, config: TrackConfig, max_iterations: int,
             swarm_size: int | None = None, accept: Callable | None = None,
             from_start: bool = True, search_level: int | None = None,
             translation: bool = False, coarse_start: bool = False,
             indices=None) -> Registration:
  """Gauss–Newton from the start, then, unless `accept`ed, the swarm and Gauss–Newton; batched.

  Every per-template argument and the result have a leading batch axis R.
  The start is refined from level 1 down (the coarser levels' optimum can be
  a wrong one near a start already in the right basin).  Where `accept` says
  its loss is good enough, that is the result; otherwise the swarm searches
  the coarsest level, its best is refined down to full resolution, and the
  better of the two is returned.  The swarm runs only for the elements that
  need it (`where_needed`).

  Args:
    frame: `prepare_frame` output, of one image shared by the batch
      ((H_l−1)(W_l−1), 4) or of one image per element (R, …).
    frame_shapes: their (H, W), static.
    template: `prepare_template` outputs stacked (R, …).
    base: (R, 3, 3) start homographies or (R, 4, 4) base poses.
    geometry: `motion.Plane` (R, …) for motion "plane", else None.
    seed: (R, 2) uint32 swarm seeds.  radius: () search half-width, pixels.
    config: settings.  max_iterations: the swarm's iteration cap (static).
    swarm_size: particles (static); `config.swarm_size` if None.
    accept: `Registration` → (R,) bool, or None to always run the swarm.
    from_start: refine the start (static); False runs the swarm alone.
    search_level: the pyramid level the swarm searches (static); the
      coarsest if None.
    translation: the swarm searches the template's 2-D image translation
      only (static): every corner offset alike for "homography", (tx, ty)
      for "plane"; the refinement then adjusts all parameters.
    coarse_start: where the start refined from level 1 is not accepted,
      refine it again from the coarsest level, and run the swarm only where
      the better of the two is not accepted either (static).
    indices: (C,) register only these elements (the result has the leading
      C); all if None.
  """
  frame_axis = 0 if frame[0].ndim == 3 else None
  batched = (frame_axis, 0, 0, 0)  # the axes of (frame, template, base, geometry)

  def subset(inputs, axes, indices):
    """The `indices` elements of the batched ones of `inputs` (all if indices is None)."""
    if indices is None:
      return inputs
    return tuple(x if axis is None else take(x, indices) for x, axis in zip(inputs, axes))

  frame, template, base, geometry, seed = subset((frame, template, base, geometry, seed),
                                                 batched + (0,), indices)
  ranges = jax.vmap(functools.partial(image_range, frame_shapes=frame_shapes, config=config),
                    in_axes=batched)(frame, template, base, geometry)

  def mapped(method, *args, indices=None):
    """`method` of every element's (or the `indices`') `_Registrar` (args batched on axis 0)."""
    def one(frame, template, base, geometry, image_range, *args):
      registrar = _Registrar(frame, frame_shapes, template, base, geometry, image_range, config)
      return method(registrar, *args)
    axes = batched + (0,) * (1 + len(args))
    return jax.vmap(one, in_axes=axes)(
        *subset((frame, template, base, geometry, ranges) + args, axes, indices))

  if config.method != "pso":
    return mapped(lambda r: r.baseline(max_iterations))

  def search(indices=None) -> Registration:
    return mapped(lambda r, s: r.search(
        s, radius, max_iterations=max_iterations, swarm_size=swarm_size or config.swarm_size,
        level=config.levels - 1 if search_level is None else search_level,
        translation=translation), seed, indices=indices)

  if not from_start:
    return search()
  start = mapped(_Registrar.start)
  good = jnp.zeros(start.loss.shape, bool) if accept is None else accept(start)
  if coarse_start and accept is not None and config.levels > 2:
    def coarse(indices) -> Registration:
      return better_of(take(start, indices), mapped(
          lambda r: r.start(top=config.levels - 1), indices=indices))
    start = where_needed(~good, coarse, start)
    good = accept(start)
  shape = template.pyramid[0].shape[1:]

  def searched(indices) -> Registration:
    found, began = search(indices), take(start, indices)
    gap = jax.vmap(_corner_gap, in_axes=(0, 0, None))(found.homography, began.homography, shape)
    return better_of(found, began)._replace(confirmed=gap <= _AGREE_PX)

  return where_needed(~good, searched, start._replace(confirmed=good))


def better_of(first: Registration, second: Registration) -> Registration:
  """Per element, the registration with the lower loss (the first on ties), counting both searches."""
  best = select(first.loss <= second.loss, first, second)
  return best._replace(num_iterations=first.num_iterations + second.num_iterations,
                       num_evaluations=first.num_evaluations + second.num_evaluations)


@functools.partial(compile_options.jit, static_argnames=("config",))
def _align(images, templates, init_homographies, offsets, seeds, geometry, *,
           config: TrackConfig) -> AlignResult:
  """`align` of a batch: (N, H, W) windows of the images whose top-left pixels are at `offsets` (N, 2).

  templates (N, h, w), init_homographies (N, 3, 3), seeds (N, 2); `geometry`
  is the `motion.Plane` (N, …) of motion "plane" in image coordinates, else
  None.  Every field of the result has the leading N axis.
  """
  _, sign = _measure(config)
  frame, shapes = prepare_frame(images, config)
  prepared = jax.vmap(functools.partial(prepare_template, config=config))(templates)
  to_window = jax.vmap(lambda o: homography.translation(-o[0], -o[1]))(offsets)
  start = to_window @ init_homographies
  if geometry is not None:  # the same plane seen in window coordinates
    geometry = geometry._replace(camera=to_window @ geometry.camera,
                                 template_to_frame0=to_window @ geometry.template_to_frame0)
    start = jnp.broadcast_to(jnp.eye(4, dtype=jnp.float32), (len(offsets), 4, 4))
  search = functools.partial(register, frame, shapes, prepared, start, geometry,
                             config=config)
  found = search(seeds, jnp.float32(config.search_radius), max_iterations=config.max_iterations,
                 coarse_start=True, accept=(None if config.accept_quality is None
                         else lambda found: found.quality >= config.accept_quality))
  weak = ~(found.quality >= config.retry_quality) & ~found.confirmed

  def retry(indices):
    # A poor match: a second, larger swarm one level finer.
    wide = search(seeds ^ jnp.uint32(0x5BD1E995), jnp.float32(config.search_radius),
                  max_iterations=config.max_iterations * config.recovery_scale,
                  swarm_size=config.swarm_size * config.recovery_scale, from_start=False,
                  search_level=max(0, config.levels - 2), indices=indices)
    return better_of(take(found, indices), wide)

  if config.method == "pso":
    found = where_needed(weak, retry, found)
  finite = jnp.isfinite(found.loss)
  to_image = jax.vmap(lambda o: homography.translation(o[0], o[1]))(offsets)
  pose = None
  if geometry is not None:
    pose = jax.vmap(functools.partial(motion.plane_pose, dof=config.dof))(found.u, start, geometry)
  return AlignResult(
      homography=jax.vmap(normalized)(to_image @ found.homography),
      score=sign * found.loss, quality=found.quality,
      status=jnp.where(finite, AlignStatus.SUCCESS, AlignStatus.NO_VALID_WARP).astype(jnp.int32),
      num_iterations=found.num_iterations, num_evaluations=found.num_evaluations, pose=pose)


def normalized(h) -> jax.Array:
  """(3, 3) h / h[2, 2] with h[2, 2] exactly 1 (XLA divides by multiplying)."""
  return (h / h[2, 2]).at[2, 2].set(1.0)


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


def check_template_size(shape, config: TrackConfig, name: str) -> None:
  """ValueError naming `name` when the coarsest pyramid level is under 4 px."""
  if min(shape) / 2 ** (config.levels - 1) < 4:
    raise ValueError(
        f"{name} of shape {tuple(shape)} is too small for levels={config.levels}:"
        " the coarsest level would be under 4 px")


def plane_geometry(camera, plane_normal, frame_shape, h0, shape, dof):
  """Validated `motion.Plane` from the user's camera and normal (None: the defaults).

  Args:
    camera: (3, 3) K or None (`plane.default_camera` of `frame_shape`).
    plane_normal: (3,) normal in frame-0 camera coordinates or None (0, 0, 1).
    frame_shape: (H, W) of the frame the template was cut from.
    h0: (3, 3) template → that frame.  shape: template (h, w).  dof: 2, 4 or 6.
  """
  k = (np.asarray(plane.default_camera(frame_shape), np.float64) if camera is None
       else np.asarray(camera, np.float64))
  if k.shape != (3, 3) or not np.all(np.isfinite(k)) or abs(np.linalg.det(k)) < 1e-12:
    raise ValueError(f"camera must be a finite, invertible 3×3 matrix, got {camera!r}")
  n = np.array([0.0, 0.0, 1.0]) if plane_normal is None else np.asarray(plane_normal, np.float64)
  if n.shape != (3,) or not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-9:
    raise ValueError(f"plane_normal must be a finite non-zero 3-vector, got {plane_normal!r}")
  n = n / np.linalg.norm(n)
  centre = np.asarray(h0, np.float64) @ np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2, 1.0])
  ray = np.linalg.solve(k, centre / centre[2])
  if not n @ ray > 1e-6:
    raise ValueError(
        f"plane_normal {plane_normal!r} puts the template's plane behind the camera: n·X = d > 0"
        " must hold for the points X seen in the template")
  return motion.plane_geometry(jnp.asarray(k, jnp.float32), jnp.asarray(n, jnp.float32), h0,
                               shape, dof)


def plane_geometries(camera, plane_normal, frame_shape, starts, shape, dof):
  """`plane_geometry` of each (3, 3) start in `starts` (R, 3, 3), stacked (leading R)."""
  return jax.tree.map(lambda *leaves: jnp.stack(leaves), *[
      plane_geometry(camera, plane_normal, frame_shape, np.asarray(h, np.float32), shape, dof)
      for h in starts])


def element_seeds(key, count: int) -> np.ndarray:
  """(count, 2) uint32 swarm seeds of a batch from one key; element 0's is the key's own.

  On the host: as device operations these cost 1 ms per `align` call.
  """
  seed = np.asarray(pso._as_seed(key))
  offsets = np.arange(count, dtype=np.uint32) * np.uint32(0x9E3779B9)  # wraps modulo 2³²
  return np.stack([np.full(count, seed[0]), seed[1] + offsets], axis=-1)


def _check_start(start, template_shape, name: str) -> np.ndarray:
  """A validated (3, 3) float64 start homography (ValueError naming `name`)."""
  start = np.asarray(start)
  if not np.issubdtype(start.dtype, np.number) or start.shape != (3, 3):
    raise ValueError(f"{name} must be a (3, 3) real matrix, got {start.dtype}{start.shape}")
  start = start.astype(np.float64)
  if not np.all(np.isfinite(start)) or abs(np.linalg.det(start)) < 1e-12:
    raise ValueError(f"{name} must be finite and invertible, got {start.tolist()!r}")
  # w of one sign at the corners: the template is not cut by the horizon (-H is H).
  rows, cols = template_shape
  corners = np.array([[0, 0], [cols - 1, 0], [cols - 1, rows - 1], [0, rows - 1]])
  depth = corners @ start[2, :2] + start[2, 2]
  if not (np.all(depth > 0) or np.all(depth < 0)):
    raise ValueError(f"{name} must map every template corner to a finite point"
                     f" (w of one sign), got w = {depth.tolist()} for {start.tolist()!r}")
  return start


def _batch(value, batched: bool, name: str) -> list:
  """The elements of a batched argument (a list of one if not batched)."""
  if not batched:
    return [value]
  if isinstance(value, (str, bytes)) or not hasattr(value, "__len__"):
    raise TypeError(f"{name} must be a batch (a leading N axis), got {type(value).__name__}")
  return list(value)


def align(image, template, init_homography, *, config: TrackConfig = TrackConfig(),
          key=0, camera=None, plane_normal=None, devices=None) -> AlignResult:
  """Registers `template` in `image`, starting from `init_homography`; or a batch of them.

  A batch of N alignments is one compiled program (`vmap`): pass images
  (N, H, W[, 3]), templates (N, h, w[, 3]) and init_homography (N, 3, 3)
  (all images of one size, all templates of one size); every field of the
  result gains the leading N axis.  With several devices the batch is split
  over them (`jax.sharding`), results equal to one device's.

  Args:
    image: (H, W) grey or (H, W, 3) colour, uint8 or float in [0, 1].
    template: (h, w) grey or (h, w, 3) colour, same conventions.
    init_homography: (3, 3) template pixel → image pixel (OpenCV convention).
    config: `TrackConfig`.  With motion "plane" the search is over `dof`
      camera-motion parameters from the view in which `init_homography`
      holds (pose identity) and the result has the `pose`.
    key: int seed or PRNG key of the swarm (element i of a batch gets its own
      stream; element 0 that of the unbatched call).
    camera: (3, 3) intrinsics K of `image` (motion "plane"); default
      f = max(H, W), principal point at the centre.  Shared by a batch.
    plane_normal: (3,) unit normal of the template's plane in the camera
      coordinates of that view, n·X = d > 0 (motion "plane"); default
      (0, 0, 1).  As for `track`; shared by a batch.
    devices: the `jax.Device`s a batch is split over; default every visible one.

  Returns:
    `AlignResult`.
  """
  if not isinstance(config, TrackConfig):
    raise TypeError(f"config must be a TrackConfig, got {type(config).__name__}")
  batched = np.ndim(init_homography) == 3
  starts = _batch(init_homography, batched, "init_homography")
  images = _batch(image, batched, "image")
  templates = _batch(template, batched, "template")
  if not len(images) == len(templates) == len(starts) >= 1:
    raise ValueError(
        f"a batch needs as many images, templates and init homographies (N >= 1), got"
        f" {len(images)}, {len(templates)} and {len(starts)}")

  def named(name, i):
    return f"{name}[{i}]" if batched else name

  images = [to_gray(x, named("image", i)) for i, x in enumerate(images)]
  templates = [to_gray(x, named("template", i)) for i, x in enumerate(templates)]
  for name, items in (("image", images), ("template", templates)):
    if any(x.shape != items[0].shape for x in items):
      raise ValueError(f"every {name} of a batch must have one shape, got"
                       f" {sorted({x.shape for x in items})}")
  check_texture(np.std(np.stack(templates), axis=(1, 2)), lambda i: named("template", i))
  shape, image_shape = templates[0].shape, images[0].shape
  config = config.for_template(shape)
  starts = [_check_start(h, shape, named("init_homography", i)) for i, h in enumerate(starts)]
  check_template_size(shape, config, "template")
  geometry = None
  if config.motion == "plane":
    geometry = plane_geometries(camera, plane_normal, image_shape, starts, shape, config.dof)
  elif camera is not None or plane_normal is not None:
    raise ValueError("camera and plane_normal apply to motion 'plane' only;"
                     f" got TrackConfig.motion={config.motion!r}")
  windows = np.array([_window(h, shape, image_shape, config) for h in starts])
  width, height = windows[:, 2].max(), windows[:, 3].max()  # one window size for the batch
  x0 = np.minimum(windows[:, 0], image_shape[1] - width)
  y0 = np.minimum(windows[:, 1], image_shape[0] - height)
  crops = np.stack([np.asarray(im[y:y + height, x:x + width]) for im, x, y in zip(images, x0, y0)])
  arguments = (crops, np.stack(templates), np.stack(starts).astype(np.float32),
               np.stack([x0, y0], axis=-1).astype(np.float32), element_seeds(key, len(starts)),
               geometry)
  mesh = sharding.batch_mesh(devices, len(starts))
  result = _align(*(arguments if mesh is None else sharding.split(arguments, mesh)), config=config)
  if mesh is not None and not all(a.is_fully_addressable for a in jax.tree.leaves(result)):
    result = sharding.to_host(result)  # spread over several processes (jax.distributed)
  if not batched:
    return _first(result)
  return jax.tree.map(lambda a: a[:len(starts)], result) if len(result.score) > len(starts) else result


# Element 0 of every field as one call (indexing each field eagerly cost 2 ms per `align`).
_first = jax.jit(lambda tree: jax.tree.map(lambda a: a[0], tree))


# The window `align` works in is a multiple of this many pixels each way, so
# that alignments of similar extent share one compiled program.
_WINDOW_STEP = 64


def _window(h, shape, image_shape, config: TrackConfig) -> tuple[int, int, int, int]:
  """(x0, y0, width, height) of the part of the image an alignment can reach.

  The start's quad grown by the search radius, the refinement's reach (the
  radius again) and the pyramid's border, rounded up to `_WINDOW_STEP`; the
  whole image when the start puts a corner at w <= 0.  Working in the window
  rather than the image cut `align`'s fixed cost (pyramid and packing)
  several-fold on 512×512 images.
  """
  rows, cols = image_shape
  corners = np.array([[0, 0, 1], [shape[1] - 1, 0, 1], [shape[1] - 1, shape[0] - 1, 1],
                      [0, shape[0] - 1, 1]], np.float64) @ h.T
  if not np.all(corners[:, 2] > 1e-9) or config.method == "ecc":  # ECC: OpenCV's exact numbers
    return 0, 0, cols, rows
  xy = corners[:, :2] / corners[:, 2:]
  margin = 2 * config.search_radius + 2 ** (config.levels + 1)
  lo = np.floor(xy.min(axis=0) - margin)
  hi = np.ceil(xy.max(axis=0) + margin)
  size = np.minimum(np.ceil((hi - lo) / _WINDOW_STEP) * _WINDOW_STEP, [cols, rows]).astype(int)
  start = np.clip(lo, 0, np.array([cols, rows]) - size).astype(int)
  return int(start[0]), int(start[1]), int(size[0]), int(size[1])
