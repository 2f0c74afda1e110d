"""PSO throughput: loss evaluations per second on 6-D Rastrigin.

Side by side in one run: jaxpso's `pso.run` (one `lax.while_loop`, random
coefficients per particle and per dimension) with each random number
generator, evosax's PSO driven by a fused `lax.scan` (its fastest form; it
draws one random pair per particle), evosax with a jitted step and a Python
loop (its README's way), and PySwarms' GlobalBestPSO (NumPy).  The machine is
shared and noisy, so the contenders are timed in interleaved rounds and the
ratio to evosax is the median of the per-round ratios.

Usage: python benchmarks/pso_throughput.py [--rounds R]
"""

from __future__ import annotations

import argparse
import logging
import time

import jax
import jax.numpy as jnp
import numpy as np

import common
from jaxpso import pso

DIM = 6
LOWER, UPPER = -5.12, 5.12
ITERATIONS = {32: 4000, 256: 2000, 4096: 200}


def rastrigin(x, args=None):
  """Rastrigin's function over the last axis; minimum 0 at the origin."""
  return 10.0 * x.shape[-1] + jnp.sum(x**2 - 10.0 * jnp.cos(2 * jnp.pi * x), axis=-1)


def jaxpso_runner(n, iterations, rng):
  config = pso.PSOConfig(swarm_size=n, max_iterations=iterations, patience=None, rng=rng)
  lower, upper = jnp.full(DIM, LOWER), jnp.full(DIM, UPPER)
  return lambda seed: pso.run(seed, rastrigin, lower, upper, config=config).loss


def evosax_runners(n, iterations):
  from evosax.algorithms import PSO

  strategy = PSO(population_size=n, solution=jnp.zeros(DIM))
  params = strategy.default_params

  def start(key):
    k_pop, k_init = jax.random.split(key)
    population = jax.random.uniform(k_pop, (n, DIM), minval=LOWER, maxval=UPPER)
    return strategy.init(k_init, population, rastrigin(population), params)

  def one_step(key, state):
    k_ask, k_tell = jax.random.split(key)
    x, state = strategy.ask(k_ask, state, params)
    state, _ = strategy.tell(k_tell, x, rastrigin(x), state, params)
    return state

  @jax.jit
  def fused(key):
    def body(carry, _):
      key, state = carry
      key, sub = jax.random.split(key)
      return (key, one_step(sub, state)), None
    (_, state), _ = jax.lax.scan(body, (key, start(key)), None, length=iterations)
    return state.best_fitness

  start_jit, step_jit = jax.jit(start), jax.jit(one_step)

  def python_loop(key):
    state = start_jit(key)
    for sub in jax.random.split(key, iterations):
      state = step_jit(sub, state)
    return state.best_fitness

  return fused, python_loop


def pyswarms_runner(n, iterations):
  import pyswarms

  logging.getLogger("pyswarms").setLevel(logging.ERROR)
  bounds = (np.full(DIM, LOWER), np.full(DIM, UPPER))

  def objective(x):
    return 10.0 * DIM + np.sum(x**2 - 10.0 * np.cos(2 * np.pi * x), axis=1)

  def run(_):
    optimizer = pyswarms.single.GlobalBestPSO(
        n_particles=n, dimensions=DIM, options={"c1": 1.5, "c2": 1.5, "w": 0.7}, bounds=bounds)
    cost, _ = optimizer.optimize(objective, iters=iterations, verbose=False)
    return cost

  return run


def main():
  parser = argparse.ArgumentParser(description=__doc__)
  parser.add_argument("--rounds", type=int, default=5)
  args = parser.parse_args()
  rows = []
  for n, iterations in ITERATIONS.items():
    evaluations = n * (iterations + 1)
    fused, python_loop = evosax_runners(n, iterations)
    contenders = {f"jaxpso rng={rng}": jaxpso_runner(n, iterations, rng) for rng in pso.RNGS}
    contenders["evosax, fused lax.scan"] = fused
    contenders["evosax, jitted step + Python loop"] = python_loop
    contenders["PySwarms GlobalBestPSO"] = pyswarms_runner(n, iterations)
    times = {name: [] for name in contenders}
    for _ in range(args.rounds):
      for name, runner in contenders.items():
        seed = jax.random.key(len(times[name])) if name.startswith("evosax") else len(times[name])
        if name.startswith("PySwarms"):
          start = time.perf_counter()
          runner(seed)
          times[name].append(time.perf_counter() - start)
        else:
          times[name].append(common.median_seconds(runner, seed, repeats=3, warmup=1))
    reference = np.asarray(times["evosax, fused lax.scan"])
    for name, seconds in times.items():
      seconds = np.asarray(seconds)
      rows.append({"swarm": n, "iterations": iterations, "contender": name,
                   "evals_per_s": float(evaluations / np.median(seconds)),
                   "ratio_to_evosax_fused": float(np.median(reference / seconds)),
                   "seconds": seconds.tolist()})
      print(rows[-1]["swarm"], name, f"{rows[-1]['evals_per_s'] / 1e6:.2f} M/s",
            f"x{rows[-1]['ratio_to_evosax_fused']:.2f}", flush=True)

  info = common.machine()
  lines = [
      "# PSO throughput: evaluations per second on 6-D Rastrigin",
      "",
      common.machine_line(info),
      "",
      "Evaluations = swarm × (iterations + 1), including the initial evaluation; jaxpso runs"
      " with only `max_iterations` active.  M evals/s from the median over interleaved rounds;"
      " ×evosax = median over rounds of (evosax fused time / contender time).  jaxpso draws r1,"
      " r2 per particle and per dimension, evosax one pair per particle.",
      "",
      "| swarm | iterations | contender | M evals/s | ×evosax fused |",
      "|---:|---:|---|---:|---:|",
  ]
  for r in rows:
    lines.append(f"| {r['swarm']} | {r['iterations']} | {r['contender']} |"
                 f" {r['evals_per_s'] / 1e6:.2f} | {r['ratio_to_evosax_fused']:.2f} |")
  common.write("pso_throughput", {"machine": info, "rows": rows}, "\n".join(lines) + "\n")


if __name__ == "__main__":
  main()
