"""The `jaxpso` command.

  jaxpso demo [--out DIR] [--frames N] [--seed S] [tracker options]
  jaxpso track VIDEO_OR_FOLDER --roi x,y,w,h --out DIR [--max-frames N] [tracker options]
  jaxpso evaluate DATASET --format pot|planartrack|ucsb|tmt|plain --methods M,M,... --out DIR

demo renders a synthetic sequence of the embedded image on a plane seen by a
moving camera (two sudden jumps, gain drift 0.1, noise 0.01), tracks its
central 100×100 region with `jaxpso.track` and prints the error against the
exact truth.  track tracks the region x,y,w,h of frame 0 through a video file
or a folder of images.  Both write to DIR:
  overlay.mp4  the frames with the tracked region (green: tracked, orange:
               recovered, red: lost; demo: the truth in blue); overlay.avi
               where this OpenCV cannot write MP4
  errors.png   (demo) corner error per frame and the centre's trajectory
  scores.png   (track) score per frame and the centre's trajectory
  results.csv  one row per frame: status, score, quality, corners, error,
               iterations, evaluations
  results.json the same, with a summary
evaluate runs methods (pso, pso:ncc, ic, ecc, sift, ...: `jaxpso.datasets.method`) over a
dataset in a published layout and writes the benchmark toolkit's result files, per-frame
errors, summary.md / summary.csv and precision.png / success.png to DIR; run again, it
resumes where it stopped (`jaxpso.evaluate`); the tracker options but --similarity apply
to every method but sift.
Tracker options: --similarity, --motion, --dof, --swarm-size, --max-iterations,
--search-radius, --levels, --resolution, --refine-steps (defaults: `jaxpso.TrackConfig`).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import os
import sys
import time

import jaxpso
from jaxpso import datasets
from jaxpso import io
from jaxpso import synthetic
from jaxpso._src import config as configs
from jaxpso._src import template as templates

_FPS = 25.0


class _UsageError(Exception):
  """A bad command line (argparse's complaint), reported as one line."""


class _Parser(argparse.ArgumentParser):
  """An ArgumentParser whose errors raise instead of printing usage and exiting 2."""

  def error(self, message):
    raise _UsageError(message)


def _default(name: str):
  return next(f.default for f in dataclasses.fields(jaxpso.TrackConfig) if f.name == name)


def _add_tracker_options(parser: argparse.ArgumentParser) -> None:
  """The `TrackConfig` settings the commands take; None keeps the config's default."""
  group = parser.add_argument_group("tracker options (default: jaxpso.TrackConfig's)")
  group.add_argument("--similarity", choices=configs.SIMILARITIES,
                     help=f"similarity measure (default {_default('similarity')})")
  group.add_argument("--motion", choices=configs.MOTIONS,
                     help=f"motion model (default {_default('motion')})")
  group.add_argument("--dof", type=int, choices=configs.DOFS,
                     help=f"pose parameters of motion plane (default {_default('dof')})")
  group.add_argument("--swarm-size", type=int, dest="swarm_size",
                     help=f"particles (default {_default('swarm_size')})")
  group.add_argument("--max-iterations", type=int, dest="max_iterations",
                     help="swarm iterations per frame at most"
                     f" (default {_default('max_iterations')})")
  group.add_argument("--search-radius", type=float, dest="search_radius",
                     help=f"searched box half-width in px (default {_default('search_radius')})")
  group.add_argument("--levels", type=int,
                     help="pyramid levels (default: by the template's size, at most"
                     f" {configs.AUTO_LEVELS})")
  group.add_argument("--resolution", type=int,
                     help=f"points per template set at most (default {templates.RESOLUTION})")
  group.add_argument("--refine-steps", type=int, dest="refine_steps",
                     help=f"Gauss–Newton steps per level (default {_default('refine_steps')})")
  group.add_argument("--seed", type=int, default=0, help="random seed (default 0)")


_TRACKER_FIELDS = ("similarity", "motion", "dof", "swarm_size", "max_iterations", "search_radius",
                   "levels", "resolution", "refine_steps")


def _config(args) -> jaxpso.TrackConfig:
  return jaxpso.TrackConfig(**{name: getattr(args, name) for name in _TRACKER_FIELDS
                               if getattr(args, name) is not None})


def _parse_roi(text: str) -> tuple[int, int, int, int]:
  """'x,y,w,h' → four ints with w, h >= 1, or ValueError naming --roi."""
  try:
    x, y, w, h = (int(part) for part in text.split(","))
  except ValueError:
    raise ValueError(f"--roi must be x,y,w,h (four integers), got {text!r}") from None
  if w < 1 or h < 1:
    raise ValueError(f"--roi width and height must be >= 1, got {text!r}")
  return x, y, w, h


def _write_overlay(out: str, make_frames) -> str:
  """Writes overlay.mp4, or overlay.avi where MP4 cannot be written; returns the path."""
  failure = None
  for name in ("overlay.mp4", "overlay.avi"):
    path = os.path.join(out, name)
    try:
      io.write_video(path, make_frames(), fps=_FPS)
      return path
    except OSError as error:
      failure = error
      if os.path.exists(path):
        os.remove(path)
  raise failure


def _write_plot(path: str, result, truth_corners=None) -> None:
  try:
    io.plot_results(path, result, truth_corners=truth_corners)
  except ImportError:
    print(f"matplotlib is not installed (pip install 'jaxpso[plots]'); {path} not written")
    return
  print(f"wrote {path}")


def _print_summary(summary: dict, seconds: float, compile_seconds: float) -> None:
  counts = summary["status_counts"]
  frames = summary["frames"]
  print(f"frames        {frames} (" + ", ".join(f"{k} {v}" for k, v in counts.items()) + ")")
  if "within_5px" in summary:
    def px(value):
      return "inf" if value is None else f"{value:.2f}"
    print(f"corner error  median {px(summary['median_error_px'])} px,"
          f" max {px(summary['max_error_px'])} px (RMS over the 4 corners)")
    print(f"within 5 px   {100 * summary['within_5px']:.1f} % of frames")
  elif summary["median_score"] is not None:
    print(f"median score  {summary['median_score']:.4f}")
  print(f"time          {1000 * seconds / frames:.0f} ms per frame ({seconds:.1f} s for"
        f" {frames} frames, after {compile_seconds:.1f} s of one-off JIT compilation)")


def _make_out(path: str) -> None:
  """Creates the output folder before any tracking, or raises OSError naming --out."""
  try:
    os.makedirs(path, exist_ok=True)
  except OSError as error:
    raise OSError(f"--out {path!r} cannot be made a folder: {error.strerror}") from None


def _compile(frames, roi, config, **kwargs) -> float:
  """Runs the tracker on the first two frames so that the timed run is compiled; seconds."""
  print("compiling the tracker (once per frame size and config)...", flush=True)
  start = time.perf_counter()
  jaxpso.track(frames, roi, config=config, **kwargs)
  return time.perf_counter() - start


def _demo(args) -> int:
  count = args.frames
  if count < 2:
    raise ValueError(f"--frames must be >= 2, got {count}")
  config = _config(args)
  _make_out(args.out)
  jumps = tuple(sorted({j for j in (count // 3, 2 * count // 3) if 0 < j < count}))
  sequence = synthetic.make_sequence(args.seed, num_frames=count, jumps=jumps, gain_drift=0.1,
                                     noise=0.01)
  height, width = sequence.frames.shape[1:]
  x, y, w, h = sequence.roi
  print(f"synthetic sequence: {count} frames of {width}×{height} px, the embedded camera image"
        f" on a plane seen by a moving camera; jumps at frames {', '.join(map(str, jumps))};"
        f" gain drift 0.1, noise 0.01")
  print(f"tracking the {w}×{h} region at ({x}, {y}) with {config.similarity},"
        f" motion {config.motion}" + (f" ({config.dof} DOF)" if config.motion == "plane" else ""))
  plane = ({"camera": sequence.camera, "plane_normal": sequence.normal}
           if config.motion == "plane" else {})
  compile_seconds = _compile(sequence.frames[:2], sequence.roi, config, key=args.seed, **plane)
  start = time.perf_counter()
  result = jaxpso.track(sequence.frames, sequence.roi, config=config, key=args.seed,
                        progress=True, **plane)
  seconds = time.perf_counter() - start

  summary = io.write_results(args.out, result, truth_corners=sequence.corners)
  _print_summary(summary, seconds, compile_seconds)
  path = _write_overlay(args.out, lambda: (
      io.draw_overlay(frame, corners, status, truth_corners=truth)
      for frame, corners, status, truth in zip(sequence.frames, result.corners, result.status,
                                               sequence.corners)))
  print(f"wrote {path}")
  _write_plot(os.path.join(args.out, "errors.png"), result, sequence.corners)
  print(f"wrote {os.path.join(args.out, 'results.csv')}, {os.path.join(args.out, 'results.json')}")
  return 0


def _track(args) -> int:
  roi = _parse_roi(args.roi)
  if args.max_frames is not None and args.max_frames < 1:
    raise ValueError(f"--max-frames must be >= 1, got {args.max_frames}")
  config = _config(args)
  frames = io.read_frames(args.source)  # checks the source before any tracking
  _make_out(args.out)
  print(f"tracking the {roi[2]}×{roi[3]} region at ({roi[0]}, {roi[1]}) of {args.source} with"
        f" {config.similarity}, motion {config.motion}")
  consumed = 0

  def counted():
    nonlocal consumed
    for frame in itertools.islice(frames, args.max_frames):
      consumed += 1
      yield frame

  compile_seconds = _compile(list(itertools.islice(io.read_frames(args.source), 2)), roi, config,
                             key=args.seed)
  start = time.perf_counter()
  try:
    result = jaxpso.track(counted(), roi, config=config, key=args.seed, progress=True)
  except Exception:
    if consumed > 1:  # end the progress line before the error
      print(file=sys.stderr)
    raise
  seconds = time.perf_counter() - start

  summary = io.write_results(args.out, result)
  _print_summary(summary, seconds, compile_seconds)
  count = summary["frames"]
  path = _write_overlay(args.out, lambda: (
      io.draw_overlay(frame, corners, status) for frame, corners, status in
      zip(itertools.islice(io.read_frames(args.source), count), result.corners, result.status)))
  print(f"wrote {path}")
  _write_plot(os.path.join(args.out, "scores.png"), result)
  print(f"wrote {os.path.join(args.out, 'results.csv')}, {os.path.join(args.out, 'results.json')}")
  return 0


def _evaluate(args) -> int:
  if args.similarity is not None:
    raise ValueError("--similarity: give each method's as NAME:SIMILARITY in --methods")
  overrides = {name: getattr(args, name) for name in _TRACKER_FIELDS
               if name != "similarity" and getattr(args, name) is not None}
  methods = [datasets.method(spec) for spec in args.methods.split(",")]
  methods = [m if m.config is None or not overrides
             else datasets.Method(m.name, dataclasses.replace(m.config, **overrides))
             for m in methods]
  report = jaxpso.evaluate(args.dataset, args.format, methods, args.out, key=args.seed,
                           sequences=args.sequences.split(",") if args.sequences else None)
  print(f"{report.ran} runs done, {report.resumed} read back from {args.out};"
        f" {report.seconds:.1f} s, {report.tracker_seconds:.1f} s of it in the trackers")
  with open(os.path.join(args.out, "summary.md")) as handle:
    print(handle.read().rstrip())
  return 0


def _parser() -> argparse.ArgumentParser:
  parser = _Parser(prog="jaxpso", description=__doc__,
                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--version", action="store_true", help="print the version and exit")
  commands = parser.add_subparsers(dest="command")
  demo = commands.add_parser("demo", help="track a synthetic sequence with known truth")
  demo.add_argument("--out", default="out", help="output folder (default out)")
  demo.add_argument("--frames", type=int, default=120, help="sequence length (default 120)")
  _add_tracker_options(demo)
  demo.set_defaults(run=_demo)
  track = commands.add_parser("track", help="track a region through a video or image folder")
  track.add_argument("source", metavar="VIDEO_OR_FOLDER",
                     help="a video file, or a folder of images (read in name order)")
  track.add_argument("--roi", required=True, metavar="x,y,w,h",
                     help="the region in frame 0: top-left corner, width and height in px")
  track.add_argument("--out", required=True, help="output folder")
  track.add_argument("--max-frames", type=int, dest="max_frames",
                     help="track at most this many frames")
  _add_tracker_options(track)
  track.set_defaults(run=_track)
  evaluate = commands.add_parser("evaluate", help="score methods on a benchmark dataset")
  evaluate.add_argument("dataset", metavar="DATASET", help="the dataset's folder")
  evaluate.add_argument("--format", required=True, choices=datasets.LAYOUTS,
                        help="the dataset's layout")
  evaluate.add_argument("--methods", default="pso,ecc,sift",
                        help="comma-separated NAME or NAME:SIMILARITY (default pso,ecc,sift)")
  evaluate.add_argument("--out", required=True, help="output folder (resumed if it exists)")
  evaluate.add_argument("--sequences", help="comma-separated sequence names (default all)")
  _add_tracker_options(evaluate)
  evaluate.set_defaults(run=_evaluate)
  return parser


def _attach_roi(argv: list[str]) -> list[str]:
  """`--roi VALUE` written as `--roi=VALUE` when VALUE starts with a minus and a
  digit: argparse takes a value such as "-5,10,40,40" (a region starting left
  of the frame) for an option.  A following option (`--roi --out DIR`) is left
  alone, so that argparse reports the missing value."""
  out, rest = [], list(argv)
  while rest:
    arg = rest.pop(0)
    if arg == "--roi" and rest and rest[0][:1] == "-" and rest[0][1:2].isdigit():
      arg = f"--roi={rest.pop(0)}"
    out.append(arg)
  return out


def main(argv=None) -> int:
  """Entry point of the `jaxpso` console script; returns the exit status.

  Errors (a bad option, a missing or unreadable file, a ValueError, TypeError
  or OSError from the library) print one line `jaxpso: error: ...` to
  stderr and return 1.
  """
  # OpenCV's FFmpeg backend logs to stderr itself ("moov atom not found"):
  # quiet by default, so that an error is the one line below.
  os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
  parser = _parser()
  try:
    args = parser.parse_args(_attach_roi(sys.argv[1:] if argv is None else argv))
    if args.version:
      from jaxpso import __version__
      print(__version__)
      return 0
    if args.command is None:
      parser.print_help()
      return 2
    return args.run(args)
  except (_UsageError, ValueError, TypeError, OSError) as error:
    message = " ".join(str(error).split()) or type(error).__name__
    print(f"jaxpso: error: {message}", file=sys.stderr)
    return 1


if __name__ == "__main__":
  sys.exit(main())
