"""POT-210's seven challenges, synthesised with exact truth: jaxpso (MI, NCC) against ECC and SIFT.

POT-210 (Liang et al., *Planar Object Tracking in the Wild*, 2018) films
planar targets with a hand-held camera in seven categories: scale change,
rotation, perspective distortion, motion blur, occlusion, out of view and
unconstrained.  Its videos cannot be installed here, so each category is
rendered from the project's CC0 photographs (`../shared/data/images`, or
$JAXPSO_IMAGES: camera, brick, gravel, grass), with the truth exact:

* scene: a 320 px poster (one photograph, 512 texels) on a plane 1 unit
  ahead of a camera of focal 600 px (480×640 frames), in front of a wall
  2.5 units away tiled with another photograph (mirrored, 1 px per texel,
  Gaussian-blurred σ 1.2 so it differs from the poster); occluders are
  rectangles cut from a third photograph, held in front of the camera.
  Seed s takes the poster, wall and occluder from the photographs
  s, s + 1, s + 2 (mod 4) and a region side of SIDES[s mod 5] px;
* motion per category (laid out over the sequence: a shorter one moves
  faster), on top of a hand tremor of about 0.7 px (unconstrained 1.5):
  scale: the camera moves along the line to the poster, the poster 0.5–2×
  its frame-0 size; rotation: the poster turns in its plane to ±180° (up to
  5.7° per frame); perspective: the poster tilts to ±58° about its vertical
  axis, then ±52° about its horizontal one; motion blur: 4 shakes of the
  camera (fewer under 90 frames; 4 frames out, 4 back at 15–27 px per
  frame, a random direction) between slow stretches; occlusion: a slow drift (about 1 px per frame),
  two occluders covering 40–60 % of the region for 20–30 frames each and one
  covering all of it for 10; out of view: the camera pans until the
  region's centre reaches a side of the frame (half the region out), back,
  then until the region leaves the frame entirely for a few frames, back;
  unconstrained: zoom 0.74–1.35×, roll ±30°, tilt ±25°, one shake at 22 px
  per frame and one occluder covering half the region for 20 frames;
* each frame averages renderings over an exposure of half the frame
  interval (as many as keep a point's motion between two under 0.8 px, 3 to
  40; textures sampled from a mip-map level by the local scale), then shot
  and read noise (variance 0.0005·v + 0.01²), 8 bits.  Deterministic per
  (category, seed).

Truth: the homography of frame 0's region into frame k at the exposure's
midpoint; the region is a square of frame 0 on the poster.  Per frame also:
`visible`, the share of the region's area inside the frame and not behind an
occluder (rasterised masks), `blur_px`, the path of the region's centre
during the exposure, and `trackable` = visible ≥ 0.5 and blur_px ≤ 8.

Methods, each on every sequence: `jaxpso.track` with
`TrackConfig(similarity="mi")` and `"ncc"` (statuses from the result);
OpenCV's ECC chained frame to frame (video.py's `track_ecc`; every frame
counts as tracked); SIFT + RANSAC: OpenCV SIFT on frame 0's region (mask),
matched against the whole frame's SIFT features by brute force with Lowe's
ratio test (0.75), `cv2.findHomography(..., cv2.RANSAC, 5.0)` from at
least 8 matches, accepted with at least 8 inliers; otherwise the previous
estimate is kept and the frame counts as lost.

Metrics (frames 1..T−1): error = RMS of the 4 corner errors; P@5/10/20 =
share within 5/10/20 px, and P@5 on trackable frames only; first loss =
first frame more than 20 px off; tracked but off = frames reported tracked
(jaxpso: status TRACKED or RECOVERED; SIFT: a homography found) more than 5
px off; doubtful = jaxpso's DOUBTFUL frames (a re-detection short of the
region's best quality, and the frames tracked from it until it is confirmed
or replaced), and how many of them are more than 5 px off;
re-acquisition delay = for each frame where `trackable` turns true, the
frames until the error is first within 5 px (≥ marks one never re-acquired,
counted to the end); ms per frame = the whole method call on the sequence ÷
(T − 1), jaxpso after one warm-up `track` on the sequence's first 3 frames
(its time, compilation included, reported apart).

Usage: python benchmarks/challenges.py [--frames 150] [--seeds 0] [--categories scale,...]
         [--methods "jaxpso MI,jaxpso NCC,ECC,SIFT+RANSAC"] [--name challenges]
       quick: python benchmarks/challenges.py --frames 40 --categories occlusion
       truth check (no tracking): python benchmarks/challenges.py --check
       frames as PNG: python benchmarks/challenges.py --save-frames /tmp/frames --methods ""
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

import cv2
import numpy as np

import common
import jaxpso

NAMES = common.PHOTOS
CATEGORIES = ("scale", "rotation", "perspective", "motion blur", "occlusion", "out of view",
              "unconstrained")
METHODS = ("jaxpso MI", "jaxpso NCC", "ECC", "SIFT+RANSAC")
JAXPSO = {"jaxpso MI": dict(similarity="mi"), "jaxpso NCC": dict(similarity="ncc")}
FRAME = (480, 640)  # rows, columns
FOCAL = 600.0
POSTER_PX = 320.0  # the poster's side in frame 0 (1 unit ahead)
WALL_DEPTH, WALL_PX, WALL_BLUR = 2.5, 1.0, 1.2  # units ahead, px per texel in frame 0, σ texels
SIDES = (160, 176, 144, 192, 128)  # region side per seed mod 5
EXPOSURE = 0.5  # of the frame interval
STEP_PX, MIN_RENDERS, MAX_RENDERS = 0.8, 3, 40
GRID = 16  # trajectory samples per frame
MIP_LEVELS = 4
TRACKABLE_VISIBLE, TRACKABLE_BLUR_PX = 0.5, 8.0
LOSS_PX, GOOD_PX, WITHIN = 20.0, 5.0, (5.0, 10.0, 20.0)
TRACKED, LOST = int(jaxpso.TrackStatus.TRACKED), int(jaxpso.TrackStatus.LOST)


@dataclasses.dataclass
class Sequence:
  """One rendered sequence and its truth.

  frames: (T, 480, 640) uint8.  corners: (T, 4, 2) true corners of the
  region.  homographies: (T, 3, 3) frame-0 pixel → frame-k pixel.  roi:
  (x, y, w, h) in frame 0.  visible, blur_px: (T,) float; trackable: (T,)
  bool.  images: the photographs of poster, wall and occluder.
  """
  category: str
  seed: int
  frames: np.ndarray
  corners: np.ndarray
  homographies: np.ndarray
  roi: tuple
  visible: np.ndarray
  blur_px: np.ndarray
  trackable: np.ndarray
  images: dict


# ---------------------------------------------------------------------------- trajectories


def _smooth(values: np.ndarray, sigma_frames: float) -> np.ndarray:
  """(N, ...) samples on the GRID low-passed along axis 0 by a Gaussian of sigma_frames (edges held)."""
  if sigma_frames <= 0:
    return values
  sigma = sigma_frames * GRID
  half = int(np.ceil(4 * sigma))
  kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma) ** 2)
  kernel /= kernel.sum()
  padded = np.concatenate([np.repeat(values[:1], half, 0), values, np.repeat(values[-1:], half, 0)])
  flat = padded.reshape(len(padded), -1)
  out = np.stack([np.convolve(flat[:, i], kernel, mode="valid") for i in range(flat.shape[1])], 1)
  return out.reshape(values.shape)


def _keyframes(times: np.ndarray, keys, sigma_frames: float = 0.0) -> np.ndarray:
  """(N,) piecewise-linear through keys [(frame, value), ...] at `times`, then smoothed."""
  at, value = zip(*keys)
  return _smooth(np.interp(times, at, value), sigma_frames)


def _tremor(rng, count: int, amplitude_px: float, width_frames: float = 2.0) -> np.ndarray:
  """(count, 2) hand tremor in px: Gaussian noise low-passed over width_frames, std amplitude_px."""
  width = width_frames * GRID
  half = int(np.ceil(4 * width))
  kernel = np.exp(-0.5 * (np.arange(-half, half + 1) / width) ** 2)
  kernel /= np.sqrt(np.sum(kernel ** 2))
  raw = rng.normal(size=(count + 2 * half, 2))
  return amplitude_px * np.stack([np.convolve(raw[:, i], kernel, mode="valid") for i in range(2)], 1)


def _pan_rotation(pan_px: np.ndarray) -> np.ndarray:
  """(N, 3) camera rotation vectors moving the image centre by pan_px (N, 2) (x right, y down)."""
  return np.stack([-np.arctan(pan_px[:, 1] / FOCAL), np.arctan(pan_px[:, 0] / FOCAL),
                   np.zeros(len(pan_px))], 1)


def _shakes(times, starts, speeds, angles, out_frames: int) -> np.ndarray:
  """(N, 2) px: a camera shake per start: out_frames at speeds[i] px/frame along angles[i], back."""
  pan = np.zeros((len(times), 2))
  for start, speed, angle in zip(starts, speeds, angles):
    reach = speed * out_frames
    profile = _keyframes(times, [(start, 0.0), (start + out_frames, reach),
                                 (start + 2 * out_frames, 0.0)], 0.15)
    pan += profile[:, None] * np.array([np.cos(angle), np.sin(angle)])
  return pan


@dataclasses.dataclass
class _Plan:
  """Motion on the grid `times` (N,): camera rotation vectors and centres, poster rotation vectors,
  (N, 3) each, and occluders [(first frame, stop frame, kind, fraction, side)]."""
  times: np.ndarray
  camera_rotation: np.ndarray
  camera_centre: np.ndarray
  poster_rotation: np.ndarray
  occluders: list


def _plan(category: str, frames: int, rng, poster_centre: np.ndarray) -> _Plan:
  """The motion of one category over `frames` frames (see the module docstring)."""
  times = np.arange(-GRID, (frames + 1) * GRID + 1) / GRID
  n = len(times)
  last = max(frames - 1, 1)
  u = times / last
  tremor_px = 1.5 if category == "unconstrained" else 0.7
  tremor = _tremor(rng, n, tremor_px)
  tremor -= tremor[GRID]  # frame 0 at rest
  pan = tremor.copy()
  centre = np.zeros((n, 3))
  poster = np.zeros((n, 3))
  occluders = []
  if category == "scale":
    zoom = np.exp(np.log(2.0) * np.sin(2 * np.pi * u))
    centre = (1.0 - 1.0 / zoom)[:, None] * poster_centre  # along the line to the poster's centre
  elif category == "rotation":
    peak = 0.95
    poster[:, 2] = np.pi / np.arcsin(peak) * np.arcsin(peak * np.sin(2 * np.pi * u))
  elif category == "perspective":
    wave = np.sin(4 * np.pi * u)
    poster[:, 1] = np.where(u < 0.5, np.deg2rad(58.0) * wave, 0.0)
    poster[:, 0] = np.where(u >= 0.5, np.deg2rad(52.0) * wave, 0.0)
  elif category == "motion blur":
    count = int(np.clip((frames + 10) // 25, 1, 4))
    starts = [round(last * (0.12 + 0.22 * i * 4 / count)) for i in range(count)]
    pan += _shakes(times, starts, rng.uniform(15, 27, count), rng.uniform(0, 2 * np.pi, count), 4)
    pan += 25 * np.stack([np.sin(2 * np.pi * times / 150 * rng.uniform(0.8, 1.2)),
                          np.sin(2 * np.pi * times / 150 * rng.uniform(0.8, 1.2))], 1)
  elif category == "occlusion":
    phase = rng.uniform(0, 2 * np.pi, 2)
    drift = 25 * np.stack([np.sin(2 * np.pi * times / 150 + phase[0]) - np.sin(phase[0]),
                           np.sin(2 * np.pi * times / 150 + phase[1]) - np.sin(phase[1])], 1)
    centre[:, :2] = -drift / FOCAL  # the poster is 1 unit ahead: 1/FOCAL units per px
    partial = [max(4, round(rng.uniform(20, 30) * frames / 150)) for _ in range(2)]
    full = max(3, round(10 * frames / 150))
    sides = rng.choice(["left", "right", "top", "bottom"], 2)
    for at, length, kind, side in ((0.15, partial[0], "partial", sides[0]),
                                   (0.47, full, "full", None),
                                   (0.70, partial[1], "partial", sides[1])):
      first = max(1, round(at * last))
      occluders.append((first, min(first + length, frames), kind, rng.uniform(0.42, 0.58), side))
  elif category == "out of view":
    # Region centre to a side of the frame (x), then beyond the top or bottom edge (y).
    centre_px = poster_centre[:2] * FOCAL + np.array([FRAME[1], FRAME[0]]) / 2
    to_side = (FRAME[1] - centre_px[0]) if rng.random() < 0.5 else -centre_px[0]
    beyond = (FRAME[0] + 120 - centre_px[1]) if rng.random() < 0.5 else -(centre_px[1] + 120)
    a, b, c, d = (round(last * f) for f in (0.04, 0.26, 0.31, 0.49))
    e, f, g, h = (round(last * f) for f in (0.53, 0.75, 0.80, 0.98))
    shift_x = _keyframes(times, [(a, 0), (b, to_side), (c, to_side), (d, 0)], 1.5)
    shift_y = _keyframes(times, [(e, 0), (f, beyond), (g, beyond), (h, 0)], 1.5)
    centre[:, 0] = -shift_x / FOCAL
    centre[:, 1] = -shift_y / FOCAL
  elif category == "unconstrained":
    phase = rng.uniform(0, 2 * np.pi, 4)
    wave = lambda cycles, p: np.sin(2 * np.pi * cycles * u + p) - np.sin(p)
    zoom = np.exp(0.3 * np.sin(2 * np.pi * 1.0 * u))
    centre = (1.0 - 1.0 / zoom)[:, None] * poster_centre
    poster[:, 2] = np.deg2rad(30.0) * np.sin(2 * np.pi * 1.5 * u)
    poster[:, 0] = np.deg2rad(25.0) * np.sin(2 * np.pi * 0.8 * u) * np.cos(phase[0])
    poster[:, 1] = np.deg2rad(25.0) * np.sin(2 * np.pi * 1.2 * u) * np.cos(phase[1])
    pan += 20 * np.stack([wave(0.7, phase[2]), wave(0.9, phase[3])], 1)
    pan += _shakes(times, [round(0.4 * last)], [22.0], [rng.uniform(0, 2 * np.pi)], 3)
    first = max(1, round(0.7 * last))
    occluders.append((first, min(first + max(4, round(20 * frames / 150)), frames), "partial",
                      0.5, rng.choice(["left", "right", "top", "bottom"])))
  else:
    raise ValueError(f"unknown category {category!r}; one of {CATEGORIES}")
  return _Plan(times, _pan_rotation(pan), centre, poster, occluders)


def _at(plan: _Plan, t: float):
  """Camera rotation, camera centre and poster rotation (3,) each at time t (frames)."""
  return tuple(np.array([np.interp(t, plan.times, a[:, i]) for i in range(3)])
               for a in (plan.camera_rotation, plan.camera_centre, plan.poster_rotation))


# ---------------------------------------------------------------------------- rendering


def _camera() -> np.ndarray:
  return np.array([[FOCAL, 0, FRAME[1] / 2], [0, FOCAL, FRAME[0] / 2], [0, 0, 1.0]])


def _homographies(plan: _Plan, t: float, poster_centre, wall_origin, texel: float, wall_texel: float):
  """(3, 3) poster texel → frame pixel and wall texel → frame pixel at time t.

  World: x right, y down, z ahead; camera x_cam = R_c (X − c).  The poster's
  texel (u, v) is P + R_p (texel (u − 255.5), texel (v − 255.5), 0); the
  wall's is (wall_texel (u − u0), wall_texel (v − v0), WALL_DEPTH).
  """
  k = _camera()
  rotvec, centre, poster_rotvec = _at(plan, t)
  rc, _ = cv2.Rodrigues(rotvec)
  rp, _ = cv2.Rodrigues(poster_rotvec)
  axes = rc @ rp * texel
  mid = 255.5
  poster = np.column_stack([axes[:, 0], axes[:, 1],
                            rc @ (poster_centre - centre) - axes[:, 0] * mid - axes[:, 1] * mid])
  wall = np.column_stack([rc[:, 0] * wall_texel, rc[:, 1] * wall_texel,
                          rc @ (np.array([-wall_texel * wall_origin[0], -wall_texel * wall_origin[1],
                                          WALL_DEPTH]) - centre)])
  return k @ poster, k @ wall


def _pyramid(image: np.ndarray) -> list[np.ndarray]:
  levels = [image]
  for _ in range(MIP_LEVELS - 1):
    levels.append(cv2.pyrDown(levels[-1]))
  return levels


def _scale(h: np.ndarray, point) -> float:
  """Geometric mean of the local scale (px per texel) of h at `point` (texel)."""
  p = np.array([[point, (point[0] + 1, point[1]), (point[0], point[1] + 1)]], np.float64)
  q = cv2.perspectiveTransform(p, h)[0]
  jac = np.column_stack([q[1] - q[0], q[2] - q[0]])
  return float(np.sqrt(abs(np.linalg.det(jac))))


def _warp_mip(pyramid, h: np.ndarray, point, border: int) -> np.ndarray:
  """Float32 frame of the texture whose texel → pixel map is h, from the mip level of h's scale."""
  level = int(np.clip(np.round(np.log2(1.0 / max(_scale(h, point), 1e-6))), 0, len(pyramid) - 1))
  hl = h @ np.diag([2.0 ** level, 2.0 ** level, 1.0])  # cv2.pyrDown: level-L texel i at 2^L i
  return cv2.warpPerspective(pyramid[level], hl, (FRAME[1], FRAME[0]), flags=cv2.INTER_LINEAR,
                             borderMode=border)


def _occluder_rects(plan: _Plan, quads_at) -> list[tuple]:
  """[(first, stop, (x0, y0, x1, y1), texture offset)] with each partial occluder's edge placed so
  that it covers its fraction of the region at its middle frame; quads_at(k) = frame k's region."""
  rects = []
  for index, (first, stop, kind, fraction, side) in enumerate(plan.occluders):
    quad = quads_at((first + stop - 1) // 2)
    lo, hi = quad.min(0), quad.max(0)
    margin = 40.0
    if kind == "full":
      box = (lo[0] - 30, lo[1] - 30, hi[0] + 30, hi[1] + 30)
    else:
      def rect(edge, side=side):
        return {"left": (lo[0] - 400, lo[1] - margin, edge, hi[1] + margin),
                "right": (edge, lo[1] - margin, hi[0] + 400, hi[1] + margin),
                "top": (lo[0] - margin, lo[1] - 400, hi[0] + margin, edge),
                "bottom": (lo[0] - margin, edge, hi[0] + margin, hi[1] + 400)}[side]
      axis = 0 if side in ("left", "right") else 1
      low, high = lo[axis], hi[axis]
      for _ in range(30):  # bisection on the edge: covered share grows toward `side`'s far end
        edge = 0.5 * (low + high)
        covered = 1.0 - _visible(quad, [_clip_rect(rect(edge))])
        grows = side in ("left", "top")
        if (covered < fraction) == grows:
          low = edge
        else:
          high = edge
      box = rect(0.5 * (low + high))
    rects.append((first, stop, _clip_rect(box), (97 * index + 13, 61 * index + 29)))
  return rects


def _clip_rect(box) -> tuple:
  x0, y0, x1, y1 = (int(round(v)) for v in box)
  return (max(x0, 0), max(y0, 0), min(x1, FRAME[1]), min(y1, FRAME[0]))


def _visible(quad: np.ndarray, rects) -> float:
  """Share of the quad (4, 2) (pixel-edge corners) inside the frame and outside every rect."""
  mask = np.zeros(FRAME, np.uint8)
  cv2.fillPoly(mask, [np.round(quad * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
  for x0, y0, x1, y1 in rects:
    mask[y0:y1, x0:x1] = 0
  x, y = quad[:, 0], quad[:, 1]
  area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
  return float(np.clip(mask.sum() / max(area, 1e-9), 0.0, 1.0))


def render(category: str, frames: int = 150, seed: int = 0, noise: bool = True,
           sharp: bool = False) -> Sequence:
  """Renders one category's sequence (deterministic per (category, seed)); see the module docstring.

  noise=False leaves out the sensor noise, sharp=True the motion blur (one
  rendering at each frame's time): for checking the truth.
  """
  rng = np.random.default_rng([seed, CATEGORIES.index(category)])
  names = {"poster": NAMES[seed % 4], "wall": NAMES[(seed + 1) % 4],
           "occluder": NAMES[(seed + 2) % 4]}
  poster_tex = common.photo(names["poster"])
  wall_tex = cv2.GaussianBlur(common.photo(names["wall"]), (0, 0), WALL_BLUR)
  occluder_tex = cv2.copyMakeBorder(common.photo(names["occluder"]) * 0.9 + 0.05, 0, 512, 0, 512,
                                    cv2.BORDER_REFLECT)
  poster_pyr, wall_pyr = _pyramid(poster_tex), _pyramid(wall_tex)
  alpha_pyr = _pyramid(np.ones_like(poster_tex))
  texel = POSTER_PX / FOCAL / poster_tex.shape[0]
  wall_texel = WALL_DEPTH / (FOCAL * WALL_PX)
  wall_origin = rng.uniform(100, 400, 2)
  offset_px = rng.uniform(-20, 20, 2)
  poster_centre = np.array([offset_px[0] / FOCAL, offset_px[1] / FOCAL, 1.0])
  jitter = rng.uniform(-15, 15, 2)  # drawn before the motion: frame 0 independent of `frames`
  plan = _plan(category, frames, rng, poster_centre)

  h0, _ = _homographies(plan, 0.0, poster_centre, wall_origin, texel, wall_texel)
  middle = cv2.perspectiveTransform(np.array([[[255.5, 255.5]]]), h0)[0, 0]
  side = SIDES[seed % len(SIDES)]
  x, y = (int(round(middle[0] + jitter[0] - side / 2)), int(round(middle[1] + jitter[1] - side / 2)))
  roi = (x, y, side, side)
  quad = np.array([[x, y], [x + side - 1, y], [x + side - 1, y + side - 1], [x, y + side - 1]],
                  np.float64)
  edges = quad + np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
  centre0 = quad.mean(0)
  h0_inv = np.linalg.inv(h0)

  def truth(t):
    hp, _ = _homographies(plan, t, poster_centre, wall_origin, texel, wall_texel)
    h = hp @ h0_inv
    return h / h[2, 2]

  rects = _occluder_rects(plan, lambda k: cv2.perspectiveTransform(edges[None], truth(k))[0])
  poster_corners = np.array([[[0, 0], [511, 0], [511, 511], [0, 511]]], np.float64)
  frame_corners = np.array([[[0, 0], [FRAME[1], 0], [FRAME[1], FRAME[0]], [0, FRAME[0]]]],
                           np.float64)
  out = np.empty((frames,) + FRAME, np.uint8)
  homographies = np.empty((frames, 3, 3))
  visible = np.empty(frames)
  blur = np.empty(frames)
  for k in range(frames):
    start, stop = k - EXPOSURE / 2, k + EXPOSURE / 2
    hp0, hw0 = _homographies(plan, start, poster_centre, wall_origin, texel, wall_texel)
    hp1, hw1 = _homographies(plan, stop, poster_centre, wall_origin, texel, wall_texel)
    # The largest motion of a poster corner or of the wall at a frame corner during the exposure.
    poster_reach = (cv2.perspectiveTransform(poster_corners, hp1)
                    - cv2.perspectiveTransform(poster_corners, hp0))
    wall_reach = cv2.perspectiveTransform(frame_corners, hw1 @ np.linalg.inv(hw0)) - frame_corners
    reach = max(np.max(np.linalg.norm(poster_reach, axis=-1)),
                np.max(np.linalg.norm(wall_reach, axis=-1)))
    count = int(np.clip(np.ceil(min(reach, 1e4) / STEP_PX) + 1, MIN_RENDERS, MAX_RENDERS))
    times = [float(k)] if sharp else np.linspace(start, stop, count)
    occluding = [(rect, origin) for first, stop_, rect, origin in rects if first <= k < stop_]
    total = np.zeros(FRAME, np.float32)
    for t in times:
      hp, hw = _homographies(plan, t, poster_centre, wall_origin, texel, wall_texel)
      wall = _warp_mip(wall_pyr, hw, (256.0, 256.0), cv2.BORDER_REFLECT)
      poster = _warp_mip(poster_pyr, hp, (255.5, 255.5), cv2.BORDER_REPLICATE)
      alpha = _warp_mip(alpha_pyr, hp, (255.5, 255.5), cv2.BORDER_CONSTANT)
      image = wall + alpha * (poster - wall)
      for (x0, y0, x1, y1), (ox, oy) in occluding:
        image[y0:y1, x0:x1] = occluder_tex[oy:oy + y1 - y0, ox:ox + x1 - x0]
      total += image
    value = total / len(times)
    if noise:
      value = value + rng.normal(size=FRAME) * np.sqrt(0.0005 * np.clip(value, 0, 1) + 0.01 ** 2)
    out[k] = np.clip(np.round(value * 255.0), 0, 255).astype(np.uint8)
    homographies[k] = truth(float(k))
    visible[k] = _visible(cv2.perspectiveTransform(edges[None], homographies[k])[0],
                          [rect for rect, _ in occluding])
    path = np.stack([cv2.perspectiveTransform(centre0[None, None], truth(t))[0, 0]
                     for t in np.linspace(start, stop, 9)])
    blur[k] = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))
  corners = np.stack([cv2.perspectiveTransform(quad[None], h)[0] for h in homographies])
  trackable = (visible >= TRACKABLE_VISIBLE) & (blur <= TRACKABLE_BLUR_PX)
  return Sequence(category, seed, out, corners, homographies, roi, visible, blur, trackable, names)


def truth_residual(seq: Sequence, max_blur_px: float = float("inf")) -> dict:
  """How exact the truth is: frame 0's region against frame k warped back by the truth.

  For every frame with the whole region visible and blur_px ≤ max_blur_px:
  the RMS grey difference (0–255) over the region's interior between frame
  0's region and frame k sampled at the truth homography
  (`cv2.WARP_INVERSE_MAP`); the same with the truth moved by 1 px in x; and
  the shift of the truth (a 0.125 px grid within ±0.75 px in x and y) that
  minimises the difference, which is 0 where the truth is exact up to the
  resampling.  Meant for `render(..., noise=False, sharp=True)`.
  """
  x, y, w, h = seq.roi
  template = seq.frames[0, y:y + h, x:x + w].astype(np.float32)
  inner = (slice(4, h - 4), slice(4, w - 4))
  to_frame0 = np.array([[1, 0, x], [0, 1, y], [0, 0, 1.0]])
  steps = np.arange(-0.75, 0.7501, 0.125)

  def rms(k, dx, dy):
    shift = np.array([[1, 0, dx], [0, 1, dy], [0, 0, 1.0]])
    back = cv2.warpPerspective(seq.frames[k].astype(np.float32),
                               shift @ seq.homographies[k] @ to_frame0, (w, h),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    return float(np.sqrt(np.mean((back - template)[inner] ** 2)))

  exact, shifted, best = [], [], []
  for k in range(1, len(seq.frames)):
    if seq.visible[k] < 0.999 or seq.blur_px[k] > max_blur_px:
      continue
    exact.append(rms(k, 0.0, 0.0))
    shifted.append(rms(k, 1.0, 0.0))
    grid = [(rms(k, dx, dy), dx, dy) for dx in steps for dy in steps]
    _, dx, dy = min(grid)
    best.append(np.hypot(dx, dy))
  if not exact:
    return {"frames": 0}
  return {"frames": len(exact), "rms_exact": float(np.median(exact)),
          "rms_exact_max": float(np.max(exact)), "rms_1px_off": float(np.median(shifted)),
          "best_shift_px_median": float(np.median(best)), "best_shift_px_max": float(np.max(best))}


def save_frames(seq: Sequence, folder: str, count: int = 6) -> None:
  """Writes `count` frames of seq as PNG (evenly spaced, the least visible, the most blurred).

  The true region is drawn in green, with the frame's visible share and blur.
  """
  os.makedirs(folder, exist_ok=True)
  picks = set(np.linspace(0, len(seq.frames) - 1, max(count - 2, 2)).round().astype(int))
  picks |= {int(np.argmin(seq.visible)), int(np.argmax(seq.blur_px))}
  for k in sorted(picks):
    image = cv2.cvtColor(seq.frames[k], cv2.COLOR_GRAY2BGR)
    cv2.polylines(image, [np.round(seq.corners[k] * 16).astype(np.int32)], True, (0, 255, 0), 1,
                  cv2.LINE_AA, shift=4)
    cv2.putText(image, f"{seq.category} {k}: visible {seq.visible[k]:.2f} blur {seq.blur_px[k]:.1f}",
                (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 255, 255), 1, cv2.LINE_AA)
    cv2.imwrite(os.path.join(folder, f"{seq.category.replace(' ', '_')}_s{seq.seed}_{k:03d}.png"),
                image)


# ---------------------------------------------------------------------------- methods


def track_sift(frames: np.ndarray, box) -> tuple[np.ndarray, np.ndarray]:
  """(T, 4, 2) corners and (T,) statuses by SIFT + RANSAC (`jaxpso.datasets.track_features`;
  TRACKED where a homography was found)."""
  x, y, w, h = box
  quad = np.array([[x, y], [x + w - 1, y], [x + w - 1, y + h - 1], [x, y + h - 1]], np.float64)
  corners, found = jaxpso.datasets.track_features(frames, quad)
  return corners, np.where(found, TRACKED, LOST)


def run_method(method: str, seq: Sequence) -> dict:
  """One method on one sequence: corners (T, 4, 2), statuses (T,), seconds, warm-up seconds."""
  frames, roi = seq.frames, seq.roi
  warmup = None
  if method in JAXPSO:
    config = jaxpso.TrackConfig(**JAXPSO[method])
    start = time.perf_counter()
    jaxpso.track(frames[:3], roi, config=config)  # compiles (or loads) and warms up
    warmup = time.perf_counter() - start
    start = time.perf_counter()
    result = jaxpso.track(frames, roi, config=config)
    seconds = time.perf_counter() - start
    corners, status = np.asarray(result.corners), np.asarray(result.status).astype(int)
  elif method == "ECC":
    from video import track_ecc
    start = time.perf_counter()
    corners = track_ecc(frames, roi)
    seconds = time.perf_counter() - start
    status = np.full(len(frames), TRACKED)
  elif method == "SIFT+RANSAC":
    start = time.perf_counter()
    corners, status = track_sift(frames, roi)
    seconds = time.perf_counter() - start
  else:
    raise ValueError(f"unknown method {method!r}; one of {METHODS}")
  return {"corners": corners, "status": status, "seconds": seconds, "warmup_s": warmup}


# ---------------------------------------------------------------------------- metrics


def _reacquisitions(errors: np.ndarray, trackable: np.ndarray) -> list[tuple[int, bool]]:
  """[(delay, re-acquired)] per frame k ≥ 1 where trackable turns true: frames to error ≤ 5 px."""
  out = []
  for k in range(1, len(errors)):
    if trackable[k] and not trackable[k - 1]:
      good = np.flatnonzero(errors[k:] <= GOOD_PX)
      out.append((int(good[0]), True) if good.size else (len(errors) - k, False))
  return out


def frame_metrics(errors: np.ndarray, status: np.ndarray, trackable: np.ndarray) -> dict:
  """Per-sequence counts over frames 1..T−1 (summable across sequences)."""
  e, s, ok = errors[1:], status[1:], trackable[1:]
  lost = np.flatnonzero(errors > LOSS_PX)
  precision = common.status_precision(s, e, GOOD_PX)
  return {"frames": int(e.size), **{f"within_{int(px)}": int(np.sum(e <= px)) for px in WITHIN},
          "trackable": int(np.sum(ok)), "trackable_within_5": int(np.sum(ok & (e <= GOOD_PX))),
          "first_loss": int(lost[0]) if lost.size else None,
          **{k: precision[k] for k in ("tracked", "tracked_but_off", "doubtful",
                                       "doubtful_but_off")},
          "reacquisitions": _reacquisitions(errors, trackable),
          "median_error_px": float(np.median(e)) if e.size else float("nan")}


def pool(rows: list[dict]) -> dict:
  """Sums of frame_metrics rows (first losses listed per sequence)."""
  out = {key: sum(r[key] for r in rows) for key in
         ("frames", "within_5", "within_10", "within_20", "trackable", "trackable_within_5",
          "tracked", "tracked_but_off", "doubtful", "doubtful_but_off")}
  out["first_loss"] = [r["first_loss"] for r in rows]
  out["reacquisitions"] = [d for r in rows for d in r["reacquisitions"]]
  out["seconds"] = sum(r["seconds"] for r in rows)
  out["warmup_s"] = [r["warmup_s"] for r in rows if r["warmup_s"] is not None]
  for px in WITHIN:
    out[f"p_at_{int(px)}"] = 100.0 * out[f"within_{int(px)}"] / max(out["frames"], 1)
  out["p_at_5_trackable"] = (100.0 * out["trackable_within_5"] / out["trackable"]
                             if out["trackable"] else None)
  out["ms_per_frame"] = 1e3 * out["seconds"] / max(out["frames"], 1)
  return out


def _fmt_loss(losses) -> str:
  if len(losses) == 1:
    return "–" if losses[0] is None else str(losses[0])
  ever = [v for v in losses if v is not None]
  return f"{len(ever)}/{len(losses)} seqs" + (f", first {min(ever)}" if ever else "")


def _fmt_reacq(delays) -> str:
  if not delays:
    return "–"
  worst = max(delays, key=lambda d: (not d[1], d[0]))
  mean = np.mean([d for d, _ in delays])
  never = any(not ok for _, ok in delays)
  mark = "≥" if never else ""
  return (f"{'≥' if not worst[1] else ''}{worst[0]} / {mark}{mean:.1f}"
          f" ({len(delays)}{', ' + str(sum(not ok for _, ok in delays)) + ' never' if never else ''})")


def _pct(value) -> str:
  return "–" if value is None else f"{value:.1f}"


# ---------------------------------------------------------------------------- output


def markdown(summary, sequences, methods, categories, info, args) -> str:
  seeds = sorted({s["seed"] for s in sequences})
  lines = [
      "# POT-210's seven challenges, synthesised: jaxpso against ECC and SIFT + RANSAC", "",
      common.machine_line(info), "",
      f"{args.frames} frames per sequence (480×640, 8-bit grey), seeds {seeds}, one sequence per"
      " category and seed: a 320 px poster (a CC0 photograph) 1 unit ahead of a moving camera"
      " (focal 600 px) in front of a wall 2.5 units away tiled with another photograph, occluders"
      " cut from a third; each frame averages renderings over half the frame interval, then"
      " shot and read noise.  The truth is the homography of frame 0's square region into each"
      " frame at the exposure's midpoint.  A frame is *trackable* where at least half the region"
      " is inside the frame and not occluded and its centre moves at most 8 px during the"
      " exposure.  Methods: `jaxpso.track` with `TrackConfig(similarity=\"mi\")` / `\"ncc\"`;"
      " OpenCV ECC chained frame to frame from the frame-0 template (benchmarks/video.py's"
      " `track_ecc`); SIFT keypoints of frame 0's region matched in every whole frame (ratio"
      " 0.75), `cv2.findHomography` RANSAC 5 px from ≥ 8 matches with ≥ 8 inliers, else the"
      " previous estimate (the frame counted lost).  Error = RMS of the 4 corner errors;"
      " P@N = % of frames 1..T−1 within N px.  ms/frame = one method call on the whole sequence"
      " ÷ (T − 1), jaxpso after a warm-up call on the first 3 frames; a shared machine, methods"
      " run one after another per sequence.  Script: benchmarks/challenges.py.", "",
      "## P@5 (%) per category", "",
      "| P@5 % | " + " | ".join(categories) + " | mean | pooled |",
      "|---|" + "---:|" * (len(categories) + 2)]
  for method in methods:
    cells = [summary[(method, c)]["p_at_5"] for c in categories]
    lines.append(f"| {method} | " + " | ".join(f"{v:.1f}" for v in cells)
                 + f" | {np.mean(cells):.1f} | {summary[(method, None)]['p_at_5']:.1f} |")
  lines += ["", "## P@5 (%) on trackable frames only", "",
            "| P@5 % (trackable) | " + " | ".join(categories) + " | pooled |",
            "|---|" + "---:|" * (len(categories) + 1)]
  for method in methods:
    lines.append(f"| {method} | " + " | ".join(_pct(summary[(method, c)]["p_at_5_trackable"])
                                              for c in categories)
                 + f" | {_pct(summary[(method, None)]['p_at_5_trackable'])} |")
  lines += ["", "## Sequences", "",
            "| category | seed | poster / wall / occluder | region (x, y, w, h) | trackable frames"
            " | visible < 0.5 | blur > 8 px | min visible | max blur (px) |",
            "|---|---:|---|---|---:|---:|---:|---:|---:|"]
  for s in sequences:
    visible, blur = np.array(s["visible"]), np.array(s["blur_px"])
    lines.append(f"| {s['category']} | {s['seed']} | {' / '.join(s['images'].values())} |"
                 f" {tuple(s['roi'])} | {int(np.sum(s['trackable'][1:]))}/{len(visible) - 1} |"
                 f" {int(np.sum(visible[1:] < TRACKABLE_VISIBLE))} |"
                 f" {int(np.sum(blur[1:] > TRACKABLE_BLUR_PX))} | {visible.min():.2f} |"
                 f" {blur.max():.1f} |")
  lines += ["", "## Per category and method", "",
            "Tracked > 5 px: frames reported tracked (jaxpso: TRACKED or RECOVERED; ECC: every"
            " frame; SIFT: a homography found) more than 5 px off / frames reported tracked."
            "  Doubtful: jaxpso's DOUBTFUL frames (a re-detection short of the region's best"
            " quality, until confirmed or replaced), more than 5 px off / all.  Re-acquisition:"
            " frames from each return to trackable to the first frame within 5 px, max / mean"
            " (transitions; ≥: not re-acquired by the end, counted to it).  First loss: first frame"
            " more than 20 px off (– never).", "",
            "| category | method | P@5 | P@10 | P@20 | P@5 trackable | first loss | tracked > 5 px"
            " | doubtful > 5 px | re-acquisition max / mean | ms/frame | warm-up s |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
  for category in list(categories) + [None]:
    for method in methods:
      row = summary[(method, category)]
      warm = f"{max(row['warmup_s']):.1f}" if row["warmup_s"] else "–"
      lines.append(f"| {category or '**all**'} | {method} | {row['p_at_5']:.1f} |"
                   f" {row['p_at_10']:.1f} | {row['p_at_20']:.1f} | {_pct(row['p_at_5_trackable'])} |"
                   f" {_fmt_loss(row['first_loss'])} | {row['tracked_but_off']}/{row['tracked']} |"
                   f" {row['doubtful_but_off']}/{row['doubtful']} |"
                   f" {_fmt_reacq(row['reacquisitions'])} | {row['ms_per_frame']:.1f} | {warm} |")
  return "\n".join(lines) + "\n"


def _rounded(values) -> list:
  return [None if not np.isfinite(v) else round(float(v), 3) for v in np.asarray(values, float)]


def main():
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--frames", type=int, default=150)
  parser.add_argument("--seeds", default="0", help="comma list, e.g. 0,1")
  parser.add_argument("--categories", default=",".join(CATEGORIES))
  parser.add_argument("--methods", default=",".join(METHODS))
  parser.add_argument("--name", default="challenges", help="results/NAME.json and .md")
  parser.add_argument("--check", action="store_true",
                      help="print the truth's residual per category (sharp, noise-free renderings);"
                      " no tracking")
  parser.add_argument("--save-frames", default=None, help="folder for a few PNG frames per sequence")
  args = parser.parse_args()
  seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
  categories = [c.strip() for c in args.categories.split(",") if c.strip()]
  methods = [m.strip() for m in args.methods.split(",") if m.strip()]
  for c in categories:
    if c not in CATEGORIES:
      parser.error(f"unknown category {c!r}; one of {', '.join(CATEGORIES)}")
  for m in methods:
    if m not in METHODS:
      parser.error(f"unknown method {m!r}; one of {', '.join(METHODS)}")

  if args.check:
    for category in categories:
      for seed in seeds:
        seq = render(category, args.frames, seed, noise=False, sharp=True)
        print(category, seed, {k: round(v, 3) for k, v in truth_residual(seq).items()}, flush=True)
    return

  rows, sequences, runs = {}, [], []
  for category in categories:
    for seed in seeds:
      start = time.perf_counter()
      seq = render(category, args.frames, seed)
      print(f"{category} seed {seed}: rendered in {time.perf_counter() - start:.1f} s,"
            f" roi {seq.roi}, trackable {int(seq.trackable[1:].sum())}/{args.frames - 1}",
            flush=True)
      if args.save_frames:
        save_frames(seq, args.save_frames)
      sequences.append({"category": category, "seed": seed, "roi": list(seq.roi),
                        "images": seq.images, "visible": _rounded(seq.visible),
                        "blur_px": _rounded(seq.blur_px), "trackable": seq.trackable.tolist()})
      for method in methods:
        out = run_method(method, seq)
        errors = jaxpso.io.corner_errors(out["corners"], seq.corners)
        row = frame_metrics(errors, out["status"], seq.trackable)
        row.update(seconds=out["seconds"], warmup_s=out["warmup_s"])
        rows.setdefault((method, category), []).append(row)
        runs.append({"category": category, "seed": seed, "method": method,
                     "seconds": out["seconds"], "warmup_s": out["warmup_s"],
                     "errors": _rounded(errors), "status": out["status"].astype(int).tolist()})
        print(f"  {method}: P@5 {100 * row['within_5'] / max(row['frames'], 1):.1f} %,"
              f" {1e3 * out['seconds'] / max(args.frames - 1, 1):.1f} ms/frame"
              + (f", warm-up {out['warmup_s']:.1f} s" if out["warmup_s"] is not None else ""),
              flush=True)
  if not methods:
    return
  summary = {}
  for method in methods:
    for category in categories:
      summary[(method, category)] = pool(rows[(method, category)])
    summary[(method, None)] = pool([r for c in categories for r in rows[(method, c)]])
  info = common.machine()
  payload = {"machine": info, "frames": args.frames, "seeds": seeds, "categories": categories,
             "methods": methods, "sequences": sequences, "runs": runs,
             "summary": [{"method": m, "category": c or "all", **{
                 k: v for k, v in s.items()}} for (m, c), s in summary.items()]}
  common.write(args.name, payload, markdown(summary, sequences, methods, categories, info, args))


if __name__ == "__main__":
  main()
