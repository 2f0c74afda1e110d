"""Frequency of convergence, the Baker–Matthews protocol: jaxpso.align vs OpenCV's ECC.

100×100 templates cut at random places of the embedded images; the 4 corners
perturbed by Gaussian noise of σ px define the initial homography; success
when the RMS of the 4 corner errors is <= 1 px.  Photometric conditions: the
image unchanged, gamma 0.5 (v ↦ √v) and inverted (v ↦ 1 − v), the template
always from the unchanged image.  OpenCV's findTransformECC (homography, 100
iterations, eps 1e-6, gaussFiltSize 5) runs on the same trials in the same
run; an exception from ECC counts as a failure.

Usage: python benchmarks/convergence.py [--trials N] [--sigmas 2,4,...]
"""

from __future__ import annotations

import argparse
import ast
import time

import cv2
import jax
import numpy as np

import common
import jaxpso
from jaxpso._src.data import load_image

SIZE = 100
SOURCE = np.float32([[0, 0], [SIZE - 1, 0], [SIZE - 1, SIZE - 1], [0, SIZE - 1]])
CONDITIONS = {"none": lambda v: v, "gamma 0.5": np.sqrt, "inverted": lambda v: 1.0 - v}


def trials(count: int, sigma: float, seed: int):
  """(image name, template origin, initial homography) for each trial."""
  rng = np.random.default_rng(seed)
  for _ in range(count):
    name = ("camera", "brick")[rng.integers(2)]
    origin = rng.integers(80, 512 - SIZE - 80, size=2).astype(np.float32)
    start = SOURCE + origin + rng.normal(0, sigma, (4, 2)).astype(np.float32)
    yield name, origin, cv2.getPerspectiveTransform(SOURCE, start).astype(np.float32)


def corner_error(h, origin) -> float:
  mapped = cv2.perspectiveTransform(SOURCE[None], np.asarray(h, np.float64))[0]
  return float(np.sqrt(np.mean(np.sum((mapped - (SOURCE + origin)) ** 2, axis=1))))


def run_ecc(image, template, start):
  criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-6)
  try:
    _, h = cv2.findTransformECC(template, image, start.copy(), cv2.MOTION_HOMOGRAPHY, criteria,
                                None, 5)
    return h
  except cv2.error:
    return None


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--trials", type=int, default=50)
  parser.add_argument("--sigmas", default="2,4,8,12,16,20")
  parser.add_argument("--conditions", default=",".join(CONDITIONS))
  parser.add_argument("--config", default="", help='TrackConfig fields, e.g. "swarm_size=64"')
  args = parser.parse_args()
  sigmas = [float(s) for s in args.sigmas.split(",")]
  images = {name: load_image(name) for name in ("camera", "brick")}
  overrides = {}
  for item in filter(None, args.config.split(",")):
    field, value = item.split("=")
    overrides[field.strip()] = ast.literal_eval(value.strip())
  config = jaxpso.TrackConfig(**overrides)
  rows = []
  for condition in args.conditions.split(","):
    change = CONDITIONS[condition]
    for sigma in sigmas:
      stats = {"jaxpso MI": ([], []), "OpenCV ECC": ([], [])}
      for i, (name, origin, start) in enumerate(trials(args.trials, sigma, int(sigma) * 7)):
        x, y = int(origin[0]), int(origin[1])
        template = images[name][y:y + SIZE, x:x + SIZE]
        image = change(images[name]).astype(np.float32)
        t0 = time.perf_counter()
        result = jax.block_until_ready(jaxpso.align(image, template, start, config=config, key=i))
        t1 = time.perf_counter()
        ecc = run_ecc(image, template, start)
        t2 = time.perf_counter()
        stats["jaxpso MI"][0].append(corner_error(result.homography, origin))
        stats["jaxpso MI"][1].append(t1 - t0)
        stats["OpenCV ECC"][0].append(np.inf if ecc is None else corner_error(ecc, origin))
        stats["OpenCV ECC"][1].append(t2 - t1)
      for method, (errors, seconds) in stats.items():
        errors = np.asarray(errors)
        rows.append({"condition": condition, "sigma": sigma, "method": method,
                     "success": float(np.mean(errors <= 1.0)),
                     "median_error_px": float(np.median(errors)),
                     "median_ms": float(np.median(seconds[1:] if len(seconds) > 1 else seconds) * 1e3)})
        print(rows[-1], flush=True)

  info = common.machine()
  lines = [
      "# Frequency of convergence (Baker–Matthews protocol): jaxpso.align vs OpenCV ECC",
      "",
      common.machine_line(info),
      "",
      f"{args.trials} trials per σ and condition; 100×100 templates at random places of the"
      " embedded camera and brick images; success = corner RMS error <= 1 px.  jaxpso:"
      f" `TrackConfig()` defaults ({config}).  ECC: homography, 100 iterations, eps 1e-6,"
      " gaussFiltSize 5.  Times are medians per alignment (jaxpso's first, compiling call"
      " excluded).",
      "",
      "| condition | σ (px) | method | success | median error (px) | median ms |",
      "|---|---:|---|---:|---:|---:|",
  ]
  for r in rows:
    lines.append(f"| {r['condition']} | {r['sigma']:g} | {r['method']} | {100 * r['success']:.0f} % |"
                 f" {r['median_error_px']:.2f} | {r['median_ms']:.1f} |")
  common.write("convergence", {"machine": info, "rows": rows}, "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
