"""The planar-tracking benchmarks' published layouts: readers, and a writer for one's own data.

Every layout gives, per sequence, the 4 corners of the target in each frame in the order TL,
TR, BR, BL (clockwise from the top left), frames that the benchmark leaves out of its
evaluation, and the frames themselves as a video file or a folder of images:

  pot          POT-210 (Liang et al., ICRA 2018).  annotation/<seq>_gt_points.txt: 8 numbers
               a line, one line a frame, a line of zeros where the frame is not annotated;
               annotation/<seq>_gt_homography.txt: 9 numbers a line, frame 0 → frame t
               row-major; annotation/<seq>_flag.txt: 1 where the frame is left out.  The
               frames: a video <seq>.avi (or .mp4, ...) or a folder <seq>/ (or <seq>/img/)
               anywhere under the root.  Attribute: the name's suffix _1 ... _7
               (`POT_ATTRIBUTES`).
  planartrack  PlanarTrack (Liu et al., ICCV 2023).  annotation/<seq>.txt,
               <seq>_homography.txt and <seq>_flag.txt as POT-210's;
               annotation/challenging_factor/<seq>_challenging_factor.txt: 8 flags
               (`PLANARTRACK_ATTRIBUTES`); the frames as POT-210's.
  ucsb, tmt    UCSB (Gauglitz et al., IJCV 2011) and TMT (Roy et al., 2015) as distributed
               with MTF: <seq>.txt beside the folder <seq>/ of frames, a header line, then
               `frame00001.jpg ulx uly urx ury lrx lry llx lly` a frame.  UCSB's attribute is
               its name after the texture (bricks_motion1 → motion).
  plain        anyone's data: <seq>/corners.csv (x1,y1,...,x4,y4 a frame, optionally under a
               header; an empty row where the frame is not annotated), the frames in
               <seq>/frames/ or as one video in <seq>/, and optionally <seq>/attributes.txt (a
               name a line).  A root holding corners.csv is itself one sequence.

`read` loads the annotations (small) and checks them against the frames; the frames are read
from disk only as `Sequence.frames` is iterated.  `write` writes frames and corners in any
layout (tests, benchmarks, or converting data).  Malformed files raise ValueError naming the
file and line.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Iterable, Iterator

import numpy as np

from jaxpso._src import homography
from jaxpso._src import video

LAYOUTS = ("pot", "planartrack", "ucsb", "tmt", "plain")
"""Names accepted by `read` and `write`."""

POT_ATTRIBUTES = ("scale change", "rotation", "perspective distortion", "motion blur",
                  "occlusion", "out of view", "unconstrained")
"""POT-210's challenge of a sequence named <object>_k is POT_ATTRIBUTES[k - 1]."""

PLANARTRACK_ATTRIBUTES = ("occlusion", "motion blur", "rotation", "scale variation",
                          "perspective distortion", "out of view", "low resolution",
                          "background clutter")
"""The factors of PlanarTrack's challenging_factor files, in their order."""

VIDEO_EXTENSIONS = (".avi", ".mp4", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".webm")
"""File name endings taken for a sequence's video."""

_MTF_HEADER = "frame ulx uly urx ury lrx lry llx lly"
# The toolkits' annotation files: annotation/<seq><corners>, annotation/<seq><homographies>.
_ANNOTATION_SUFFIXES = {"pot": ("_gt_points.txt", "_gt_homography.txt"),
                        "planartrack": (".txt", "_homography.txt")}


@dataclasses.dataclass(frozen=True, eq=False)
class Sequence:
  """One annotated sequence; its frames are read lazily.

  Attributes:
    name: the sequence's name in its dataset.
    source: its video file or frame folder.
    corners: (T, 4, 2) float64 corners TL, TR, BR, BL per frame; NaN where not annotated.
    homographies: (T, 3, 3) frame 0 → frame t: the dataset's own where it has them (pot,
      planartrack), else from the corners; NaN where not annotated.
    excluded: (T,) bool, frames the benchmark leaves out (flagged or not annotated).
    attributes: the sequence's challenge attributes.
    annotation: the file the corners were read from (named in errors).
  """
  name: str
  source: str
  corners: np.ndarray
  homographies: np.ndarray
  excluded: np.ndarray
  attributes: tuple[str, ...]
  annotation: str

  def __len__(self) -> int:
    return len(self.corners)

  @property
  def first(self) -> int:
    """The first annotated frame, where a tracker starts."""
    return int(np.argmax(~np.isnan(self.corners[:, 0, 0])))

  def frames(self, *, gray: bool = True) -> Iterator[np.ndarray]:
    """The T frames, read one at a time; ValueError naming the annotation file where the
    frames are more or fewer than its lines."""
    count = 0
    for frame in video.read_frames(self.source, gray=gray):
      count += 1
      if count > len(self):
        raise ValueError(f"{self.annotation}: {len(self)} lines, but {self.source} has more"
                         " frames")
      yield frame
    if count < len(self):
      raise ValueError(f"{self.annotation}: {len(self)} lines, but {self.source} has"
                       f" {count} frames")


def _numbers(path: str, width: int, *, skip=0, named=False, blank_ok=False) -> np.ndarray:
  """(lines, width) float64 numbers of a text file, comma or white-space separated.

  skip: header lines; named: each line starts with a frame name (dropped); blank_ok: an empty
  line (or one of empty fields) is a row of NaN.  Trailing empty lines are ignored.
  ValueError naming file and line otherwise.
  """
  try:
    with open(path, encoding="utf-8") as handle:
      lines = handle.read().splitlines()
  except UnicodeDecodeError:
    raise ValueError(f"{path}: not a text file") from None
  while lines and not lines[-1].strip(" ,\t"):
    lines.pop()
  rows = []
  for number, line in enumerate(lines[skip:], start=skip + 1):
    fields = [f for f in re.split(r"[,\s]+", line.strip()) if f]
    if named and fields:
      fields = fields[1:]
    if not fields and blank_ok:
      rows.append([math.nan] * width)
      continue
    if len(fields) != width:
      raise ValueError(f"{path}, line {number}: expected {width} values, got {len(fields)}")
    bad = next((f for f in fields if not _is_number(f)), None)
    if bad is not None:
      raise ValueError(f"{path}, line {number}: {bad!r} is not a number")
    values = [float(f) for f in fields]
    if not all(math.isfinite(v) for v in values):
      raise ValueError(f"{path}, line {number}: values must be finite")
    rows.append(values)
  if not rows:
    raise ValueError(f"{path}: no annotation lines")
  return np.array(rows, np.float64)


def _is_number(text: str) -> bool:
  try:
    float(text)
  except ValueError:
    return False
  return True


def frame_homographies(corners: np.ndarray) -> np.ndarray:
  """(T, 3, 3) float64 homographies from the first annotated frame's (T, 4, 2) corners to each
  frame's (`homography.host_homography_from_corners`); NaN where a frame is not annotated or
  its corners are degenerate."""
  annotated = ~np.isnan(corners).any(axis=(1, 2))
  out = np.full((len(corners), 3, 3), math.nan)
  first = corners[np.argmax(annotated)][None]
  try:
    out[annotated] = homography.host_homography_from_corners(
        np.broadcast_to(first, corners[annotated].shape), corners[annotated])
  except np.linalg.LinAlgError:  # three corners on a line somewhere: each frame on its own
    for t in np.flatnonzero(annotated):
      try:
        out[t] = homography.host_homography_from_corners(first, corners[t][None])[0]
      except np.linalg.LinAlgError:
        pass
  return out


def _count_frames(source: str) -> int | None:
  """Frames of a folder (its images), or of a video as its container states (None if not)."""
  if os.path.isdir(source):
    return len(video.image_files(source))
  import cv2  # lazily, as in video.py

  capture = cv2.VideoCapture(source)
  try:
    if not capture.isOpened():
      raise ValueError(f"OpenCV cannot open {source!r} as a video")
    count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
  finally:
    capture.release()
  return count if count > 0 else None


def _index(root: str) -> dict[str, str]:
  """{sequence name: its video file or image folder} of everything under root."""
  found = {}
  for folder, folders, files in os.walk(root):
    folders.sort()
    for name in sorted(files):
      stem, ext = os.path.splitext(name)
      if ext.lower() in VIDEO_EXTENSIONS:
        found.setdefault(stem, os.path.join(folder, name))
    if any(f.lower().endswith(video.IMAGE_EXTENSIONS) for f in files):
      base = os.path.basename(folder)
      name = os.path.basename(os.path.dirname(folder)) if base == "img" else base
      found.setdefault(name, folder)
  return found


def _check(source: str, annotation: str, corners: np.ndarray) -> None:
  """ValueError naming the annotation file where its lines are not the source's frames."""
  count = _count_frames(source)
  if count is not None and count != len(corners):
    raise ValueError(f"{annotation}: {len(corners)} lines, but {source} has {count} frames")


def _toolkit(root: str, layout: str) -> list[Sequence]:
  """POT-210's and PlanarTrack's layout (annotation folder, flags, homographies)."""
  suffix, homography_suffix = _ANNOTATION_SUFFIXES[layout]
  folder = next((os.path.join(root, *parts) for parts in (("annotation", "annotation"),
                                                          ("annotation",), ("annos",))
                 if os.path.isdir(os.path.join(root, *parts))), None)
  names = [] if folder is None else sorted(
      f[:-len(suffix)] for f in os.listdir(folder)
      if f.endswith(suffix) and not f.endswith(("_flag.txt", "_homography.txt")))
  if not names:
    raise ValueError(f"{root} is not in the {layout} layout: no annotation/<seq>{suffix}")
  sources = _index(root)
  sequences = []
  for name in names:
    points = os.path.join(folder, name + suffix)
    if name not in sources:
      raise ValueError(f"{points}: no video {name}.avi (or .mp4, ...) or image folder {name}/"
                       f" under {root}")
    values = _numbers(points, 8)
    corners = values.reshape(-1, 4, 2)
    corners[np.all(values == 0, axis=1)] = math.nan
    excluded = np.isnan(corners[:, 0, 0])
    flags = os.path.join(folder, name + "_flag.txt")
    if os.path.exists(flags):
      flag = _numbers(flags, 1)[:, 0]
      if len(flag) != len(corners):
        raise ValueError(f"{flags}: {len(flag)} lines, but {points} has {len(corners)}")
      excluded = excluded | (flag != 0)
    path = os.path.join(folder, name + homography_suffix)
    if os.path.exists(path):
      homographies = _numbers(path, 9).reshape(-1, 3, 3)
      if len(homographies) != len(corners):
        raise ValueError(f"{path}: {len(homographies)} lines, but {points} has {len(corners)}")
      homographies[np.isnan(corners[:, 0, 0])] = math.nan
    else:
      homographies = frame_homographies(corners)
    if layout == "pot":
      match = re.search(r"_(\d)$", name)
      attributes = ((POT_ATTRIBUTES[int(match.group(1)) - 1],)
                    if match and 1 <= int(match.group(1)) <= 7 else ())
    else:
      factors = os.path.join(folder, "challenging_factor", name + "_challenging_factor.txt")
      attributes = ()
      if os.path.exists(factors):
        flags_ = _numbers(factors, len(PLANARTRACK_ATTRIBUTES))[0]
        attributes = tuple(a for a, f in zip(PLANARTRACK_ATTRIBUTES, flags_) if f)
    _check(sources[name], points, corners)
    sequences.append(Sequence(name, sources[name], corners, homographies, excluded, attributes,
                              points))
  return sequences


def _mtf(root: str, layout: str) -> list[Sequence]:
  """MTF's layout of UCSB and TMT: <seq>.txt beside the frame folder <seq>/."""
  names = sorted(f[:-4] for f in os.listdir(root)
                 if f.endswith(".txt") and os.path.isdir(os.path.join(root, f[:-4])))
  if not names:
    raise ValueError(f"{root} is not in the {layout} layout: no <seq>.txt beside a folder <seq>/")
  sequences = []
  for name in names:
    path = os.path.join(root, name + ".txt")
    with open(path, encoding="utf-8") as handle:
      header = handle.readline().split()
    if header[:1] != ["frame"]:
      raise ValueError(f"{path}, line 1: expected the header {_MTF_HEADER!r}")
    corners = _numbers(path, 8, skip=1, named=True).reshape(-1, 4, 2)
    attributes = ()
    if layout == "ucsb" and "_" in name:
      attributes = (re.sub(r"\d+$", "", name.split("_", 1)[1]),)
    source = os.path.join(root, name)
    _check(source, path, corners)
    sequences.append(Sequence(name, source, corners, frame_homographies(corners),
                              np.zeros(len(corners), bool), attributes, path))
  return sequences


def _plain_one(folder: str) -> Sequence:
  path = os.path.join(folder, "corners.csv")
  with open(path, encoding="utf-8") as handle:
    first_line = handle.readline()
  header = bool(first_line.strip()) and not _is_number(re.split(r"[,\s]+", first_line.strip())[0])
  corners = _numbers(path, 8, skip=int(header), blank_ok=True).reshape(-1, 4, 2)
  if np.isnan(corners[:, 0, 0]).all():
    raise ValueError(f"{path}: no frame is annotated")
  frames = os.path.join(folder, "frames")
  if os.path.isdir(frames):
    source = frames
  else:
    videos = sorted(f for f in os.listdir(folder) if f.lower().endswith(VIDEO_EXTENSIONS))
    images = video.image_files(folder)
    if len(videos) > 1:
      raise ValueError(f"{folder}: several videos ({', '.join(videos)}); keep one")
    if not videos and not images:
      raise ValueError(f"{folder}: no frames/ folder, video or images beside corners.csv")
    source = os.path.join(folder, videos[0]) if videos else folder
  attributes = ()
  listed = os.path.join(folder, "attributes.txt")
  if os.path.exists(listed):
    with open(listed, encoding="utf-8") as handle:
      attributes = tuple(line.strip() for line in handle if line.strip())
  _check(source, path, corners)
  return Sequence(os.path.basename(os.path.abspath(folder)), source, corners,
                  frame_homographies(corners), np.isnan(corners[:, 0, 0]), attributes, path)


def _plain(root: str, layout: str) -> list[Sequence]:
  if os.path.exists(os.path.join(root, "corners.csv")):
    return [_plain_one(root)]
  folders = sorted(f for f in os.listdir(root)
                   if os.path.exists(os.path.join(root, f, "corners.csv")))
  if not folders:
    raise ValueError(f"{root} is not in the plain layout: no <seq>/corners.csv")
  return [_plain_one(os.path.join(root, f)) for f in folders]


_READERS = {"pot": _toolkit, "planartrack": _toolkit, "ucsb": _mtf, "tmt": _mtf,
            "plain": _plain}


def read(root, layout: str) -> list[Sequence]:
  """The annotated sequences of the dataset at `root`, in name order.

  Args:
    root: the dataset's folder (str or os.PathLike).
    layout: one of `LAYOUTS`.

  Returns:
    A list of `Sequence`, annotations loaded, frames read when iterated.

  Raises:
    FileNotFoundError: no such folder.  ValueError: an unknown layout, a folder in another
    layout, a malformed file (naming file and line), annotations with more or fewer lines
    than the frames, a sequence without frames.
  """
  if layout not in LAYOUTS:
    raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
  path = os.fspath(root)
  if not os.path.isdir(path):
    raise FileNotFoundError(f"no such dataset folder: {path!r}")
  return _READERS[layout](path, layout)


def _format(values) -> str:
  return " ".join(repr(float(v)) for v in np.ravel(values))


def write_points(path: str, corners: np.ndarray) -> None:
  """POT-210's / PlanarTrack's corner file: 8 numbers a line, zeros for a NaN (T, 4, 2) row."""
  with open(path, "w") as handle:
    handle.writelines(_format(np.nan_to_num(c, nan=0.0)) + "\n" for c in corners)


def write_homographies(path: str, homographies: np.ndarray) -> None:
  """(T, 3, 3) frame 0 → t homographies, 9 numbers a line (the identity where NaN)."""
  with open(path, "w") as handle:
    for h in homographies:
      handle.write(_format(np.eye(3) if np.isnan(h).any() else h) + "\n")


def write_mtf(path: str, corners: np.ndarray) -> None:
  """MTF's ground-truth format: a header, then `frameNNNNN.png ulx uly ... lly` a frame."""
  if np.isnan(corners).any():
    raise ValueError(f"{path}: MTF's layout annotates every frame; corners hold NaN")
  with open(path, "w") as handle:
    handle.write(_MTF_HEADER + "\n")
    handle.writelines(f"frame{t + 1:05d}.png {_format(c)}\n" for t, c in enumerate(corners))


def write_csv(path: str, corners: np.ndarray) -> None:
  """The plain layout's corners.csv: a header, x1,y1,...,x4,y4 a frame, empty where NaN."""
  with open(path, "w") as handle:
    handle.write("x1,y1,x2,y2,x3,y3,x4,y4\n")
    handle.writelines(("" if np.isnan(c).any() else _format(c).replace(" ", ",")) + "\n"
                      for c in corners)


def write(root, layout: str, name: str, frames: Iterable, corners, *, excluded=None,
          attributes: Iterable[str] = ()) -> str:
  """Writes one sequence in `layout` under `root`; returns its frame folder.

  Frames go out as PNG images (lossless), corners with every digit (`read` gives them back
  exactly).  pot and planartrack also get frame 0 → t homographies from the corners, flags
  and (planartrack) the challenging factors of `attributes` (`PLANARTRACK_ATTRIBUTES`); pot's
  attribute comes from the name (`POT_ATTRIBUTES`).

  Args:
    root: the dataset folder (created).
    layout: one of `LAYOUTS`.
    name: the sequence's name (a file name, no separators).
    frames: (T, H, W) or (T, H, W, 3) uint8 frames, or an iterable of them.
    corners: (T, 4, 2) TL, TR, BR, BL per frame; NaN rows: not annotated.
    excluded: (T,) bool, frames flagged out of the evaluation (pot, planartrack), default none.
    attributes: attribute names (planartrack, plain; ucsb's comes from the name).
  """
  import cv2

  if layout not in LAYOUTS:
    raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
  if not name or os.sep in name or name != name.strip():
    raise ValueError(f"name must be a plain file name, got {name!r}")
  corners = np.asarray(corners, np.float64)
  if corners.ndim != 3 or corners.shape[1:] != (4, 2):
    raise ValueError(f"corners must be (T, 4, 2), got shape {corners.shape}")
  root = os.fspath(root)
  annotation = {"pot": os.path.join(root, "annotation"),
                "planartrack": os.path.join(root, "annotation")}.get(layout, root)
  folder = {"pot": os.path.join(root, "frames", name), "planartrack": os.path.join(root, name),
            "ucsb": os.path.join(root, name), "tmt": os.path.join(root, name),
            "plain": os.path.join(root, name, "frames")}[layout]
  os.makedirs(folder, exist_ok=True)
  os.makedirs(annotation, exist_ok=True)
  count = 0
  for count, frame in enumerate(frames, start=1):
    image = video.to_rgb_uint8(frame)
    cv2.imwrite(os.path.join(folder, f"frame{count:05d}.png"), image[..., ::-1])
  if count != len(corners):
    raise ValueError(f"{count} frames but {len(corners)} rows of corners")
  if layout in ("pot", "planartrack"):
    stem = os.path.join(annotation, name)
    points_suffix, homography_suffix = _ANNOTATION_SUFFIXES[layout]
    write_points(stem + points_suffix, corners)
    write_homographies(stem + homography_suffix, frame_homographies(corners))
    flags = np.zeros(len(corners), bool) if excluded is None else np.asarray(excluded, bool)
    with open(stem + "_flag.txt", "w") as handle:
      handle.writelines(f"{int(f)}\n" for f in flags)
    if layout == "planartrack":
      os.makedirs(os.path.join(annotation, "challenging_factor"), exist_ok=True)
      wanted = set(attributes)
      with open(os.path.join(annotation, "challenging_factor",
                             name + "_challenging_factor.txt"), "w") as handle:
        handle.write(" ".join(str(int(a in wanted)) for a in PLANARTRACK_ATTRIBUTES) + "\n")
  elif layout in ("ucsb", "tmt"):
    write_mtf(os.path.join(root, name + ".txt"), corners)
  else:
    write_csv(os.path.join(root, name, "corners.csv"), corners)
    if attributes:
      with open(os.path.join(root, name, "attributes.txt"), "w") as handle:
        handle.writelines(a + "\n" for a in attributes)
  return folder
