"""`align`: one registration of a template in an image, or a batch of them.

`align(image, template, init_homography)` checks its inputs
(`jaxpso._src.checks`), prepares them on the host (the template's point
sets, `jaxpso._src.template`; the image's pyramid around the start,
`jaxpso._src.atlas`; the batch, `jaxpso._src.batching`) and runs one
compiled program: the stages of `jaxpso._src.register` (Gauss–Newton from
the start; when that does not reach `TrackConfig.accept_quality`, a coarser
start, up to two quick swarms of `TrackConfig.quick_iterations` and
Gauss–Newton from their best, then where they fall short the full swarm; a
retry when the searches disagree on a poor match; settled at any quality
once three of these estimates agree).  `TrackConfig` (`jaxpso._src.config`)
holds the settings; its `method` swaps the pipeline for a gradient baseline
(`jaxpso._src.baselines`).  Neither the image's nor the template's size,
nor any setting but the few `TrackConfig.statics`, enters the compiled
program, so one program serves every alignment of a (similarity, motion,
method, swarm) and is kept across processes (`jaxpso._src.programs`).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import enum
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxpso._src import atlas
from jaxpso._src import baselines
from jaxpso._src import batching
from jaxpso._src import checks
from jaxpso._src import homography
from jaxpso._src import motion
from jaxpso._src import problem as problems
from jaxpso._src import programs
from jaxpso._src import register
from jaxpso._src import sharding
from jaxpso._src import template as templates
from jaxpso._src.config import TrackConfig
from jaxpso._src.config import score_sign


class AlignStatus(enum.IntEnum):
  """Outcome of an alignment; 0 is success."""
  SUCCESS = 0
  NO_VALID_WARP = 1
  BUDGET = 2  # `TrackConfig.max_evaluations` spent before the search settled: its best so far
  NO_MATCH = 3  # the best stays under `TrackConfig.hopeless_quality`: the later searches skipped


class AlignResult(NamedTuple):
  """Outcome of `align`.

  Attributes:
    homography: (3, 3) template → image homography, h[2, 2] = 1.
    score: () the similarity at it (an error for "ssd", else higher is better).
    quality: () the score relative to the template's own (`problem.quality`):
      about 1 for a match, lower the worse.  Where too few template pixels
      fall inside the image to score any warp (status `NO_VALID_WARP`: a
      start that puts the template outside it), score is +inf ("ssd") or
      −inf and quality −inf; never NaN.
    status: () int32 `AlignStatus`.
    num_iterations: () int32 PSO iterations plus refinement steps.
    num_evaluations: () int32 swarm evaluations (particles × iterations) plus
      refinement steps (each one similarity and its gradient).
    pose: (4, 4) camera motion from the view of `init_homography` to the
      image's for motion "plane" (translation in units of the plane's
      distance), else None.
    visible: () float32 the share of the template that the homography puts
      inside the image (`homography.inside_share`); the quality is judged on
      that share alone.
  """
  homography: jax.Array
  score: jax.Array
  quality: jax.Array
  status: jax.Array
  num_iterations: jax.Array
  num_evaluations: jax.Array
  pose: jax.Array | None = None
  visible: jax.Array | None = None


def _result(found: problems.Candidate, exhausted, hopeless, bases, geometry, offsets, sizes,
            config) -> AlignResult:
  """`AlignResult` of a batch's best candidates, homographies moved from window to image pixels
  (and for motion "plane", `geometry` given, the pose from the base poses `bases`).

  exhausted (N,) bool: the budget ended the search; hopeless () float32:
  `Knobs.hopeless_quality`; offsets (N, 4): each
  window's top-left pixel in its image and the image's (w, h); sizes (N, 2)
  the templates' (h, w).

  An unbatched `align` takes element 0 inside the program (`single`):
  indexing it after the program was one more dispatch, 0.1–0.15 ms of a
  6 ms alignment."""
  def one(found, exhausted, base, geometry, offset, size):
    pose = None if geometry is None else motion.plane_pose(found.u, base, geometry, config.dof)
    to_image = homography.translation(offset[0], offset[1])
    status = jnp.select([~jnp.isfinite(found.loss), exhausted, found.quality < hopeless],
                        [AlignStatus.NO_VALID_WARP, AlignStatus.BUDGET, AlignStatus.NO_MATCH],
                        AlignStatus.SUCCESS)
    h = problems.normalized(to_image @ found.homography)
    return AlignResult(
        homography=h, score=score_sign(config) * found.loss, quality=found.quality,
        status=status.astype(jnp.int32), num_iterations=found.num_iterations,
        num_evaluations=found.num_evaluations, pose=pose,
        visible=homography.inside_share(h, size, offset[2:]))

  return batching.each(one, found, exhausted, bases[:, 0], geometry, offsets, sizes)


@functools.partial(programs.Program, static_argnames=("config", "single", "mesh"))
def _align(images: atlas.Atlas, prepared: templates.Template, bases, geometry, seeds, offsets,
           knobs: problems.Knobs, *, config: TrackConfig, single: bool = False,
           mesh=None) -> AlignResult:
  """`align` of a batch of N: every argument has the leading N axis (knobs excepted).

  images: the `atlas.Atlas` of each image's window, whose top-left pixel is
  at `offsets` (N, 4)[:, :2] in the image of (w, h) `offsets[:, 2:]`; bases
  (N, 2, 3, 3) the start in window coordinates twice (or (N, 2, 4, 4) identity poses, with `geometry` the
  `motion.Plane`s in window coordinates); seeds (N, 2) uint32.  With
  `single` (N = 1), the result without the N axis; with a `mesh` of several
  devices, each runs its share (`sharding.per_device`).
  """
  def share(images, prepared, bases, geometry, seeds, offsets, knobs):
    contexts = batching.each(lambda *a: register.context(*a, config), images, prepared, bases,
                             geometry, seeds)
    state = register.run(contexts, knobs, "align", config)
    return _result(state.best, state.exhausted, knobs.hopeless_quality, bases, geometry, offsets,
                   prepared.size, config)

  return _on_devices(share, mesh, single, images, prepared, bases, geometry, seeds, offsets, knobs)


@functools.partial(programs.Program, static_argnames=("config", "single", "mesh"))
def _align_baseline(images: atlas.Atlas, pyramids: list, prepared: templates.Template, bases,
                    geometry, seeds, offsets, knobs: problems.Knobs, *,
                    config: TrackConfig, single: bool = False, mesh=None) -> AlignResult:
  """`_align` with `config.method`'s gradient registration; `pyramids` the templates' levels, (N, h_l, w_l) each."""
  def share(images, pyramids, prepared, bases, geometry, seeds, offsets, knobs):
    contexts = batching.each(lambda *a: register.context(*a, config), images, prepared, bases,
                             geometry, seeds)
    found = batching.each(lambda c, p: register.baseline(c, p, knobs, config), contexts, pyramids)
    return _result(found, jnp.zeros(found.loss.shape, bool), -jnp.inf, bases, geometry, offsets,
                   prepared.size, config)

  return _on_devices(share, mesh, single, images, pyramids, prepared, bases, geometry, seeds,
                     offsets, knobs)


def _on_devices(share, mesh, single: bool, *args) -> AlignResult:
  """`share(*args)` (a batch's alignments; the last argument, the knobs, shared) on each device
  of `mesh` (`sharding.per_device`); with `single`, element 0 alone."""
  result = sharding.per_device(share, mesh, shared=(len(args) - 1,))(*args)
  return jax.tree.map(lambda a: a[0], result) if single else result


def align(image, template, init_homography, *, config: TrackConfig = TrackConfig(),
          key=0, camera=None, plane_normal=None, devices=None) -> AlignResult:
  """Registers `template` in `image`, starting from `init_homography`; or a batch of them.

  A batch of N alignments is one compiled program: pass images
  (N, H, W[, 3]), templates (N, h, w[, 3]) and init_homography (N, 3, 3);
  the images may differ in size, and so may the templates (but with a
  gradient baseline, `TrackConfig.method`, the templates must share one
  shape).  Every field of the result gains the leading N axis.  With
  several devices the batch is split over them (`jax.sharding`).  On a CPU
  an element's result is bit-identical alone (with its key, below), in any
  batch and on any number of devices (`batching.each`); on an accelerator
  the batch is vectorised (`vmap`).

  Args:
    image: (H, W) grey or (H, W, 3) colour, uint8 or float in [0, 1].
    template: (h, w) grey or (h, w, 3) colour, same conventions; each side
      `checks.TEMPLATE_SIDES` (8 to 4096) pixels.
    init_homography: (3, 3) template pixel → image pixel (OpenCV convention).
    config: `TrackConfig`.  With motion "plane" the search is over `dof`
      camera-motion parameters from the view in which `init_homography`
      holds (pose identity) and the result has the `pose`.
    key: int seed or PRNG key of the swarm (element i of a batch gets its own
      stream; element 0 that of the unbatched call).  For a batch also one
      key per element (a list, (N,) ints or keys, or (N, 2) raw uint32
      keys): element i then gets the stream, and so the result, of the
      unbatched call with key[i].
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
  starts = batching.elements(init_homography, batched, "init_homography")
  images = batching.elements(image, batched, "image")
  templates_ = batching.elements(template, batched, "template")
  if not len(images) == len(templates_) == len(starts) >= 1:
    raise ValueError(
        f"a batch needs as many images, templates and init homographies (N >= 1), got"
        f" {len(images)}, {len(templates_)} and {len(starts)}")

  def named(name, i):
    return f"{name}[{i}]" if batched else name

  images = [np.asarray(checks.to_gray(x, named("image", i))) for i, x in enumerate(images)]
  templates_ = [np.asarray(checks.to_gray(x, named("template", i)))
                for i, x in enumerate(templates_)]
  if config.method != "pso" and any(t.shape != templates_[0].shape for t in templates_):
    raise ValueError(f"every template of a batch aligned by {config.method!r} must have one shape,"
                     f" got {sorted({t.shape for t in templates_})}")
  checks.check_texture(np.array([np.std(t) for t in templates_]), lambda i: named("template", i))
  shapes = [t.shape for t in templates_]
  configs = [config.for_template(t.shape, t) for t in templates_]
  for i, (shape, c) in enumerate(zip(shapes, configs)):
    checks.check_template_size(shape, c.levels, c.resolution, named("template", i))
  starts = [checks.check_start(h, shape, named("init_homography", i))
            for i, (h, shape) in enumerate(zip(starts, shapes))]
  if config.motion != "plane" and (camera is not None or plane_normal is not None):
    raise ValueError("camera and plane_normal apply to motion 'plane' only;"
                     f" got TrackConfig.motion={config.motion!r}")
  windows = [_window(h, shape, im.shape, c) for h, shape, im, c in zip(starts, shapes, images, configs)]
  crops = [im[y:y + hgt, x:x + wid] for im, (x, y, wid, hgt) in zip(images, windows)]
  for i, (crop, c) in enumerate(zip(crops, configs)):
    checks.check_image_size(crop.shape, c.levels, named("image", i))
  size = max(atlas.capacity(sum(h * w for h, w in atlas.level_shapes(crop.shape, c.levels)))
             for crop, c in zip(crops, configs))
  pyramids = [atlas.build(crop, c.levels, size) for crop, c in zip(crops, configs)]
  offsets = np.array([(*w[:2], im.shape[1], im.shape[0]) for w, im in zip(windows, images)],
                     np.float32)
  to_window = np.stack([np.array([[1, 0, -x], [0, 1, -y], [0, 0, 1]], np.float64)
                        for x, y in offsets[:, :2]])
  geometry = None
  if config.motion == "plane":
    geometry = motion.checked_plane_geometries(camera, plane_normal, images[0].shape, starts,
                                               shapes, config.dof)
    geometry = geometry._replace(camera=(to_window @ geometry.camera).astype(np.float32),
                                 template_to_frame0=(to_window @ geometry.template_to_frame0)
                                 .astype(np.float32))
    bases = np.broadcast_to(np.eye(4, dtype=np.float32), (len(starts), 2, 4, 4))
  else:
    bases = np.repeat((to_window @ np.stack(starts))[:, None], 2, axis=1).astype(np.float32)
  statics = config.statics()
  prepared = batching.stack([templates.prepared(t, c.levels, c.pixels, c.bins, statics.resolution)
                             for t, c in zip(templates_, configs)])
  arguments = (batching.stack(pyramids), prepared, bases, geometry,
               batching.element_seeds(key, len(starts), batched), offsets)
  mesh = sharding.batch_mesh(devices, len(starts))
  if mesh is not None:
    arguments = sharding.split(arguments, mesh)
  knobs = config.knobs()
  single = not batched  # a batch of one on one device (`sharding.batch_mesh`)
  if config.method == "pso":
    result = _align(*arguments, knobs, config=statics, single=single, mesh=mesh)
  else:
    levels = baselines.template_pyramids(templates_, configs[0].levels)
    result = _align_baseline(arguments[0], sharding.split(levels, mesh) if mesh else levels,
                             *arguments[1:], knobs,
                             config=dataclasses.replace(config, levels=configs[0].levels).statics(),
                             single=single, mesh=mesh)
  if mesh is not None and not all(a.is_fully_addressable for a in jax.tree.leaves(result)):
    result = sharding.to_host(result)  # spread over several processes (jax.distributed)
  if not single and len(result.score) > len(starts):
    result = jax.tree.map(lambda a: a[:len(starts)], result)
  for spent in _TALLIES.get():
    spent += (int(np.sum(result.num_iterations)), int(np.sum(result.num_evaluations)))
  return result


class Spent:
  """The summed `num_iterations` and `num_evaluations` of the `align` calls in a `counted`
  block (a batch's summed over its elements)."""

  def __init__(self):
    self.iterations = self.evaluations = 0

  def __iadd__(self, counts):
    self.iterations += counts[0]
    self.evaluations += counts[1]
    return self


_TALLIES: contextvars.ContextVar[tuple[Spent, ...]] = contextvars.ContextVar("tallies",
                                                                             default=())


@contextlib.contextmanager
def counted():
  """A block whose `align` calls are counted: yields a `Spent` that each call in it adds to
  (a call in nested blocks, to each)."""
  spent = Spent()
  token = _TALLIES.set(_TALLIES.get() + (spent,))
  try:
    yield spent
  finally:
    _TALLIES.reset(token)


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
