"""Batch and device invariance of `jaxpso.align`: one template's result in a batch, alone, and split over devices.

Templates of 40–96 px per side cut at random places of the embedded camera
and brick images.  Three in four images are the source image warped by a
random near-identity homography (`cv2.warpPerspective`, bilinear: a
sub-pixel truth and the resampling's blur), one in four is the source itself
(a pixel-aligned truth); one in three is cropped to 420×460, so that the
batch mixes image sizes as well as template sizes.  The start moves each
true corner by Gaussian noise of σ 2 px.

Per similarity (`TrackConfig(similarity=...)`, defaults otherwise) the
templates are aligned as one batch on 1 host device, as the same batch split
over 2 and 4 host devices, and each alone; the batch has one key per element
(`key=[...]`), so that element i draws the swarm stream of the lone call
with key[i].  Reported: how many templates come out bit-identical, and
within 1e-3 px, and the largest distance of a template corner between the
batch and the lone call, and between the 1-device batch and the 2- and
4-device ones, apart for the alignments where a swarm ran (more than 300
evaluations in either call; the refinement alone takes at most a few dozen)
and those refined from the start only; and the median corner error from
the truth.

Usage: python benchmarks/invariance.py [--templates 16] [--similarities mi,ncc,ssd]
"""

from __future__ import annotations

import os

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                           + " --xla_force_host_platform_device_count=4").strip()

import argparse  # noqa: E402  (the flag must be set before JAX starts)

import cv2  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402

import common  # noqa: E402
import jaxpso  # noqa: E402
from jaxpso.data import load_image  # noqa: E402

FIRST_KEY, START_SIGMA, SWARM_EVALUATIONS, TOLERANCE_PX = 100, 2.0, 300, 1e-3


def rectangle(shape) -> np.ndarray:
  """(4, 2) float32 corners of an (h, w) template: top-left, top-right, bottom-right, bottom-left."""
  h, w = shape
  return np.float32([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]])


def cases(count: int, seed: int = 11):
  """(images, templates, starts (N, 3, 3), true corners (N, 4, 2), pixel-aligned (N,) bool)."""
  rng = np.random.default_rng(seed)
  sources = [load_image("camera"), load_image("brick")]
  images, templates, starts, truths, aligned = [], [], [], [], []
  for i in range(count):
    source = sources[i % 2]
    w, h = (int(v) for v in rng.integers(40, 100, 2))
    x, y = int(rng.integers(100, 412 - w)), int(rng.integers(100, 412 - h))
    rect = rectangle((h, w))
    if i % 4 == 3:
      image, warp = source, np.eye(3)
    else:
      c, s = np.cos(0.02 * rng.normal()), np.sin(0.02 * rng.normal())
      warp = np.array([[c, -s, rng.uniform(-3, 3)], [s, c, rng.uniform(-3, 3)],
                       [1e-5 * rng.normal(), 1e-5 * rng.normal(), 1.0]])
      image = cv2.warpPerspective(source, warp, (512, 512), flags=cv2.INTER_LINEAR)
    if i % 3 == 1:
      image = np.ascontiguousarray(image[:420, :460])
    truth = cv2.perspectiveTransform((rect + np.float32([x, y]))[None], warp)[0]
    moved = truth + rng.normal(0, START_SIGMA, (4, 2))
    images.append(image)
    templates.append(source[y:y + h, x:x + w].copy())
    starts.append(cv2.getPerspectiveTransform(rect, moved.astype(np.float32)))
    truths.append(truth)
    aligned.append(i % 4 == 3)
  return images, templates, np.stack(starts), np.stack(truths), np.array(aligned)


def corners(homography, template) -> np.ndarray:
  """(4, 2) the template's corners mapped by a (3, 3) homography."""
  return cv2.perspectiveTransform(rectangle(template.shape)[None],
                                  np.asarray(homography, np.float64))[0]


def run(similarity: str, data) -> dict:
  """Every template aligned in batches on 1, 2, 4 devices and alone: per-template differences."""
  images, templates, starts, truths, aligned = data
  config = jaxpso.TrackConfig(similarity=similarity)
  devices = jax.devices()
  keys = [FIRST_KEY + i for i in range(len(templates))]
  batches = {k: jaxpso.align(images, templates, starts, config=config, key=keys, devices=devices[:k])
             for k in (1, 2, 4) if k <= len(devices)}
  rows = []
  for i, template in enumerate(templates):
    alone = jaxpso.align(images[i], template, starts[i], config=config, key=keys[i])
    one = corners(batches[1].homography[i], template)
    rows.append(dict(
        size=list(template.shape), pixel_aligned=bool(aligned[i]),
        evaluations=[int(batches[1].num_evaluations[i]), int(alone.num_evaluations)],
        alone_px=float(np.abs(one - corners(alone.homography, template)).max()),
        devices_px={k: float(np.abs(corners(b.homography[i], template) - one).max())
                    for k, b in batches.items() if k > 1},
        error_px=float(np.abs(one - truths[i]).max())))
  return dict(similarity=similarity, rows=rows)


def summarise(result: dict) -> dict:
  rows = result["rows"]
  swarm = [r for r in rows if max(r["evaluations"]) > SWARM_EVALUATIONS]
  refined = [r for r in rows if max(r["evaluations"]) <= SWARM_EVALUATIONS]

  def spread(group, key):
    values = [r[key] for r in group]
    return dict(count=len(values), equal=sum(v == 0 for v in values),
                within=sum(v <= TOLERANCE_PX for v in values), max=max(values, default=None))

  devices = [max(r["devices_px"].values(), default=0.0) for r in rows]
  return dict(similarity=result["similarity"], alignments=len(rows),
              refined=spread(refined, "alone_px"), swarm=spread(swarm, "alone_px"),
              refined_max_evaluations=max((max(r["evaluations"]) for r in refined), default=None),
              devices_equal=sum(d == 0 for d in devices),
              devices_within=sum(d <= TOLERANCE_PX for d in devices), devices_max=max(devices),
              median_error_px=float(np.median([r["error_px"] for r in rows])))


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--templates", type=int, default=16)
  parser.add_argument("--similarities", default="mi,ncc,ssd")
  args = parser.parse_args()
  data = cases(args.templates)
  results = [run(s, data) for s in args.similarities.split(",")]
  summaries = [summarise(r) for r in results]
  for s in summaries:
    print(s, flush=True)

  def cell(spread):
    if not spread["count"]:
      return "–"
    return (f"{spread['equal']} / {spread['within']} / {spread['count']}"
            f" (max {spread['max']:.1e})")

  info = common.machine()
  lines = [
      "# Batch and device invariance of align",
      "",
      common.machine_line(info),
      "",
      f"{args.templates} templates of 40–96 px (camera and brick; three in four images warped by a"
      " random near-identity homography, one in four pixel-aligned; one in three cropped to"
      " 420×460), starts σ 2 px, `TrackConfig(similarity=...)` defaults.  Each template aligned in"
      " one batch (1 host device, one key per element), the same batch on 2 and 4 host devices,"
      " and alone with its element's key.  Cells: templates bit-identical / within 1e-3 px /"
      f" templates (largest corner difference, px).  \"Swarm ran\": more than {SWARM_EVALUATIONS}"
      " evaluations in the batch or the lone call.",
      "",
      "| similarity | batch vs alone, refined from the start | batch vs alone, swarm ran |"
      " 1 vs 2 and 4 devices, all | median error from the truth (px) |",
      "|---|---:|---:|---:|---:|",
  ]
  for s in summaries:
    lines.append(f"| {s['similarity']} | {cell(s['refined'])} | {cell(s['swarm'])} |"
                 f" {s['devices_equal']} / {s['devices_within']} / {s['alignments']}"
                 f" (max {s['devices_max']:.1e}) |"
                 f" {s['median_error_px']:.3f} |")
  lines += ["", "Per template (evaluations: batch, alone):", "",
            "| similarity | size (h×w) | pixel-aligned | evaluations | batch vs alone (px) |"
            " 2 / 4 devices vs 1 (px) | error (px) |", "|---|---|---|---:|---:|---:|---:|"]
  for result in results:
    for r in result["rows"]:
      devices = " / ".join(f"{v:.1e}" for v in r["devices_px"].values())
      lines.append(f"| {result['similarity']} | {r['size'][0]}×{r['size'][1]} |"
                   f" {'yes' if r['pixel_aligned'] else 'no'} |"
                   f" {r['evaluations'][0]}, {r['evaluations'][1]} | {r['alone_px']:.1e} |"
                   f" {devices} | {r['error_px']:.3f} |")
  common.write("invariance", {"machine": info, "summary": summaries, "results": results},
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
