"""Frame-by-frame tracking of planar regions: `track`.

Frame 0's region is the template; a batch of R regions (or of R sequences)
is tracked together, every step `vmap`ped over the regions.  Every later
frame is one call of one compiled program (`_frame_step`): the frame's
pyramid, a start chosen between
the constant-velocity prediction and the previous estimate, the registration
of `align.register` (Gauss–Newton from the start; when that falls short of
`TrackConfig.accept_quality`, the swarm and Gauss–Newton from its best), a
quality check and, when the quality is low, a recovery search around the last
good estimate: a larger swarm over the template's translation in a wider box,
then Gauss–Newton (for the regions that need them only: `align.where_needed`).
A frame whose quality stays low is LOST: the last good estimate is kept and
the motion prediction is reset.  For motion "plane" the camera pose is
accumulated, T̂ ← T(x) · T̂.  With a gradient baseline
(`TrackConfig.method`) the registration is that method's, without recovery.
"""

from __future__ import annotations

import enum
import functools
import itertools
import sys
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import align
from jaxpso._src import compile_options
from jaxpso._src import homography
from jaxpso._src import motion
from jaxpso._src import plane
from jaxpso._src import pso
from jaxpso._src import sampling
from jaxpso._src import sharding


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
      the worse (1 at frame 0; `TrackConfig.lost_threshold` is the threshold).
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
  """What every frame step shares (a pytree; every leaf has the leading region axis R)."""
  template: align.Template
  geometry: motion.Plane | None
  seed: jax.Array  # (R, 2) uint32


class _Carry(NamedTuple):
  """The tracker's state between frames (a pytree; leading region axis R)."""
  estimate: jax.Array  # (R, 3, 3) homography or (R, 4, 4) pose: the last good estimate
  velocity: jax.Array  # same shape: estimate_t · estimate_{t-1}⁻¹
  frame: jax.Array  # (R,) int32 index of the next frame


def _inverse(m):
  """Inverse of a homography or a rigid pose."""
  return plane.invert_pose(m) if m.shape == (4, 4) else homography.inverse(m)


def _frame_seed(seed, frame):
  return jnp.stack([seed[0], pso._mix(seed[1] ^ pso._mix(frame.astype(jnp.uint32)))])


@functools.partial(compile_options.jit, static_argnames=("config",))
def _prepare(templates, config: align.TrackConfig) -> align.Template:
  """(R, h, w) templates → their `align.Template`s stacked (one compiled program)."""
  return jax.vmap(functools.partial(align.prepare_template, config=config))(templates)


@functools.partial(compile_options.jit, static_argnames=("config",))
def _frame_step(carry: _Carry, image, constants: _Constants, *, config: align.TrackConfig):
  """One frame of R regions: (carry, (H, W) image shared or (R, H, W) one per region) →
  (carry, per-frame outputs, each with the leading R)."""
  frame, shapes = align.prepare_frame(image, config)
  frame_axis = 0 if image.ndim == 3 else None
  template = constants.template
  shape = template.pyramid[0].shape[1:]
  loss_of, sign = align._measure(config)
  zero = jnp.zeros(motion.dimension(config.motion, config.dof), jnp.float32)

  def homography_of(estimate, geometry):  # one region's estimate → (3, 3)
    return motion.to_homography(zero, base=estimate, geometry=geometry, shape=shape,
                                motion=config.motion, dof=config.dof)

  def predict(frame, template, estimate, velocity, geometry):
    """The constant-velocity prediction or the previous estimate, whichever scores better."""
    predicted = velocity @ estimate
    both = jnp.stack([homography_of(predicted, geometry), homography_of(estimate, geometry)])
    patches, masks = sampling.sample_quads(frame[0], shapes[0], both, shape)
    losses = loss_of(template.reference(0, align.intensity_range(patches[1], masks[1])),
                     patches, masks)
    return jnp.where(losses[0] <= losses[1], predicted, estimate)

  start = carry.estimate
  if config.predict:
    start = jax.vmap(predict, in_axes=(frame_axis, 0, 0, 0, 0))(
        frame, template, carry.estimate, carry.velocity, constants.geometry)

  seed = jax.vmap(_frame_seed)(constants.seed, carry.frame)
  search = functools.partial(align.register, frame, shapes, template, geometry=constants.geometry,
                             config=config)
  found = search(base=start, seed=seed, radius=jnp.float32(config.search_radius),
                 max_iterations=config.max_iterations,
                 accept=(None if config.accept_quality is None
                         else lambda found: found.quality >= config.accept_quality))
  weak = ~(found.quality >= config.lost_threshold)

  def recover(indices):
    # What accumulates while the target is lost is mostly translation, and a
    # swarm over every motion parameter in the wide box seldom found it.
    wide = search(base=carry.estimate, seed=seed ^ jnp.uint32(0x5BD1E995),
                  radius=jnp.float32(config.search_radius * config.recovery_scale),
                  max_iterations=config.max_iterations * config.recovery_scale,
                  swarm_size=config.swarm_size * config.recovery_scale, translation=True,
                  indices=indices)
    alone, began, last = align.take((found, start, carry.estimate), indices)
    return align.better_of(alone, wide), align.select(alone.loss <= wide.loss, began, last)

  base = start
  if config.method == "pso":
    found, base = align.where_needed(weak, recover, (found, start))
  quality = found.quality
  lost = ~(quality >= config.lost_threshold) | ~jnp.all(jnp.isfinite(found.u), axis=-1)
  status = jnp.where(lost, TrackStatus.LOST,
                     jnp.where(weak, TrackStatus.RECOVERED, TrackStatus.TRACKED)).astype(jnp.int32)

  estimate = found.homography
  if config.motion != "homography":
    estimate = jax.vmap(functools.partial(motion.plane_pose, dof=config.dof))(
        found.u, base, constants.geometry)
  estimate = align.select(lost, carry.estimate, estimate)
  identity = jnp.broadcast_to(jnp.eye(estimate.shape[-1], dtype=estimate.dtype), estimate.shape)
  velocity = align.select(lost, identity, estimate @ jax.vmap(_inverse)(carry.estimate))
  h = jax.vmap(lambda e, g: align.normalized(homography_of(e, g)))(estimate, constants.geometry)
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
  """Per-frame output dicts of (R, ...) → one dict of (R, n, ...) NumPy arrays (waits for the last)."""
  host = sharding.to_host(outputs)
  return {k: np.stack([o[k] for o in host], axis=1) for k in host[0]}


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


_END = object()


def _lockstep(sequences, count: int):
  """An iterator over lists holding frame t of each of `count` sequences, and their length if known."""
  if isinstance(sequences, (np.ndarray, jax.Array)):
    if sequences.ndim not in (4, 5):
      raise ValueError(f"with sequences=True, frames must be (R, T, H, W) or (R, T, H, W, 3), or R"
                       f" iterables of frames; got an array of shape {sequences.shape}")
  elif isinstance(sequences, (str, bytes)) or not hasattr(sequences, "__len__"):
    raise TypeError("with sequences=True, frames must be an array or a sequence of R sequences,"
                    f" got {type(sequences).__name__}")
  if len(sequences) != count:
    raise ValueError(f"with sequences=True, frames must hold one sequence per region: {count}"
                     f" regions, {len(sequences)} sequences")
  iterators, lengths = zip(*(_frames(s) for s in sequences))

  def steps():
    for index, step in enumerate(itertools.zip_longest(*iterators, fillvalue=_END)):
      if any(f is _END for f in step):
        raise ValueError(f"the sequences must have one length: some end after {index} frames,"
                         " some do not")
      yield list(step)

  known = None if None in lengths else lengths[0]
  return steps(), known


def _template_geometry(roi, frame_shape, name: str = "roi"):
  """roi → (its (4, 2) corners TL, TR, BR, BL in frame 0, template shape (h, w))."""
  array = np.asarray(roi, np.float64) if not isinstance(roi, (str, bytes)) else None
  if array is None or array.shape not in ((4,), (4, 2)):
    raise ValueError(f"{name} must be (x, y, w, h) or (4, 2) corners TL, TR, BR, BL; got {roi!r}")
  if not np.all(np.isfinite(array)):
    raise ValueError(f"{name} must be finite, got {roi!r}")
  height, width = frame_shape
  if array.shape == (4,):
    x, y, w, h = array
    if w < 1 or h < 1 or w != int(w) or h != int(h):
      raise ValueError(f"{name} width and height must be positive integers, got {roi!r}")
    corners = np.array([[x, y], [x + w - 1, y], [x + w - 1, y + h - 1], [x, y + h - 1]])
    shape = (int(h), int(w))
  else:
    corners = array
    w = 0.5 * (np.linalg.norm(corners[1] - corners[0]) + np.linalg.norm(corners[2] - corners[3]))
    h = 0.5 * (np.linalg.norm(corners[3] - corners[0]) + np.linalg.norm(corners[2] - corners[1]))
    shape = (int(round(h)) + 1, int(round(w)) + 1)
    if not np.all(np.asarray(motion.corner_turns(corners)) > 0) or min(shape) < 2:
      raise ValueError(
          f"{name} corners must form a convex, non-degenerate quadrilateral in the order TL, TR,"
          f" BR, BL (clockwise on the image), got {roi!r}")
  if (corners.min(axis=0) < 0).any() or corners[:, 0].max() > width - 1 or corners[:, 1].max() > height - 1:
    raise ValueError(f"{name} {roi!r} must lie inside frame 0 of shape {frame_shape}")
  return corners, shape


def _regions(roi):
  """roi → (list of single rois, whether it was a batch)."""
  if isinstance(roi, (str, bytes)):
    raise ValueError(f"roi must be (x, y, w, h) or (4, 2) corners, or a batch of them; got {roi!r}")
  ndim = np.ndim(roi)
  batched = ndim == 3 or (ndim == 2 and np.shape(roi)[-1] == 4)
  if batched and len(roi) == 0:
    raise ValueError("roi must hold at least one region, got an empty batch")
  return (list(roi) if batched else [roi]), batched


def _to_common_grid(shape, common):
  """(3, 3) scale from a region's template pixels (h, w) to the batch's common grid."""
  return np.diag([(common[1] - 1) / max(shape[1] - 1, 1), (common[0] - 1) / max(shape[0] - 1, 1),
                  1.0])


def track(frames, roi, *, config: align.TrackConfig = align.TrackConfig(), key=0, camera=None,
          plane_normal=None, sequences: bool = False, devices=None,
          progress: bool = False) -> TrackResult:
  """Tracks the region `roi` of frame 0 through `frames`; or a batch of regions.

  A batch of R regions, `roi` of shape (R, 4) or (R, 4, 2), is tracked in one
  compiled program (`vmap` over the templates); every field of the result
  gains a leading R axis.  The templates are sampled on one common grid (the
  largest region's height and width), and the homographies are reported
  from each region's own template pixels.  With `sequences=True` region r is
  tracked in sequence r of `frames`.  The costly searches (the swarm, the
  recovery) run only for the regions that need them (`align.where_needed`).
  With several devices the regions are split over them (`jax.sharding`).

  Args:
    frames: (T, H, W) or (T, H, W, 3) array, or any iterable of frames (a
      video reader), uint8 or float in [0, 1], grey or colour, all one size.
      With `sequences=True`: (R, T, H, W[, 3]), or R such sequences of one length.
    roi: (x, y, w, h) box in frame 0 (integer w, h), or (4, 2) corners TL,
      TR, BR, BL in frame-0 pixels; or (R, 4) boxes or (R, 4, 2) corners.
    config: `TrackConfig` (motion, similarity, swarm, refinement, recovery).
    key: int seed or PRNG key; a fixed key gives bit-identical results.
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
      pixels, a bad or out-of-frame ROI, a textureless template, a bad camera
      or normal.  TypeError: a bad dtype or config.
  """
  if not isinstance(config, align.TrackConfig):
    raise TypeError(f"config must be a TrackConfig, got {type(config).__name__}")
  rois, batched = _regions(roi)
  count = len(rois)
  if sequences:
    iterator, total = _lockstep(frames, count)
  else:
    single, total = _frames(frames)
    iterator = ([frame] for frame in single)
  first = next(iterator, None)
  if first is None:
    raise ValueError("frames must hold at least one frame, got none")
  def frame_name(r, index):
    return f"frames[{r}][{index}]" if sequences else f"frames[{index}]"

  frame0 = [align.to_gray(f, frame_name(r, 0)) for r, f in enumerate(first)]
  if any(f.shape != frame0[0].shape for f in frame0):
    raise ValueError(f"the sequences' frames must have one size, got {[f.shape for f in frame0]}")
  frame_shape = frame0[0].shape

  def name(r):
    return f"roi[{r}]" if batched else "roi"

  regions = [_template_geometry(roi, frame_shape, name(r)) for r, roi in enumerate(rois)]
  common = tuple(max(shape[i] for _, shape in regions) for i in (0, 1))
  config = config.for_template(common)  # the templates are sampled on the common grid
  for r, (_, shape) in enumerate(regions):
    align.check_template_size(shape, config, name(r))
  to_common = np.stack([_to_common_grid(shape, common) for _, shape in regions])
  # Common grid → frame 0, for every region at once (eager calls per region
  # cost more than tracking a frame of a 64-region batch).
  rect = np.asarray(homography.rect_corners(common), np.float32)
  starts = np.asarray(homography.homography_from_corners(
      rect, np.stack([corners for corners, _ in regions]).astype(np.float32)), np.float64)
  starts = starts / starts[:, 2:, 2:]
  if sequences:
    templates = jnp.stack([sampling.warp_image(f, jnp.asarray(h, jnp.float32), common)[0]
                           for f, h in zip(frame0, starts)])
  else:
    templates = sampling.warp_image(frame0[0], jnp.asarray(starts, jnp.float32), common)[0]
  align.check_texture(np.asarray(jnp.std(templates, axis=(1, 2))),
                      lambda r: f"{name(r)} {rois[r]!r}")
  geometry = None
  if config.motion == "plane":
    geometry = align.plane_geometries(camera, plane_normal, frame_shape, starts, common,
                                      config.dof)
  elif camera is not None or plane_normal is not None:
    raise ValueError("camera and plane_normal apply to motion 'plane' only;"
                     f" got TrackConfig.motion={config.motion!r}")
  starts = starts.astype(np.float32)
  size = 3 if geometry is None else 4
  first_estimate = starts if geometry is None else np.broadcast_to(np.eye(4, dtype=np.float32),
                                                                   (count, 4, 4))
  mesh = sharding.batch_mesh(devices, count)
  prepared = _prepare(sharding.split(templates, mesh), config)
  constants = _Constants(prepared, sharding.split(geometry, mesh),
                         sharding.split(align.element_seeds(key, count), mesh))
  carry = sharding.split(_Carry(first_estimate, np.broadcast_to(np.eye(size, dtype=np.float32),
                                                       (count, size, size)),
                       np.ones(count, np.int32)), mesh)

  first_score = (np.zeros(count, np.float32) if config.similarity == "ssd"
                 else -sharding.to_host(prepared.self_loss)[:count])
  chunks = [{k: v[:, None] for k, v in dict(
      homography=starts, score=first_score, quality=np.ones(count, np.float32),
      status=np.full(count, TrackStatus.TRACKED, np.int32), estimate=np.asarray(first_estimate),
      num_iterations=np.zeros(count, np.int32),
      num_evaluations=np.zeros(count, np.int32)).items()}]
  outputs = []
  for index, raw in enumerate(iterator, start=1):
    images = [align.to_gray(f, frame_name(r, index)) for r, f in enumerate(raw)]
    for r, image in enumerate(images):
      if image.shape != frame_shape:
        raise ValueError(f"{frame_name(r, index)} has shape {image.shape}, frame 0 has"
                         f" {frame_shape}: all frames must have one size")
    image = (sharding.split(np.stack(images), mesh) if sequences
             else sharding.replicate(images[0], mesh))
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
  stacked = {k: np.concatenate([c[k][:count] for c in chunks], axis=1) for k in chunks[0]}
  own = stacked["homography"] @ to_common[:, None]  # own template pixels → frame
  own = own / own[..., 2:, 2:]
  mapped = stacked["homography"] @ np.c_[rect, np.ones(4, np.float32)].T  # (R, T, 3, 4)
  corners = np.swapaxes(mapped[..., :2, :] / mapped[..., 2:, :], -1, -2)
  result = TrackResult(
      homographies=own.astype(np.float32), corners=corners,
      scores=stacked["score"], quality=stacked["quality"], status=stacked["status"],
      poses=stacked["estimate"] if geometry is not None else None,
      num_iterations=stacked["num_iterations"], num_evaluations=stacked["num_evaluations"])
  return result if batched else jax.tree.map(lambda a: a[0], result)
