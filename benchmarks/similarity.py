"""Throughput of a swarm's full evaluation: warp_image + similarity.

Pixel-evaluations per second = template pixels × candidates / s, for a 100×100
template in the 512×512 embedded image, swarms of 32, 256 and 1024.  Two ways
of timing:
  call: one jitted call evaluates the swarm once;
  loop: ten evaluations (moving the swarm a little each time) inside one
        jitted `fori_loop`, the way the tracker's PSO evaluates a swarm.
The second table times the similarity alone on precomputed patches.  The
third compares the alternatives for the warp and the MI joint histogram.

Usage: python benchmarks/similarity.py [--quick]
"""

from __future__ import annotations

import argparse
import functools

import jax
import jax.numpy as jnp
import numpy as np

import common
from jaxpso import similarity
from jaxpso import warp
from jaxpso._src import data
from jaxpso._src.similarity import _bspline3, _neg_entropy, _parzen

SHAPE = (100, 100)
OFFSET = (206.0, 156.0)
LOOP = 10


def swarm(n: int, key) -> jax.Array:
  """n homographies: the template box moved by corner offsets of σ = 4 px."""
  offsets = 4.0 * jax.random.normal(key, (n, 8))
  return warp.compose(warp.translation(*map(jnp.float32, OFFSET)),
                      warp.corner_offsets_to_homography(offsets, SHAPE))


def looped(evaluate):
  """Ten swarm evaluations in one compiled loop, nudging the swarm each time."""
  def run(homographies):
    def body(i, total):
      nudged = homographies.at[:, 0, 2].add(1e-3 * i.astype(jnp.float32))
      return total + evaluate(nudged)
    return jax.lax.fori_loop(0, LOOP, body, jnp.zeros(homographies.shape[0]))
  return run


# --- alternatives for the warp -------------------------------------------------
def warp_four_gathers(image, homographies):
  """Bilinear sampling with four scalar gathers (the straightforward version)."""
  grid = warp.template_grid(SHAPE)
  height, width = image.shape
  (points, valid) = warp.warp_points(homographies, grid.reshape(-1, 2), image.shape)
  x = jnp.where(valid, points[..., 0], 0.0)
  y = jnp.where(valid, points[..., 1], 0.0)
  x0 = jnp.clip(jnp.floor(x), 0, width - 2)
  y0 = jnp.clip(jnp.floor(y), 0, height - 2)
  fx, fy = x - x0, y - y0
  flat = image.reshape(-1)
  i = y0.astype(jnp.int32) * width + x0.astype(jnp.int32)
  a, b, c, d = flat[i], flat[i + 1], flat[i + width], flat[i + width + 1]
  top, bottom = a + fx * (b - a), c + fx * (d - c)
  patches = jnp.where(valid, top + fy * (bottom - top), 0.0)
  return patches.reshape(-1, *SHAPE), valid.reshape(-1, *SHAPE)


# --- alternatives for the MI joint histogram ------------------------------------
def mi_from_counts(counts):
  p = counts / jnp.sum(counts, axis=(-2, -1), keepdims=True)
  return (_neg_entropy(p, (-2, -1)) - _neg_entropy(p.sum(-1), -1)
          - _neg_entropy(p.sum(-2), -1))


def mi_dense_naive(template, patches, mask, bins):
  """Both sides' dense Parzen weights per candidate, joint = WaᵀWb per candidate."""
  wa = _parzen(jnp.broadcast_to(template, patches.shape), bins, 0.0, 1.0)
  wb = _parzen(patches, bins, 0.0, 1.0) * mask[..., None]
  return mi_from_counts(jnp.einsum("chwi,chwj->cij", wa, wb))


def mi_dense_template_once(wa, patches, mask, bins):
  """Template weights binned once; candidate-major (c, h, w, bins) patch weights."""
  wb = _parzen(patches, bins, 0.0, 1.0) * mask[..., None]
  return mi_from_counts(jnp.einsum("hwi,chwj->cij", wa, wb))


def _four_weights(v, bins):
  """First bin index and the 4 cubic B-spline weights of each intensity."""
  s = 1.0 + jnp.clip(v, 0.0, 1.0) * (bins - 3)
  k = jnp.clip(jnp.floor(s), 1, bins - 3)
  t = s - k
  w = jnp.stack([(1 - t) ** 3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1,
                 t**3], axis=-1) / 6
  return k.astype(jnp.int32) - 1, w


def mi_one_hot(wa, patches, mask, bins):
  """Patch weights placed into a dense row by one-hot selects, then WaᵀWb."""
  k, w = _four_weights(patches, bins)
  offset = jnp.arange(bins) - k[..., None]
  wb = jnp.zeros(patches.shape + (bins,))
  for m in range(4):
    wb = jnp.where(offset == m, w[..., m:m + 1], wb)
  return mi_from_counts(jnp.einsum("hwi,chwj->cij", wa, wb * mask[..., None]))


def mi_scatter(template, patches, mask, bins):
  """The 4×4 B-spline outer product of every pixel scatter-added into the joint."""
  ka, wa4 = _four_weights(template, bins)
  kb, wb4 = _four_weights(patches, bins)
  n = patches.shape[0]
  rows = ka[None, :, :, None, None] + jnp.arange(4)[:, None]
  cols = kb[:, :, :, None, None] + jnp.arange(4)[None, :]
  values = wa4[None, :, :, :, None] * wb4[:, :, :, None, :] * mask[..., None, None]
  index = (jnp.arange(n)[:, None, None, None, None] * bins + rows) * bins + cols
  counts = jnp.zeros(n * bins * bins).at[index.reshape(-1)].add(values.reshape(-1))
  return mi_from_counts(counts.reshape(n, bins, bins))


def mi_bin_major(wa_flat, patches, mask, bins):
  """The library's layout: (c·bins, h·w) patch weights times (h·w, bins), unchunked."""
  c = patches.shape[0]
  s = 1.0 + jnp.clip(patches, 0.0, 1.0).reshape(c, 1, -1) * (bins - 3)
  wb = _bspline3(s - jnp.arange(bins, dtype=jnp.float32)[:, None]) * mask.reshape(c, 1, -1)
  return mi_from_counts((wb.reshape(c * bins, -1) @ wa_flat).reshape(c, bins, bins))


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--quick", action="store_true", help="fewer repeats, for a smoke test")
  args = parser.parse_args()
  repeats = 3 if args.quick else 7
  time_it = functools.partial(common.median_seconds, repeats=repeats)

  image = jnp.asarray(data.load_image("camera"))
  truth = warp.translation(*map(jnp.float32, OFFSET))
  template = warp.warp_image(image, truth, SHAPE)[0]
  pixels = SHAPE[0] * SHAPE[1]
  measures = {
      "ssd": lambda p, m: similarity.ssd(template, p, m),
      "ncc": lambda p, m: similarity.ncc(template, p, m),
      "mi": lambda p, m: similarity.mi(template, p, m),
  }
  rows = []
  for n in (32, 256, 1024):
    homographies = swarm(n, jax.random.key(n))
    patches, mask = jax.jit(lambda h: warp.warp_image(image, h, SHAPE))(homographies)
    for name, measure in measures.items():
      evaluate = lambda h, measure=measure: measure(*warp.warp_image(image, h, SHAPE))
      call = time_it(jax.jit(evaluate), homographies)
      loop = time_it(jax.jit(looped(evaluate)), homographies) / LOOP
      alone = time_it(jax.jit(measure), patches, mask)
      rows.append({"swarm": n, "measure": name, "call_s": call, "loop_s": loop,
                   "alone_s": alone})
      print(rows[-1], flush=True)

  alternatives = []
  n = 256
  homographies = swarm(n, jax.random.key(1))
  patches, mask = jax.jit(lambda h: warp.warp_image(image, h, SHAPE))(homographies)
  ssd_four = lambda h: similarity.ssd(template, *warp_four_gathers(image, h))
  ssd_quad = lambda h: similarity.ssd(template, *warp.warp_image(image, h, SHAPE))
  for label, evaluate in (("warp: 4 scalar gathers + ssd", ssd_four),
                          ("warp: one 4-wide gather (library) + ssd", ssd_quad)):
    alternatives.append({"variant": label, "bins": None,
                         "call_s": time_it(jax.jit(evaluate), homographies),
                         "loop_s": time_it(jax.jit(looped(evaluate)), homographies) / LOOP})
    print(alternatives[-1], flush=True)
  for bins in (8, 16, 32):
    wa = _parzen(template, bins, 0.0, 1.0)
    variants = {
        "dense Parzen, both sides per candidate": lambda p, m: mi_dense_naive(template, p, m, bins),
        "dense Parzen, template once, (c,h,w,bins)": lambda p, m: mi_dense_template_once(wa, p, m, bins),
        "one-hot select matmul": lambda p, m: mi_one_hot(wa, p, m, bins),
        "4×4 B-spline scatter": lambda p, m: mi_scatter(template, p, m, bins),
        "bin-major GEMM, unchunked": lambda p, m: mi_bin_major(wa.reshape(-1, bins), p, m, bins),
        "bin-major GEMM, chunks of 16 (library)": lambda p, m: similarity.mi(template, p, m, bins=bins),
    }
    reference = np.asarray(jax.jit(variants["dense Parzen, both sides per candidate"])(patches, mask))
    for label, mi in variants.items():
      got = np.asarray(jax.jit(mi)(patches, mask))
      assert np.allclose(got, reference, atol=1e-4), (label, np.abs(got - reference).max())
      evaluate = lambda h, mi=mi: mi(*warp.warp_image(image, h, SHAPE))
      alternatives.append({"variant": "warp + MI: " + label, "bins": bins,
                           "call_s": time_it(jax.jit(evaluate), homographies),
                           "loop_s": time_it(jax.jit(looped(evaluate)), homographies) / LOOP})
      print(alternatives[-1], flush=True)

  info = common.machine()
  rate = lambda seconds, n: pixels * n / seconds / 1e6
  lines = [
      "# Swarm evaluation throughput: warp_image + similarity",
      "",
      common.machine_line(info),
      "",
      "100×100 template in a 512×512 image, MI with 8 bins (the default).  M px/s = template"
      " pixels × candidates / s (median of repeated runs).  *call*: one jitted call per swarm"
      " evaluation; *loop*: 10 evaluations inside one compiled loop, as in the tracker."
      "  ×SSD = time relative to warp + SSD at the same swarm size and timing.",
      "",
      "| swarm | measure | warp + measure, call (M px/s) | ×SSD | in loop (M px/s) | ×SSD | measure alone (M px/s) |",
      "|---:|---|---:|---:|---:|---:|---:|",
  ]
  by_key = {(r["swarm"], r["measure"]): r for r in rows}
  for r in rows:
    base = by_key[(r["swarm"], "ssd")]
    lines.append(
        f"| {r['swarm']} | {r['measure']} | {rate(r['call_s'], r['swarm']):.1f} |"
        f" {r['call_s'] / base['call_s']:.2f} | {rate(r['loop_s'], r['swarm']):.1f} |"
        f" {r['loop_s'] / base['loop_s']:.2f} | {rate(r['alone_s'], r['swarm']):.1f} |")
  lines += [
      "",
      f"## Alternatives (swarm of {n}, warp + measure)",
      "",
      "| variant | bins | call (M px/s) | in loop (M px/s) |",
      "|---|---:|---:|---:|",
  ]
  for r in alternatives:
    lines.append(f"| {r['variant']} | {r['bins'] or ''} | {rate(r['call_s'], n):.1f} |"
                 f" {rate(r['loop_s'], n):.1f} |")
  common.write("similarity", {"machine": info, "rows": rows, "alternatives": alternatives},
               "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
