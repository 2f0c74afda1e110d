"""Frame-by-frame tracking of a planar region: `track`.

Frame 0's region is the template.  Every later frame is one call of one
compiled program (`_frame_step`): the frame's pyramid, a start chosen between
the constant-velocity prediction and the previous estimate, the registration
of `align.register` (Gauss–Newton from the start; when that falls short of
`TrackConfig.accept_quality`, the swarm and Gauss–Newton from its best), a
quality check and, when the quality is low, a recovery search around the last
good estimate: a larger swarm over the template's translation in a wider box,
then Gauss–Newton (a `lax.cond`, compiled once with the rest).  A frame whose
quality stays low is LOST: the last good estimate is kept and the motion
prediction is reset.  For motion "plane" the
camera pose is accumulated, T̂ ← T(x) · T̂.  With a gradient baseline
(`TrackConfig.method`) the registration is that method's, without recovery.
"""

from __future__ import annotations

import enum
import functools
import sys
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import align
from jaxpso._src import homography
from jaxpso._src import motion
from jaxpso._src import plane
from jaxpso._src import pso
from jaxpso._src import sampling


class TrackStatus(enum.IntEnum):
  """Per-frame outcome of `track`; 0 is success."""
  TRACKED = 0
  RECOVERED = 1  # found by the wider recovery search
  LOST = 2  # quality too low: the last good estimate is kept


class TrackResult(NamedTuple):
  """Outcome of `track`, one entry per frame (NumPy arrays).

  Attributes:
    homographies: (T, 3, 3) template pixel → frame pixel, h[2, 2] = 1.
    corners: (T, 4, 2) the template's corners (TL, TR, BR, BL) in each frame.
    scores: (T,) similarity at the estimate (an error for "ssd").
    quality: (T,) `align.quality` of the estimate: about 1 for a match, lower
      the worse (1 at frame 0; `TrackConfig.lost_quality` is the threshold).
    status: (T,) int32 `TrackStatus`.
    poses: (T, 4, 4) frame-0 → frame camera poses for motion "plane", else None.
    num_iterations: (T,) swarm iterations plus refinement steps (0 at frame 0).
    num_evaluations: (T,) similarity evaluations.
  """
  homographies: np.ndarray
  corners: np.ndarray
  scores: np.ndarray
  quality: np.ndarray
  status: np.ndarray
  poses: np.ndarray | None
  num_iterations: np.ndarray
  num_evaluations: np.ndarray


class _Constants(NamedTuple):
  """What every frame step shares (a pytree)."""
  template: align.Template
  geometry: motion.Plane | None
  seed: jax.Array


class _Carry(NamedTuple):
  """The tracker's state between frames (a pytree)."""
  estimate: jax.Array  # (3, 3) homography or (4, 4) pose: the last good estimate
  velocity: jax.Array  # same shape: estimate_t · estimate_{t-1}⁻¹
  frame: jax.Array  # () int32 index of the next frame


def _inverse(m):
  """Inverse of a homography or a rigid pose."""
  return plane.invert_pose(m) if m.shape == (4, 4) else homography.inverse(m)


def _frame_seed(seed, frame):
  return jnp.stack([seed[0], pso._mix(seed[1] ^ pso._mix(frame.astype(jnp.uint32)))])


@functools.partial(jax.jit, static_argnames=("config",))
def _frame_step(carry: _Carry, image, constants: _Constants, *, config: align.TrackConfig):
  """One frame: (carry, (H, W) grey image) → (carry, per-frame outputs)."""
  frame, shapes = align.prepare_frame(image, config)
  template = constants.template
  shape = template.pyramid[0].shape
  loss_of, sign = align._measure(config)
  to_h = functools.partial(motion.to_homography, geometry=constants.geometry, shape=shape,
                           motion=config.motion, dof=config.dof)
  dim = motion.dimension(config.motion, config.dof)
  zero = jnp.zeros(dim, jnp.float32)

  start = carry.estimate
  if config.predict:
    predicted = carry.velocity @ carry.estimate
    both = jnp.stack([to_h(zero, predicted), to_h(zero, carry.estimate)])
    patches, masks = sampling.sample_quads(frame[0], shapes[0], both, shape)
    losses = loss_of(template.reference(0, align.intensity_range(patches[1], masks[1])),
                     patches, masks)
    start = jnp.where(losses[0] <= losses[1], predicted, carry.estimate)

  seed = _frame_seed(constants.seed, carry.frame)
  search = functools.partial(align.register, frame, shapes, template, geometry=constants.geometry,
                             config=config)
  found = search(base=start, seed=seed, radius=jnp.float32(config.search_radius),
                 max_iterations=config.max_iterations,
                 accept=(None if config.accept_quality is None
                         else lambda found: found.quality >= config.accept_quality))
  weak = ~(found.quality >= config.lost_quality)

  def recover(_):
    # What accumulates while the target is lost is mostly translation, and a
    # swarm over every motion parameter in the wide box seldom found it.
    wide = search(base=carry.estimate, seed=seed ^ jnp.uint32(0x5BD1E995),
                  radius=jnp.float32(config.search_radius * config.recovery_scale),
                  max_iterations=config.max_iterations * config.recovery_scale,
                  swarm_size=config.swarm_size * config.recovery_scale, translation=True)
    base = jnp.where(found.loss <= wide.loss, start, carry.estimate)
    return align.better_of(found, wide), base

  base = start
  if config.method == "pso":
    found, base = jax.lax.cond(weak, recover, lambda _: (found, start), None)
  quality = found.quality
  lost = ~(quality >= config.lost_quality) | ~jnp.all(jnp.isfinite(found.u))
  status = jnp.where(lost, TrackStatus.LOST,
                     jnp.where(weak, TrackStatus.RECOVERED, TrackStatus.TRACKED)).astype(jnp.int32)

  estimate = (found.homography if config.motion == "homography"
              else motion.plane_pose(found.u, base, constants.geometry, config.dof))
  estimate = jnp.where(lost, carry.estimate, estimate)
  velocity = jnp.where(lost, jnp.eye(estimate.shape[0], dtype=estimate.dtype),
                       estimate @ _inverse(carry.estimate))
  h = align.normalized(to_h(zero, estimate))
  outputs = dict(homography=h, score=sign * found.loss,
                 quality=quality, status=status, estimate=estimate,
                 num_iterations=found.num_iterations, num_evaluations=found.num_evaluations)
  return _Carry(estimate, velocity, carry.frame + 1), outputs


# `track` moves the per-frame outputs to the host in chunks of this many
# frames.  Kept on the device to the end, they held 12.7 KB per frame
# (benchmarks/long_run.py: +56 MiB from frame 500 to 5000), and jnp.stack
# compiled a T-operand concatenation per field (2 fields of 5000 frames:
# 41 s and +336 MiB; np.stack on the host: 0.07 s).
_HOST_CHUNK = 256


def _to_host(outputs: list) -> dict:
  """Per-frame output dicts → one dict of (n, ...) NumPy arrays (waits for the last frame)."""
  host = jax.device_get(outputs)
  return {k: np.stack([o[k] for o in host]) for k in host[0]}


def _frames(frames):
  """An iterator over the frames, and their number if known."""
  if isinstance(frames, (np.ndarray, jax.Array)):
    if frames.ndim not in (3, 4):
      raise ValueError(
          f"frames must be (T, H, W) or (T, H, W, 3), or an iterable of frames;"
          f" got an array of shape {frames.shape}")
    return iter(frames), frames.shape[0]
  if isinstance(frames, (str, bytes)) or not hasattr(frames, "__iter__"):
    raise TypeError(f"frames must be an array or an iterable of frames, got {type(frames).__name__}")
  return iter(frames), (len(frames) if hasattr(frames, "__len__") else None)


def _template_geometry(roi, frame_shape):
  """roi → (template → frame-0 homography (3, 3), template shape (h, w))."""
  array = np.asarray(roi, np.float64) if not isinstance(roi, (str, bytes)) else None
  if array is None or array.shape not in ((4,), (4, 2)):
    raise ValueError(f"roi must be (x, y, w, h) or (4, 2) corners TL, TR, BR, BL; got {roi!r}")
  if not np.all(np.isfinite(array)):
    raise ValueError(f"roi must be finite, got {roi!r}")
  height, width = frame_shape
  if array.shape == (4,):
    x, y, w, h = array
    if w < 1 or h < 1 or w != int(w) or h != int(h):
      raise ValueError(f"roi width and height must be positive integers, got {roi!r}")
    corners = np.array([[x, y], [x + w - 1, y], [x + w - 1, y + h - 1], [x, y + h - 1]])
    shape = (int(h), int(w))
  else:
    corners = array
    w = 0.5 * (np.linalg.norm(corners[1] - corners[0]) + np.linalg.norm(corners[2] - corners[3]))
    h = 0.5 * (np.linalg.norm(corners[3] - corners[0]) + np.linalg.norm(corners[2] - corners[1]))
    shape = (int(round(h)) + 1, int(round(w)) + 1)
    if not np.all(np.asarray(motion.corner_turns(corners)) > 0) or min(shape) < 2:
      raise ValueError(
          f"roi corners must form a convex, non-degenerate quadrilateral in the order TL, TR,"
          f" BR, BL (clockwise on the image), got {roi!r}")
  if (corners.min(axis=0) < 0).any() or corners[:, 0].max() > width - 1 or corners[:, 1].max() > height - 1:
    raise ValueError(f"roi {roi!r} must lie inside frame 0 of shape {frame_shape}")
  rect = np.asarray(homography.rect_corners(shape), np.float64)
  h0 = np.asarray(homography.homography_from_corners(jnp.asarray(rect, jnp.float32),
                                                     jnp.asarray(corners, jnp.float32)))
  return jnp.asarray(h0 / h0[2, 2], jnp.float32), shape


def track(frames, roi, *, config: align.TrackConfig = align.TrackConfig(), key=0, camera=None,
          plane_normal=None, progress: bool = False) -> TrackResult:
  """Tracks the region `roi` of frame 0 through `frames`.

  Args:
    frames: (T, H, W) or (T, H, W, 3) array, or any iterable of frames (a
      video reader), uint8 or float in [0, 1], grey or colour, all one size.
    roi: (x, y, w, h) box in frame 0 (integer w, h), or (4, 2) corners TL,
      TR, BR, BL in frame-0 pixels.
    config: `TrackConfig` (motion, similarity, swarm, refinement, recovery).
    key: int seed or PRNG key; a fixed key gives bit-identical results.
    camera: (3, 3) intrinsics K for motion "plane"; default f = max(H, W) and
      the principal point at the frame's centre.
    plane_normal: (3,) normal of the target plane in frame-0 camera
      coordinates with n·X = d > 0 on the plane (d is taken as 1, so
      translations are in units of the plane's distance); default (0, 0, 1),
      fronto-parallel.  A rough normal is allowed.
    progress: print a progress line to stderr.

  Returns:
    `TrackResult`.

  Raises:
    ValueError: zero frames, frames of differing sizes or with non-finite
      pixels, a bad or out-of-frame ROI, a textureless template, a bad camera
      or normal.  TypeError: a bad dtype or config.
  """
  if not isinstance(config, align.TrackConfig):
    raise TypeError(f"config must be a TrackConfig, got {type(config).__name__}")
  iterator, total = _frames(frames)
  first = next(iterator, None)
  if first is None:
    raise ValueError("frames must hold at least one frame, got none")
  frame0 = align.to_gray(first, "frames[0]")
  h0, shape = _template_geometry(roi, frame0.shape)
  align.check_template_size(shape, config, "roi")
  template = sampling.warp_image(frame0, h0, shape)[0]
  if float(jnp.std(template)) < 1e-3:
    raise ValueError(f"roi {roi!r} is textureless (intensity std < 1e-3): nothing to track")
  prepared = align.prepare_template(template, config)
  geometry = None
  if config.motion == "plane":
    geometry = align.plane_geometry(camera, plane_normal, frame0.shape, h0, shape, config.dof)
  elif camera is not None or plane_normal is not None:
    raise ValueError("camera and plane_normal apply to motion 'plane' only;"
                     f" got TrackConfig.motion={config.motion!r}")
  constants = _Constants(prepared, geometry, pso._as_seed(key))
  first_estimate = h0 if geometry is None else jnp.eye(4, dtype=jnp.float32)
  carry = _Carry(first_estimate, jnp.eye(first_estimate.shape[0], dtype=jnp.float32),
                 jnp.ones([], jnp.int32))

  first_score = 0.0 if config.similarity == "ssd" else -prepared.self_loss
  chunks = []
  outputs = [dict(homography=h0, score=jnp.float32(first_score), quality=jnp.float32(1.0),
                  status=jnp.int32(TrackStatus.TRACKED), estimate=first_estimate,
                  num_iterations=jnp.int32(0), num_evaluations=jnp.int32(0))]
  for index, raw in enumerate(iterator, start=1):
    image = align.to_gray(raw, f"frames[{index}]")
    if image.shape != frame0.shape:
      raise ValueError(
          f"frames[{index}] has shape {image.shape}, frame 0 has {frame0.shape}: all frames"
          " must have one size")
    carry, out = _frame_step(carry, image, constants, config=config)
    outputs.append(out)
    if len(outputs) == _HOST_CHUNK:
      chunks.append(_to_host(outputs))
      outputs = []
    if progress:
      of = f"/{total}" if total else ""
      print(f"\rtracking: frame {index + 1}{of}", end="", file=sys.stderr, flush=True)
  if progress:
    print(file=sys.stderr)
  if outputs:
    chunks.append(_to_host(outputs))
  stacked = {k: np.concatenate([c[k] for c in chunks]) for k in chunks[0]}
  corners, _ = homography.apply_to_points(jnp.asarray(stacked["homography"]),
                                          homography.rect_corners(shape))
  return TrackResult(
      homographies=stacked["homography"], corners=np.asarray(corners),
      scores=stacked["score"], quality=stacked["quality"], status=stacked["status"],
      poses=stacked["estimate"] if geometry is not None else None,
      num_iterations=stacked["num_iterations"], num_evaluations=stacked["num_evaluations"])
