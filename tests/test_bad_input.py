"""Bad input through the public API: a ValueError/TypeError/FileNotFoundError naming the
argument and the offending value, before anything compiles; the command's one-line error.

Every case is (call, exception, argument, value): the message must match both
the argument's and the value's pattern.  Data-dependent failure (the target
leaving the frame) is a status instead, checked at the end.
"""

import math
import pathlib
import re
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

import jaxpso
from jaxpso import cli
from jaxpso import io
from jaxpso import pso
from jaxpso import similarity
from jaxpso import warp

IMAGE = jaxpso.data.load_image("camera")[128:224, 160:288].copy()  # (96, 128) texture
TEMPLATE = IMAGE[32:64, 48:80].copy()  # 32×32, truly at (48, 32)
START = np.array([[1, 0, 48], [0, 1, 32], [0, 0, 1]], np.float32)
CONFIG = jaxpso.TrackConfig(levels=1, swarm_size=8, max_iterations=3, search_radius=4.0)
PLANE = jaxpso.TrackConfig(levels=1, swarm_size=8, max_iterations=3, search_radius=4.0,
                           motion="plane")
FRAMES = np.stack([IMAGE[:48, :64], IMAGE[1:49, 1:65]])  # (2, 48, 64)
ROI = (16, 8, 24, 24)


def _with(array, index, value):
  """A copy of `array` with `value` at `index`."""
  array = np.array(array)
  array[index] = value
  return array


def _names(argument, value) -> str:
  """A regex matching a message that names `argument` and `value` (regexes), in any order."""
  return rf"(?s)(?=.*{argument})(?=.*{value})"


def _raises(call, error, argument, value):
  """`call()` raises `error` whose message names `argument` and `value`."""
  with pytest.raises(error, match=_names(argument, value)):
    call()


def _cases(*cases):
  """pytest params (call, error, argument, value) with the first field as id."""
  return [pytest.param(*case[1:], id=case[0]) for case in cases]


# --- align --------------------------------------------------------------------------------------

_TILTED = np.array([[1, 0, 48], [0, 1, 32], [-0.1, 0, 1]], np.float32)  # w < 0 past x = 10


@pytest.mark.parametrize("call, error, argument, value", _cases(
    ("image-1d", lambda: jaxpso.align(IMAGE[0], TEMPLATE, START), ValueError, "image",
     r"\(128,\)"),
    ("image-4-channels", lambda: jaxpso.align(np.zeros((96, 128, 4), np.float32), TEMPLATE,
                                              START), ValueError, "image", r"\(96, 128, 4\)"),
    ("image-empty", lambda: jaxpso.align(np.zeros((0, 0), np.float32), TEMPLATE, START),
     ValueError, "image", r"\(0, 0\)"),
    ("image-bool", lambda: jaxpso.align(IMAGE > 0.5, TEMPLATE, START), TypeError, "image",
     "bool"),
    ("image-nan", lambda: jaxpso.align(_with(IMAGE, (5, 7), np.nan), TEMPLATE, START),
     ValueError, "image", r"nan at index \(5, 7\)"),
    ("template-int", lambda: jaxpso.align(IMAGE, TEMPLATE.astype(np.int32), START), TypeError,
     "template", "int32"),
    ("template-inf", lambda: jaxpso.align(IMAGE, _with(TEMPLATE, (0, 0), np.inf), START),
     ValueError, "template", "inf"),
    ("template-textureless", lambda: jaxpso.align(IMAGE, np.full((32, 32), 0.5, np.float32),
                                                  START), ValueError, "template",
     r"textureless \(intensity std 0"),
    ("template-nearly-flat", lambda: jaxpso.align(IMAGE, 0.5 + 0.008 * np.sign(TEMPLATE - 0.5),
                                                  START), ValueError, "template",
     r"textureless \(intensity std 0\.00\d+ < 0\.01"),
    ("template-too-small", lambda: jaxpso.align(IMAGE, TEMPLATE[:16, :16], START,
                                                config=jaxpso.TrackConfig(levels=4)),
     ValueError, "template", r"\(16, 16\).*levels=4"),
    ("template-below-range", lambda: jaxpso.align(IMAGE, TEMPLATE[:6, :30], START), ValueError,
     "template", r"\(6, 30\) is outside the supported sizes: every side must be 8 to 4096"),
    ("resolution-above-template", lambda: jaxpso.align(
        IMAGE, TEMPLATE[:16, :16], START, config=jaxpso.TrackConfig(resolution=300)),
     ValueError, "resolution", r"300 .*template of shape \(16, 16\) \(256 pixels\)"),
    ("homography-2x2", lambda: jaxpso.align(IMAGE, TEMPLATE, np.eye(2)), ValueError,
     "init_homography", r"\(2, 2\)"),
    ("homography-text", lambda: jaxpso.align(IMAGE, TEMPLATE, np.full((3, 3), "1")), ValueError,
     "init_homography", "<U1"),
    ("homography-singular", lambda: jaxpso.align(IMAGE, TEMPLATE, np.zeros((3, 3))), ValueError,
     "init_homography", r"\[\[0\.0, 0\.0, 0\.0\]"),
    ("homography-nan", lambda: jaxpso.align(IMAGE, TEMPLATE, _with(START, (0, 2), np.nan)),
     ValueError, "init_homography", "nan"),
    ("homography-w-negative", lambda: jaxpso.align(IMAGE, TEMPLATE, _TILTED), ValueError,
     "init_homography", r"w = \[1\.0, -2\.1"),
    ("config-dict", lambda: jaxpso.align(IMAGE, TEMPLATE, START, config={"levels": 1}),
     TypeError, "config", "dict"),
    ("key-float", lambda: jaxpso.align(IMAGE, TEMPLATE, START, config=CONFIG, key=0.5),
     TypeError, "key", r"float32\(\)"),
))
def test_align(call, error, argument, value):
  _raises(call, error, argument, value)


# --- TrackConfig and PSOConfig --------------------------------------------------------------------


@pytest.mark.parametrize("fields, error, argument, value", _cases(
    ("similarity", dict(similarity="sad"), ValueError, "similarity", "'sad'"),
    ("motion", dict(motion="affine"), ValueError, "motion", "'affine'"),
    ("method", dict(method="newton"), ValueError, "method", "'newton'"),
    ("variant", dict(variant="adam"), ValueError, "variant", "'adam'"),
    ("topology", dict(topology="star"), ValueError, "topology", "'star'"),
    ("dof", dict(motion="plane", dof=3), ValueError, "dof", "3"),
    ("dof-bool", dict(motion="plane", dof=True), ValueError, "dof", "True"),
    ("bins-1", dict(bins=1), ValueError, "bins", "1"),
    ("bins-3", dict(bins=3), ValueError, "bins", "3"),
    ("levels-0", dict(levels=0), ValueError, "levels", "0"),
    ("levels-float", dict(levels=2.5), ValueError, "levels", "2.5"),
    ("swarm-0", dict(swarm_size=0), ValueError, "swarm_size", "0"),
    ("swarm-1", dict(swarm_size=1), ValueError, "swarm_size", "1"),
    ("iterations-0", dict(max_iterations=0), ValueError, "max_iterations", "0"),
    ("patience-0", dict(patience=0), ValueError, "patience", "0"),
    ("refine-steps", dict(refine_steps=-1), ValueError, "refine_steps", "-1"),
    ("retries", dict(retries=-1), ValueError, "retries", "-1"),
    ("quick-iterations", dict(quick_iterations=-1), ValueError, "quick_iterations", "-1"),
    ("quick-iterations-float", dict(quick_iterations=8.0), ValueError, "quick_iterations", "8.0"),
    ("radius-0", dict(search_radius=0.0), ValueError, "search_radius", "0.0"),
    ("radius-inf", dict(search_radius=math.inf), ValueError, "search_radius", "inf"),
    ("radius-none", dict(search_radius=None), TypeError, "search_radius", "None"),
    ("pixels", dict(pixels=1.5), ValueError, "pixels", "1.5"),
    ("resolution-below-8x8", dict(resolution=63), ValueError, "resolution", ">= 64, got 63"),
    ("resolution-float", dict(resolution=2560.0), ValueError, "resolution", "2560.0"),
    ("pixels-text", dict(pixels="all"), TypeError, "pixels", "'all'"),
    ("min-valid", dict(min_valid=0.0), ValueError, "min_valid", "0.0"),
    ("lost-quality", dict(lost_quality=2.0), ValueError, "lost_quality", "2.0"),
    ("retry-quality-nan", dict(retry_quality=math.nan), ValueError, "retry_quality", "nan"),
    ("hopeless-quality", dict(hopeless_quality=1.5), ValueError, "hopeless_quality", "1.5"),
    ("hopeless-quality-nan", dict(hopeless_quality=math.nan), ValueError, "hopeless_quality",
     "nan"),
    ("hopeless-quality-text", dict(hopeless_quality="low"), TypeError, "hopeless_quality",
     "'low'"),
    ("accept-quality", dict(accept_quality=1.5), ValueError, "accept_quality", "1.5"),
    ("predict", dict(predict="yes"), TypeError, "predict", "'yes'"),
    ("recovery", dict(recovery_scale=0), ValueError, "recovery_scale", "0"),
    ("retry-scale", dict(retry_scale=0), ValueError, "retry_scale", "0"),
    ("retry-scale-float", dict(retry_scale=1.5), ValueError, "retry_scale", "1.5"),
    ("budget-0", dict(max_evaluations=0), ValueError, "max_evaluations", "0"),
    ("budget-negative", dict(max_evaluations=-100), ValueError, "max_evaluations", "-100"),
    ("budget-float", dict(max_evaluations=5000.0), ValueError, "max_evaluations", "5000.0"),
    ("budget-bool", dict(max_evaluations=True), ValueError, "max_evaluations", "True"),
    ("budget-huge", dict(max_evaluations=2**31), ValueError, "max_evaluations", "2147483648"),
    ("coast", dict(coast=1), TypeError, "coast", "1"),
))
def test_track_config(fields, error, argument, value):
  _raises(lambda: jaxpso.TrackConfig(**fields), error, argument, value)


@pytest.mark.parametrize("fields, error, argument, value", _cases(
    ("swarm-0", dict(swarm_size=0), ValueError, "swarm_size", "0"),
    ("swarm-1", dict(swarm_size=1), ValueError, "swarm_size", "1"),
    ("variant", dict(variant="adam"), ValueError, "variant", "'adam'"),
    ("topology", dict(topology="star"), ValueError, "topology", "'star'"),
    ("boundary", dict(boundary="wrap"), ValueError, "boundary", "'wrap'"),
    ("rng", dict(rng="philox"), ValueError, "rng", "'philox'"),
    ("neighbours-odd", dict(neighbours=3), ValueError, "neighbours", "3"),
    ("informants-0", dict(informants=0), ValueError, "informants", "0"),
    ("iterations-0", dict(max_iterations=0), ValueError, "max_iterations", "0"),
    ("patience-0", dict(patience=0), ValueError, "patience", "0"),
    ("tolerance-negative", dict(tolerance=-1e-3), ValueError, "tolerance", "-0.001"),
    ("tolerance-nan", dict(tolerance=math.nan), ValueError, "tolerance", "nan"),
    ("target-nan", dict(target_loss=math.nan), ValueError, "target_loss", "nan"),
    ("target-text", dict(target_loss="low"), TypeError, "target_loss", "'low'"),
    ("stop-weights-2", dict(stop_weights=(0.5, 0.5)), ValueError, "stop_weights",
     r"\(0\.5, 0\.5\)"),
    ("stop-weights-negative", dict(stop_weights=(-1.0, 0.0, 0.0)), ValueError, "stop_weights",
     r"\(-1\.0, 0\.0, 0\.0\)"),
    ("grid-step-0", dict(grid_step=0.0), ValueError, "grid_step", "0.0"),
    ("batched-text", dict(batched="yes"), TypeError, "batched", "'yes'"),
))
def test_pso_config(fields, error, argument, value):
  _raises(lambda: pso.PSOConfig(**fields), error, argument, value)


# --- pso.run / pso.trace / pso.init ---------------------------------------------------------------


def _sphere(x, args):
  del args
  return jnp.sum(x * x)


def _vector(x, args):
  del args
  return x


_SMALL = pso.PSOConfig(swarm_size=4, max_iterations=2)
_LO, _HI = np.zeros(2, np.float32), np.ones(2, np.float32)


@pytest.mark.parametrize("kwargs, error, argument, value", _cases(
    ("lower-equals-upper", dict(upper=np.float32([1, 0])), ValueError, "lower.*upper",
     r"dimension 1 has lower=0\.0, upper=0\.0"),
    ("lower-above-upper", dict(lower=np.float32([2, 0])), ValueError, "lower.*upper",
     r"lower=2\.0, upper=1\.0"),
    ("upper-inf", dict(upper=np.float32([1, np.inf])), ValueError, "upper", "upper=inf"),
    ("lower-int", dict(lower=np.zeros(2, np.int32)), TypeError, "lower", "int32"),
    ("lower-empty", dict(lower=np.zeros(0, np.float32), upper=np.ones(0, np.float32)),
     ValueError, "lower", r"\(0,\)"),
    ("bounds-2d", dict(lower=np.zeros((2, 2), np.float32), upper=np.ones((2, 2), np.float32)),
     ValueError, "lower and upper", r"\(2, 2\)"),
    ("bounds-differ", dict(upper=np.ones(3, np.float32)), ValueError, "lower and upper",
     r"\(2,\) and \(3,\)"),
    # run and trace check the key inside jit, where only its dtype and shape are known.
    ("key-float", dict(key=0.5), TypeError, "key", r"float32\(\)"),
    ("key-text", dict(key="seed"), TypeError, "key", "'seed'|<class 'str'>"),
    ("key-shape", dict(key=np.zeros(3, np.uint32)), TypeError, "key", r"uint32\(3,\)"),
    ("loss-not-callable", dict(loss_fn="sphere"), TypeError, "loss_fn", "str"),
    ("loss-vector", dict(loss_fn=_vector), ValueError, "loss_fn", r"\(2,\)"),
    ("config-dict", dict(config={"swarm_size": 4}), TypeError, "config", "dict"),
    ("grid-step-length", dict(config=pso.PSOConfig(swarm_size=4, grid_step=(0.1, 0.1, 0.1))),
     ValueError, "grid_step", "3 entries for 2 dimensions"),
    ("positions-shape", dict(positions=np.zeros((5, 2), np.float32)), ValueError, "positions",
     r"\(5, 2\)"),
    ("positions-nan", dict(positions=np.full((4, 2), np.nan, np.float32)), ValueError,
     "positions", "nan"),
    ("velocities-shape", dict(velocities=np.zeros((4, 3), np.float32)), ValueError,
     "velocities", r"\(4, 3\)"),
    ("centre-alone", dict(centre=np.zeros(2, np.float32)), ValueError, "centre and scale",
     "scale=None"),
    ("centre-shape", dict(centre=np.zeros(3, np.float32), scale=1.0), ValueError, "centre",
     r"\(3,\)"),
    ("scale-negative", dict(centre=np.zeros(2, np.float32), scale=-1.0), ValueError, "scale",
     "-1"),
    ("scale-nan", dict(centre=np.zeros(2, np.float32), scale=np.nan), ValueError, "scale",
     "nan"),
    ("centre-outside", dict(centre=np.float32([0.0, 9.0]), scale=1.0), ValueError, "centre",
     "inside the box"),
))
@pytest.mark.parametrize("function", [pso.run, pso.trace, pso.init])
def test_pso(function, kwargs, error, argument, value):
  kwargs = dict(dict(key=0, loss_fn=_sphere, lower=_LO, upper=_HI, config=_SMALL), **kwargs)
  args = [kwargs.pop(name) for name in ("key", "loss_fn", "lower", "upper")]
  _raises(lambda: function(*args, None, **kwargs), error, argument, value)


@pytest.mark.parametrize("hparams, error, argument, value", _cases(
    ("tuple", (0.7,) * 6, TypeError, "hparams", "tuple"),
    ("c1-nan", pso.default_hparams()._replace(c1=np.float32(np.nan)), ValueError, r"hparams\.c1",
     "nan"),
    ("clamp-0", pso.default_hparams()._replace(velocity_clamp=0.0), ValueError,
     r"hparams\.velocity_clamp", "0"),
))
@pytest.mark.parametrize("function", [pso.run, pso.trace])
def test_pso_hparams(function, hparams, error, argument, value):
  _raises(lambda: function(0, _sphere, _LO, _HI, config=_SMALL, hparams=hparams), error,
          argument, value)


# --- jaxpso.similarity --------------------------------------------------------------------------

_A = np.asarray(IMAGE[:8, :10])
_MEASURES = [similarity.ssd, similarity.ncc, similarity.mi, similarity.nmi]


@pytest.mark.parametrize("args, kwargs, error, argument, value", _cases(
    ("a-int", (_A.astype(np.int32), _A), {}, TypeError, "a", "int32"),
    ("b-1d", (_A, _A[0]), {}, ValueError, "b", r"\(10,\)"),
    ("a-empty", (_A[:0], _A[:0]), {}, ValueError, "b", r"\(0, 10\)"),
    ("a-text", ("flat", _A), {}, TypeError, "a", "'flat'"),
    ("windows-differ", (_A, _A[:, :9]), {}, ValueError, "a and b", r"\(8, 10\) and \(8, 9\)"),
    ("a-nan", (_with(_A, (2, 3), np.nan), _A), {}, ValueError, "a", r"nan at index \(2, 3\)"),
    ("b-inf", (_A, _with(_A, (0, 1), -np.inf)), {}, ValueError, "b", "-inf"),
    ("mask-int", (_A, _A, np.ones((8, 10), np.int32)), {}, TypeError, "mask", "int32"),
    ("mask-shape", (_A, _A, np.ones((8, 9), bool)), {}, ValueError, "mask", r"\(8, 9\)"),
    ("mask-nan", (_A, _A, _with(np.ones((8, 10), np.float32), (1, 1), np.nan)), {}, ValueError,
     "mask", "nan"),
    ("min-valid-0", (_A, _A), dict(min_valid=0.0), ValueError, "min_valid", "0.0"),
    ("min-valid-text", (_A, _A), dict(min_valid="half"), ValueError, "min_valid", "'half'"),
))
@pytest.mark.parametrize("measure", _MEASURES, ids=lambda f: f.__name__)
def test_similarity(measure, args, kwargs, error, argument, value):
  _raises(lambda: measure(*args, **kwargs), error, rf"\b{argument}\b", value)


@pytest.mark.parametrize("kwargs, argument, value", _cases(
    ("bins-1", dict(bins=1), "bins", "1"),
    ("bins-3", dict(bins=3), "bins", "3"),
    ("bins-float", dict(bins=8.5), "bins", "8.5"),
    ("range-reversed", dict(value_range=(1.0, 0.0)), "value_range", r"\(1\.0, 0\.0\)"),
    ("range-nan", dict(value_range=(0.0, math.nan)), "value_range", "nan"),
    ("range-3", dict(value_range=(0.0, 0.5, 1.0)), "value_range", r"\(0\.0, 0\.5, 1\.0\)"),
))
@pytest.mark.parametrize("function", [similarity.mi, similarity.nmi, similarity.joint_histogram,
                                      similarity.entropy, similarity.soft_bins],
                         ids=lambda f: f.__name__)
def test_histogram_options(function, kwargs, argument, value):
  args = (_A,) if function in (similarity.entropy, similarity.soft_bins) else (_A, _A)
  _raises(lambda: function(*args, **kwargs), ValueError, argument, value)


# --- jaxpso.warp --------------------------------------------------------------------------------

_EYE = np.eye(3, dtype=np.float32)
_NORMAL = np.float32([0, 0, 1])
_K = np.asarray(warp.default_camera((48, 64)))


@pytest.mark.parametrize("call, error, argument, value", _cases(
    ("warp-image-nan", lambda: warp.warp_image(_with(_A, (1, 2), np.nan), _EYE, (4, 4)),
     ValueError, "image", r"nan at index \(1, 2\)"),
    ("warp-image-3d", lambda: warp.warp_image(np.zeros((4, 4, 3), np.float32), _EYE, (4, 4)),
     ValueError, "image", r"\(4, 4, 3\)"),
    ("warp-image-int", lambda: warp.warp_image(_A.astype(np.int32), _EYE, (4, 4)), TypeError,
     "image", "int32"),
    ("warp-image-1-row", lambda: warp.warp_image(_A[:1], _EYE, (4, 4)), ValueError, "image",
     r"\(1, 10\)"),
    ("warp-image-shape", lambda: warp.warp_image(_A, _EYE, (0, 4)), ValueError, "shape",
     r"\(0, 4\)"),
    ("warp-image-h-inf", lambda: warp.warp_image(_A, _with(_EYE, (2, 0), np.inf), (4, 4)),
     ValueError, "homographies", "inf"),
    ("warp-image-h-2x2", lambda: warp.warp_image(_A, np.eye(2, dtype=np.float32), (4, 4)),
     ValueError, "homographies", r"\(2, 2\)"),
    ("warp-points-frame", lambda: warp.warp_points(_EYE, np.zeros((3, 2), np.float32), (0, 4)),
     ValueError, "frame_shape", r"\(0, 4\)"),
    ("pyr-down-nan", lambda: warp.pyr_down(_with(_A, (0, 0), np.nan)), ValueError, "image",
     "nan"),
    ("pyramid-levels-0", lambda: warp.gaussian_pyramid(_A, 0), ValueError, "levels", "0"),
    ("pyramid-levels-many", lambda: warp.gaussian_pyramid(_A, 5), ValueError, "levels", "5"),
    ("inverse-int", lambda: warp.inverse(np.eye(3, dtype=np.int32)), TypeError, "h", "int32"),
    ("inverse-nan", lambda: warp.inverse(_with(_EYE, (1, 1), np.nan)), ValueError, "h", "nan"),
    ("compose-shape", lambda: warp.compose(_EYE, np.ones((3, 4), np.float32)), ValueError, "b",
     r"\(3, 4\)"),
    ("normalize-empty", lambda: warp.normalize(np.zeros((0, 3, 3), np.float32)), ValueError,
     "h", r"\(0, 3, 3\)"),
    ("points-nan", lambda: warp.apply_to_points(_EYE, np.full((4, 2), np.nan, np.float32)),
     ValueError, "points", "nan"),
    ("points-shape", lambda: warp.apply_to_points(_EYE, np.ones((4, 3), np.float32)),
     ValueError, "points", r"\(4, 3\)"),
    ("corners-3", lambda: warp.homography_from_corners(np.ones((3, 2), np.float32),
                                                       np.ones((4, 2), np.float32)),
     ValueError, "src", r"\(3, 2\)"),
    ("offsets-7", lambda: warp.corner_offsets_to_homography(np.zeros(7, np.float32), (4, 4)),
     ValueError, "x", r"\(7,\)"),
    ("offsets-shape", lambda: warp.corner_offsets_to_homography(np.zeros(8, np.float32), (1, 4)),
     ValueError, "shape", r"\(1, 4\)"),
    ("to-offsets-shape", lambda: warp.homography_to_corner_offsets(_EYE, (0, 4)), ValueError,
     "shape", r"\(0, 4\)"),
    ("level-float", lambda: warp.homography_to_level(_EYE, 1.5), TypeError, "level", "1.5"),
    ("translation-text", lambda: warp.translation("one", 1.0), TypeError, "tx", "'one'"),
    ("scaling-nan", lambda: warp.scaling(np.float32(np.nan)), ValueError, r"\bs\b", "nan"),
    ("rect-corners-0", lambda: warp.rect_corners((0, 5)), ValueError, "shape", r"\(0, 5\)"),
    ("rect-corners-3", lambda: warp.rect_corners((1, 2, 3)), ValueError, "shape",
     r"\(1, 2, 3\)"),
    ("grid-negative", lambda: warp.template_grid((-1, 3)), ValueError, "shape", r"\(-1, 3\)"),
    ("expand-dof-3", lambda: warp.expand_dof(np.zeros(3, np.float32), 3), ValueError, "dof",
     "3"),
    ("focal-0", lambda: warp.camera_matrix(np.float32(0), np.float32(1), np.float32(1)),
     ValueError, "focal", "0"),
    ("focal-nan", lambda: warp.camera_matrix(np.float32(np.nan), np.float32(1), np.float32(1)),
     ValueError, "focal", "nan"),
    ("plane-camera-singular", lambda: warp.plane_homography(np.eye(4, dtype=np.float32),
                                                            np.zeros((3, 3), np.float32),
                                                            _NORMAL),
     ValueError, "camera", r"\[\[0\.0, 0\.0, 0\.0\]"),
    ("plane-normal-0", lambda: warp.plane_homography(np.eye(4, dtype=np.float32), _K,
                                                     np.zeros(3, np.float32)),
     ValueError, "normal", r"0\., 0\., 0\."),
    ("plane-distance-0", lambda: warp.plane_homography(np.eye(4, dtype=np.float32), _K, _NORMAL,
                                                       0.0),
     ValueError, "distance", "0"),
    ("plane-pose-3x3", lambda: warp.plane_homography(_EYE, _K, _NORMAL), ValueError, "pose",
     r"\(3, 3\)"),
    ("pose-from-h-camera", lambda: warp.pose_from_homography(_EYE, np.diag(np.float32([1, 1, 0])),
                                                             _NORMAL),
     ValueError, "camera", r"\[\[1\.0, 0\.0, 0\.0\]"),
    ("invert-pose-nan", lambda: warp.invert_pose(np.full((4, 4), np.nan, np.float32)),
     ValueError, "pose", "nan"),
    ("rodrigues-2", lambda: warp.rodrigues(np.zeros(2, np.float32)), ValueError, "omega",
     r"\(2,\)"),
))
def test_warp(call, error, argument, value):
  _raises(call, error, argument, value)


# --- track --------------------------------------------------------------------------------------


def _track(frames=FRAMES, roi=ROI, **kwargs):
  return lambda: jaxpso.track(frames, roi, **dict(dict(config=CONFIG), **kwargs))


def _corners(roi):
  x, y, w, h = roi
  return np.float32([[x, y], [x + w - 1, y], [x + w - 1, y + h - 1], [x, y + h - 1]])


@pytest.mark.parametrize("call, error, argument, value", _cases(
    ("no-frames", _track(frames=[]), ValueError, "frames", "none"),
    ("zero-frames-array", _track(frames=FRAMES[:0]), ValueError, "frames", "none"),
    ("one-2d-frame", _track(frames=FRAMES[0]), ValueError, "frames", r"\(48, 64\)"),
    ("5d-array", _track(frames=FRAMES[None, ..., None]), ValueError, "frames",
     r"\(1, 2, 48, 64, 1\)"),
    ("not-iterable", _track(frames=5), TypeError, "frames", "int"),
    ("sizes-differ", _track(frames=[FRAMES[0], FRAMES[1][:-1]]), ValueError, r"frames\[1\]",
     r"\(47, 64\)"),
    ("nan-frame-1", _track(frames=_with(FRAMES, (1, 3, 4), np.nan)), ValueError, r"frames\[1\]",
     r"nan at index \(3, 4\)"),
    ("inf-frame-0", _track(frames=_with(FRAMES, (0, 0, 0), np.inf)), ValueError, r"frames\[0\]",
     "inf"),
    ("int-frames", _track(frames=FRAMES.astype(np.int32)), TypeError, r"frames\[0\]", "int32"),
    ("4-channels", _track(frames=np.zeros((2, 48, 64, 4), np.float32)), ValueError,
     r"frames\[0\]", r"\(48, 64, 4\)"),
    ("roi-empty", _track(roi=(16, 8, 0, 24)), ValueError, "roi", r"\(16, 8, 0, 24\)"),
    ("roi-negative-size", _track(roi=(16, 8, 24, -24)), ValueError, "roi",
     r"\(16, 8, 24, -24\)"),
    ("roi-fractional", _track(roi=(16, 8, 23.5, 24)), ValueError, "roi", r"23\.5"),
    ("roi-partly-outside", _track(roi=(50, 8, 24, 24)), ValueError, "roi",
     r"\(50, 8, 24, 24\).*\(48, 64\)"),
    ("roi-wholly-outside", _track(roi=(100, 80, 24, 24)), ValueError, "roi",
     r"\(100, 80, 24, 24\)"),
    ("roi-negative-origin", _track(roi=(-1, 8, 24, 24)), ValueError, "roi", r"\(-1, 8, 24, 24\)"),
    ("roi-3-numbers", _track(roi=(16, 8, 24)), ValueError, "roi", r"\(16, 8, 24\)"),
    ("roi-nan", _track(roi=(np.nan, 8, 24, 24)), ValueError, "roi", "nan"),
    ("roi-text", _track(roi="16,8,24,24"), ValueError, "roi", "'16,8,24,24'"),
    ("roi-mirrored", _track(roi=_corners(ROI)[::-1]), ValueError, "roi", r"39\., 31\."),
    ("roi-too-small", _track(config=jaxpso.TrackConfig(levels=4)), ValueError, "roi",
     r"\(24, 24\).*levels=4"),
    ("resolution-above-roi", _track(config=jaxpso.TrackConfig(resolution=600)), ValueError,
     "resolution", r"600 .*roi of shape \(24, 24\) \(576 pixels\)"),
    ("roi-textureless", _track(frames=np.full((2, 48, 64), 0.5, np.float32)), ValueError, "roi",
     r"\(16, 8, 24, 24\).*textureless"),
    ("config-dict", _track(config={"levels": 1}), TypeError, "config", "dict"),
    ("key-text", _track(key="seed"), TypeError, "key", "'seed'"),
    ("camera-singular", _track(config=PLANE, camera=np.zeros((3, 3))), ValueError, "camera",
     r"0\., 0\., 0\."),
    ("normal-away", _track(config=PLANE, plane_normal=(0.0, 0.0, -1.0)), ValueError,
     "plane_normal", r"-1\.0"),
    ("camera-for-homography", _track(camera=np.eye(3)), ValueError, "camera", "'homography'"),
))
def test_track(call, error, argument, value):
  _raises(call, error, argument, value)


def test_one_frame_is_a_one_frame_result():
  result = jaxpso.track(FRAMES[:1], ROI, config=CONFIG)
  for field, value in result._asdict().items():
    if value is not None:
      assert len(value) == 1 and not np.isnan(value).any(), field
  np.testing.assert_allclose(result.corners[0], _corners(ROI), atol=1e-4)
  assert result.status[0] == jaxpso.TrackStatus.TRACKED


# --- the command --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
  """A tiny video, an undecodable video, a folder with an undecodable image, an empty folder."""
  root = tmp_path_factory.mktemp("sources")
  io.write_video(root / "tiny.avi", FRAMES)
  (root / "junk.mp4").write_bytes(b"not a video")
  (root / "broken").mkdir()
  (root / "broken" / "frame0.png").write_bytes(b"\x89PNG truncated")
  (root / "empty").mkdir()
  (root / "file").write_text("not a folder")
  return root


@pytest.mark.parametrize("argv, argument, value", _cases(
    ("missing-video", ["track", "{root}/missing.avi", "--roi", "1,2,3,4", "--out", "{out}"],
     "video file or image folder", "missing.avi"),
    ("undecodable-video", ["track", "{root}/junk.mp4", "--roi", "1,2,3,4", "--out", "{out}"],
     "video", "junk.mp4"),
    ("undecodable-image", ["track", "{root}/broken", "--roi", "1,2,3,4", "--out", "{out}"],
     "image", "frame0.png"),
    ("empty-folder", ["track", "{root}/empty", "--roi", "1,2,3,4", "--out", "{out}"], "folder",
     "empty"),
    ("roi-3-numbers", ["track", "{root}/tiny.avi", "--roi", "1,2,3", "--out", "{out}"], "--roi",
     "'1,2,3'"),
    ("roi-empty", ["track", "{root}/tiny.avi", "--roi", "1,2,0,5", "--out", "{out}"], "--roi",
     "'1,2,0,5'"),
    ("roi-outside", ["track", "{root}/tiny.avi", "--roi=50,8,24,24", "--out", "{out}", "--levels",
                     "1"], "roi", r"\(50, 8, 24, 24\)"),
    ("roi-missing", ["track", "{root}/tiny.avi", "--out", "{out}"], "--roi", "required"),
    ("out-is-a-file", ["track", "{root}/tiny.avi", "--roi", "16,8,24,24", "--out", "{root}/file"],
     "--out", "file"),
    ("max-frames-0", ["track", "{root}/tiny.avi", "--roi", "1,2,3,4", "--out", "{out}",
                      "--max-frames", "0"], "--max-frames", "0"),
    ("radius-inf", ["demo", "--out", "{out}", "--search-radius", "inf"], "search_radius", "inf"),
    ("swarm-1", ["demo", "--out", "{out}", "--swarm-size", "1"], "swarm_size", "1"),
    ("swarm-text", ["demo", "--out", "{out}", "--swarm-size", "many"], "--swarm-size", "'many'"),
    ("similarity", ["demo", "--out", "{out}", "--similarity", "sad"], "--similarity", "'sad'"),
    ("frames-1", ["demo", "--out", "{out}", "--frames", "1"], "--frames", "1"),
    ("command", ["bogus"], "command", "'bogus'"),
))
def test_command_is_one_line_and_exit_1(sources, tmp_path, capsys, argv, argument, value):
  argv = [a.format(root=sources, out=tmp_path / "out") for a in argv]
  assert cli.main(argv) == 1
  err = capsys.readouterr().err.splitlines()
  assert len(err) == 1 and err[0].startswith("jaxpso: error: "), err
  assert re.search(_names(argument, value), err[0]), err[0]


@pytest.mark.parametrize("argv", [
    ["track", "{root}/junk.mp4", "--roi", "1,2,3,4", "--out", "{out}"],  # FFmpeg logs on its own
    ["track", "{root}/tiny.avi", "--roi", "1,2,3,4", "--out", "{out}", "--levels", "0"],
])
def test_python_m_jaxpso_prints_one_line_without_traceback(sources, tmp_path, argv):
  argv = [a.format(root=sources, out=tmp_path / "out") for a in argv]
  done = subprocess.run([sys.executable, "-m", "jaxpso", *argv], capture_output=True, text=True,
                        cwd=pathlib.Path(__file__).resolve().parents[1], timeout=120)
  assert done.returncode == 1
  assert done.stderr.startswith("jaxpso: error: ") and done.stderr.count("\n") == 1, done.stderr
  assert "Traceback" not in done.stderr + done.stdout
