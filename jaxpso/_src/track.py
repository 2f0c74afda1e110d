"""Frame-by-frame tracking of planar regions: `track`.

Frame 0's region is the template; a batch of R regions (or of R sequences)
is tracked together, every step `vmap`ped over the regions.  Every later
frame is one call of one compiled program (`_frame_step`) on the frame's
pyramid (built on the host, `jaxpso._src.atlas`): a start chosen between the
damped constant-velocity prediction and the previous estimate, then the stages of
`jaxpso._src.register` (Gauss–Newton from the start; when that falls short
of `TrackConfig.accept_quality`, or moved far to a quality under the one the
region had, once more from the coarsest level, then a
quick swarm and Gauss–Newton from its best, and where that is neither
accepted nor confirmed by both refinements of the start the full swarm;
when the quality stays under `TrackConfig.lost_threshold`, a recovery
search around the last good estimate: wider swarms over the template's
translation, then Gauss–Newton), each only for the regions that need it.
A frame whose quality stays low is LOST: the program keeps the last good
estimate and resets the motion prediction; on the host the region is then
registered from its visible part, or (moving fast) with its template
smeared along its motion (`blur`), or found again by `detect`, else its
estimate coasts on its last motion (`TrackConfig.redetect`, `coast`).  For
motion "plane" the camera pose is
accumulated, T̂ ← T(x) · T̂.  With a gradient baseline
(`TrackConfig.method`) the registration is that method's, without recovery.
Neither the frame size nor the regions' sizes enter the compiled program.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import functools
import gc
import math
import sys
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import align as aligning
from jaxpso._src import atlas
from jaxpso._src import baselines
from jaxpso._src import batching
from jaxpso._src import blur
from jaxpso._src import checks
from jaxpso._src import detect as detection
from jaxpso._src import visible as visibility
from jaxpso._src import homography
from jaxpso._src import motion
from jaxpso._src import periodic
from jaxpso._src import plane
from jaxpso._src import problem as problems
from jaxpso._src import programs
from jaxpso._src import register
from jaxpso._src import sharding
from jaxpso._src import swarm_random
from jaxpso._src import template as templates
from jaxpso._src import track_inputs
from jaxpso._src.config import COAST_DECAY
from jaxpso._src.config import TrackConfig
from jaxpso._src.config import score_sign


class TrackStatus(enum.IntEnum):
  """Per-frame outcome of `track`; 0 is success."""
  TRACKED = 0
  RECOVERED = 1  # found by the wider recovery search
  LOST = 2  # too little of it seen: the last good estimate, coasting (`TrackConfig.coast`)
  DOUBTFUL = 3  # a re-detection, or tracking from it, short of the region's best (`_DOUBT_FRAMES`)


class TrackResult(NamedTuple):
  """Outcome of `track`, one entry per frame (NumPy arrays).

  Attributes:
    homographies: (T, 3, 3) template pixel → frame pixel, h[2, 2] = 1.
    corners: (T, 4, 2) the template's corners (TL, TR, BR, BL) in each frame.
    scores: (T,) similarity at the estimate (an error for "ssd").
    quality: (T,) `problem.quality` of the estimate: about 1 for a match,
      lower the worse (1 at frame 0; `TrackConfig.lost_threshold` is the
      threshold); -inf on a LOST frame where no candidate warp was
      admissible with enough valid pixels, or the match's shape was
      impossible or jumped (`_plausible`) (never NaN).
    status: (T,) int32 `TrackStatus`.
    poses: (T, 4, 4) frame-0 → frame camera poses for motion "plane", else None.
    num_iterations: (T,) swarm iterations plus refinement steps (0 at frame 0), as
      `num_evaluations` counts them.
    num_evaluations: (T,) similarity evaluations of the frame step and of every `align` run
      for the frame on the host, adopted or not (the visible part, smeared templates,
      `detect`'s candidates, a periodic template's shifts).
    visible: (T,) the share of the region judged visible: where the whole
      template matched, the share of the estimate inside the frame
      (`homography.inside_share`); on a
      frame the step lost or matched less than 75 % inside the frame, the
      share of `visible.GRID`² blocks inside the frame that match the
      template at the estimate (`visible.register_part`; 1 after a
      re-detection); 0 on a LOST frame with `TrackConfig.redetect` off.
  """
  homographies: np.ndarray
  corners: np.ndarray
  scores: np.ndarray
  quality: np.ndarray
  status: np.ndarray
  poses: np.ndarray | None
  num_iterations: np.ndarray
  num_evaluations: np.ndarray
  visible: np.ndarray


class _Constants(NamedTuple):
  """What every frame step shares (a pytree; every leaf has the leading region axis R)."""
  template: templates.Template
  geometry: motion.Plane | None
  seed: jax.Array  # (R, 2) uint32
  pyramid: list | None  # the baselines' dense template levels, (R, h_l, w_l) each


# The prediction carries this fraction of the last inter-frame motion.  With
# all of it, an error the image barely constrains (a plane pose's rotation
# against its translation) grows by itself, e_{t+1} = 2 e_t − e_{t−1}: with a
# fraction α it follows the roots 1 and α of z² − (1 + α) z + α, so it stays
# bounded.
_PREDICTED_FRACTION = 0.5


class _Carry(NamedTuple):
  """The tracker's state between frames (a pytree; leading region axis R)."""
  estimate: jax.Array  # (R, 3, 3) homography or (R, 4, 4) pose: the last good estimate
  velocity: jax.Array  # same shape: estimate_t · estimate_{t-1}⁻¹
  frame: jax.Array  # (R,) int32 index of the next frame
  reference: jax.Array  # (R,) float32 the quality of the last searched match (`problem.Context`)


def _inverse(m):
  """Inverse of a homography or a rigid pose."""
  return plane.invert_pose(m) if m.shape == (4, 4) else homography.inverse(m)


def _damped(velocity):
  """(R, 3, 3) or (R, 4, 4) inter-frame motions → `_PREDICTED_FRACTION` of each, the predicted step.

  A pose is scaled in its parameters (translation, rotation vector); a
  homography as I + α (V − I), V with V[2, 2] = 1 (its α-th power to first order).
  """
  if velocity.shape[-1] == 4:
    return plane.pose_from_params(_PREDICTED_FRACTION * jax.vmap(plane.params_from_pose)(velocity))
  eye = jnp.eye(3, dtype=velocity.dtype)
  # × the reciprocal, not ÷: one rounding in every program (batching.each)
  return eye + _PREDICTED_FRACTION * (velocity * (1.0 / velocity[:, 2:, 2:]) - eye)


def _frame_seed(seed, frame):
  mixed = swarm_random._mix(seed[1] ^ swarm_random._mix(frame.astype(jnp.uint32)))
  return jnp.stack([seed[0], mixed])


def _predict(contexts: problems.Context, knobs, config):
  """Contexts whose start (base 0, the prediction) falls back to the previous estimate (base 1)
  where that scores better over the full-resolution set (`template.FULL`)."""
  def losses(context):
    problem = problems.Problem(context, knobs, config)
    zero = jnp.zeros((2, problem.dim), jnp.float32)
    h = problem.homography(zero, jnp.arange(2))
    stats = problem._scores(h, 0, templates.FULL, config.resolution, (2,), problem.ranges(1),
                            None)
    return problem._loss(stats, templates.FULL, zero, jnp.arange(2))

  contexts = register.with_range(contexts, jnp.ones(contexts.seed.shape[0], bool), config)
  keep = batching.each(losses, contexts)
  previous = keep[:, 0] > keep[:, 1]

  def fall_back(a):
    return jnp.where(previous.reshape((-1,) + (1,) * (a.ndim - 1)), a[:, 1:2].repeat(2, 1), a)

  return contexts._replace(bases=fall_back(contexts.bases), quads=fall_back(contexts.quads),
                           image_ranges=fall_back(contexts.image_ranges))


@functools.partial(programs.Program, static_argnames=("config", "mesh"))
def _frame_step(carry: _Carry, image: atlas.Atlas, constants: _Constants, knobs: problems.Knobs,
                *, config: TrackConfig, mesh=None):
  """One frame of R regions: (carry, the frame's atlas, shared (1-D pixels) or one per region) →
  (carry, per-frame outputs, each with the leading R); with a `mesh` of several devices, each
  runs its share of the regions (`sharding.per_device`)."""
  shared = (1, 3) if image.pixels.ndim == 1 else (3,)
  return sharding.per_device(functools.partial(_regions_step, config=config), mesh, shared)(
      carry, image, constants, knobs)


def _regions_step(carry: _Carry, image: atlas.Atlas, constants: _Constants, knobs: problems.Knobs,
                  config: TrackConfig):
  """`_frame_step` for the regions of one device."""
  seeds = jax.vmap(_frame_seed)(constants.seed, carry.frame)
  predicted = jnp.where(knobs.predict, _damped(carry.velocity) @ carry.estimate, carry.estimate)
  bases = jnp.stack([predicted, carry.estimate], axis=1)
  contexts = batching.each(lambda *a: register.context(*a, config), image, constants.template,
                           bases, constants.geometry, seeds)
  # A shared image stays shared (`vmap` returned it copied per region).
  contexts = contexts._replace(image=image, reference=carry.reference)
  contexts = jax.lax.cond(knobs.predict, lambda c: _predict(c, knobs, config), lambda c: c,
                          contexts)
  if config.method == "pso":
    state = register.run(contexts, knobs, "track", config)
    found, recovered, searched = state.best, state.recovered, state.searched
  else:
    found = batching.each(lambda c, p: register.baseline(c, p, knobs, config), contexts,
                          constants.pyramid)
    recovered = searched = jnp.zeros(found.loss.shape, bool)
  quality = found.quality
  lost = ~(quality >= knobs.lost_quality) | ~jnp.all(jnp.isfinite(found.u), axis=-1)
  status = jnp.where(lost, TrackStatus.LOST,
                     jnp.where(recovered, TrackStatus.RECOVERED, TrackStatus.TRACKED))
  base = jnp.take_along_axis(contexts.bases, found.base[:, None, None, None], axis=1)[:, 0]
  estimate = found.homography
  if config.motion != "homography":
    estimate = jax.vmap(functools.partial(motion.plane_pose, dof=config.dof))(
        found.u, base, constants.geometry)
  estimate = batching.select(lost, carry.estimate, estimate)
  identity = jnp.broadcast_to(jnp.eye(estimate.shape[-1], dtype=estimate.dtype), estimate.shape)
  velocity = batching.select(lost, identity, estimate @ jax.vmap(_inverse)(carry.estimate))
  h = found.homography
  if config.motion != "homography":
    zero = jnp.zeros(motion.dimension(config.motion, config.dof), jnp.float32)
    h = jax.vmap(lambda e, g, size: problems.normalized(motion.to_homography(
        zero, base=e, geometry=g, shape=size, motion=config.motion, dof=config.dof)))(
            estimate, constants.geometry, constants.template.size)
  h = batching.select(lost, jax.vmap(problems.normalized)(_last_homography(carry, constants,
                                                                            config)), h)
  frame_size = image.levels[..., 0, 1:3].astype(jnp.float32)  # (w, h), shared or per region
  inside = jax.vmap(homography.inside_share)(
      h, constants.template.size, jnp.broadcast_to(frame_size, (h.shape[0], 2)))
  outputs = dict(homography=h, score=score_sign(config) * found.loss, quality=quality,
                 status=status.astype(jnp.int32), estimate=estimate,
                 num_iterations=found.num_iterations, num_evaluations=found.num_evaluations,
                 inside=inside)
  # A search's match sets the reference; an accepted start only raises it.
  reference = jnp.where(lost, carry.reference,
                        jnp.where(searched, quality, jnp.maximum(carry.reference, quality)))
  return _Carry(estimate, velocity, carry.frame + 1, reference.astype(jnp.float32)), outputs


def _last_homography(carry: _Carry, constants: _Constants, config):
  """(R, 3, 3) the homographies of the last good estimates."""
  if config.motion == "homography":
    return carry.estimate
  zero = jnp.zeros(motion.dimension(config.motion, config.dof), jnp.float32)
  return jax.vmap(lambda e, g, size: motion.to_homography(
      zero, base=e, geometry=g, shape=size, motion=config.motion, dof=config.dof))(
          carry.estimate, constants.geometry, constants.template.size)


# A frame step's match with less than this share of the region inside the
# frame is checked from the region's visible part: its quality is judged on
# the pixels inside, and a region half out of the frame was matched 12–18 px
# off at quality 0.72–0.97 (benchmarks/challenges.py, out of view).
_MIN_IN_FRAME = 0.75
# A visible part's registration counts within this many pixels (RMS over the
# corners) of the frame step's match, or of the last estimate plus twice the
# last inter-frame motion for every frame since it: a part with the
# occluder's edge in it was registered 6–52 px off at a quality above the
# lost threshold (challenges.py, occlusion).
_PART_REACH_PX = 4.0
# A LOST region last seen less than _MIN_IN_FRAME inside the frame is also
# searched for partly outside it (`detect(partial=...)`), within this factor
# of its last scale and this many degrees of its last rotation (one step of
# `detect`'s grids either way): over the whole ranges, places at the frame's
# edge matched on half a patch outscored it (challenges.py, seed 1, out of
# view).
_REENTRY_SCALE, _REENTRY_DEG = 2.0 ** (1 / 3), 15.0
# A detection whose quality falls more than a margin short of the best the
# region has been TRACKED at is in doubt (DOUBTFUL) for _DOUBT_FRAMES
# frames, until its quality comes within half the margin of that best: on
# each of them `detect` runs again, and a place a margin better and over
# _PART_REACH_PX away replaces the estimate.  Leaving doubt at the margin
# itself, that brick was TRACKED at 0.93 (best 0.98) on one frame.  A
# periodic texture half out of the frame was re-detected a brick (79 px) off
# at NCC 0.80-0.87 and tracked there at 0.81-0.94, where the truth, once in
# full view, scored 0.95-0.98 (challenges.py, seed 1, out of view; 0.97 its
# best before).  A detection by the smeared template (motion blur) counts
# only within a margin of the region's reference: smearing raised that
# wrong brick from 0.65-0.77 to 0.79-0.86.  The margin is _DOUBT_SHARE of
# the span from the lost threshold to 1 (`_margin`): NCC 0.05, MI 0.0875
# (a shake on a brick texture, MI 0.90 before it: the smeared truth 0.84).
_DOUBT_SHARE, _DOUBT_FRAMES = 0.25, 15


class _Recent(NamedTuple):
  """On the host, per region: the last frame's homography (R, 3, 3) float64; the homographies
  before and after its last step between two frames not LOST (R, 3, 3 each; both the
  re-acquired one after a loss), whose motion the region is predicted to go on with; the
  frames since the last estimate not LOST (R,); the last TRACKED frame's homography
  (R, 3, 3), where a region that left the frame comes back (`_reentry_ranges`); the
  templates' corners (R, 4, 2).

  Per frame only copies: matrix products and inverses on the host, in
  OpenBLAS, cost the device step's threads 0.3-0.6 ms a frame (video.py).
  """
  homography: np.ndarray
  before: np.ndarray
  after: np.ndarray
  gap: np.ndarray
  tracked: np.ndarray
  rects: np.ndarray

  def motion(self, r: int) -> np.ndarray:
    """(3, 3) region r's last inter-frame motion, h[2, 2] = 1."""
    m = self.after[r] @ np.linalg.inv(self.before[r])
    return m / m[2, 2]

  def speed(self, r: int, shape) -> float:
    """RMS corner motion of region r's last step (a template of `shape`)."""
    return _corner_distance(self.after[r], self.before[r], shape)


def _corner_distance(a, b, shape) -> float:
  """RMS distance of the corners of an (h, w) template mapped by the homographies a and b."""
  rect = np.c_[homography.host_rect_corners(shape), np.ones(4)].T
  pa, pb = np.asarray(a, np.float64) @ rect, np.asarray(b, np.float64) @ rect
  return float(np.sqrt(np.mean(np.sum((pa[:2] / pa[2] - pb[:2] / pb[2]) ** 2, axis=0))))


# A match is rejected (its frame LOST, then re-acquired as one) where it
# mirrors the template (frame 0's corners turn clockwise on the image,
# `track_inputs.template_geometry`) or puts a corner behind the camera (no
# plane in front of the camera looks so), or, right after a frame not
# LOST, where a side's
# length changes more than _MAX_SIDE_CHANGE times from the last frame's.
# Photographs moving under occlusion, blur or a change of light (240 wild
# cases, 2026-11-28) were TRACKED 15-190 px off after such jumps (a side 0.07
# to 0.6 of the last frame's, at NCC up to 0.96), where the true sides
# changed under 3 % a frame.  A re-detection (RECOVERED), and a match after
# a LOST frame, is held to the last TRACKED match's shape, sides scaled by
# their mean, within _MAX_SHAPE_CHANGE times _SHAPE_DRIFT per frame since a
# frame not LOST (a target can turn while it is hidden): detections there
# lay 58-75 px off with a side 0.08-0.33 of the others' share.
_MAX_SIDE_CHANGE, _MAX_SHAPE_CHANGE, _SHAPE_DRIFT = 1.5, 2.0, 1.03


_NEXT = np.array([1, 2, 3, 0])  # each corner's next, clockwise on the image


def _sides(h: np.ndarray, rects: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """((R, 4, 2) the sides (corner i to corner i + 1), (R,) whether every corner has w > 0) of
  the template corners `rects` (R, 4, 2) mapped by the homographies h (R, 3, 3); elementwise:
  a product in OpenBLAS costs the device step's threads, a call of NumPy some µs."""
  h = np.asarray(h, np.float64)
  mapped = (h[:, None, :, 0] * rects[..., :1] + h[:, None, :, 1] * rects[..., 1:]
            + h[:, None, :, 2])  # (R, 4, 3)
  w = mapped[..., 2:]
  in_front = np.all(w[..., 0] > 0, axis=1)
  corners = mapped[..., :2] / np.where(w > 0, w, 1.0)
  return corners[:, _NEXT] - corners, in_front


def _plausible(h: np.ndarray, rects: np.ndarray, last: np.ndarray | None = None,
               shape_only: bool = False, slack=1.0) -> np.ndarray:
  """(R,) whether the matches h (R, 3, 3) of templates with corners `rects` (R, 4, 2) keep every
  corner in front (w > 0) and turn them clockwise as frame 0 does (not mirrored), and, given
  homographies `last` (R, 3, 3), change no side's length more than `_MAX_SIDE_CHANGE` times
  from theirs (`shape_only`: the sides scaled by their mean, `_MAX_SHAPE_CHANGE`), times
  `slack` (R,) or a scalar."""
  sides, in_front = _sides(h, rects)
  turns = sides[..., 0] * sides[:, _NEXT, 1] - sides[..., 1] * sides[:, _NEXT, 0]
  kept = in_front & np.all(turns > 0, axis=1)
  if last is None:
    return kept
  lengths = [np.sqrt(np.sum(a * a, axis=-1)) for a in (sides, _sides(last, rects)[0])]
  if shape_only:
    lengths = [a / np.maximum(np.mean(a, axis=1, keepdims=True), 1e-9) for a in lengths]
  change = lengths[0] / np.maximum(lengths[1], 1e-9)
  bound = (_MAX_SHAPE_CHANGE if shape_only else _MAX_SIDE_CHANGE) * np.reshape(slack, (-1, 1))
  return kept & np.all((change <= bound) & (change >= 1 / bound), axis=1)


def _inside_share(h, shape, frame_shape) -> float:
  """The share of a template of `shape` (h, w) that the (3, 3) homography h puts inside a frame
  of `frame_shape` (H, W)."""
  return float(homography.inside_share(h, np.asarray(shape, np.float32),
                                       np.asarray(frame_shape[::-1], np.float32), xp=np))


def _pose(h: np.ndarray, geometry, r: int) -> np.ndarray:
  """Region r's estimate for the (3, 3) homography h: h itself, or for motion "plane" the pose of
  its frame-0 → frame homography."""
  if geometry is None:
    return np.asarray(h, np.float32)
  from_frame0 = np.asarray(h, np.float64) @ np.linalg.inv(geometry.template_to_frame0[r])
  return np.asarray(plane.pose_from_homography(from_frame0.astype(np.float32), geometry.camera[r],
                                               geometry.normal[r]))


def _leaving(recent: _Recent, r: int, shape, frame_shape) -> bool:
  """Whether region r (a template of `shape`) was last TRACKED less than `_MIN_IN_FRAME` inside
  a frame of `frame_shape`: leaving it, or coming back."""
  return _inside_share(recent.tracked[r], shape, frame_shape) < _MIN_IN_FRAME


def _translation_of(motion_: np.ndarray, h: np.ndarray, shape) -> np.ndarray:
  """(3, 3) the translation by which the (3, 3) `motion_` moves the centre of a template of
  `shape` (h, w) placed by the (3, 3) homography h."""
  centre = h @ np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2, 1.0])
  moved = motion_ @ centre
  shift = moved[:2] / moved[2] - centre[:2] / centre[2]
  return np.array([[1.0, 0, shift[0]], [0, 1, shift[1]], [0, 0, 1]])


def _coasted(recent: _Recent, r: int, shape, frame_shape) -> np.ndarray:
  """(3, 3) region r's homography on its next lost frame: the last one moved by `COAST_DECAY`^k of
  its last motion (to first order), k the lost frames before it; unmoved after a motion of
  more than a quarter of the template's side, or where the extrapolated warp would fold the
  template (a corner across the horizon).  A region last TRACKED less than
  `_MIN_IN_FRAME` inside the frame is leaving it: it moves on by the whole shift of its
  centre in the last motion, keeping its shape, and stops at its last place partly inside
  the frame.  The last steps of a region leaving match it squeezed into the frame; moved by
  the whole motion, a region leaving at 8 px a frame under 8 px of blur was squeezed on to
  4.0-9.3 px off at 27-10 % inside (test_detect)."""
  motion_ = recent.motion(r)
  if recent.speed(r, shape) > max(shape) / 4:
    return recent.homography[r]
  leaving = _leaving(recent, r, shape, frame_shape)
  if leaving:
    step = _translation_of(motion_, recent.homography[r], shape)
  else:
    step = np.eye(3) + COAST_DECAY ** recent.gap[r] * (motion_ - np.eye(3))
  h = step @ recent.homography[r]
  h = h / h[2, 2]
  if (leaving and _inside_share(h, shape, frame_shape) <= 0.0) or not checks.is_start(h, shape):
    return recent.homography[r]
  return h


def _reacquired(carry: _Carry, before: _Carry, out: dict, check, recent: _Recent, images: list,
                templates_: list, geometry, config: TrackConfig, index: int, mesh, doubt: dict,
                peak: np.ndarray):
  """(carry, out, {region: visible share}) with the regions `check` (indices) registered from
  their visible part, or found again by `detect` in their frames, or else LOST (the estimate
  coasting with `TrackConfig.coast`, which also moves a region last TRACKED partly outside
  the frame with its part inside, `_follow_part`).

  `check` holds the regions the frame step lost and those whose match lies
  less than `_MIN_IN_FRAME` inside the frame, on this frame or the one
  before; `before` is the carry before the step.  The visible part
  (`visible.register_part`, from the step's estimate, and where that lies
  more than `_PART_REACH_PX` from the motion's prediction (`_coasted`) also
  from the prediction: a region under half inside, NCC's step squeezed half
  of it into the frame, 9-17 px off at 0.87-0.91, test_detect) counts where
  it lies within reach of the step's match or of the motion and its quality
  reaches `TrackConfig.lost_threshold`, or short of it the whole template's
  smeared by the blur fitted there does
  (`_smeared_part`: a region coming back into the frame under motion blur
  faster than its last motion) (TRACKED);
  else, on the same terms, the template smeared along the region's motion
  (`blur.register_blurred`: a region moving at least `blur.MIN_MOTION_PX` a
  frame, at least `blur.MIN_INSIDE` inside, LOST for at most `blur.MAX_GAP`
  frames); else a detection that
  reaches it (RECOVERED; the next frame starts from it with no motion): for
  a region last TRACKED less than `_MIN_IN_FRAME` inside, also at places
  partly outside the frame (`_reentry_ranges`), where its visible part must
  confirm it (`_confirmed_part`).  A
  region in `doubt` ({region: (last frame, its `peak`)}, changed in place)
  not LOST is first challenged by a detection (`_margin`), and leaves doubt
  where that replaces it within the margin of its best; `peak` (R,) holds
  the best quality each region was TRACKED at.  On the host: it runs
  only for the regions in `check`; with `TrackConfig.redetect` off only the
  coasting.
  """
  either_sign = config.similarity == "mi"
  bounded = detection.bounded(config)
  carry, before, out = _host_copies(carry, before, out)
  found, shares, spent = {}, {}, {}  # spent: {region: its `aligning.Spent`}
  for r in (int(r) for r in check):
    with aligning.counted() as spent[r]:
      shape = templates_[r].shape
      if not config.redetect:
        _keep_lost(carry, before, out, recent, geometry, config, r, shape, images[r].shape)
        continue
      smeared_from = float(before.reference[r]) - _margin(config)
      left = _reentry_ranges(recent.tracked[r], shape, images[r].shape)
      detected = False  # `detect` run on this frame: `whole` its result (None: no place), `share`
      if r in doubt and out["status"][r] != TrackStatus.LOST:
        whole, share = _detected(images[r], templates_[r], config, index, smeared_from, left,
                                 peak[r] - _margin(config))
        detected = True
        if (whole is not None and float(whole.quality) >= out["quality"][r] + _margin(config)
            and _corner_distance(whole.homography, out["homography"][r], shape) > _PART_REACH_PX):
          found[r], shares[r] = (whole, TrackStatus.RECOVERED), share
          if float(whole.quality) >= peak[r] - _margin(config):
            del doubt[r]
          continue
        if out["inside"][r] >= _MIN_IN_FRAME:
          continue
      predicted = _coasted(recent, r, shape, images[r].shape)  # the last estimate moved on
      start = predicted if out["status"][r] == TrackStatus.LOST else out["homography"][r]
      reach = _PART_REACH_PX + 2.0 * recent.speed(r, shape) * (recent.gap[r] + 1)
      part = None
      for origin in ([start] if _corner_distance(start, predicted, shape) <= _PART_REACH_PX
                     else [start, predicted]):
        part, shares[r] = visibility.register_part(images[r], templates_[r], origin, bounded, index,
                                                   either_sign)
        if part is not None and (
            _corner_distance(part.homography, recent.homography[r], shape) <= reach
            or _corner_distance(part.homography, out["homography"][r], shape) <= _PART_REACH_PX):
          if float(part.quality) < config.lost_threshold:
            part = _smeared_part(images[r], templates_[r], part, bounded, index, either_sign)
          if part is not None and float(part.quality) >= config.lost_threshold:
            break
        part = None
      if part is not None:
        found[r] = part, TrackStatus.TRACKED
        continue
      if (recent.speed(r, shape) >= blur.MIN_MOTION_PX and recent.gap[r] <= blur.MAX_GAP
          and _inside_share(start, shape, images[r].shape) >= blur.MIN_INSIDE):
        smeared = blur.register_blurred(images[r], templates_[r], start, recent.motion(r), bounded,
                                        index)
        share = 0.0 if smeared is None else _inside_share(smeared.homography, shape,
                                                          images[r].shape)
        if (smeared is not None and float(smeared.quality) >= config.lost_threshold
            and share >= blur.MIN_INSIDE
            and _corner_distance(smeared.homography, recent.homography[r], shape) <= reach):
          found[r], shares[r] = (smeared, TrackStatus.TRACKED), share
          continue
      if not detected:
        whole, share = _detected(images[r], templates_[r], config, index, smeared_from, left,
                                 peak[r] - _margin(config))
      if whole is not None and float(whole.quality) >= config.lost_threshold:
        found[r], shares[r] = (whole, TrackStatus.RECOVERED), share
        if float(whole.quality) < peak[r] - _margin(config):
          doubt[r] = index + _DOUBT_FRAMES, float(peak[r])
      else:
        _keep_lost(carry, before, out, recent, geometry, config, r, shape, images[r].shape)
        if config.coast and _leaving(recent, r, shape, images[r].shape):
          _follow_part(carry, out, geometry, images[r], templates_[r], r, either_sign)
  for r, (f, status) in found.items():
    if _kept_shape(recent, r, f.homography, status):
      _adopt(carry, before, out, recent, geometry, r, f, status)
    else:
      _keep_lost(carry, before, out, recent, geometry, config, r, templates_[r].shape,
                 images[r].shape)
  _add_spent(out, spent)
  return sharding.split(carry, mesh), out, shares


def _kept_shape(recent: _Recent, r: int, h, status: TrackStatus) -> bool:
  """Whether region r's match h (3, 3) is `_plausible` (`_plausible_steps`; a detection,
  RECOVERED, as after a LOST frame)."""
  return bool(_plausible_steps(np.asarray(h, np.float64)[None], recent, slice(r, r + 1),
                               status != TrackStatus.RECOVERED)[0])


def _plausible_steps(h: np.ndarray, recent: _Recent, regions: slice, follows=True) -> np.ndarray:
  """(R,) whether the matches h (R, 3, 3) of `regions` are `_plausible`: against the last frame's
  homographies right after a frame not LOST (and where `follows`), else against the shape of
  the last TRACKED ones, `_SHAPE_DRIFT` looser a frame since one not LOST."""
  rects, gap = recent.rects[regions], recent.gap[regions]
  steps = _plausible(h, rects, recent.homography[regions])
  if follows and not np.any(gap):
    return steps
  return np.where((gap == 0) & follows, steps,
                  _plausible(h, rects, recent.tracked[regions], shape_only=True,
                             slack=_SHAPE_DRIFT ** gap))


def _host_copies(carry: _Carry, before: _Carry, out: dict) -> tuple[_Carry, _Carry, dict]:
  """Writable NumPy copies of a frame step's carry, the carry before it and its outputs."""
  carry, before = (_Carry(*(np.array(leaf) for leaf in sharding.to_host(c)))
                   for c in (carry, before))
  return carry, before, {k: np.array(v) for k, v in sharding.to_host(out).items()}


def _adopt(carry: _Carry, before: _Carry, out: dict, recent: _Recent, geometry, r: int, found,
           status: TrackStatus) -> None:
  """Region r's match replaced by `found` (an `AlignResult`) with `status` in `carry` and `out`
  (host copies, changed in place; `before` the carry before the frame step); its motion since
  the last frame becomes the velocity where it is TRACKED right after a frame not LOST."""
  h = np.asarray(found.homography, np.float32)
  estimate = _pose(h, geometry, r)
  carry.estimate[r] = estimate
  velocity = np.eye(estimate.shape[-1], dtype=np.float32)
  if status == TrackStatus.TRACKED and recent.gap[r] == 0:
    velocity = (estimate.astype(np.float64) @ np.linalg.inv(before.estimate[r])).astype(
        np.float32)
  carry.velocity[r] = velocity
  out["homography"][r], out["estimate"][r] = h, estimate
  out["score"][r], out["quality"][r] = float(found.score), float(found.quality)
  out["status"][r] = status


def _add_spent(out: dict, spent: dict) -> None:
  """`out`'s (a frame step's host copy, changed in place) counts with the host's alignments
  added: `spent` {region: its `aligning.Spent`}, adopted or not."""
  for r, used in spent.items():
    out["num_iterations"][r] += used.iterations
    out["num_evaluations"][r] += used.evaluations


def _smeared_part(image: np.ndarray, template: np.ndarray, part, config: TrackConfig, index: int,
                  either_sign: bool):
  """The whole template smeared by the blur fitted at the visible part's match
  (`blur.register_fitted`), where it lands within `_PART_REACH_PX` of it, else None."""
  smeared = blur.register_fitted(image, template, np.asarray(part.homography), config, index,
                                 either_sign)
  if smeared is None or _corner_distance(smeared.homography, part.homography,
                                         template.shape) > _PART_REACH_PX:
    return None
  return smeared


def _reentry_ranges(h: np.ndarray, shape, frame_shape):
  """`detect`'s (scales, angles) ranges of places partly outside the frame for a region last
  seen (at the (3, 3) homography h) less than `_MIN_IN_FRAME` inside, which comes back
  through an edge: within `_REENTRY_SCALE` and `_REENTRY_DEG` of h's scale and rotation at the
  template's centre; else None."""
  if _inside_share(h, shape, frame_shape) >= _MIN_IN_FRAME:
    return None
  rows, cols = shape
  centre = np.array([(cols - 1) / 2, (rows - 1) / 2, 1.0])
  mapped = np.asarray(h, np.float64) @ np.stack([centre, centre + [1, 0, 0], centre + [0, 1, 0]],
                                                axis=1)
  xy = mapped[:2] / mapped[2]
  jacobian = xy[:, 1:] - xy[:, :1]
  angle = math.degrees(math.atan2(jacobian[1, 0], jacobian[0, 0]))
  scale = math.sqrt(abs(np.linalg.det(jacobian)))
  return ((scale / _REENTRY_SCALE, scale * _REENTRY_SCALE),
          (angle - _REENTRY_DEG, angle + _REENTRY_DEG))


def _confirmed_part(image: np.ndarray, template: np.ndarray, found, config: TrackConfig,
                    index: int, either_sign: bool, least: float):
  """(match, visible share) of a detection partly outside the frame: its visible part
  registered from it (`visible.register_part`, or short of `least` `_smeared_part`), where
  that lands within `_PART_REACH_PX` of it at a quality of at least `least` (the region's
  best less the margin); else (`found` at quality -inf, 0).  Unconfirmed, a poster's other
  half at the frame's edge was RECOVERED at NCC 0.95, 103 px off (challenges.py, out of
  view)."""
  part, share = visibility.register_part(image, template, np.asarray(found.homography),
                                         config, index, either_sign)
  if part is not None and float(part.quality) < least:  # motion blur
    part = _smeared_part(image, template, part, config, index, either_sign)
  if (part is None or not float(part.quality) >= least
      or _corner_distance(part.homography, found.homography, template.shape) > _PART_REACH_PX):
    return found._replace(quality=jnp.float32(-jnp.inf)), 0.0
  return part, share


def _margin(config: TrackConfig) -> float:
  """The quality margin of a detection in doubt: `_DOUBT_SHARE` of the span from the lost
  threshold to a perfect match."""
  return _DOUBT_SHARE * (1.0 - config.lost_threshold)


def _detected(image: np.ndarray, template: np.ndarray, config: TrackConfig, index: int,
              blurred_from: float, partial, least: float):
  """(`detect`'s `AlignResult`, visible share) for a template in a frame (frame `index` seeds
  it), a smeared match (motion blur) counting from the quality `blurred_from`; `partial`:
  `_reentry_ranges`'s (scales, angles) or None.  A match less than `_MIN_IN_FRAME` inside
  the frame is `_confirmed_part` at `least`.  (None, 0) where no place could be correlated
  (a template flat at every scale `detect` matches it at)."""
  found = detection.search(image, template, config, index, detection.SCALES, detection.ANGLES,
                           detection.CANDIDATES, blurred_from, partial)
  if found is None:
    return None, 0.0
  if _inside_share(found.homography, template.shape, image.shape) >= _MIN_IN_FRAME:
    return found, 1.0
  return _confirmed_part(image, template, found, detection.bounded(config), index,
                         config.similarity == "mi", least)


# A periodic template's match (`periodic.aliased`) moves to the template
# shift within `periodic.reach` that correlates best with the frame, where
# `align` from there reaches a higher quality, up to _ALIAS_MOVES times (a
# match found a period or two away).  It is DOUBTFUL where a shift at least
# _ALIAS_APART_PX from it correlates within _ALIAS_TIE of it (the texture
# goes on past the template, or the border that tells the places apart is
# hidden), or where its quality falls more than `_margin` short of the best
# the region was TRACKED at, frame 0's 1 included.  Fuzzing, 2026-11-28
# (benchmarks/periodic.py): a 50-120 px stripes template pasted on a
# photograph correlated 0.84-0.99 a few pixels along its stripes from the
# truth's 1.0; squeezed or turned along its stripes it matched 3-17 px off
# at NCC 0.87, MI 0.67-0.96 and SSD 0.59-0.65 where no shift did better,
# some from the first frame on.
_ALIAS_MOVES, _ALIAS_APART_PX, _ALIAS_TIE = 3, 2, 0.01


def _dealiased(carry: _Carry, before: _Carry, out: dict, regions, recent: _Recent, images: list,
               templates_: list, geometry, config: TrackConfig, index: int, mesh,
               best: np.ndarray):
  """(carry, out) with the periodic regions `regions` (indices, not LOST) moved to their best
  template shift, DOUBTFUL where that is not clear (`_ALIAS_TIE`) or their quality falls a
  `_margin` short of `best` (R,); frame `index` seeds `align`."""
  either_sign = config.similarity == "mi"
  carry, before, out = _host_copies(carry, before, out)
  spent = {}  # {region: its `aligning.Spent`}
  for r in regions:
    with aligning.counted() as spent[r]:
      template = templates_[r]
      d = periodic.reach(template.shape)
      at = np.zeros(2, int)  # the match's shift in `scores`
      for _ in range(_ALIAS_MOVES):
        h = out["homography"][r].astype(np.float64)
        shift, scores = periodic.best_shift(images[r], template, h, either_sign)
        if not np.any(shift):
          break
        moved = h @ np.array([[1.0, 0, shift[0]], [0, 1, shift[1]], [0, 0, 1]])
        found = aligning.align(images[r], template, moved, config=detection.bounded(config),
                               key=index)
        if (not float(found.quality) > out["quality"][r]
            or not _kept_shape(recent, r, found.homography, TrackStatus.TRACKED)):
          break
        _adopt(carry, before, out, recent, geometry, r, found, out["status"][r])
      else:
        at = shift
      rows, cols = np.mgrid[-d:d + 1, -d:d + 1]
      apart = np.maximum(np.abs(cols - at[0]), np.abs(rows - at[1])) >= _ALIAS_APART_PX
      here = scores[d + at[1], d + at[0]]  # -1: too little inside the frame to compare
      if ((here > -1.0 and np.any(scores[apart] >= here - _ALIAS_TIE))
          or out["quality"][r] < best[r] - _margin(config)):
        out["status"][r] = TrackStatus.DOUBTFUL
  _add_spent(out, spent)
  return sharding.split(carry, mesh), out


def _rejected(carry: _Carry, before: _Carry, out: dict, regions, recent: _Recent, shapes: list,
              frame_shape, mesh):
  """(carry, out) with the frame step's matches of `regions` (indices), not `_plausible`, LOST as
  the step makes a frame LOST: the estimate, reference and homography of the frame before, no
  velocity, quality -inf (no admissible warp); `shapes` the templates' (rows, cols)."""
  carry, before, out = _host_copies(carry, before, out)
  for r in regions:
    carry.estimate[r] = out["estimate"][r] = before.estimate[r]
    carry.velocity[r] = np.eye(carry.velocity.shape[-1], dtype=np.float32)
    carry.reference[r] = before.reference[r]
    out["homography"][r] = recent.homography[r]
    out["inside"][r] = _inside_share(recent.homography[r], shapes[r], frame_shape)
    out["status"][r], out["quality"][r] = TrackStatus.LOST, -np.inf
  return sharding.split(carry, mesh), out


def _keep_lost(carry: _Carry, before: _Carry, out: dict, recent: _Recent, geometry,
               config: TrackConfig, r: int, shape, frame_shape) -> None:
  """Region r LOST in `carry` and `out` (host copies of the step's and, `before`, of the carry
  before it; changed in place): its last estimate, or with `TrackConfig.coast` that estimate
  moved on (`_coasted`, in a frame of `frame_shape`)."""
  if out["status"][r] != TrackStatus.LOST:  # too little of it inside the frame to tell
    carry.reference[r] = before.reference[r]
    out["status"][r] = TrackStatus.LOST
  h = _coasted(recent, r, shape, frame_shape) if config.coast else recent.homography[r]
  estimate = _pose(h, geometry, r) if config.coast else before.estimate[r]
  carry.estimate[r], carry.velocity[r] = estimate, np.eye(estimate.shape[-1], dtype=np.float32)
  out["homography"][r], out["estimate"][r] = h, estimate


def _follow_part(carry: _Carry, out: dict, geometry, image: np.ndarray, template: np.ndarray,
                 r: int, either_sign: bool) -> None:
  """Region r, LOST at the frame's edge, moved in `carry` and `out` (host copies, changed in
  place) with its part inside the frame (`visible.followed`) where that correlates at
  `visible.FOLLOW_NCC`; still LOST: too little is inside to tell its shape.  Coasting
  alone, a region coming back at 13 px a frame lay 15-82 px off at 12-50 % inside
  (challenges.py, out of view)."""
  h, score = visibility.followed(image, template, out["homography"][r].astype(np.float64),
                                 either_sign)
  if score >= visibility.FOLLOW_NCC:
    h = h.astype(np.float32)
    carry.estimate[r] = out["estimate"][r] = _pose(h, geometry, r)
    out["homography"][r] = h


def _moved(recent: _Recent, h: np.ndarray, status: np.ndarray) -> _Recent:
  """`recent` after a frame whose homographies are h (R, 3, 3) and statuses `status` (R,)."""
  h = np.asarray(h, np.float64)
  lost = status == TrackStatus.LOST
  step = (~lost & (recent.gap == 0))[:, None, None]
  kept = lost[:, None, None]
  before = np.where(kept, recent.before, np.where(step, recent.homography, h))
  after = np.where(kept, recent.after, h)
  tracked = np.where((status == TrackStatus.TRACKED)[:, None, None], h, recent.tracked)
  return recent._replace(homography=h, before=before, after=after,
                         gap=np.where(lost, recent.gap + 1, 0), tracked=tracked)


# `track` moves the per-frame outputs to the host in chunks of this many
# frames: kept on the device to the end, they grew the memory with the clip,
# and jnp.stack compiled a T-operand concatenation per field
# (benchmarks/README.md, long_run.py).
_HOST_CHUNK = 256


def _to_host(outputs: list) -> dict:
  """Per-frame output dicts of (R, ...) → one dict of (R, n, ...) NumPy arrays (waits for the last)."""
  host = sharding.to_host(outputs)
  return {k: np.stack([o[k] for o in host], axis=1) for k in host[0]}


def _starts(regions: list) -> np.ndarray:
  """(R, 3, 3) float32 homographies from each template onto its corners in frame 0, h[2, 2] = 1.

  `regions`: R (corners (4, 2), (rows, cols)) pairs.  On the host: as eager
  JAX operations they compiled some thirty small programs in every process.
  """
  rects = np.stack([homography.host_rect_corners(shape) for _, shape in regions])
  corners = np.stack([c for c, _ in regions]).astype(np.float64)
  return homography.host_homography_from_corners(rects, corners).astype(np.float32)


@contextlib.contextmanager
def _collector_frozen():
  """Python's cyclic garbage collector leaves the objects that exist on entry out of its
  collections until exit (`gc.freeze`), unless the caller froze some itself.

  A full collection among the objects JAX keeps paused a frame for 64 ms,
  26x the sequence's median (benchmarks/frame_times.py, tracking.py's plane
  case, frame 32; 2026-11-27); the frames' own garbage is still collected.
  """
  mine = gc.get_freeze_count() == 0
  if mine:
    gc.freeze()
  try:
    yield
  finally:
    if mine:
      gc.unfreeze()


def track(frames, roi, *, config: TrackConfig = TrackConfig(), key=0, camera=None,
          plane_normal=None, sequences: bool = False, devices=None,
          progress: bool = False) -> TrackResult:
  """Tracks the region `roi` of frame 0 through `frames`; or a batch of regions.

  A batch of R regions, `roi` of shape (R, 4) or (R, 4, 2), is tracked in one
  compiled program; every field of the result gains a leading R axis.  Each
  region keeps its own template (its own pixels; with a gradient baseline
  all regions must have one size).  With `sequences=True` region r is
  tracked in sequence r of `frames`.  The costly searches (the swarm, the
  recovery) run only for the regions that need them.  With several devices
  the regions are split over them (`jax.sharding`).  On a CPU a region's
  track is bit-identical alone, in any batch and on any number of devices
  (`batching.each`); on an accelerator the batch is vectorised (`vmap`).

  Args:
    frames: (T, H, W) or (T, H, W, 3) array, or any iterable of frames (a
      video reader), uint8 or float in [0, 1], grey or colour, all one size.
      With `sequences=True`: (R, T, H, W[, 3]), or R such sequences of one length.
    roi: (x, y, w, h) box in frame 0 (integer w, h), or (4, 2) corners TL,
      TR, BR, BL in frame-0 pixels; or (R, 4) boxes or (R, 4, 2) corners.
      Each side of a region's template `checks.TEMPLATE_SIDES` (8 to 4096) pixels.
    config: `TrackConfig` (motion, similarity, swarm, refinement, recovery).
    key: int seed or PRNG key; a fixed key gives bit-identical results.  For
      a batch also one key per region (a list, (R,) ints or keys, or (R, 2)
      raw uint32 keys): region r is then tracked as alone with key[r].
    camera: (3, 3) intrinsics K for motion "plane"; default f = max(H, W) and
      the principal point at the frame's centre.
    plane_normal: (3,) normal of the target plane in frame-0 camera
      coordinates with n·X = d > 0 on the plane (d is taken as 1, so
      translations are in units of the plane's distance); default (0, 0, 1),
      fronto-parallel.  A rough normal is allowed.  Shared by a batch.
    sequences: `frames` holds one sequence per region.
    devices: the `jax.Device`s the regions are split over; default every
      visible one.
    progress: print a progress line to stderr.

  Returns:
    `TrackResult`.

  Raises:
    ValueError: zero frames, frames of differing sizes or with non-finite
      pixels, a bad or out-of-frame ROI, a template outside the supported
      sizes or textureless, a bad camera or normal.  TypeError: a bad dtype
      or config.
  """
  if not isinstance(config, TrackConfig):
    raise TypeError(f"config must be a TrackConfig, got {type(config).__name__}")
  rois, batched = track_inputs.regions(roi)
  count = len(rois)
  if sequences:
    iterator, total = track_inputs.lockstep(frames, count)
  else:
    single, total = track_inputs.frame_iterator(frames)
    iterator = ([frame] for frame in single)
  first = next(iterator, None)
  if first is None:
    raise ValueError("frames must hold at least one frame, got none")

  def frame_name(r, index):
    return f"frames[{r}][{index}]" if sequences else f"frames[{index}]"

  frame0 = [np.asarray(checks.to_gray(f, frame_name(r, 0))) for r, f in enumerate(first)]
  if any(f.shape != frame0[0].shape for f in frame0):
    raise ValueError(f"the sequences' frames must have one size, got {[f.shape for f in frame0]}")
  frame_shape = frame0[0].shape

  def name(r):
    return f"roi[{r}]" if batched else "roi"

  regions = [track_inputs.template_geometry(roi, frame_shape, name(r))
             for r, roi in enumerate(rois)]
  shapes = [shape for _, shape in regions]
  if config.method != "pso" and len(set(shapes)) > 1:
    raise ValueError(f"every region tracked by {config.method!r} must have one size, got"
                     f" {sorted(set(shapes))}")
  for r, shape in enumerate(shapes):
    checks.check_template_size(shape, config.for_template(shape).levels, config.resolution, name(r))
  pixels = [frame0[r if sequences else 0] for r in range(count)]
  templates_ = [track_inputs.template(f, corners, shape)
                for f, (corners, shape) in zip(pixels, regions)]
  checks.check_texture(np.array([np.std(t) for t in templates_]),
                       lambda r: f"{name(r)} {rois[r]!r}")
  configs = [config.for_template(t.shape, t) for t in templates_]
  aliased = np.array([config.redetect and config.method == "pso" and periodic.aliased(t)
                      for t in templates_])
  levels = max(c.levels for c in configs)
  checks.check_image_size(frame_shape, levels, "frames[0]")
  starts = _starts(regions)
  geometry = None
  if config.motion == "plane":
    geometry = motion.checked_plane_geometries(camera, plane_normal, frame_shape, starts,
                                               shapes, config.dof)
  elif camera is not None or plane_normal is not None:
    raise ValueError("camera and plane_normal apply to motion 'plane' only;"
                     f" got TrackConfig.motion={config.motion!r}")
  size = 3 if geometry is None else 4
  first_estimate = starts if geometry is None else np.broadcast_to(np.eye(4, dtype=np.float32),
                                                                   (count, 4, 4))
  mesh = sharding.batch_mesh(devices, count)
  statics = config.statics()
  prepared = batching.stack([templates.prepared(t, c.levels, c.pixels, c.bins, statics.resolution)
                             for t, c in zip(templates_, configs)])
  pyramid = None
  if config.method != "pso":
    pyramid = baselines.template_pyramids(templates_, configs[0].levels)
    statics = dataclasses.replace(config, levels=configs[0].levels).statics()
  constants = sharding.split(_Constants(prepared, geometry, batching.element_seeds(key, count, batched),
                                        pyramid), mesh)
  carry = sharding.split(_Carry(
      first_estimate, np.broadcast_to(np.eye(size, dtype=np.float32), (count, size, size)),
      np.ones(count, np.int32), np.ones(count, np.float32)), mesh)
  knobs = sharding.replicate(config.knobs(), mesh)
  capacity = atlas.capacity(sum(h * w for h, w in atlas.level_shapes(frame_shape, levels)))

  chunks = [{k: v[:, None] for k, v in dict(
      homography=starts, score=np.zeros(count, np.float32),
      quality=np.ones(count, np.float32),
      status=np.full(count, TrackStatus.TRACKED, np.int32), estimate=np.asarray(first_estimate),
      num_iterations=np.zeros(count, np.int32),
      num_evaluations=np.zeros(count, np.int32), inside=np.ones(count, np.float32)).items()}]
  outputs, shares, doubt, peak = [], {}, {}, np.full(count, -np.inf)
  reacquire = (config.redetect or config.coast) and config.method == "pso"
  rects = np.stack([homography.host_rect_corners(shape) for shape in shapes])  # (R, 4, 2)
  recent = _Recent(*[starts.astype(np.float64)] * 3, np.zeros(count, np.int64),
                   starts.astype(np.float64), rects)
  # Regions the last frame step matched less than _MIN_IN_FRAME inside the frame: checked
  # on the next frame too, wherever its step matches them (a region 39 % inside under 12 px
  # of blur was matched 42 px off, wholly inside, at NCC 0.8+: test_detect).
  edge = np.zeros(count, bool)

  def settled(carry, step):
    """The frame step's (carry, out), with its LOST regions and those mostly outside the frame
    re-acquired (`_reacquired`)."""
    out, images, index, before = step
    if not reacquire:
      return carry, out
    host = sharding.to_host({k: out[k] for k in ("status", "inside", "quality", "homography")})
    plausible = _plausible_steps(host["homography"][:count], recent, slice(None))
    rejected = np.flatnonzero((host["status"][:count] != TrackStatus.LOST) & ~plausible)
    if rejected.size:
      carry, out = _rejected(carry, before, out, rejected, recent, shapes, frame_shape, mesh)
      host = sharding.to_host({k: out[k] for k in ("status", "inside", "quality")})
    check = host["status"][:count] == TrackStatus.LOST
    if config.redetect:
      check |= (host["inside"][:count] < _MIN_IN_FRAME) | edge
      edge[:] = host["inside"][:count] < _MIN_IN_FRAME
    for r, (last, best) in list(doubt.items()):
      if index > last or host["quality"][r] >= best - _margin(config) / 2:
        del doubt[r]
      else:
        check[r] = True
    check = np.flatnonzero(check)
    if check.size:
      frames = images if sequences else images * count
      carry, out, measured = _reacquired(carry, before, out, check, recent, frames, templates_,
                                         geometry, config, index, mesh, doubt, peak)
      shares.update({(r, index): share for r, share in measured.items()})
      host = sharding.to_host({k: out[k] for k in ("status", "quality")})
    for r, (last, best) in doubt.items():  # each also in `check`: `out` is on the host
      if host["status"][r] != TrackStatus.LOST and host["quality"][r] < best - _margin(config) / 2:
        out["status"][r] = host["status"][r] = TrackStatus.DOUBTFUL
    periodic_ = np.flatnonzero(aliased & (host["status"][:count] != TrackStatus.LOST))
    if periodic_.size:
      carry, out = _dealiased(carry, before, out, periodic_, recent,
                              images if sequences else images * count, templates_, geometry,
                              config, index, mesh, np.maximum(peak, 1.0))
      host = sharding.to_host({k: out[k] for k in ("status", "quality")})
    tracked = host["status"][:count] == TrackStatus.TRACKED
    peak[tracked] = np.maximum(peak[tracked], host["quality"][:count][tracked])
    return carry, out

  # A frame step's LOST regions are re-acquired once the next frame's pyramid
  # is built: the host builds it while the device runs the step (waiting for
  # each step's status first cost 15-30 % of the time per frame); the host's
  # record of the motion follows once the next step is running.
  with _collector_frozen():
    pending = None
    for index, raw in enumerate(iterator, start=1):
      images = [np.asarray(checks.to_gray(f, frame_name(r, index))) for r, f in enumerate(raw)]
      for r, image in enumerate(images):
        if image.shape != frame_shape:
          raise ValueError(f"{frame_name(r, index)} has shape {image.shape}, frame 0 has"
                           f" {frame_shape}: all frames must have one size")
      if sequences:
        image = sharding.split(batching.stack([atlas.build(i, levels, capacity) for i in images]),
                               mesh)
      else:
        image = sharding.replicate(atlas.build(images[0], levels, capacity), mesh)
      if pending is not None:
        carry, out = settled(carry, pending)
        outputs.append(out)
      before = carry
      carry, step_out = _frame_step(carry, image, constants, knobs, config=statics, mesh=mesh)
      if pending is not None and reacquire:
        host = sharding.to_host({k: out[k] for k in ("status", "homography")})
        recent = _moved(recent, host["homography"][:count], host["status"][:count])
      pending = step_out, images, index, before
      if len(outputs) == _HOST_CHUNK:
        chunks.append(_to_host(outputs))
        outputs = []
      if progress:
        of = f"/{total}" if total else ""
        print(f"\rtracking: frame {index + 1}{of}", end="", file=sys.stderr, flush=True)
  if pending is not None:
    outputs.append(settled(carry, pending)[1])
  if progress:
    print(file=sys.stderr)
  if outputs:
    chunks.append(_to_host(outputs))
  stacked = {k: np.concatenate([c[k][:count] for c in chunks], axis=1) for k in chunks[0]}
  inside = stacked.pop("inside")
  visible = np.where(stacked["status"] != TrackStatus.LOST, inside, 0.0).astype(np.float32)
  for (r, index), share in shares.items():
    visible[r, index] = share
  self_loss = prepared.self_loss[:, templates.SIMILARITIES.index(config.similarity)]
  stacked["score"][:, 0] = 0.0 if config.similarity == "ssd" else -self_loss
  own = stacked["homography"].astype(np.float64)
  own = own / own[..., 2:, 2:]
  rects = np.stack([np.c_[homography.host_rect_corners(shape), np.ones(4)]
                    for shape in shapes])  # (R, 4, 3)
  mapped = own @ np.swapaxes(rects, -1, -2)[:, None]  # (R, T, 3, 4)
  corners = np.swapaxes(mapped[..., :2, :] / mapped[..., 2:, :], -1, -2)
  result = TrackResult(
      homographies=own.astype(np.float32), corners=corners,
      scores=stacked["score"], quality=stacked["quality"], status=stacked["status"],
      poses=stacked["estimate"] if geometry is not None else None,
      num_iterations=stacked["num_iterations"], num_evaluations=stacked["num_evaluations"],
      visible=visible)
  return result if batched else jax.tree.map(lambda a: a[0], result)
