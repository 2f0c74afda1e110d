"""The settings of `align` and `track`: `TrackConfig` and the names it accepts.

Why a module of its own: `align`, `track`, the registration stages they
compile (`jaxpso._src.register`, the gradient baselines) and the command
line all read one `TrackConfig`, and `track` should not reach it through
`align`; neither of them is imported here.  `TrackConfig` splits its
settings in two: the few `statics` that shape a compiled program (and key
it, `jaxpso._src.programs`) and the runtime `knobs` that reach the program
as data, so that changing them never recompiles.  The measured reasons for
its defaults are in benchmarks/README.md (Measured reasons behind defaults).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import numpy as np

from jaxpso._src import atlas
from jaxpso._src import baselines
from jaxpso._src import checks
from jaxpso._src import problem as problems
from jaxpso._src import pso
from jaxpso._src import template as templates

SIMILARITIES = ("mi", "ncc", "ssd")
"""Names accepted by `TrackConfig.similarity`."""
MOTIONS = ("homography", "plane")
"""Names accepted by `TrackConfig.motion`."""
DOFS = (2, 4, 6)
"""Values accepted by `TrackConfig.dof` (motion "plane")."""

# `TrackConfig.levels=None`: the coarsest level keeps the template's shorter
# side at least COARSEST_PX pixels, with at most AUTO_LEVELS levels.
COARSEST_PX, AUTO_LEVELS = 12, atlas.MAX_LEVELS

# `TrackConfig.lost_quality=None`: the quality below which a frame is lost.
LOST_QUALITY = {"mi": 0.65, "ncc": 0.8, "ssd": 0.5}
# `TrackConfig.hopeless_quality=None`: align skips its full search and
# retries where the best after its quick searches stays under this, and its
# retries where the full search's does (-inf: never).  NCC on convergence.py's
# trials (6 conditions, σ 4-20, 50 each, 2026-11-27): after the starts and
# the full search the inverted image's best is under 0.3 on 211 of 249
# trials, every later success's at least 0.40 (1 149 of 1 494).  It costs
# one of runtime.py's 100 noise trials (σ 0.08): 0.18 after the search, a
# retry found the truth at 0.51; at 0.2 the same, at 0.15 the inverted
# calls keep their retries (median 142 against 17 ms).  MI finds 8 of its
# 1 478 successes in a retry after a search best of 0.03-0.07, so it has
# none.  SSD has none either: its successes reach down to -0.32 after the
# search (gain and shading lower its quality); -0.5 would stop 149 of 249
# inverted calls, but on test_align's inverted image a warp that collapses
# the template scores -0.23 to 0.38 and none would stop.  Stopping NCC
# after the quick searches too (convergence.py, 36 cells × 50, 2026-12-07)
# left every cell's success as it was and the inverted image's median
# evaluations fell from 1 986-1 996 to 652-660.
HOPELESS_QUALITY = {"mi": -math.inf, "ncc": 0.3, "ssd": -math.inf}
COAST_DECAY = 0.8
"""`TrackConfig.coast`: the k-th lost frame (k = 0, 1, ...) moves the estimate by this to the
k-th power of the last inter-frame motion (in all about 5 frames' worth)."""


@dataclasses.dataclass(frozen=True)
class TrackConfig:
  """Settings of `align` and `track`.

  The measurements behind the defaults: benchmarks/README.md, "Measured
  reasons behind defaults".

  Only method, similarity, motion, dof, bins, swarm_size, variant,
  topology and resolution shape the compiled programs (`statics`); every other setting
  reaches them as data (`knobs`), so changing it never recompiles.

  Attributes:
    method (str): "pso" (default: the swarm, then Gauss–Newton) or a gradient
      baseline of `jaxpso.baselines` ("fa", "fc", "ic", "esm", "ha", "adam",
      "lbfgs", "ecc"; `jaxpso.METHODS`), which starts from the start alone,
      runs at most `max_iterations` per pyramid level and has no retry or
      recovery search.
    similarity (str): "mi" (default), "ncc" or "ssd".
    motion (str): "homography" (8 corner offsets) or "plane" (plane-induced, `dof`).
    dof (int): pose parameters of motion "plane": 2 (tx, ty), 4 (+ tz, wz) or 6.
    bins (int): histogram bins of MI, at least 4.
    swarm_size (int): particles of the swarm.
    max_iterations (int): PSO iterations at most (a baseline's per level).
    quick_iterations (int): `align`'s search first runs one swarm of this
      many iterations, then where that falls short a second one on other
      seeds (one pyramid level finer where the first disagreed with the
      start's refinements); a quick search's refined best is the result
      where it reaches `retry_quality` or agrees within 1 px with the best
      so far on a quality of at least 0.8, and only otherwise the search of
      `max_iterations` runs.  0 skips them.  Whatever the quality, `align`
      also settles on its best once three of its estimates (Gauss–Newton
      from the start at two levels, each search's) agree with it within
      2 px: noise or a real change of appearance keeps a right match's
      quality far under the thresholds.  `track` runs a quick search
      where the start falls short, a second one (other seeds) where that is
      neither accepted nor, not lost, confirmed by both starts (within
      1 px) or by the best so far on a quality of at least 0.8, and the
      full search only where the second falls short the same way.
    patience (int | None): PSO stagnation stop (None disables).
    variant (str): PSO variant (`jaxpso.pso.VARIANTS`).
    topology (str): PSO topology (`jaxpso.pso.TOPOLOGIES`).
    search_radius (float): half-width, in full-resolution pixels of corner
      motion, of the box searched in every motion parameter around the start.
    levels (int | None): pyramid levels (at most `AUTO_LEVELS`); the swarm
      searches the coarsest.  None (the default): as many as keep the
      template's shorter side at least `COARSEST_PX` pixels on the coarsest
      level, at most `AUTO_LEVELS` (`for_template`): 4 for a 100×100
      template, 3 for 48×48; and none coarser than the first on which the
      template's texture is flat (a 1 px checkerboard: 1 level).
    refine_steps (int): Gauss–Newton (Levenberg–Marquardt) steps per pyramid
      level after the swarm (0 disables the refinement).
    pixels (float): fraction in (0, 1] of the full-resolution template's
      pixels the refinement uses there, those with the largest gradient
      magnitude (at least 256 or all of them, at most `resolution`); 1 uses
      every pixel.  The coarser levels and the swarm always use every pixel.
    accept_quality (float | None): the start refined by Gauss–Newton alone
      is the result, and the swarm is skipped, when its `quality` reaches
      this; None always runs the swarm.  `track` also accepts a start within
      0.02 of the quality of the region's last searched match (if that was
      ≥ 0.8): noise and blur lower the right alignment's quality too, and the
      swarm should not run on every frame for it; but a start that moved
      more than 8 px to a quality under that 0.02 margin waits for the
      coarser refinement below to agree.  `align` refines its start from
      the coarsest level first and accepts that alone from a quality of
      0.99 (or this, if higher); under it, the start refined from level 1
      too, the better of the two counts, accepted at this quality or where
      both agree within 1 px on a quality of at least 0.35 (under image
      noise or on a real second view the right alignment's quality stays
      far under 0.95).
    resolution (int | None): points each of the template's sets holds at
      most (a pixel budget; static).  A template level with more keeps those
      of largest gradient, and the full-resolution loss and `quality` a
      regular subsample (every s-th row and column), so a region of any size
      costs at most this many points per set.  None (the default):
      `template.RESOLUTION` (1 280, about 36×36).  At least 64 (8×8) and at
      most the template's pixels.
    min_valid (float): fraction of template pixels that must land in the image.
    predict (bool): `track` starts each frame from a prediction carrying half
      the last inter-frame motion (or from the previous estimate, whichever
      scores better).  Half, not all: with all of it a plane pose's weakly
      constrained rotation/translation error grows by itself.
    lost_quality (float | None): `track` declares a frame lost when its
      `quality` stays below this after the recovery search
      (`lost_threshold`).  None (the default): `LOST_QUALITY` of the
      similarity, between the scores of wrong and of correct matches.
    retry_quality (float): `align` runs a second search (`retry_scale`
      swarms of other seeds, each `retry_scale` × the iterations, same
      box, one pyramid level finer) when the quality of its first result is
      below this and the swarm's result and the start's refinement disagree,
      and keeps the better result.
    hopeless_quality (float | None): `align` runs neither its full search
      nor a retry where the best of its starts and quick searches stays
      under this quality (`hopeless_threshold`), nor a retry where the full
      search's does, and its status is `AlignStatus.NO_MATCH`: an image that
      holds no match for the similarity (NCC on an inverted image) ends
      after its quick searches instead of every retry.  None (the
      default): `HOPELESS_QUALITY` of the similarity (NCC 0.3; MI and SSD
      never).
    retries (int): `align` runs the retry again with other seeds, up to this
      many more times, while its result stays below `retry_quality` and
      disagrees (a corner over 1 px apart) with the best so far, and keeps
      the lowest loss.  Two independent searches that agree confirm a
      result whatever the image noise; where they disagree at least one is
      wrong.  0 is the single retry.
    redetect (bool): on every frame `track` would report LOST it registers
      the region's visible part, then (a region moving fast) its template
      smeared along its motion, then runs `jaxpso.detect` (the template
      searched in the whole frame at any rotation and a scale of 0.5–2×,
      `motion_blur` on); a match whose quality reaches `lost_threshold` is
      TRACKED (a detection RECOVERED) and the next frames continue from
      it; a detection well under the region's best quality is DOUBTFUL,
      and challenged by `detect` on the next frames.  A periodic template's
      match moves to the template shift that correlates best around it,
      DOUBTFUL where another one does as well (`periodic`).  With it or
      `coast`, a match mirrored, folded or whose sides jump more than 1.5×
      in a frame is LOST, then re-acquired as above.  Off: a
      lost region keeps its last good estimate until the recovery search
      around it finds the target again.
    max_evaluations (int or None): the budget of one `align` call, or of
      one region's frame in `track`, in similarity evaluations (particles ×
      iterations plus refinement steps, `AlignResult.num_evaluations`): the
      stages stop once they have spent it and the best so far is the result,
      `AlignStatus.BUDGET` where the search had not settled.  Checked
      between stages, so a call overshoots by at most its last stage.  None:
      no cap.  The default lets `align` run its searches and one or two
      retries.
    coast (bool): on a frame `track` reports LOST, the region's estimate
      moves on with its last inter-frame motion, damped by `COAST_DECAY`
      per lost frame (a target hidden while it moves is looked for, and
      reported, where it went); a region leaving the frame (last TRACKED
      under 3/4 inside) moves on by the whole shift of its centre,
      keeping its shape, and stops at its last place partly inside, and
      where at least 15 % of it is inside it moves with that part
      (`visible.followed`); off: the last good estimate is kept.
    recovery_scale (int): `track`'s recovery search has this many times the
      radius and iterations of the normal search, and as many swarms; its
      swarm searches the template's 2-D translation only, and Gauss–Newton
      the full motion from its best.
    retry_scale (int): `align`'s retry has this many swarms, each with this
      many times the iterations of the normal search (`retry_quality`).
      Measured against 3 on convergence.py's trials (MI and NCC, 6
      conditions × σ 2-20 × 50, 2026-11-27): no cell lower, 6 higher, a
      quarter fewer evaluations in each cell's slowest call (median); 1
      lost a trial in 4 MI cells (benchmarks/README.md).
  """
  method: str = "pso"
  similarity: str = "mi"
  motion: str = "homography"
  dof: int = 6
  bins: int = 16
  swarm_size: int = 32
  max_iterations: int = 40
  quick_iterations: int = 8
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
  hopeless_quality: float | None = None
  retries: int = 4
  recovery_scale: int = 3
  retry_scale: int = 2
  redetect: bool = True
  coast: bool = True
  max_evaluations: int | None = 20000

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
    for name in ("swarm_size", "max_iterations", "recovery_scale", "retry_scale"):
      checks.check_int(getattr(self, name), f"TrackConfig.{name}", 1)
    if self.levels is not None:
      checks.check_int(self.levels, "TrackConfig.levels", 1)
      if self.levels > AUTO_LEVELS:
        raise ValueError(f"TrackConfig.levels must be at most {AUTO_LEVELS}, got {self.levels!r}")
    checks.check_int(self.bins, "TrackConfig.bins", 4)  # the B-spline kernel spans 4 bins
    checks.check_int(self.refine_steps, "TrackConfig.refine_steps", 0)
    checks.check_int(self.retries, "TrackConfig.retries", 0)
    checks.check_int(self.quick_iterations, "TrackConfig.quick_iterations", 0)
    if not 0 < checks.check_real(self.search_radius, "TrackConfig.search_radius") < math.inf:
      raise ValueError(
          f"TrackConfig.search_radius must be finite and > 0, got {self.search_radius!r}")
    if not 0.0 < checks.check_real(self.pixels, "TrackConfig.pixels") <= 1.0:
      raise ValueError(f"TrackConfig.pixels must be in (0, 1], got {self.pixels!r}")
    if self.resolution is not None:
      checks.check_int(self.resolution, "TrackConfig.resolution", templates.MIN_RESOLUTION)
    if not 0.0 < checks.check_real(self.min_valid, "TrackConfig.min_valid") <= 1.0:
      raise ValueError(f"TrackConfig.min_valid must be in (0, 1], got {self.min_valid!r}")
    for name in ("lost_quality", "retry_quality", "accept_quality", "hopeless_quality"):
      value = getattr(self, name)
      if value is not None and not checks.check_real(value, f"TrackConfig.{name}") <= 1.0:
        raise ValueError(f"TrackConfig.{name} must be <= 1, got {value!r}")
    if self.max_evaluations is not None and checks.check_int(
        self.max_evaluations, "TrackConfig.max_evaluations", 1) >= 2**31 - 1:
      raise ValueError(f"TrackConfig.max_evaluations must be < 2**31 - 1 (or None), got"
                       f" {self.max_evaluations!r}")
    for name in ("predict", "redetect", "coast"):
      if not isinstance(getattr(self, name), bool):
        raise TypeError(f"TrackConfig.{name} must be a bool, got {getattr(self, name)!r}")
    self.pso_config()  # validates the PSO settings

  @property
  def lost_threshold(self) -> float:
    """`lost_quality`, or the similarity's `LOST_QUALITY` when it is None."""
    return LOST_QUALITY[self.similarity] if self.lost_quality is None else self.lost_quality

  @property
  def hopeless_threshold(self) -> float:
    """`hopeless_quality`, or the similarity's `HOPELESS_QUALITY` when it is None."""
    if self.hopeless_quality is None:
      return HOPELESS_QUALITY[self.similarity]
    return self.hopeless_quality

  def for_template(self, shape, template: np.ndarray | None = None,
                   coarsest: float = COARSEST_PX) -> "TrackConfig":
    """This config with `levels` chosen for a template of `shape` (h, w) when it is None: as
    many as keep its shorter side at least `coarsest` pixels.

    Given the template's (h, w) pixels, the levels also end above the first
    that shows none of its texture (`template.textured_levels`).
    """
    if self.levels is not None:
      return self
    config = _with_levels(self, tuple(shape), coarsest=coarsest)
    if template is None:
      return config
    return _with_levels(self, tuple(shape), templates.textured_levels(template, config.levels),
                        coarsest)

  def pso_config(self) -> pso.PSOConfig:
    """The swarm's settings (batched loss over the whole swarm)."""
    return pso.PSOConfig(swarm_size=self.swarm_size, variant=self.variant,
                         topology=self.topology, max_iterations=self.max_iterations,
                         patience=self.patience, batched=True)

  def statics(self) -> "TrackConfig":
    """The settings that shape the compiled programs, the others at their defaults (a program's key)."""
    return _statics(self)

  def knobs(self) -> problems.Knobs:
    """The runtime settings as `problem.Knobs` of device scalars (made once per config)."""
    return _knobs(self)

  def host_knobs(self) -> problems.Knobs:
    """`knobs` as NumPy scalars."""
    off = np.float32(np.inf)
    return problems.Knobs(
        search_radius=np.float32(self.search_radius),
        max_iterations=np.int32(self.max_iterations),
        quick_iterations=np.int32(self.quick_iterations),
        patience=np.int32(2**31 - 1 if self.patience is None else self.patience),
        refine_steps=np.int32(self.refine_steps),
        accept_quality=off if self.accept_quality is None else np.float32(self.accept_quality),
        retry_quality=np.float32(self.retry_quality),
        hopeless_quality=np.float32(self.hopeless_threshold), retries=np.int32(self.retries),
        lost_quality=np.float32(self.lost_threshold), min_valid=np.float32(self.min_valid),
        recovery_scale=np.int32(self.recovery_scale), retry_scale=np.int32(self.retry_scale),
        predict=np.bool_(self.predict),
        max_evaluations=np.int32(2**31 - 1 if self.max_evaluations is None
                                 else self.max_evaluations))


@functools.lru_cache(maxsize=256)
def _knobs(config: TrackConfig) -> problems.Knobs:
  return jax.device_put(config.host_knobs())  # jnp.asarray compiles a program per dtype


_RUNTIME = ("search_radius", "max_iterations", "quick_iterations", "patience", "refine_steps",
            "accept_quality", "retry_quality", "hopeless_quality", "retries", "lost_quality",
            "min_valid", "recovery_scale", "retry_scale", "predict", "redetect", "coast",
            "max_evaluations", "levels", "pixels")


@functools.lru_cache(maxsize=256)
def _statics(config: TrackConfig) -> TrackConfig:
  defaults = TrackConfig()
  config = dataclasses.replace(config, resolution=config.resolution or templates.RESOLUTION)
  if config.method != "pso":  # a baseline's loops are unrolled per level
    return dataclasses.replace(config, **{k: getattr(defaults, k) for k in _RUNTIME
                                          if k not in ("levels", "max_iterations", "min_valid")})
  return dataclasses.replace(config, **{k: getattr(defaults, k) for k in _RUNTIME})


@functools.lru_cache(maxsize=64)
def _with_levels(config: TrackConfig, shape: tuple, most: int = AUTO_LEVELS,
                 coarsest: float = COARSEST_PX) -> TrackConfig:
  """`TrackConfig.for_template` with at most `most` levels, cached (`dataclasses.replace`
  re-validates the config)."""
  levels = 1
  while levels < min(most, AUTO_LEVELS) and min(shape) / 2 ** levels >= coarsest:
    levels += 1
  return dataclasses.replace(config, levels=levels)


def score_sign(config: TrackConfig) -> float:
  """The sign that turns a loss into the similarity's score (SSD is reported as the error)."""
  return 1.0 if config.similarity == "ssd" else -1.0
