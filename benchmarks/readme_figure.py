"""The README's picture: one frame of `jaxpso demo`'s overlay video.

Runs `jaxpso demo` with its defaults (`jaxpso.cli.main`: 120 frames of the
embedded camera image on a plane seen by a moving camera, sudden jumps at
frames 40 and 80, gain drift 0.1, noise 0.01; the central 100×100 region
tracked with `jaxpso.track`) into a temporary folder, takes one frame of the
overlay video it wrote (the tracked region green when TRACKED, orange when
RECOVERED, red when LOST; the truth in blue) and writes it as a PNG.  Frame
80 by default: the second jump, where the swarm runs.  Prints that frame's
row of the demo's results.json and how far the tracked corners moved since
the previous frame.  About 20 s on 2 CPU cores with a cold compilation cache.

Writes benchmarks/results/readme_figure.png (320×240, about 60 KB).

Usage: python benchmarks/readme_figure.py [--frame N] [--out PATH]
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import sys
import tempfile

import numpy as np

from jaxpso import cli
from jaxpso import io

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "readme_figure.png")


def demo_frame(frame: int) -> tuple[np.ndarray, dict, dict | None]:
  """Frame `frame` of the demo's overlay video (RGB uint8), its results row and the one before."""
  with tempfile.TemporaryDirectory() as folder:
    with contextlib.redirect_stdout(sys.stderr):  # the demo's own report, kept off stdout
      status = cli.main(["demo", "--out", folder])
    if status != 0:
      raise RuntimeError(f"jaxpso demo failed with exit status {status}")
    # cli writes overlay.avi where this OpenCV cannot write MP4.
    video = next(path for path in (os.path.join(folder, name)
                                   for name in ("overlay.mp4", "overlay.avi"))
                 if os.path.exists(path))
    image = next(itertools.islice(io.read_frames(video), frame, None), None)
    with open(os.path.join(folder, "results.json")) as f:
      rows = json.load(f)["frames"]
  if image is None:
    raise ValueError(f"--frame must be below the demo's {len(rows)} frames, got {frame}")
  return image, rows[frame], rows[frame - 1] if frame > 0 else None


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--frame", type=int, default=80,
                      help="frame of the demo's overlay video (default 80, the second jump)")
  parser.add_argument("--out", default=OUT, help=f"PNG to write (default {OUT})")
  args = parser.parse_args(argv)
  if args.frame < 0:
    parser.error(f"--frame must be >= 0, got {args.frame}")

  image, row, previous = demo_frame(args.frame)
  import cv2  # pylint: disable=import-outside-toplevel
  os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
  if not cv2.imwrite(args.out, cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                     [cv2.IMWRITE_PNG_COMPRESSION, 9]):
    raise OSError(f"cannot write {args.out!r}")
  print(f"frame {row['frame']}: {row['status']}, corner error {row['error_px']:.2f} px,"
        f" quality {row['quality']:.3f}, {row['evaluations']} evaluations")
  if previous is not None:
    moved = np.linalg.norm(np.subtract(row["corners"], previous["corners"]), axis=-1)
    print(f"tracked corners moved {moved.mean():.1f} px (mean; at most {moved.max():.1f} px)"
          f" since frame {previous['frame']}")
  print(f"wrote {args.out} ({image.shape[1]}×{image.shape[0]} px,"
        f" {os.path.getsize(args.out) / 1024:.0f} KiB)")


if __name__ == "__main__":
  main()
