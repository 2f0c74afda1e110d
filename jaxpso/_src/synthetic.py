"""Synthetic sequences: a textured plane seen by a moving camera, with exact truth.

The plane n · X = d of frame-0 camera coordinates carries the texture (an
embedded image).  A smooth 6-DOF camera trajectory, optional sudden jumps,
gain/bias drift, an intensity change part-way, blur and noise give frames
whose ground-truth homographies (template pixel → frame pixel) and poses are
exact: every frame is rendered by pulling the texture through the same
plane-induced homography H = K (R + t nᵀ/d) K⁻¹ that the tracker estimates.
An occluder can hide the region for a run of frames, and the frames can be
rendered lazily, one at a time, for sequences too long to hold in memory.
"""

from __future__ import annotations

import functools
import math
from typing import Iterator, NamedTuple

import jax
import numpy as np

from jaxpso._src import checks
from jaxpso._src import data
from jaxpso._src import homography
from jaxpso._src import plane
from jaxpso._src import sampling

INTENSITY_CHANGES = ("gamma", "invert")
"""Kinds accepted by `make_sequence(intensity_change=(frame, kind))`."""


class Sequence(NamedTuple):
  """A synthetic sequence and its ground truth.

  Attributes:
    frames: (T, H, W) float32 frames in [0, 1]; with `make_sequence(...,
      lazy=True)` a one-pass iterator rendering them one (H, W) frame at a time.
    homographies: (T, 3, 3) true template → frame homographies (identity
      plus the ROI offset at frame 0), normalised to h[2, 2] = 1; in occluded
      frames, where the region is behind the occluder.
    corners: (T, 4, 2) true template corners (TL, TR, BR, BL) in each frame.
    poses: (T, 4, 4) true poses: frame-0 camera → frame-t camera.
    visible: (T,) bool, False in the frames where the occluder hides the region.
    roi: (x, y, w, h) of the template in frame 0.
    camera: (3, 3) intrinsics K.
    normal: (3,) unit plane normal in frame-0 camera coordinates.
    distance: plane distance d (n · X = d).
  """
  frames: np.ndarray
  homographies: np.ndarray
  corners: np.ndarray
  poses: np.ndarray
  visible: np.ndarray
  roi: tuple[int, int, int, int]
  camera: np.ndarray
  normal: np.ndarray
  distance: float


def _trajectory(rng, num_frames: int, translation: float, rotation: float,
                jumps, jump_size: float) -> np.ndarray:
  """(T, 6) pose parameters (tx, ty, tz, wx, wy, wz): smooth sinusoids plus jumps.

  Every axis follows amplitude · sin(2π k / period + phase) with a random
  period of 40–120 frames, so the motion between frames is small; a jump at
  frame k adds a random offset of `jump_size` (in units of the amplitudes)
  that persists, a sudden large inter-frame motion.
  """
  k = np.arange(num_frames)[:, None]
  period = rng.uniform(40, 120, size=6)
  phase = rng.uniform(0, 2 * np.pi, size=6)
  amplitude = np.array([translation, translation, 0.5 * translation,
                        rotation, rotation, rotation])
  params = amplitude * (np.sin(2 * np.pi * k / period + phase) - np.sin(phase))
  for frame in jumps:
    params[frame:] += jump_size * amplitude * rng.choice([-1.0, 1.0], size=6)
  return params


def _texture_to_frame0(camera, normal, distance, texture_shape, frame_shape):
  """Homography from texture pixels to frame-0 pixels for the textured plane.

  The texture is laid on the plane centred on the point the optical axis
  hits, spanning twice the width of frame 0's view, so moderate camera motion
  never shows the texture's edge.
  """
  inv_k = np.linalg.inv(camera)
  centre_ray = inv_k @ np.array([(frame_shape[1] - 1) / 2, (frame_shape[0] - 1) / 2, 1.0])
  origin = distance * centre_ray / (normal @ centre_ray)  # plane point on the axis
  # In-plane axes: image x and y directions projected onto the plane.
  e1 = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
  e1 /= np.linalg.norm(e1)
  e2 = np.cross(normal, e1)
  scale = 2.0 * (frame_shape[1] / camera[0, 0]) * origin[2] / texture_shape[1]
  centre = np.array([(texture_shape[1] - 1) / 2, (texture_shape[0] - 1) / 2])
  columns = np.stack([scale * e1, scale * e2,
                      origin - scale * (centre[0] * e1 + centre[1] * e2)], axis=1)
  return camera @ columns


# The occluder covers the region's bounding box grown by this fraction of the
# region's larger side on every side.
_OCCLUDER_MARGIN = 0.25


def _occluder_box(corners, margin: float, frame_shape) -> tuple[slice, slice]:
  """(rows, columns) slices of the frame that the occluder covers around the (4, 2) `corners`."""
  height, width = frame_shape
  x0, y0 = np.floor(corners.min(axis=0) - margin).astype(int)
  x1, y1 = np.ceil(corners.max(axis=0) + margin).astype(int) + 1
  return slice(max(y0, 0), min(y1, height)), slice(max(x0, 0), min(x1, width))


def _poses(params: np.ndarray) -> np.ndarray:
  """(T, 4, 4) float64 `plane.pose_from_params` of (T, 6) parameters, on the host.

  As eager JAX operations this compiled some thirty small programs in every process.
  """
  omega = params[:, 3:]
  theta2 = np.sum(omega * omega, -1)[:, None, None]
  theta = np.sqrt(np.maximum(theta2, 1e-300))
  small = theta2 < 1e-12
  a = np.where(small, 1 - theta2 / 6, np.sin(theta) / theta)
  b = np.where(small, 0.5 - theta2 / 24, (1 - np.cos(theta)) / np.maximum(theta2, 1e-300))
  x, y, z = omega[:, 0], omega[:, 1], omega[:, 2]
  zero = np.zeros_like(x)
  skew = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(-1, 3, 3)
  poses = np.broadcast_to(np.eye(4), (len(params), 4, 4)).copy()
  poses[:, :3, :3] = np.eye(3) + a * skew + b * (skew @ skew)
  poses[:, :3, 3] = params[:, :3]
  return poses


@functools.partial(jax.jit, static_argnames=("shape",))
def _render(texture, frame_to_texture, *, shape):
  """(1, H, W) the texture pulled through a (1, 3, 3) frame → texture homography.

  One program per frame shape and process (a `jax.jit` per sequence compiled one per sequence).
  """
  return sampling.warp_image(texture, frame_to_texture, shape)[0]


def make_sequence(seed: int = 0, *, num_frames: int = 100, frame_shape=(240, 320),
                  roi_size=(100, 100), texture: str = "camera", camera=None,
                  normal=(0.0, 0.0, 1.0), distance: float = 1.0,
                  translation: float = 0.05, rotation: float = 0.03, jumps=(),
                  jump_size: float = 1.0, gain_drift: float = 0.0, noise: float = 0.0,
                  blur: float = 0.0, intensity_change: tuple[int, str] | None = None,
                  occlusion: tuple[int, int] | None = None, lazy: bool = False) -> Sequence:
  """Renders a sequence of the textured plane seen by a moving camera.

  Frame t is texture(M_t⁻¹ q) with M_t = K [R_t s e1 | R_t s e2 | R_t X₀ + t_t],
  the texture → frame-t homography of the plane, so the true template →
  frame homography is exactly K (R_t + t_t nᵀ/d) K⁻¹ · T(roi offset).

  Args:
    seed: random seed of the trajectory, the noise and the occluder.
    num_frames: T >= 1.
    frame_shape: (H, W) of the frames.
    roi_size: (h, w) of the template, centred in frame 0.
    texture: an embedded image name (`jaxpso._src.data.IMAGES`).
    camera: (3, 3) intrinsics; `plane.default_camera(frame_shape)` if None.
    normal: plane normal in frame-0 camera coordinates (any length > 0).
    distance: plane distance d > 0.
    translation: amplitude of the smooth translation, in units of d.
    rotation: amplitude of the smooth rotation, in radians.
    jumps: frames at which the camera jumps.
    jump_size: size of a jump in units of the amplitudes.
    gain_drift: amplitude of a slow gain change: frames are scaled by
      1 + gain_drift · sin(2π k / T) (and offset by gain_drift / 2 · (k / T)).
    noise: standard deviation of additive Gaussian noise.
    blur: standard deviation (px) of a Gaussian blur, 0 for none.
    intensity_change: (frame, kind) applies kind ("gamma": v ↦ √v, "invert":
      v ↦ 1 − v) to that frame and the following ones.
    occlusion: (start, stop) hides the region in frames start ≤ k < stop
      (0 < start < stop ≤ T) behind an occluder of uniform noise in [0, 1],
      new in every frame, over the region's bounding box grown by a quarter
      of its larger side each way; blur and noise apply to it as well.  The
      other frames are those of the sequence without occlusion.
    lazy: `frames` is an iterator that renders each frame when it is asked
      for, so memory does not grow with T; its frames equal the eager ones.

  Returns:
    `Sequence` with frames clipped to [0, 1].
  """
  checks.check_int(num_frames, "num_frames", 1)
  height, width = checks.check_shape2d(frame_shape, "frame_shape")
  h, w = checks.check_shape2d(roi_size, "roi_size")
  if h > height or w > width:
    raise ValueError(f"roi_size {roi_size} does not fit in frame_shape {frame_shape}")
  camera = plane.checked_camera(camera, (height, width))
  normal = plane.checked_normal(normal, "normal")
  if not (math.isfinite(distance) and distance > 0):
    raise ValueError(f"distance must be > 0, got {distance!r}")
  jumps = tuple(int(j) for j in jumps)
  if any(not 0 < j < num_frames for j in jumps):
    raise ValueError(f"jumps must be frames in (0, {num_frames}), got {jumps}")
  if intensity_change is not None:
    start, kind = intensity_change
    if kind not in INTENSITY_CHANGES or not 0 <= int(start) < num_frames:
      raise ValueError(
          f"intensity_change must be (frame in [0, {num_frames}), one of {INTENSITY_CHANGES}),"
          f" got {intensity_change!r}")
  visible = np.ones(num_frames, bool)
  if occlusion is not None:
    try:
      hidden_from, hidden_to = (int(k) for k in occlusion)
    except (TypeError, ValueError):
      hidden_from = hidden_to = -1
    if not 0 < hidden_from < hidden_to <= num_frames:
      raise ValueError(
          f"occlusion must be (start, stop) with 0 < start < stop <= num_frames = {num_frames},"
          f" got {occlusion!r}")
    visible[hidden_from:hidden_to] = False

  rng = np.random.default_rng(seed)
  occluder_rng = rng.spawn(1)[0]  # a stream of its own: rng's noise stays that of no occlusion
  params = _trajectory(rng, num_frames, translation, rotation, jumps, jump_size)
  poses = _poses(np.asarray(params, np.float64))
  rotations, shifts = poses[:, :3, :3], poses[:, :3, 3]
  frame0_to_frame = camera @ (rotations + shifts[:, :, None] * normal[None, None, :] / distance) \
      @ np.linalg.inv(camera)

  x0, y0 = (width - w) // 2, (height - h) // 2
  truth = frame0_to_frame @ np.array([[1.0, 0, x0], [0, 1, y0], [0, 0, 1]])
  truth /= truth[:, 2:3, 2:3]
  rect = np.c_[homography.host_rect_corners((h, w)), np.ones(4)]
  mapped = rect @ np.swapaxes(truth, -1, -2)  # (T, 4, 3)
  corners = mapped[..., :2] / mapped[..., 2:]

  image = data.load_image(texture)
  minification = image.shape[1] / (2.0 * width)  # texture pixels per frame-0 pixel
  if minification > 1 or blur:
    import cv2  # lazily: `import jaxpso` stays free of OpenCV
  if minification > 1:  # prefilter so that rendering does not alias
    image = cv2.GaussianBlur(image, (0, 0), 0.5 * minification)
  texture_to_frame0 = _texture_to_frame0(camera, normal, distance, image.shape, (height, width))
  texture_to_frame = frame0_to_frame @ texture_to_frame0
  frame_to_texture = np.linalg.inv(texture_to_frame)
  frame_to_texture /= frame_to_texture[:, 2:3, 2:3]
  frame_to_texture = frame_to_texture.astype(np.float32)
  texture = jax.device_put(image.astype(np.float32))
  margin = _OCCLUDER_MARGIN * max(h, w)

  def frames() -> Iterator[np.ndarray]:
    """The (H, W) float32 frames in order; the noise is drawn frame by frame."""
    for k in range(num_frames):
      frame = np.asarray(_render(texture, frame_to_texture[k:k + 1], shape=(height, width)),
                         np.float64)[0]
      if gain_drift:
        frame = frame * (1 + gain_drift * np.sin(2 * np.pi * k / num_frames)) \
            + 0.5 * gain_drift * k / num_frames
      if intensity_change is not None and k >= int(intensity_change[0]):
        frame = np.sqrt(np.clip(frame, 0, None)) if intensity_change[1] == "gamma" else 1.0 - frame
      if not visible[k]:
        rows, columns = _occluder_box(corners[k], margin, (height, width))
        frame[rows, columns] = occluder_rng.uniform(0.0, 1.0, frame[rows, columns].shape)
      if blur:
        frame = cv2.GaussianBlur(frame, (0, 0), blur)
      if noise:
        frame = frame + rng.normal(0, noise, frame.shape)
      yield np.clip(frame, 0.0, 1.0).astype(np.float32)

  return Sequence(frames=frames() if lazy else np.stack(list(frames())),
                  homographies=truth.astype(np.float32), corners=corners.astype(np.float32),
                  poses=poses.astype(np.float32), visible=visible, roi=(x0, y0, w, h),
                  camera=camera.astype(np.float32), normal=normal.astype(np.float32),
                  distance=float(distance))
