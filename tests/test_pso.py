"""Tests for the particle swarm optimizer, `jaxpso.pso`.

Expected values come from the definitions in the module docstring and in
`PSOConfig`: neighbourhoods recomputed in NumPy from the documented topologies,
personal and swarm bests recomputed from the recorded losses, stopping
iterations derived from the stated criteria, and the benchmark optima
(sphere, Rosenbrock, Rastrigin) known in closed form.

Compilation dominates the runtime: every (loss_fn, PSOConfig, shapes) triple
compiles once.  The loss functions are therefore defined once at module level,
most tests share the configuration `CFG`, and independent cases are batched
with `jax.vmap` (over keys, problems, `args` or `hparams`) inside one call.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxpso import pso
from jaxpso._src import programs as compiled_programs
from jaxpso._src.pso import _run_impl
from jaxpso._src.swarm_random import _as_seed
from jaxpso._src.swarm_random import _uniform
from jaxpso._src.swarm_random import _uniform_pair
from jaxpso._src.topology import _neighbourhood_best

D = 3
LOWER = jnp.full(D, -5.0)
UPPER = jnp.full(D, 5.0)
SHIFT = jnp.asarray([1.5, -2.0, 0.5], jnp.float32)
# Only max_iterations active: the reference configuration of most tests.
CFG = pso.PSOConfig(swarm_size=16, max_iterations=40, patience=None)


# ------------------------------------------------------------ loss functions
def _sphere(x, shift):
  return jnp.sum((x - shift) ** 2)


_BATCHED_SHAPES = []


def _sphere_rows(x, shift):
  """The sphere for a whole (n, d) swarm (`PSOConfig(batched=True)`)."""
  _BATCHED_SHAPES.append(x.shape)
  return jnp.sum((x - shift) ** 2, axis=1)


_TRACES = [0]


def _counted_sphere(x, shift):
  """The sphere, counting how often it is traced."""
  _TRACES[0] += 1
  return jnp.sum((x - shift) ** 2)


def _constant(x, args):
  del args
  return 1.0 + 0.0 * jnp.sum(x)


def _fill(x, value):
  """`value` everywhere (NaN, +inf or -inf in the tests)."""
  return value + 0.0 * jnp.sum(x)


def _half_nan(x, shift):
  """The sphere where x[0] <= 0, NaN elsewhere (the unconstrained optimum is in the NaN half)."""
  return jnp.where(x[0] > 0, jnp.nan, jnp.sum((x - shift) ** 2))


def _benchmark(x, args):
  """Problem 0: shifted 3-D sphere; 1: 2-D Rosenbrock; 2: 2-D Rastrigin.

  The 2-D problems use x[0], x[1] and add x[2]² so that all three share one
  3-D box and one compile (the minimum stays 0, at (1, 1, 0) and (0, 0, 0)).
  """
  problem, shift = args
  sphere = jnp.sum((x - shift) ** 2)
  a, b = x[0], x[1]
  rosenbrock = 100 * (b - a * a) ** 2 + (1 - a) ** 2 + x[2] ** 2
  z = x[:2]
  rastrigin = 20 + jnp.sum(z * z - 10 * jnp.cos(2 * jnp.pi * z)) + x[2] ** 2
  return jnp.stack([sphere, rosenbrock, rastrigin])[problem]


def _vector_loss(x, args):
  del args
  return x[:2]


def _int_loss(x, args):
  del args
  return jnp.sum(x).astype(jnp.int32)


def _untouchable(x, args):
  raise AssertionError("the loss must not be traced when the inputs are invalid")


def _np_sphere(x, shift):
  """Float64 sphere of (..., d) positions."""
  return np.sum((np.asarray(x, np.float64) - np.asarray(shift, np.float64)) ** 2, axis=-1)


@functools.partial(jax.jit, static_argnames=("loss_fn", "config", "length"))
def _rollout(key, lower, upper, args, hparams, *, loss_fn, config, length):
  """`init` then `length` calls of `step`; returns (initial state, stacked states)."""
  state = pso.init(key, loss_fn, lower, upper, args, config=config)

  def body(s, _):
    s = pso.step(s, loss_fn, lower, upper, args, config=config, hparams=hparams)
    return s, s

  _, states = jax.lax.scan(body, state, None, length=length)
  return state, states


def _prepend(first, stacked):
  """Joins an initial state and the stacked states along a new leading axis."""
  return jax.tree.map(lambda a, b: np.concatenate([np.asarray(a)[None], np.asarray(b)]),
                      first, stacked)


def _assert_same_result(a, b):
  for name in ("x", "loss", "status", "num_iterations", "num_evaluations"):
    np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
  for name in ("x", "v", "best_x", "best_loss"):
    np.testing.assert_array_equal(getattr(a.state, name), getattr(b.state, name),
                                  err_msg=f"state.{name}")


# --------------------------------------------------------------- convergence
_SEEDS = jnp.arange(5)
_PROBLEMS = jnp.arange(3)
_OPTIMA = np.array([np.asarray(SHIFT), [1.0, 1.0, 0.0], [0.0, 0.0, 0.0]])


def _convergence_config(variant, topology):
  # SPSO-2011 converges more slowly than the inertia/constriction family: it
  # gets twice the budget, not a laxer threshold.
  return pso.PSOConfig(swarm_size=24, variant=variant, topology=topology,
                       max_iterations=600 if variant == "spso2011" else 300, patience=None)


def _check_convergence(config):
  solve = jax.vmap(jax.vmap(
      lambda key, problem: pso.run(key, _benchmark, LOWER, UPPER, (problem, SHIFT), config=config),
      (0, None)), (None, 0))
  result = solve(_SEEDS, _PROBLEMS)
  loss, x = np.asarray(result.loss), np.asarray(result.x)  # (3, 5), (3, 5, 3)
  assert np.all(np.isfinite(loss))
  # The reported loss is the loss at the reported point.
  np.testing.assert_array_equal(np.asarray(result.status), pso.Status.MAX_ITERATIONS)
  # A single seed may land in a Rastrigin side basin (the swarm is stochastic):
  # success is judged by the median over the five seeds.
  median = np.median(loss, axis=1)
  distance = np.median(np.linalg.norm(x - _OPTIMA[:, None, :], axis=-1), axis=1)
  assert median[0] < 1e-6, f"sphere: median loss {median[0]}"
  assert distance[0] < 1e-3, f"sphere: median distance {distance[0]}"
  assert median[1] < 1e-2, f"Rosenbrock: median loss {median[1]}"
  assert median[2] < 1.0, f"Rastrigin: median loss {median[2]}"
  # The global Rastrigin basin: every coordinate within 0.5 of the optimum.
  assert distance[2] < 0.5, f"Rastrigin: median distance {distance[2]}"


@pytest.mark.parametrize("variant", pso.VARIANTS)
def test_every_variant_converges_with_the_global_topology(variant):
  _check_convergence(_convergence_config(variant, "global"))


@pytest.mark.parametrize("topology", pso.TOPOLOGIES)
def test_every_topology_converges_with_constriction(topology):
  _check_convergence(_convergence_config("constriction", topology))


# ---------------------------------------------------------------- topologies
def _reference_neighbourhoods(topology, n, iteration, config, informants):
  """Index lists of each particle's neighbourhood, from the documented definitions."""
  if topology == "global":
    return [list(range(n))] * n
  if topology in ("ring", "local", "dynamic"):
    if topology == "ring":
      radius = 1
    elif topology == "local":
      radius = config.neighbours // 2
    else:
      radius = 1 + (iteration * (n // 2)) // config.max_iterations  # exact floor
    return [[(i + o) % n for o in range(-radius, radius + 1)] for i in range(n)]
  if topology == "wheel":
    return [list(range(n))] + [[i, 0] for i in range(1, n)]
  if topology == "von_neumann":
    # The most square factorisation rows × cols = n, rows <= cols, row-major.
    rows = min((r for r in range(1, n + 1) if n % r == 0 and r * r <= n),
               key=lambda r: n // r - r)
    cols = n // rows
    out = []
    for i in range(n):
      r, c = divmod(i, cols)
      out.append([i, ((r - 1) % rows) * cols + c, ((r + 1) % rows) * cols + c,
                  r * cols + (c - 1) % cols, r * cols + (c + 1) % cols])
    return out
  assert topology == "random"
  return [[i] + [int(j) for j in informants[i]] for i in range(n)]


def _probe_state(best_loss, informants, iteration):
  """A state whose personal best of particle j is (j, -j): the choice is readable."""
  n = best_loss.shape[0]
  best_x = np.stack([np.arange(n), -np.arange(n)]).astype(np.float32)
  i = int(np.argmin(best_loss))
  zeros = jnp.zeros((2, n), jnp.float32)
  return pso.PSOState(
      x=zeros, v=zeros, loss=jnp.asarray(best_loss), best_x=jnp.asarray(best_x),
      best_loss=jnp.asarray(best_loss), swarm_x=jnp.asarray(best_x[:, i]),
      swarm_loss=jnp.asarray(best_loss[i]), informants=jnp.asarray(informants, jnp.int32),
      iteration=jnp.asarray(iteration, jnp.int32), stall=jnp.zeros([], jnp.int32),
      num_evaluations=jnp.zeros([], jnp.int32), seed=jnp.zeros(2, jnp.uint32))


def _check_choice(out, best_loss, neighbourhoods):
  out = np.asarray(out)
  chosen = np.round(out[0]).astype(int)
  np.testing.assert_array_equal(out[1], -chosen)  # a whole personal best, not a mixture
  for i, members in enumerate(neighbourhoods):
    assert chosen[i] in members, f"particle {i} follows {chosen[i]}, not in {members}"
    assert best_loss[chosen[i]] == best_loss[members].min(), f"particle {i}"
  # The best of the neighbourhood bests is the swarm's best.
  assert best_loss[chosen].min() == best_loss.min()


@pytest.mark.parametrize("n", [2, 3, 8, 12, 13, 32])
@pytest.mark.parametrize("topology", [t for t in pso.TOPOLOGIES if t != "dynamic"])
def test_neighbourhood_best_matches_the_documented_topology(topology, n):
  config = pso.PSOConfig(swarm_size=n, topology=topology, neighbours=4, informants=3)
  rng = np.random.default_rng(n)
  for trial in range(3):
    best_loss = rng.random(n).astype(np.float32)
    if trial == 2:  # particles that never saw a finite loss
      best_loss[rng.choice(n, size=max(1, n // 4), replace=False)] = np.inf
    k = config.informants if topology == "random" else 0
    informants = rng.integers(0, n, size=(n, k))
    out = _neighbourhood_best(_probe_state(best_loss, informants, 0), config.limits(), config)
    assert out.shape == (2, n)
    _check_choice(out, best_loss, _reference_neighbourhoods(topology, n, 0, config, informants))


@pytest.mark.parametrize("max_iterations", [10, 30])
@pytest.mark.parametrize("n", [8, 12, 13, 32])
def test_dynamic_neighbourhood_radius_grows_with_the_iteration(n, max_iterations):
  config = pso.PSOConfig(swarm_size=n, topology="dynamic", max_iterations=max_iterations)
  best_loss = np.random.default_rng(n).random(n).astype(np.float32)
  iterations = np.arange(max_iterations + 1)
  state = _probe_state(best_loss, np.zeros((n, 0)), 0)
  outs = jax.jit(jax.vmap(lambda t: _neighbourhood_best(
      state._replace(iteration=t), config.limits(), config)))(jnp.asarray(iterations, jnp.int32))
  for t, out in zip(iterations, np.asarray(outs)):
    _check_choice(out, best_loss,
                  _reference_neighbourhoods("dynamic", n, int(t), config, None))
  # At the last iteration the neighbourhood is the whole swarm.
  np.testing.assert_array_equal(np.round(outs[-1][0]), np.argmin(best_loss))


# --------------------------------------------- invariants, bounds and clamps
_BOUNDED = [("clip", "inertia", "global"), ("reflect", "spso2011", "random"),
            ("reinit", "constriction", "dynamic")]


def _check_invariants(first, states, config, lower, upper, shift):
  s = _prepend(first, states)
  n = config.swarm_size
  steps = s.x.shape[0]
  assert s.x.shape == (steps, lower.shape[0], n)
  np.testing.assert_array_equal(s.iteration, np.arange(steps))
  np.testing.assert_array_equal(s.num_evaluations, n * (np.arange(steps) + 1))
  # The recorded losses are the losses at the recorded positions.
  np.testing.assert_allclose(s.loss, _np_sphere(np.swapaxes(s.x, 1, 2), shift),
                             rtol=1e-5, atol=1e-6)
  # Personal bests: the strict running minimum of each particle's losses.
  best_loss, best_x = s.loss[0], s.x[0]
  stall = 0
  for t in range(steps):
    if t:
      improved = s.loss[t] < best_loss
      best_loss = np.where(improved, s.loss[t], best_loss)
      best_x = np.where(improved[None], s.x[t], best_x)
      assert np.all(s.best_loss[t] <= s.best_loss[t - 1]), f"a personal best rose at {t}"
      # The stall rule in float32, like the swarm: reset by a gain > tolerance·max(1, |best|).
      previous, current = s.swarm_loss[t - 1], s.swarm_loss[t]
      gained = previous - current > np.float32(config.tolerance) * max(np.float32(1), abs(previous))
      stall = 0 if gained else stall + 1
      assert int(s.stall[t]) == stall, f"stall at iteration {t}"
      if config.topology == "random" and s.swarm_loss[t] < s.swarm_loss[t - 1]:
        # Informants are kept after an iteration that improved the swarm's best.
        np.testing.assert_array_equal(s.informants[t], s.informants[t - 1])
    np.testing.assert_array_equal(s.best_loss[t], best_loss)
    np.testing.assert_array_equal(s.best_x[t], best_x)
    assert s.swarm_loss[t] == s.best_loss[t].min()
    holders = np.flatnonzero(s.best_loss[t] == s.swarm_loss[t])
    assert any(np.array_equal(s.swarm_x[t], s.best_x[t][:, j]) for j in holders)
  # Positions never leave the box.
  lo, hi = np.asarray(lower)[None, :, None], np.asarray(upper)[None, :, None]
  assert np.all((s.x >= lo) & (s.x <= hi))
  return s


@pytest.mark.parametrize("boundary,variant,topology", _BOUNDED)
def test_invariants_bounds_and_velocity_clamp(boundary, variant, topology):
  config = pso.PSOConfig(swarm_size=12, variant=variant, topology=topology, max_iterations=30,
                         patience=5, boundary=boundary)
  lower, upper = jnp.asarray([-5.0, -1.0, 0.0]), jnp.asarray([5.0, 3.0, 0.5])
  shift = jnp.asarray([4.0, 2.9, 0.1])
  span = np.asarray(upper - lower)
  run = functools.partial(_rollout, loss_fn=_sphere, config=config, length=30)
  default = pso.default_hparams(variant)
  # Huge coefficients throw the particles far outside the box each iteration.
  wild = default._replace(c1=jnp.float32(50.0), c2=jnp.float32(50.0))
  for hparams, clamp in [(default, math.inf), (wild._replace(velocity_clamp=jnp.float32(0.2)), 0.2),
                         (wild._replace(velocity_clamp=jnp.float32(math.inf)), math.inf)]:
    s = _check_invariants(*run(jax.random.key(7), lower, upper, shift, hparams), config,
                          lower, upper, shift)
    speed = np.abs(s.v[1:])
    limit = np.float32(clamp) * span[None, :, None]
    assert np.all(speed <= limit), f"|v| exceeds the clamp {clamp}"
    if clamp < math.inf:
      np.testing.assert_allclose(speed.max(axis=(0, 2)), limit[0, :, 0], rtol=1e-6)
    if boundary == "clip" and hparams is not default:
      lo, hi = np.asarray(lower)[None, :, None], np.asarray(upper)[None, :, None]
      on_bound = (s.x == lo) | (s.x == hi)
      assert on_bound.mean() > 0.1  # the wild swarm really was clipped


_GRID = pso.PSOConfig(swarm_size=16, max_iterations=20, patience=None, grid_step=(0.25, 0.5))


def _grid_positions(lower, upper, shift):
  first, states = _rollout(jax.random.key(3), jnp.asarray(lower), jnp.asarray(upper),
                           jnp.asarray(shift), pso.default_hparams(), loss_fn=_sphere,
                           config=_GRID, length=20)
  return np.concatenate([np.asarray(first.x)[None], np.asarray(states.x)])  # (T + 1, 2, n)


def _assert_on_grid(x, lower):
  steps = np.asarray(_GRID.grid_step)[None, :, None]
  k = (x - np.asarray(lower, np.float64)[None, :, None]) / steps
  np.testing.assert_allclose(k, np.round(k), atol=1e-4, err_msg="positions off the grid")


def test_grid_step_puts_every_position_on_the_grid():
  lower, upper = [-1.0, -2.0], [1.0, 2.0]  # box spans whole multiples of the steps
  x = _grid_positions(lower, upper, [0.3, 1.1])
  assert np.all((x >= np.asarray(lower)[None, :, None]) & (x <= np.asarray(upper)[None, :, None]))
  _assert_on_grid(x, lower)
  assert len(np.unique(x[:, 0])) > 3  # the swarm moved over several grid points


def test_grid_step_keeps_positions_on_the_grid_when_the_box_is_not_a_multiple():
  # The box [-1, 0.9] × [-2, 1.8] does not end on the grid lower + k·step; the
  # optimum sits in the top corner, so particles reach the upper bounds.  The
  # grid points inside the box are -1, ..., 0.75 and -2, ..., 1.5: a position
  # must be one of them, not the off-grid bound itself.
  lower, upper = [-1.0, -2.0], [0.9, 1.8]
  x = _grid_positions(lower, upper, [0.9, 1.8])
  assert np.all((x >= np.asarray(lower)[None, :, None]) & (x <= np.asarray(upper)[None, :, None]))
  _assert_on_grid(x, lower)


# -------------------------------------------------------------------- layout
def test_state_is_dimension_major_and_results_have_documented_shapes():
  config = pso.PSOConfig(swarm_size=16, topology="random", informants=3)
  state = pso.init(0, _sphere, LOWER, UPPER, SHIFT, config=config)
  for name in ("x", "v", "best_x"):
    assert getattr(state, name).shape == (D, 16), name
  assert state.loss.shape == state.best_loss.shape == (16,)
  assert state.swarm_x.shape == (D,) and state.swarm_loss.shape == ()
  assert state.informants.shape == (16, 3)
  assert state.seed.shape == (2,) and state.seed.dtype == jnp.uint32
  assert int(state.iteration) == 0 and int(state.num_evaluations) == 16
  # The layout is the transpose of the (n, d) positions: each column is one particle.
  np.testing.assert_allclose(state.loss, _np_sphere(np.asarray(state.x).T, SHIFT), rtol=1e-6)
  assert np.all((np.asarray(state.x) >= -5) & (np.asarray(state.x) <= 5))
  assert np.all(np.abs(np.asarray(state.v)) <= 5.0)  # within ± half the box


def test_run_equals_trace_and_trace_positions_are_particle_major():
  result = pso.run(1, _sphere, LOWER, UPPER, SHIFT, config=CFG)
  traced, record = pso.trace(1, _sphere, LOWER, UPPER, SHIFT, config=CFG, keep_positions=True)
  assert result.x.shape == (D,) and result.loss.shape == ()
  assert record.x.shape == (CFG.max_iterations, CFG.swarm_size, D)
  assert record.best_loss.shape == (CFG.max_iterations,)
  _assert_same_result(result, traced)
  np.testing.assert_array_equal(record.x[-1], np.asarray(result.state.x).T)
  np.testing.assert_array_equal(record.best_loss[-1], result.loss)
  # Each recorded best is the lowest loss of the positions visited so far
  # (the initial swarm included: `init` with the same key starts the same swarm).
  start = pso.init(1, _sphere, LOWER, UPPER, SHIFT, config=CFG)
  visited = np.concatenate([np.asarray(start.x).T[None], np.asarray(record.x)])
  seen = np.minimum.accumulate(_np_sphere(visited, SHIFT).min(axis=1))[1:]
  np.testing.assert_allclose(record.best_loss, seen, rtol=1e-5, atol=1e-7)


# ------------------------------------------------------ termination, status
def test_max_iterations_status_and_evaluation_count():
  result = pso.run(2, _sphere, LOWER, UPPER, SHIFT, config=CFG)
  assert int(result.status) == pso.Status.MAX_ITERATIONS
  assert int(result.num_iterations) == CFG.max_iterations
  assert int(result.num_evaluations) == CFG.swarm_size * (CFG.max_iterations + 1)
  assert float(result.loss) == pytest.approx(float(_np_sphere(result.x, SHIFT)), rel=1e-5)


def test_patience_stops_a_constant_loss():
  config = pso.PSOConfig(swarm_size=8, max_iterations=100, patience=7)
  result = pso.run(0, _constant, LOWER, UPPER, None, config=config)
  assert int(result.status) == pso.Status.STAGNATED
  assert int(result.num_iterations) == 7 == int(result.state.stall)
  assert int(result.num_evaluations) == 8 * (7 + 1)


def test_target_loss_stops_at_the_first_iteration_reaching_it():
  _, record = pso.trace(1, _sphere, LOWER, UPPER, SHIFT, config=CFG, keep_positions=True)
  best = np.asarray(record.best_loss)
  target = float(best[19])
  assert best[0] > target
  expected = 1 + int(np.argmax(best <= target))  # iterations done when it is first reached
  config = dataclasses.replace(CFG, target_loss=target)
  result = pso.run(1, _sphere, LOWER, UPPER, SHIFT, config=config)
  assert int(result.status) == pso.Status.TARGET_REACHED
  assert float(result.loss) <= target
  assert int(result.num_iterations) == expected <= 20
  assert int(result.num_evaluations) == CFG.swarm_size * (expected + 1)


def test_stop_weights_combination_stops_before_any_single_criterion():
  # Weights (0.5, 0.5, 0) can never fire first: t/T and stall/patience are both
  # < 1 while neither single criterion has fired, so the score stays < 1.  With
  # (0.7, 0.7, 0) and a constant loss (stall == t) the score 0.7·t/100 +
  # 0.7·t/100 first reaches 1 at t = 72, long before t = 100.
  weights, limit = (0.7, 0.7, 0.0), 100
  config = pso.PSOConfig(swarm_size=8, max_iterations=limit, patience=limit,
                         stop_weights=weights)
  expected = next(t for t in range(limit + 1)
                  if weights[0] * t / limit + weights[1] * t / limit >= 1)
  assert expected == 72
  result = pso.run(0, _constant, LOWER, UPPER, None, config=config)
  assert int(result.status) == pso.Status.COMBINED
  assert int(result.num_iterations) == expected
  assert int(result.num_evaluations) == 8 * (expected + 1)


def test_limits_hold_the_termination_settings_and_static_drops_them():
  config = dataclasses.replace(CFG, max_iterations=50, patience=7, tolerance=1e-3,
                               target_loss=0.25, stop_weights=(0.5, 0.25, 1.0))
  limits = config.limits()
  assert isinstance(limits, pso.PSOLimits)
  expected = dict(max_iterations=(50, np.int32, ()), patience=(7, np.int32, ()),
                  tolerance=(1e-3, np.float32, ()), target_loss=(0.25, np.float32, ()),
                  stop_weights=([0.5, 0.25, 1.0], np.float32, (3,)))
  for name, (value, dtype, shape) in expected.items():
    field = getattr(limits, name)
    assert not isinstance(field, jax.Array), name  # host values: no device dispatch
    assert (field.dtype, field.shape) == (dtype, shape), name
    np.testing.assert_array_equal(field, np.asarray(value, dtype), err_msg=name)
  # Disabled criteria: a patience no stall reaches, a target no loss reaches, no weights.
  off = CFG.limits()
  assert int(off.patience) == 2**31 - 1 and float(off.target_loss) == -np.inf
  np.testing.assert_array_equal(off.stop_weights, np.zeros(3, np.float32))
  # Configs that differ only in termination share one static config; others do not.
  assert config.static() == CFG.static() and hash(config.static()) == hash(CFG.static())
  assert config.static() != dataclasses.replace(CFG, topology="ring").static()
  assert dataclasses.replace(config.static(), **{k: getattr(config, k) for k in expected}) == config


def test_every_status_from_one_compiled_program():
  # A constant loss never improves, so the stall equals the iteration.
  base = pso.PSOConfig(swarm_size=8, max_iterations=100, patience=None)
  cases = [
      (dict(), pso.Status.MAX_ITERATIONS, 100),  # the stall reaches 100, patience is off
      (dict(patience=7), pso.Status.STAGNATED, 7),
      (dict(patience=100, stop_weights=(0.7, 0.7, 0.0)), pso.Status.COMBINED, 72),
      (dict(stop_weights=(2.0, 0.0, 0.0)), pso.Status.COMBINED, 50),
      (dict(target_loss=1.0), pso.Status.TARGET_REACHED, 0),
      (dict(max_iterations=30, tolerance=0.5, target_loss=0.5), pso.Status.MAX_ITERATIONS, 30),
  ]
  programs = compiled_programs.counts()["compiled"]
  for changes, status, iterations in cases:
    result = pso.run(0, _constant, LOWER, UPPER, None, config=dataclasses.replace(base, **changes))
    assert (int(result.status), int(result.num_iterations)) == (status, iterations), changes
    assert int(result.num_evaluations) == 8 * (iterations + 1)
  assert compiled_programs.counts()["compiled"] - programs <= 1  # none if compiled already


# ------------------------------------------------------------- non-finite
def test_nan_half_of_the_box_never_becomes_a_best():
  result, record = pso.trace(4, _half_nan, LOWER, UPPER, SHIFT, config=CFG, keep_positions=True)
  best = np.asarray(record.best_loss)
  assert np.all(np.isfinite(best)) and np.all(np.diff(best) <= 0)
  assert np.isfinite(float(result.loss)) and float(result.x[0]) <= 0
  assert float(result.loss) == pytest.approx(float(_np_sphere(result.x, SHIFT)), rel=1e-5)
  for name in ("loss", "best_loss"):
    assert not np.any(np.isnan(np.asarray(getattr(result.state, name)))), name
  # Particles in the NaN half carry +inf, never a finite value.
  in_nan_half = np.asarray(result.state.x)[0] > 0
  assert np.all(np.asarray(result.state.loss)[in_nan_half] == np.inf)
  # The constrained optimum lies on the plane x[0] = 0: (0, -2, 0.5), loss 2.25.
  assert float(result.loss) < 2.25 + 0.05
  assert int(result.status) == pso.Status.MAX_ITERATIONS


def test_loss_that_is_never_finite_ends_non_finite():
  config = pso.PSOConfig(swarm_size=8, max_iterations=50, patience=10)
  values = jnp.asarray([jnp.nan, jnp.inf, -jnp.inf])
  result = jax.vmap(lambda v: pso.run(0, _fill, LOWER, UPPER, v, config=config))(values)
  np.testing.assert_array_equal(result.status, pso.Status.NON_FINITE)
  np.testing.assert_array_equal(result.loss, np.inf)
  np.testing.assert_array_equal(result.num_iterations, 10)  # the stall still counts


def test_first_finite_best_after_a_non_finite_start_resets_the_stall():
  # All particles start in the NaN half; with no attraction and inertia 1 they
  # all move into the finite half in one step, a strict improvement of the
  # swarm's best (from +inf to 0.5) that must reset the stagnation count.
  config = pso.PSOConfig(swarm_size=4, max_iterations=10, patience=5)
  lower, upper = jnp.asarray([-1.0, -1.0]), jnp.asarray([1.0, 1.0])
  shift = jnp.zeros(2)
  hparams = pso.default_hparams()._replace(
      inertia_start=jnp.float32(1.0), inertia_end=jnp.float32(1.0), c1=jnp.float32(0.0),
      c2=jnp.float32(0.0))
  state = pso.init(0, _half_nan, lower, upper, shift, config=config,
                   positions=np.full((4, 2), 0.5, np.float32),
                   velocities=np.full((4, 2), -1.0, np.float32))
  assert float(state.swarm_loss) == np.inf
  moved = pso.step(state, _half_nan, lower, upper, shift, config=config, hparams=hparams)
  assert float(moved.swarm_loss) == pytest.approx(0.5)
  # With tolerance 0 the same move resets the count; any tolerance must too.
  exact = dataclasses.replace(config, tolerance=0.0)
  assert int(pso.step(state, _half_nan, lower, upper, shift, config=exact,
                      hparams=hparams).stall) == 0
  assert int(moved.stall) == 0


# ------------------------------------------------------------- determinism
def test_same_key_is_bit_identical_and_different_keys_differ():
  a = pso.run(5, _sphere, LOWER, UPPER, SHIFT, config=CFG)
  b = pso.run(5, _sphere, LOWER, UPPER, SHIFT, config=CFG)
  c = pso.run(6, _sphere, LOWER, UPPER, SHIFT, config=CFG)
  _assert_same_result(a, b)
  assert not np.array_equal(a.state.x, c.state.x)
  # An int seed means jax.random.key(seed).
  _assert_same_result(a, pso.run(jax.random.key(5), _sphere, LOWER, UPPER, SHIFT, config=CFG))


@pytest.mark.parametrize("changes", [
    dict(variant="spso2011", topology="random"),
    dict(variant="linear_inertia", topology="dynamic", boundary="reflect"),
    dict(variant="constriction", topology="von_neumann", boundary="reinit", grid_step=0.25),
], ids=["spso2011-random", "linear-dynamic-reflect", "constriction-reinit-grid"])
def test_run_and_trace_are_bit_identical_in_every_branch(changes):
  # `run` (lax.while_loop) and `trace` (lax.scan) with only max_iterations
  # active, on the random draws of each variant, topology and boundary rule:
  # the same key gives the same swarm, run to run and form to form.
  config = dataclasses.replace(CFG, **changes)
  looped = pso.run(7, _sphere, LOWER, UPPER, SHIFT, config=config)
  scanned, record = pso.trace(7, _sphere, LOWER, UPPER, SHIFT, config=config)
  again, record_again = pso.trace(7, _sphere, LOWER, UPPER, SHIFT, config=config)
  _assert_same_result(looped, scanned)
  _assert_same_result(scanned, again)
  np.testing.assert_array_equal(record.best_loss, record_again.best_loss)
  np.testing.assert_array_equal(looped.state.informants, scanned.state.informants)


def test_vmap_over_keys_equals_a_python_loop():
  keys = jnp.arange(3)
  batched = jax.vmap(lambda k: pso.run(k, _sphere, LOWER, UPPER, SHIFT, config=CFG))(keys)
  for i in range(3):
    single = pso.run(i, _sphere, LOWER, UPPER, SHIFT, config=CFG)
    # Observed bit-identical on the CPU (vmap changes no reduction order here).
    _assert_same_result(jax.tree.map(lambda a: a[i], batched), single)


@pytest.mark.parametrize("rng", pso.RNGS)
def test_every_rng_runs_deterministically(rng):
  config = dataclasses.replace(CFG, rng=rng)
  a = pso.run(0, _sphere, LOWER, UPPER, SHIFT, config=config)
  b = pso.run(0, _sphere, LOWER, UPPER, SHIFT, config=config)
  c = pso.run(1, _sphere, LOWER, UPPER, SHIFT, config=config)
  _assert_same_result(a, b)
  assert not np.array_equal(a.state.x, c.state.x)
  assert float(a.loss) < 1e-2 and float(c.loss) < 1e-2
  if rng != "hash":
    reference = pso.run(0, _sphere, LOWER, UPPER, SHIFT, config=CFG)
    assert not np.array_equal(a.state.x, reference.state.x)


# ---------------------------------------------------------- hash generator
_STAT_SHAPE = (4, 12500)  # (d, n)-like, 50k values
_SEED = jnp.asarray([0x12345678, 0x9ABCDEF0], jnp.uint32)


def _chi_square(values, bins=16):
  counts, _ = np.histogram(values, bins=bins, range=(0.0, 1.0))
  expected = values.size / bins
  return float(np.sum((counts - expected) ** 2 / expected))


def _corr(a, b):
  return float(np.corrcoef(np.ravel(a), np.ravel(b))[0, 1])


def _check_uniform(values, resolution):
  values = np.asarray(values, np.float64)
  assert values.shape == _STAT_SHAPE
  assert values.min() >= 0.0 and values.max() < 1.0
  np.testing.assert_array_equal(values * 2.0**resolution, np.round(values * 2.0**resolution))
  assert abs(values.mean() - 0.5) < 0.01
  assert abs(values.var() - 1 / 12) < 0.005
  # 15 degrees of freedom: P(chi² > 60) < 1e-6 for uniform numbers.
  assert _chi_square(values) < 60
  assert abs(_corr(values[:, 1:], values[:, :-1])) < 0.02  # neighbouring elements


def test_hash_uniform_is_flat_and_uncorrelated():
  draw = lambda t, stream, seed=_SEED: np.asarray(
      _uniform(seed, jnp.int32(t), stream, _STAT_SHAPE, jnp.float32, "hash"))
  base = draw(3, 0)
  _check_uniform(base, 24)
  assert abs(_corr(base, draw(4, 0))) < 0.02  # consecutive iterations
  assert abs(_corr(base, draw(3, 1))) < 0.02  # neighbouring streams
  assert abs(_corr(base, draw(3, 6))) < 0.02
  other_seed = _SEED.at[1].add(jnp.uint32(1))
  assert abs(_corr(base, draw(3, 0, other_seed))) < 0.02
  np.testing.assert_array_equal(base, draw(3, 0))  # a pure function


def test_hash_uniform_pair_is_flat_and_uncorrelated():
  draw = lambda t, stream: [np.asarray(r) for r in _uniform_pair(
      _SEED, jnp.int32(t), stream, _STAT_SHAPE, jnp.float32, "hash")]
  r1, r2 = draw(3, 0)
  _check_uniform(r1, 16)
  _check_uniform(r2, 16)
  assert abs(_corr(r1, r2)) < 0.02  # the two halves of one hash
  s1, s2 = draw(4, 0)
  assert abs(_corr(r1, s1)) < 0.02 and abs(_corr(r2, s2)) < 0.02
  t1, _ = draw(3, 1)
  assert abs(_corr(r1, t1)) < 0.02
  # The single-number stream differs from the pair stream's numbers.
  single = np.asarray(_uniform(_SEED, jnp.int32(3), 0, _STAT_SHAPE, jnp.float32, "hash"))
  assert abs(_corr(single, r2)) < 0.02


# ---------------------------------------------------------------- retraces
def test_new_args_bounds_or_hparams_do_not_recompile():
  first = pso.run(0, _counted_sphere, LOWER, UPPER, SHIFT, config=CFG)
  after_first = _TRACES[0]
  assert after_first >= 1
  other = jnp.asarray([-3.0, 0.5, 2.0])
  second = pso.run(0, _counted_sphere, LOWER, UPPER, other, config=CFG)
  after_second = _TRACES[0]
  hparams = pso.default_hparams()._replace(inertia_start=jnp.float32(0.6),
                                            inertia_end=jnp.float32(0.6))
  third = pso.run(0, _counted_sphere, LOWER - 1.0, UPPER + 2.0, other, config=CFG,
                  hparams=hparams)
  # The loss is traced only while compiling (its validation with
  # jax.eval_shape runs inside the compiled function): a cache hit adds none.
  assert _TRACES[0] - after_second == 0
  assert after_second - after_first == 0
  # The new data were used.
  np.testing.assert_allclose(first.x, SHIFT, atol=0.05)
  np.testing.assert_allclose(second.x, other, atol=0.05)
  np.testing.assert_allclose(third.x, other, atol=0.05)
  assert not np.array_equal(second.state.x, third.state.x)


def test_new_termination_settings_do_not_recompile():
  config = dataclasses.replace(CFG, swarm_size=12)  # a program of its own
  first = pso.run(0, _counted_sphere, LOWER, UPPER, SHIFT, config=config)
  traces, programs = _TRACES[0], compiled_programs.counts()["compiled"]
  cases = [
      (dict(max_iterations=25), pso.Status.MAX_ITERATIONS),
      (dict(patience=3, tolerance=0.5), pso.Status.STAGNATED),
      (dict(target_loss=1e-2), pso.Status.TARGET_REACHED),
      (dict(stop_weights=(2.0, 0.0, 0.0)), pso.Status.COMBINED),
  ]
  for changes, status in cases:
    result = pso.run(0, _counted_sphere, LOWER, UPPER, SHIFT,
                     config=dataclasses.replace(config, **changes))
    assert int(result.status) == status, changes
  # The settings were used, not those of the compiling call.
  assert int(result.num_iterations) == 20  # 2 · t / 40 >= 1
  _assert_same_result(first, pso.run(0, _counted_sphere, LOWER, UPPER, SHIFT, config=config))
  assert (_TRACES[0], compiled_programs.counts()["compiled"]) == (traces, programs)
  # `trace` takes them at runtime too, except max_iterations: its scan length.
  pso.trace(0, _counted_sphere, LOWER, UPPER, SHIFT, config=config)
  traces = _TRACES[0]
  stopped, _ = pso.trace(0, _counted_sphere, LOWER, UPPER, SHIFT, config=dataclasses.replace(
      config, patience=3, target_loss=1e-2, stop_weights=(0.0, 0.0, 1.0)))
  assert int(stopped.status) == pso.Status.TARGET_REACHED
  assert _TRACES[0] == traces
  pso.trace(0, _counted_sphere, LOWER, UPPER, SHIFT,
            config=dataclasses.replace(config, max_iterations=25))
  assert _TRACES[0] > traces


def test_traced_limits_equal_the_configured_runs():
  # As a caller's compiled program runs the swarm: the limits are traced (here vmapped).
  configs = [dataclasses.replace(CFG, variant="linear_inertia", topology="dynamic", **changes)
             for changes in (dict(max_iterations=20), dict(patience=4, tolerance=0.1),
                             dict(target_loss=1e-3),
                             dict(patience=40, tolerance=1.0, stop_weights=(0.6, 0.9, 0.0)))]
  limits = jax.tree.map(lambda *v: np.stack(v), *(c.limits() for c in configs))
  hparams = pso.default_hparams("linear_inertia")
  solve = jax.jit(jax.vmap(lambda lim: _run_impl(
      0, LOWER, UPPER, SHIFT, hparams, None, None, None, None, loss_fn=_sphere,
      config=configs[0].static(), limits=lim)))
  batched = solve(limits)
  np.testing.assert_array_equal(batched.status, [
      pso.Status.MAX_ITERATIONS, pso.Status.STAGNATED, pso.Status.TARGET_REACHED,
      pso.Status.COMBINED])
  for i, config in enumerate(configs):
    single = pso.run(0, _sphere, LOWER, UPPER, SHIFT, config=config)
    _assert_same_result(jax.tree.map(lambda a, i=i: a[i], batched), single)


def test_hparams_can_be_vmapped():
  inertias = jnp.asarray([0.5, 0.7], jnp.float32)
  base = pso.default_hparams()

  def with_inertia(w):
    return base._replace(inertia_start=w, inertia_end=w)

  batched = jax.vmap(lambda w: pso.run(0, _sphere, LOWER, UPPER, SHIFT, config=CFG,
                                       hparams=with_inertia(w)))(inertias)
  for i in range(2):
    single = pso.run(0, _sphere, LOWER, UPPER, SHIFT, config=CFG,
                     hparams=with_inertia(inertias[i]))
    _assert_same_result(jax.tree.map(lambda a: a[i], batched), single)
  assert not np.array_equal(batched.state.x[0], batched.state.x[1])


# -------------------------------------------------------------- warm start
def test_centre_and_scale_warm_start():
  config = pso.PSOConfig(swarm_size=32)
  centre = jnp.asarray([4.5, 0.0, -1.0])
  for scale in (jnp.asarray([1.0, 2.0, 0.5]), jnp.float32(1.5)):
    state = pso.init(0, _sphere, LOWER, UPPER, SHIFT, config=config, centre=centre, scale=scale)
    x, v = np.asarray(state.x), np.asarray(state.v)
    spread = np.broadcast_to(np.asarray(scale), (D,))[:, None]
    np.testing.assert_array_equal(x[:, 0], centre)
    low = np.maximum(np.asarray(centre)[:, None] - spread, -5.0)
    high = np.minimum(np.asarray(centre)[:, None] + spread, 5.0)
    assert np.all((x >= low) & (x <= high))
    assert np.any(x[0] == 5.0)  # centre + scale exceeds the box: clipped
    assert np.all(np.abs(v) <= spread / 2)
    np.testing.assert_allclose(state.loss, _np_sphere(x.T, SHIFT), rtol=1e-6)


def test_positions_and_velocities_warm_start_are_used_as_given():
  config = pso.PSOConfig(swarm_size=8)
  rng = np.random.default_rng(0)
  positions = rng.uniform(-4, 4, size=(8, D)).astype(np.float32)
  velocities = rng.uniform(-1, 1, size=(8, D)).astype(np.float32)
  state = pso.init(0, _sphere, LOWER, UPPER, SHIFT, config=config, positions=positions,
                   velocities=velocities)
  np.testing.assert_array_equal(state.x, positions.T)
  np.testing.assert_array_equal(state.v, velocities.T)
  np.testing.assert_array_equal(state.best_x, positions.T)
  np.testing.assert_allclose(state.loss, _np_sphere(positions, SHIFT), rtol=1e-6)
  assert float(state.swarm_loss) == float(np.min(state.loss))
  # Positions outside the box are clipped into it.
  outside = positions.copy()
  outside[0] = [9.0, -9.0, 0.0]
  state = pso.init(0, _sphere, LOWER, UPPER, SHIFT, config=config, positions=outside)
  np.testing.assert_array_equal(np.asarray(state.x)[:, 0], [5.0, -5.0, 0.0])


def test_warm_start_converges_faster_on_a_shifted_problem():
  config = pso.PSOConfig(swarm_size=16, max_iterations=300, patience=None, target_loss=1e-6)
  keys = jnp.arange(5)
  moved = SHIFT + jnp.asarray([0.1, -0.1, 0.05])
  cold = jax.vmap(lambda k, s: pso.run(k, _sphere, LOWER, UPPER, s, config=config),
                  (0, None))
  previous = cold(keys, SHIFT)
  fresh = cold(keys + 10, moved)
  warm = jax.vmap(lambda k, c: pso.run(k, _sphere, LOWER, UPPER, moved, config=config,
                                       centre=c, scale=0.3))(keys + 10, previous.x)
  np.testing.assert_array_equal(previous.status, pso.Status.TARGET_REACHED)
  np.testing.assert_array_equal(warm.status, pso.Status.TARGET_REACHED)
  # Loose and over the median of five seeds: individual runs are noisy.
  assert np.median(warm.num_iterations) < 0.8 * np.median(fresh.num_iterations)


# ---------------------------------------------------------- batched loss
def test_batched_loss_receives_the_swarm_and_matches_the_vmapped_form():
  config = dataclasses.replace(CFG, batched=True)
  batched = pso.run(3, _sphere_rows, LOWER, UPPER, SHIFT, config=config)
  single = pso.run(3, _sphere, LOWER, UPPER, SHIFT, config=CFG)
  assert _BATCHED_SHAPES and all(s == (CFG.swarm_size, D) for s in _BATCHED_SHAPES)
  # Observed bit-identical on the CPU.
  _assert_same_result(batched, single)


# -------------------------------------------------------------- bad input
_ONE, _TWO = jnp.zeros(2), jnp.ones(2)


@pytest.mark.parametrize("kwargs,error,match", [
    (dict(swarm_size=0), ValueError, "swarm_size"),
    (dict(swarm_size=1), ValueError, "swarm_size"),
    (dict(variant="adam"), ValueError, "variant"),
    (dict(topology="star"), ValueError, "topology"),
    (dict(boundary="wrap"), ValueError, "boundary"),
    (dict(rng="philox"), ValueError, "rng"),
    (dict(neighbours=3), ValueError, "neighbours"),
    (dict(tolerance=-1e-3), ValueError, "tolerance"),
    (dict(patience=0), ValueError, "patience"),
    (dict(max_iterations=0), ValueError, "max_iterations"),
    (dict(informants=0), ValueError, "informants"),
    (dict(stop_weights=(0.5, 0.5)), ValueError, "stop_weights"),
    (dict(stop_weights=(0.5, 0.5, 0.0), patience=None), ValueError, "patience"),
    (dict(stop_weights=(0.5, 0.0, 0.5)), ValueError, "target_loss"),
    (dict(grid_step=0.0), ValueError, "grid_step"),
])
def test_bad_config_is_rejected(kwargs, error, match):
  with pytest.raises(error, match=match):
    pso.PSOConfig(**kwargs)


_SMALL = pso.PSOConfig(swarm_size=4, max_iterations=3)


@pytest.mark.parametrize("call,error,match", [
    (dict(lower=jnp.asarray([0.0, 1.0]), upper=jnp.asarray([1.0, 1.0])), ValueError,
     "dimension 1"),
    (dict(lower=jnp.asarray([0.0, 2.0]), upper=jnp.asarray([1.0, 1.0])), ValueError,
     "dimension 1"),
    (dict(lower=jnp.zeros(2), upper=jnp.ones(3)), ValueError, "lower and upper"),
    (dict(lower=jnp.zeros((2, 1)), upper=jnp.ones((2, 1))), ValueError, "lower and upper"),
    (dict(lower=jnp.asarray([0.0, -jnp.inf]), upper=_TWO), ValueError, "finite"),
    (dict(lower=_ONE, upper=jnp.asarray([1.0, jnp.nan])), ValueError, "finite"),
    (dict(hparams=(0.7, 0.7, 1.5, 1.5, 1.0, 1.0)), TypeError, "hparams"),
    (dict(hparams={"c1": 1.0}), TypeError, "hparams"),
    (dict(positions=np.zeros((5, 2), np.float32)), ValueError, "positions"),
    (dict(positions=np.zeros((4, 3), np.float32)), ValueError, "positions"),
    pytest.param(dict(positions=np.zeros((2, 4, 2), np.float32)), ValueError, "positions",
                 id="positions-with-a-leading-axis"),
    (dict(positions=np.full((4, 2), np.nan, np.float32)), ValueError, "positions"),
    (dict(velocities=np.zeros((4, 3), np.float32)), ValueError, "velocities"),
    pytest.param(dict(velocities=np.zeros((2, 4, 2), np.float32)), ValueError, "velocities",
                 id="velocities-with-a-leading-axis"),
    (dict(centre=np.zeros(2, np.float32)), ValueError, "centre"),
    (dict(scale=1.0), ValueError, "centre"),
    (dict(centre=np.zeros(3, np.float32), scale=1.0), ValueError, "centre"),
    pytest.param(dict(centre=np.zeros((2, 2), np.float32), scale=1.0), ValueError, "centre",
                 id="centre-with-a-leading-axis"),
    (dict(centre=np.zeros(2, np.float32), scale=np.ones(3, np.float32)), ValueError, "scale"),
    (dict(positions=np.zeros((4, 2), np.float32), centre=np.zeros(2, np.float32), scale=1.0),
     ValueError, "centre"),
    (dict(config=dataclasses.replace(_SMALL, grid_step=(0.1, 0.1, 0.1))), ValueError,
     "grid_step"),
    (dict(config={"swarm_size": 4}), TypeError, "config"),
])
def test_bad_input_is_rejected_before_the_loss_is_traced(call, error, match):
  kwargs = dict(lower=_ONE - 1.0, upper=_TWO, config=_SMALL)
  kwargs.update(call)
  lower, upper = kwargs.pop("lower"), kwargs.pop("upper")
  for function in (pso.run, pso.trace):
    with pytest.raises(error, match=match):
      function(0, _untouchable, lower, upper, None, **kwargs)
  if "hparams" not in kwargs:
    with pytest.raises(error, match=match):
      pso.init(0, _untouchable, lower, upper, None, **kwargs)


@pytest.mark.parametrize("loss_fn,batched,error", [
    (_vector_loss, False, ValueError),
    (_int_loss, False, TypeError),
    (_sphere, True, ValueError),  # a scalar for the whole (n, d) swarm
])
def test_bad_loss_is_rejected_naming_loss_fn(loss_fn, batched, error):
  config = dataclasses.replace(_SMALL, batched=batched)
  for function in (pso.run, pso.init):
    with pytest.raises(error, match="loss_fn"):
      function(0, loss_fn, _ONE, _TWO, _ONE, config=config)
  with pytest.raises(TypeError, match="loss_fn"):
    pso.run(0, "sphere", _ONE, _TWO, None, config=_SMALL)


def test_bad_key_and_variant_are_rejected():
  with pytest.raises(TypeError, match="key"):
    pso.run(jnp.zeros(3), _sphere, _ONE, _TWO, _ONE, config=_SMALL)
  with pytest.raises(TypeError, match="key"):
    pso.run(0.5, _sphere, _ONE, _TWO, _ONE, config=_SMALL)
  with pytest.raises(ValueError, match="variant"):
    pso.default_hparams("adam")
  with pytest.raises(TypeError, match="lower"):
    pso.run(0, _untouchable, jnp.zeros(2, jnp.int32), _TWO, None, config=_SMALL)


@pytest.mark.parametrize("key", [0, 1, 7, 2**31 - 1, 2**31, 2**32 - 1, 2**32 + 5, -1, -12345])
def test_an_int_seed_draws_the_same_seed_as_the_jax_key_of_that_int(key):
  # Derived on the host (no eager JAX operations to compile), equal to JAX's own.
  expected = np.asarray(jax.random.bits(jax.random.key(key), (2,), jnp.uint32))
  np.testing.assert_array_equal(_as_seed(key), expected)
