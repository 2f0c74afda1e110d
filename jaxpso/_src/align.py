"""One registration of a template in an image: the swarm, then a gradient polish.

`align(image, template, init_homography)` searches the 8 corner offsets of
the template (motion "homography") with the PSO engine at the coarsest level
of a Gaussian pyramid, where the similarity's basin is widest and a swarm
evaluation cheapest, then refines the best homography at full resolution with
a few Adam steps on the differentiable similarity (the hybrid: the swarm finds
the basin, the gradient the last sub-pixel).  Everything after input checks
is one compiled function per (shapes, config).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxpso._src import checks
from jaxpso._src import homography
from jaxpso._src import pso
from jaxpso._src import sampling
from jaxpso._src import similarity

SIMILARITIES = ("mi", "ncc", "ssd")
"""Names accepted by `TrackConfig.similarity`."""
MOTIONS = ("homography",)
"""Names accepted by `TrackConfig.motion` (the plane model follows with `track`)."""


class AlignStatus(enum.IntEnum):
  """Outcome of an alignment; 0 is success."""
  SUCCESS = 0
  NO_VALID_WARP = 1


@dataclasses.dataclass(frozen=True)
class TrackConfig:
  """Static settings of `align` (and, later, `track`); a change recompiles.

  Attributes:
    similarity: "mi" (default), "ncc" or "ssd".
    motion: "homography" (8 corner offsets).
    bins: histogram bins of MI (16: 100 % vs 70 % success at σ = 2 with 8,
      the sharper optimum outweighing the cost; benchmarks/convergence.py).
    swarm_size: particles of the swarm.
    max_iterations: PSO iterations at most.
    patience: PSO stagnation stop (None disables).
    variant: PSO variant (`jaxpso.pso.VARIANTS`).
    topology: PSO topology (`jaxpso.pso.TOPOLOGIES`).
    search_radius: half-width in full-resolution pixels of the box searched
      for each corner coordinate around the initial homography.
    levels: pyramid levels; the swarm searches the coarsest.
    refine_steps: Adam steps at full resolution after the swarm (0 disables).
    refine_rate: Adam learning rate, in pixels of corner offset.
    min_valid: fraction of template pixels that must land in the image.
  """
  similarity: str = "mi"
  motion: str = "homography"
  bins: int = 16
  swarm_size: int = 32
  max_iterations: int = 40
  patience: int | None = 10
  variant: str = "constriction"
  topology: str = "global"
  search_radius: float = 24.0
  levels: int = 3
  refine_steps: int = 60
  refine_rate: float = 0.1
  min_valid: float = 0.5

  def __post_init__(self):
    if self.similarity not in SIMILARITIES:
      raise ValueError(f"TrackConfig.similarity must be one of {SIMILARITIES}, got {self.similarity!r}")
    if self.motion not in MOTIONS:
      raise ValueError(f"TrackConfig.motion must be one of {MOTIONS}, got {self.motion!r}")
    for name in ("levels", "swarm_size", "max_iterations", "bins"):
      checks.check_int(getattr(self, name), f"TrackConfig.{name}", 1)
    checks.check_int(self.refine_steps, "TrackConfig.refine_steps", 0)
    for name in ("search_radius", "refine_rate"):
      if not float(getattr(self, name)) > 0:
        raise ValueError(f"TrackConfig.{name} must be > 0, got {getattr(self, name)!r}")
    self.pso_config()  # validates the PSO settings

  def pso_config(self) -> pso.PSOConfig:
    """The swarm's settings (batched loss over the whole swarm)."""
    return pso.PSOConfig(swarm_size=self.swarm_size, variant=self.variant,
                         topology=self.topology, max_iterations=self.max_iterations,
                         patience=self.patience, batched=True)


class AlignResult(NamedTuple):
  """Outcome of `align`.

  Attributes:
    homography: (3, 3) template → image homography, h[2, 2] = 1.
    score: () the similarity at it (an error for "ssd", else higher is better).
    status: () int32 `AlignStatus`.
    num_iterations: () int32 PSO iterations plus refinement steps.
    num_evaluations: () int32 swarm evaluations (particles × iterations) plus
      refinement steps (each one similarity and its gradient).
  """
  homography: jax.Array
  score: jax.Array
  status: jax.Array
  num_iterations: jax.Array
  num_evaluations: jax.Array


def to_gray(image, name: str) -> jax.Array:
  """(H, W) or (H, W, 3) uint8 or float image → (H, W) float32 grey in [0, 1]."""
  array = image if isinstance(image, jax.Array) else np.asarray(image)
  if array.dtype != np.uint8 and not jnp.issubdtype(array.dtype, jnp.floating):
    raise TypeError(f"{name} must be uint8 or float, got dtype {array.dtype}")
  if not (array.ndim == 2 or (array.ndim == 3 and array.shape[-1] == 3)):
    raise ValueError(f"{name} must be (H, W) grey or (H, W, 3) colour, got shape {array.shape}")
  grey = jnp.asarray(array, jnp.float32)
  if array.dtype == np.uint8:
    grey = grey / 255.0
  if grey.ndim == 3:
    grey = grey @ jnp.asarray([0.299, 0.587, 0.114], jnp.float32)
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


def _polish(image, template, start, level: int, loss_of, config: TrackConfig):
  """Adam on the corner offsets at one pyramid level; returns the best full-resolution
  homography seen and its loss."""
  reference = (similarity.soft_bins(template, bins=config.bins)
               if config.similarity == "mi" else template)
  start_l = homography.homography_to_level(start, level)

  def loss(x):  # x: (8,) corner offsets in level pixels
    warp_h = start_l @ homography.corner_offsets_to_homography(x, template.shape)
    return loss_of(reference, *sampling.warp_image(image, warp_h, template.shape))

  optimizer = optax.adam(config.refine_rate)

  def step(_, carry):
    x, state, best_x, best_loss = carry
    value, grad = jax.value_and_grad(loss)(x)
    better = value < best_loss
    best_x, best_loss = jnp.where(better, x, best_x), jnp.where(better, value, best_loss)
    updates, state = optimizer.update(jnp.where(jnp.isfinite(grad), grad, 0.0), state)
    return optax.apply_updates(x, updates), state, best_x, best_loss

  zero = jnp.zeros(8, jnp.float32)
  x, _, best_x, best_loss = jax.lax.fori_loop(
      0, config.refine_steps, step, (zero, optimizer.init(zero), zero, jnp.float32(jnp.inf)))
  last = loss(x)
  x = jnp.where(last < best_loss, x, best_x)
  warp_h = start_l @ homography.corner_offsets_to_homography(x, template.shape)
  return homography.homography_from_level(warp_h, level), jnp.minimum(last, best_loss)


@functools.partial(jax.jit, static_argnames=("config",))
def _align(image, template, init_homography, seed, *, config: TrackConfig) -> AlignResult:
  loss_of, sign = _measure(config)
  coarse = config.levels - 1
  image_pyramid = sampling.gaussian_pyramid(image, config.levels)
  template_pyramid = sampling.gaussian_pyramid(template, config.levels)
  image_c, template_c = image_pyramid[-1], template_pyramid[-1]
  shape_c = template_c.shape
  reference_c = (similarity.soft_bins(template_c, bins=config.bins)
                 if config.similarity == "mi" else template_c)
  start_c = homography.homography_to_level(init_homography, coarse)
  radius = config.search_radius / 2**coarse

  def swarm_loss(x, args):  # x: (n, 8) corner offsets at the coarse level
    frame, start = args
    candidates = start @ homography.corner_offsets_to_homography(x, shape_c)
    return loss_of(reference_c, *sampling.warp_image(frame, candidates, shape_c))

  box = jnp.full(8, radius, jnp.float32)
  found = pso._run(seed, -box, box, (image_c, start_c), pso.default_hparams(config.variant),
                   None, None, jnp.zeros(8, jnp.float32), box,
                   loss_fn=swarm_loss, config=config.pso_config())
  best_c = start_c @ homography.corner_offsets_to_homography(found.x, shape_c)
  best, loss = homography.homography_from_level(best_c, coarse), found.loss
  if coarse:
    # The coarse level's optimum can disagree with the full-resolution one
    # (a close start pulled away): keep the start when it scores better at
    # full resolution.
    reference = (similarity.soft_bins(template, bins=config.bins)
                 if config.similarity == "mi" else template)
    both = jnp.stack([init_homography, best])
    scores = loss_of(reference, *sampling.warp_image(image, both, template.shape))
    best = jnp.where(scores[0] <= scores[1], init_homography, best)
  for level in reversed(range(coarse)):  # coarse-to-fine gradient polish
    best, loss = _polish(image_pyramid[level], template_pyramid[level], best, level,
                         loss_of, config)
  finite = jnp.isfinite(loss)
  return AlignResult(
      homography=best / best[2, 2], score=sign * loss,
      status=jnp.where(finite, AlignStatus.SUCCESS, AlignStatus.NO_VALID_WARP).astype(jnp.int32),
      num_iterations=found.num_iterations + coarse * config.refine_steps,
      num_evaluations=found.num_evaluations + coarse * (config.refine_steps + 1))


def align(image, template, init_homography, *, config: TrackConfig = TrackConfig(),
          key=0) -> AlignResult:
  """Registers `template` in `image`, starting from `init_homography`.

  Args:
    image: (H, W) grey or (H, W, 3) colour, uint8 or float in [0, 1].
    template: (h, w) grey or (h, w, 3) colour, same conventions.
    init_homography: (3, 3) template pixel → image pixel (OpenCV convention).
    config: `TrackConfig`.
    key: int seed or PRNG key of the swarm.

  Returns:
    `AlignResult`.
  """
  if not isinstance(config, TrackConfig):
    raise TypeError(f"config must be a TrackConfig, got {type(config).__name__}")
  image = to_gray(image, "image")
  template = to_gray(template, "template")
  init_homography = checks.as_checked(init_homography, (3, 3), "init_homography", "(3, 3)")
  if init_homography.shape != (3, 3):
    raise ValueError(f"init_homography must have shape (3, 3), got {init_homography.shape}")
  if abs(float(jnp.linalg.det(init_homography))) < 1e-12:
    raise ValueError(f"init_homography must be invertible, got {np.asarray(init_homography)!r}")
  smallest = min(template.shape) / 2 ** (config.levels - 1)
  if smallest < 4:
    raise ValueError(
        f"template of shape {template.shape} is too small for levels={config.levels}:"
        " the coarsest level would be under 4 px")
  return _align(image, template, init_homography.astype(jnp.float32), pso._as_seed(key),
                config=config)
