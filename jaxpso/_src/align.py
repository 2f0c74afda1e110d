"""`align`: one registration of a template in an image, or a batch of them.

`align(image, template, init_homography)` prepares its inputs on the host
(the template's point sets, `jaxpso._src.template`; the image's pyramid
around the start, `jaxpso._src.atlas`) and runs one compiled program: the
stages of `jaxpso._src.register` (Gauss–Newton from the start; when that
does not reach `TrackConfig.accept_quality`, a coarser start, the swarm and
Gauss–Newton from its best; a retry when the swarm and the start disagree
on a poor match).  `TrackConfig.method` swaps the pipeline for a gradient
baseline (`jaxpso._src.baselines`).  Neither the image's nor the
template's size, nor any setting but the few `TrackConfig.statics`, enters
the compiled program, so one program serves every alignment of a
(similarity, motion, method, swarm) and is kept across processes
(`jaxpso._src.programs`).
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

from jaxpso._src import atlas
from jaxpso._src import baselines
from jaxpso._src import checks
from jaxpso._src import homography
from jaxpso._src import motion
from jaxpso._src import plane
from jaxpso._src import programs
from jaxpso._src import pso
from jaxpso._src import register
from jaxpso._src import sharding
from jaxpso._src import template as templates

SIMILARITIES = ("mi", "ncc", "ssd")
"""Names accepted by `TrackConfig.similarity`."""
MOTIONS = ("homography", "plane")
"""Names accepted by `TrackConfig.motion`."""
DOFS = (2, 4, 6)
"""Values accepted by `TrackConfig.dof` (motion "plane")."""


class AlignStatus(enum.IntEnum):
  """Outcome of an alignment; 0 is success."""
  SUCCESS = 0
  NO_VALID_WARP = 1


# `TrackConfig.levels=None`: the coarsest level keeps the template's shorter
# side at least COARSEST_PX pixels, with at most AUTO_LEVELS levels.
COARSEST_PX, AUTO_LEVELS = 12, atlas.MAX_LEVELS

# `TrackConfig.lost_quality=None`: the quality below which a frame is lost.
LOST_QUALITY = {"mi": 0.65, "ncc": 0.8, "ssd": 0.5}

# Supported template sides (pixels): the coarsest level needs a few pixels,
# and beyond the largest the template's pyramid would need more levels.
TEMPLATE_SIDES = (8, 4096)


@dataclasses.dataclass(frozen=True)
class TrackConfig:
  """Settings of `align` and `track`.

  Only method, similarity, motion, dof, bins, swarm_size, variant and
  topology shape the compiled programs (`statics`); every other setting
  reaches them as data (`knobs`), so changing it never recompiles.

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
    levels: pyramid levels (at most `AUTO_LEVELS`); the swarm searches the
      coarsest.  None (the default): as many as keep the template's shorter
      side at least `COARSEST_PX` pixels on the coarsest level, at most
      `AUTO_LEVELS` (`for_template`): 4 for a 100×100 template, 3 for 48×48.  With 4
      levels a 48×48 template's coarsest level is 6×6, and on a clip
      translating 5 px a frame 4 of its 12 fully visible frames came out
      10–14 px off (quality 0.41–0.51); with 3, none
      (tests/test_track.py::test_small_templates_get_fewer_levels).
    refine_steps: Gauss–Newton (Levenberg–Marquardt) steps per pyramid level
      after the swarm (0 disables the refinement).
    pixels: fraction of the full-resolution template's pixels the
      refinement uses there, those with the largest gradient magnitude (at
      least 256 or all of them, at most `resolution`); 1 uses
      every pixel.  The coarser levels and
      the swarm always use every pixel (selecting at levels 1–3 as well
      made the refinement from the start converge less often: at σ = 8 px
      the swarm had to run in most trials, 15 ms vs 10 ms per alignment).
    accept_quality: the start refined by Gauss–Newton alone is the result,
      and the swarm is skipped, when its `quality` reaches this; None always
      runs the swarm.  `track` also accepts a start within 0.02 of the quality
      of the region's last searched match (if that was ≥ 0.8): noise and blur lower the right
      alignment's quality too, and the swarm should not run on every frame
      for it (benchmarks/video.py).  `align` refines a start that falls short once more
      from the coarsest level before it runs the swarm: at σ = 12 px
      (benchmarks/convergence.py) the swarm then ran in 38 % of the trials
      instead of 74 %, with success unchanged or higher at every σ.
    resolution: points each of the template's sets holds at most (a pixel
      budget; static).  A template level with more keeps those of largest
      gradient, and the full-resolution loss and `quality` a regular
      subsample (every s-th row and column), so a region of any size costs
      at most this many points per set.  None (the default):
      `template.RESOLUTION` (2 560, about 50×50; the trade-off is measured
      in benchmarks/README.md, resolution).  At least 64 (8×8) and at most
      the template's pixels.
    min_valid: fraction of template pixels that must land in the image.
    predict: `track` starts each frame from a prediction carrying half the
      last inter-frame motion (or from the previous estimate, whichever
      scores better).  Half, not all: with all of it a plane pose's weakly
      constrained rotation/translation error grows by itself
      (benchmarks/tracking.py).  Off by default: it changes nothing on
      the synthetic sequences.
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
    retry_quality: `align` runs a second search (`recovery_scale` swarms of
      other seeds, each `recovery_scale` × the iterations, same box, one
      pyramid level finer) when the quality of its first result is below
      this and the swarm's result and the start's refinement disagree, and
      keeps the better result.  At σ = 16 / 20 px (50 trials each) the
      retry one level finer raised success from 94 / 92 % (same level) to
      98 / 92 %; the agreement test keeps correct alignments of a noisy
      image (quality 0.7–0.95) from paying for it (σ = 8, noise 0.03:
      111 → 24 ms median).
    recovery_scale: `track`'s recovery search has this many times the radius
      and iterations of the normal search, and as many swarms; its swarm searches the
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
  resolution: int | None = None
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
      if self.levels > AUTO_LEVELS:
        raise ValueError(f"TrackConfig.levels must be at most {AUTO_LEVELS}, got {self.levels!r}")
    checks.check_int(self.bins, "TrackConfig.bins", 4)  # the B-spline kernel spans 4 bins
    checks.check_int(self.refine_steps, "TrackConfig.refine_steps", 0)
    if not 0 < checks.check_real(self.search_radius, "TrackConfig.search_radius") < math.inf:
      raise ValueError(
          f"TrackConfig.search_radius must be finite and > 0, got {self.search_radius!r}")
    if not 0.0 < checks.check_real(self.pixels, "TrackConfig.pixels") <= 1.0:
      raise ValueError(f"TrackConfig.pixels must be in (0, 1], got {self.pixels!r}")
    if self.resolution is not None:
      checks.check_int(self.resolution, "TrackConfig.resolution", templates.MIN_RESOLUTION)
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

  def statics(self) -> "TrackConfig":
    """The settings that shape the compiled programs, the others at their defaults (a program's key)."""
    return _statics(self)

  def knobs(self) -> register.Knobs:
    """The runtime settings as `register.Knobs` of device scalars (made once per config)."""
    return _knobs(self)

  def host_knobs(self) -> register.Knobs:
    """`knobs` as NumPy scalars."""
    off = np.float32(np.inf)
    return register.Knobs(
        search_radius=np.float32(self.search_radius),
        max_iterations=np.int32(self.max_iterations),
        patience=np.int32(2**31 - 1 if self.patience is None else self.patience),
        refine_steps=np.int32(self.refine_steps),
        accept_quality=off if self.accept_quality is None else np.float32(self.accept_quality),
        retry_quality=np.float32(self.retry_quality),
        lost_quality=np.float32(self.lost_threshold), min_valid=np.float32(self.min_valid),
        recovery_scale=np.int32(self.recovery_scale), predict=np.bool_(self.predict))


@functools.lru_cache(maxsize=256)
def _knobs(config: TrackConfig) -> register.Knobs:
  return jax.tree.map(jnp.asarray, config.host_knobs())


_RUNTIME = ("search_radius", "max_iterations", "patience", "refine_steps", "accept_quality",
            "retry_quality", "lost_quality", "min_valid", "recovery_scale", "predict", "levels",
            "pixels")


@functools.lru_cache(maxsize=256)
def _statics(config: TrackConfig) -> TrackConfig:
  defaults = TrackConfig()
  config = dataclasses.replace(config, resolution=config.resolution or templates.RESOLUTION)
  if config.method != "pso":  # a baseline's loops are unrolled per level
    return dataclasses.replace(config, **{k: getattr(defaults, k) for k in _RUNTIME
                                          if k not in ("levels", "max_iterations", "min_valid")})
  return dataclasses.replace(config, **{k: getattr(defaults, k) for k in _RUNTIME})


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
    quality: () the score relative to the template's own (`register.quality`):
      about 1 for a match, lower the worse.
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
  grey = array.astype(xp.float32) if xp is jnp else array.astype(np.float32, copy=False)
  if array.dtype == np.uint8:
    grey = grey * xp.float32(1 / 255)
  if grey.ndim == 3:
    grey = grey @ xp.asarray([0.299, 0.587, 0.114], xp.float32)
  if min(grey.shape) < 2:
    raise ValueError(f"{name} must be at least 2×2 pixels, got shape {grey.shape}")
  checks.check_finite_if_concrete(grey, name)
  return grey


def score_sign(config: TrackConfig) -> float:
  """The sign that turns a loss into the similarity's score (SSD is reported as the error)."""
  return 1.0 if config.similarity == "ssd" else -1.0


def _result(found: register.Candidate, offsets, pose, config) -> AlignResult:
  """`AlignResult` of a batch's best candidates, homographies moved from window to image pixels."""
  to_image = jax.vmap(lambda o: homography.translation(o[0], o[1]))(offsets)
  finite = jnp.isfinite(found.loss)
  return AlignResult(
      homography=jax.vmap(register.normalized)(to_image @ found.homography),
      score=score_sign(config) * found.loss, quality=found.quality,
      status=jnp.where(finite, AlignStatus.SUCCESS, AlignStatus.NO_VALID_WARP).astype(jnp.int32),
      num_iterations=found.num_iterations, num_evaluations=found.num_evaluations, pose=pose)


@functools.partial(programs.Program, static_argnames=("config",))
def _align(images: atlas.Atlas, prepared: templates.Template, bases, geometry, seeds, offsets,
           knobs: register.Knobs, *, config: TrackConfig) -> AlignResult:
  """`align` of a batch of N: every argument has the leading N axis (knobs excepted).

  images: the `atlas.Atlas` of each image's window, whose top-left pixel is
  at `offsets` (N, 2) in the image; bases (N, 2, 3, 3) the start in window
  coordinates twice (or (N, 2, 4, 4) identity poses, with `geometry` the
  `motion.Plane`s in window coordinates); seeds (N, 2) uint32.
  """
  contexts = register.each(lambda *a: register.context(*a, config), images, prepared, bases,
                           geometry, seeds)
  found = register.run(contexts, knobs, "align", config).best
  pose = None
  if geometry is not None:
    pose = jax.vmap(functools.partial(motion.plane_pose, dof=config.dof))(
        found.u, bases[:, 0], geometry)
  return _result(found, offsets, pose, config)


@functools.partial(programs.Program, static_argnames=("config",))
def _align_baseline(images: atlas.Atlas, pyramids: list, prepared: templates.Template, bases,
                    geometry, seeds, offsets, knobs: register.Knobs, *,
                    config: TrackConfig) -> AlignResult:
  """`_align` with `config.method`'s gradient registration; `pyramids` the templates' levels, (N, h_l, w_l) each."""
  contexts = register.each(lambda *a: register.context(*a, config), images, prepared, bases,
                           geometry, seeds)
  found = register.each(lambda c, p: register.baseline(c, p, knobs, config), contexts, pyramids)
  pose = None
  if geometry is not None:
    pose = jax.vmap(functools.partial(motion.plane_pose, dof=config.dof))(
        found.u, bases[:, 0], geometry)
  return _result(found, offsets, pose, config)


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
  """ValueError naming `name` when a side is outside `TEMPLATE_SIDES`, the coarsest level is
  under 4 px or `TrackConfig.resolution` exceeds its pixels."""
  low, high = TEMPLATE_SIDES
  if not low <= min(shape) or not max(shape) <= high:
    raise ValueError(f"{name} of shape {tuple(shape)} is outside the supported sizes: every side"
                     f" must be {low} to {high} pixels")
  if config.resolution is not None and config.resolution > shape[0] * shape[1]:
    raise ValueError(f"TrackConfig.resolution={config.resolution} is larger than {name} of shape"
                     f" {tuple(shape)} ({shape[0] * shape[1]} pixels)")
  if min(shape) / 2 ** (config.levels - 1) < 4:
    raise ValueError(
        f"{name} of shape {tuple(shape)} is too small for levels={config.levels}:"
        " the coarsest level would be under 4 px")


def check_image_size(shape, config: TrackConfig, name: str) -> None:
  """ValueError naming `name` when the image's coarsest level would be under 2×2 pixels."""
  coarsest = atlas.level_shapes(shape, config.levels)[-1]
  if min(coarsest) < 2:
    raise ValueError(f"levels={config.levels} is too many for {name} of shape {tuple(shape)}:"
                     " its coarsest level would be smaller than 2×2")


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


def plane_geometries(camera, plane_normal, frame_shape, starts, shapes, dof):
  """`plane_geometry` of each (3, 3) start in `starts` (R, 3, 3) with template shapes `shapes`, stacked."""
  return jax.tree.map(lambda *leaves: np.stack(leaves), *[
      jax.tree.map(np.asarray, plane_geometry(camera, plane_normal, frame_shape,
                                              np.asarray(h, np.float32), shape, dof))
      for h, shape in zip(starts, shapes)])


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


def align(image, template, init_homography, *, config: TrackConfig = TrackConfig(),
          key=0, camera=None, plane_normal=None, devices=None) -> AlignResult:
  """Registers `template` in `image`, starting from `init_homography`; or a batch of them.

  A batch of N alignments is one compiled program (`vmap`): pass images
  (N, H, W[, 3]), templates (N, h, w[, 3]) and init_homography (N, 3, 3);
  the images may differ in size, and so may the templates (but with a
  gradient baseline, `TrackConfig.method`, the templates must share one
  shape).  Every field of the result gains the leading N axis.  With
  several devices the batch is split over them (`jax.sharding`), results
  equal to one device's up to float rounding.

  Args:
    image: (H, W) grey or (H, W, 3) colour, uint8 or float in [0, 1].
    template: (h, w) grey or (h, w, 3) colour, same conventions; each side
      `TEMPLATE_SIDES` (8 to 4096) pixels.
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
  templates_ = _batch(template, batched, "template")
  if not len(images) == len(templates_) == len(starts) >= 1:
    raise ValueError(
        f"a batch needs as many images, templates and init homographies (N >= 1), got"
        f" {len(images)}, {len(templates_)} and {len(starts)}")

  def named(name, i):
    return f"{name}[{i}]" if batched else name

  images = [np.asarray(to_gray(x, named("image", i))) for i, x in enumerate(images)]
  templates_ = [np.asarray(to_gray(x, named("template", i))) for i, x in enumerate(templates_)]
  if config.method != "pso" and any(t.shape != templates_[0].shape for t in templates_):
    raise ValueError(f"every template of a batch aligned by {config.method!r} must have one shape,"
                     f" got {sorted({t.shape for t in templates_})}")
  check_texture(np.array([np.std(t) for t in templates_]), lambda i: named("template", i))
  shapes = [t.shape for t in templates_]
  configs = [config.for_template(shape) for shape in shapes]
  for i, (shape, c) in enumerate(zip(shapes, configs)):
    check_template_size(shape, c, named("template", i))
  starts = [_check_start(h, shape, named("init_homography", i))
            for i, (h, shape) in enumerate(zip(starts, shapes))]
  if config.motion != "plane" and (camera is not None or plane_normal is not None):
    raise ValueError("camera and plane_normal apply to motion 'plane' only;"
                     f" got TrackConfig.motion={config.motion!r}")
  windows = [_window(h, shape, im.shape, c) for h, shape, im, c in zip(starts, shapes, images, configs)]
  crops = [im[y:y + hgt, x:x + wid] for im, (x, y, wid, hgt) in zip(images, windows)]
  for i, (crop, c) in enumerate(zip(crops, configs)):
    check_image_size(crop.shape, c, named("image", i))
  size = max(atlas.capacity(sum(h * w for h, w in atlas.level_shapes(crop.shape, c.levels)))
             for crop, c in zip(crops, configs))
  pyramids = [atlas.build(crop, c.levels, size) for crop, c in zip(crops, configs)]
  offsets = np.array([w[:2] for w in windows], np.float32)
  to_window = np.stack([np.array([[1, 0, -x], [0, 1, -y], [0, 0, 1]], np.float64)
                        for x, y in offsets])
  geometry = None
  if config.motion == "plane":
    geometry = plane_geometries(camera, plane_normal, images[0].shape, starts, shapes, config.dof)
    geometry = geometry._replace(camera=(to_window @ geometry.camera).astype(np.float32),
                                 template_to_frame0=(to_window @ geometry.template_to_frame0)
                                 .astype(np.float32))
    bases = np.broadcast_to(np.eye(4, dtype=np.float32), (len(starts), 2, 4, 4))
  else:
    bases = np.repeat((to_window @ np.stack(starts))[:, None], 2, axis=1).astype(np.float32)
  statics = config.statics()
  prepared = _stack([templates.prepared(t, c.levels, c.pixels, c.bins, statics.resolution)
                     for t, c in zip(templates_, configs)])
  arguments = (_stack(pyramids), prepared, bases, geometry, element_seeds(key, len(starts)),
               offsets)
  mesh = sharding.batch_mesh(devices, len(starts))
  if mesh is not None:
    arguments = sharding.split(arguments, mesh)
  knobs = config.knobs()
  if config.method == "pso":
    result = _align(*arguments, knobs, config=statics)
  else:
    levels = template_pyramids(templates_, configs[0].levels)
    result = _align_baseline(arguments[0], sharding.split(levels, mesh) if mesh else levels,
                             *arguments[1:], knobs,
                             config=dataclasses.replace(config, levels=configs[0].levels).statics())
  if mesh is not None and not all(a.is_fully_addressable for a in jax.tree.leaves(result)):
    result = sharding.to_host(result)  # spread over several processes (jax.distributed)
  if not batched:
    return _first(result)
  return jax.tree.map(lambda a: a[:len(starts)], result) if len(result.score) > len(starts) else result


def _stack(trees: list):
  """A list of equally structured NumPy pytrees → one with a leading axis (a view for one tree)."""
  if len(trees) == 1:
    return jax.tree.map(lambda leaf: np.asarray(leaf)[None], trees[0])
  return jax.tree.map(lambda *leaves: np.stack(leaves), *trees)


# Element 0 of every field as one call (indexing each field eagerly cost 2 ms per `align`).
_first = jax.jit(lambda tree: jax.tree.map(lambda a: a[0], tree))


def _window(h, shape, image_shape, config: TrackConfig) -> tuple[int, int, int, int]:
  """(x0, y0, width, height) of the part of the image an alignment can reach.

  The start's quad grown by the search radius, the refinement's reach (the
  radius again) and the pyramid's border; the whole image when the start
  puts a corner at w <= 0.  Working in the window rather than the image
  keeps the host's pyramid small.
  """
  rows, cols = image_shape
  corners = np.array([[0, 0, 1], [shape[1] - 1, 0, 1], [shape[1] - 1, shape[0] - 1, 1],
                      [0, shape[0] - 1, 1]], np.float64) @ h.T
  if not np.all(corners[:, 2] > 1e-9) or config.method == "ecc":  # ECC: OpenCV's exact numbers
    return 0, 0, cols, rows
  xy = corners[:, :2] / corners[:, 2:]
  margin = 2 * config.search_radius + 2 ** (config.levels + 1)
  lo = np.clip(np.floor(xy.min(axis=0) - margin), 0, [cols, rows]).astype(int)
  hi = np.clip(np.ceil(xy.max(axis=0) + margin) + 1, 0, [cols, rows]).astype(int)
  # At least the pyramid's needs each way: grow an empty or thin window around its centre.
  least = np.minimum(2 ** config.levels + 1, [cols, rows])
  grow = np.maximum(least - (hi - lo), 0)
  lo = np.clip(lo - grow // 2, 0, np.array([cols, rows]) - least)
  hi = np.maximum(hi, lo + least)
  return int(lo[0]), int(lo[1]), int(hi[0] - lo[0]), int(hi[1] - lo[1])
