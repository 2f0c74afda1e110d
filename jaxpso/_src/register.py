"""The stages of a registration, the pipeline that chains them, and its contexts.

`align` and `track` register each template by stages (`ALIGN`, `TRACK`) of
one template's registration in one image (`problem.Problem`: Gauss–Newton
down the pyramid, the swarm, the full-resolution check): a start, a
coarser start, a search, a retry or a recovery search, each run only where
the previous ones fell short.  This module holds those stages, the
transitions between them (`_advance_align`, `_advance_track`), the loop
that runs them for a batch (`run`), the gradient baselines' registration
(`baseline`, the alternative to `run`), and the `problem.Context` every
registration starts from (`context`, `with_range`).

Why stages in a loop: every stage is one pass of the same loop body (an
optional swarm, then Gauss–Newton from a top level down, then the
full-resolution check), so the compiled program holds one copy of the
swarm, one of Gauss–Newton (the pyramid level is data) and one of the check,
whatever the number of stages or levels; unrolled, the same pipeline
compiled a copy of Gauss–Newton per level and call site, and XLA took
several times as long (benchmarks/README.md, cold_start.py).  The image
(`atlas`) and the template (`template`) are point sets and buffers of fixed
capacity, so neither image nor template size enters the program either.

In a batch (`run`) on a CPU, every element runs the stage loop alone, one
after another.  On an accelerator the first stage runs for every element
at once, and the others only for the elements still short of it, gathered
a few at a time (`batching.where_needed`): under `vmap` a per-element
`lax.cond` would run the swarm for every element.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxpso._src import atlas
from jaxpso._src import baselines
from jaxpso._src import batching
from jaxpso._src import homography
from jaxpso._src import measures
from jaxpso._src import motion
from jaxpso._src import problem as problems
from jaxpso._src import similarity
from jaxpso._src import template as templates

# Two registrations agree when no template corner is further apart than this
# (full-resolution pixels).
_AGREE_PX = 1.0
# After a search, align settles on its best (track: a quick search settles a
# frame not lost) once this many of its stages'
# estimates (Gauss–Newton from the start at level 1 and at the coarsest
# level, each search's refined best: `_seen_and_votes`) agree with it,
# whatever its quality: the searches start from random particles over the
# whole box, so agreeing with them on one basin is evidence that it is the
# box's best, and on noisy or real image pairs the right alignment's quality
# stays far under retry_quality (0.3-0.7: benchmarks/results/runtime_cases.md).
# Two were not enough: a quick search and the coarser start can share a
# wrong basin (Baker-Matthews, gain, σ 4: 6.2 px off at 0.55, the full
# search then finding the truth at 0.98).
_VOTES = 3
# align counts a vote within this many pixels (`motion.corner_gap`): on real photo
# pairs and under noise the top of a match's basin is flat, and the stages
# that find it land 1-2 px apart, so every retry ran.  Replayed on traces of
# convergence.py's trials (36 cells × 50, MI) 2 px loses no success, 3 px
# one; runtime.py's real pairs spend 7 202 instead of 13 252 evaluations at
# the 90th percentile.  track keeps _AGREE_PX.
_ALIGN_VOTE_PX = 2.0
# Estimates `State.seen` holds (a later one replaces the last).
_SEEN = 8
# `track` also accepts a start within this margin of its last search's
# quality, where that was at least _MIN_REFERENCE (`_advance_track`).
_REFERENCE_MARGIN, _MIN_REFERENCE = 0.02, 0.8
# align refines its start from the coarsest level first (the widest basin) and
# accepts that refinement alone from this quality; under it the start is
# refined from level 1 too, and the better of the two counts.  The coarse
# level's optimum can lie in a wrong basin near a start already in the right
# one (convergence.py, shading, σ 2, NCC: 13 px off at 0.987, the start's own
# refinement 0.999), or 1 px off at 0.953 (gamma, σ 4, MI); the level-1
# refinement first, the order before, accepted a wrong basin at 0.95-0.99 (NCC:
# convergence.py none σ 16 86 % against 96 % coarse first; runtime.py clean 96 %
# against 99 %) and ran both starts on most calls (runtime.py clean: a median of
# 33 evaluations, 18 with the coarse refinement first).
_SURE_QUALITY = 0.99
# align's two refinements of the start settle the call where they agree (within
# _AGREE_PX) on a quality of at least this: on real photo pairs and under
# noise a right match's quality is 0.2-0.8 (benchmarks/results/runtime_cases.md),
# and the quick searches ran on most such calls (runtime.py's real pairs, MI: a
# median of 351 evaluations, 42 with this floor, the same 76 % success).  Where
# both land in one wrong basin its quality was lower (convergence.py, 6
# conditions × σ 2-20 × 50, MI, NCC and SSD, 2026-11-28: 0.02-0.05 MI, 0.30
# NCC, shading σ 20); 0.35 loses none of those trials, 0.2 that NCC one.
_STARTS_AGREE_QUALITY = 0.35
# A start's refinement that moved further than this (u, about pixels) is
# accepted under that margin only where the coarser start confirms it.
_NEAR_PX = 8.0
# The wide searches (retry, recovery) and align's quick search draw other swarm streams.
_WIDE_SEED, _QUICK_SEED = 0x5BD1E995, 0x27D4EB2F


def baseline(context: problems.Context, pyramid: list, knobs: problems.Knobs,
             config) -> problems.Candidate:
  """`config.method`'s gradient registration from the start (unbatched); `pyramid` the template's dense levels."""
  problem = problems.Problem(context, knobs, config)
  ranges = problem.ranges(0)

  def loss_at(level, h, patch, mask):
    template = pyramid[level]
    if config.similarity == "mi":
      weights = jnp.moveaxis(measures.bin_weights(template, config.bins, ranges.template), -2, -1)
      value = -similarity.mi(similarity.SoftBins(weights, ranges.image[0], ranges.image[1]), patch,
                             mask, min_valid=config.min_valid)
    elif config.similarity == "ncc":
      value = -similarity.ncc(template, patch, mask, min_valid=config.min_valid)
    else:
      value = similarity.ssd(template, patch, mask, min_valid=config.min_valid)
    return jnp.where(motion.admissible(h, template.shape), value, jnp.inf)

  u, _, iterations, evaluations = baselines.register(
      config.method, context.image, pyramid, lambda v: problem.homography(v, 0), problem.dim,
      loss_at, similarity=config.similarity, levels=config.levels,
      iterations=config.max_iterations)
  return problem.finish(u, 0, iterations, evaluations - 1)


def better(first: problems.Candidate, second: problems.Candidate) -> problems.Candidate:
  """Per element the candidate of lower loss (the first on ties), counting both searches."""
  best = batching.select(first.loss <= second.loss, first, second)
  return best._replace(num_iterations=first.num_iterations + second.num_iterations,
                       num_evaluations=first.num_evaluations + second.num_evaluations)


# ------------------------------------------------------------------- stages
@dataclasses.dataclass(frozen=True)
class Stage:
  """One stage: an optional swarm, then Gauss–Newton from `top` down, then the check.

  Attributes:
    swarm: run the swarm first (else start from u = 0).
    quick: one swarm of `quick_iterations` iterations (align's quick search).
    finer: the swarm searches one level finer than the coarsest.
    finer_if_disputed: the swarm searches one level finer where the best
      so far is not `confirmed` (the previous search disagreed with it).
    wide: `recovery_scale` swarms of `recovery_scale` × the iterations,
      other seeds (track's recovery); with `retry`, `retry_scale` (align's
      retry).
    retry: a wide search scaled by `Knobs.retry_scale`.
    widen: the wide search's box is also `recovery_scale` × the radius.
    translation: the swarm searches the 2-D translation only.
    settle: Gauss–Newton ends above full resolution where a level's
      estimate comes within this many pixels of the best so far, and the
      best stands for the stage's estimate (`Problem.descend`; 0: never).
    top: Gauss–Newton's first level: 0 level 1 (refining the start alone:
      the coarser levels' optimum can be a wrong one near a start already in
      the right basin), 1 the coarsest, 2 the swarm's.
    base: 0 the start, 1 the last good estimate (`problem.Context.bases`).
  """
  swarm: bool = False
  quick: bool = False
  finer: bool = False
  finer_if_disputed: bool = False
  wide: bool = False
  retry: bool = False
  widen: bool = False
  translation: bool = False
  settle: float = 0.0
  top: int = 0
  base: int = 0


ALIGN = (Stage(top=1), Stage(settle=_AGREE_PX), Stage(swarm=True, quick=True, top=2),
         Stage(swarm=True, quick=True, finer_if_disputed=True, top=2), Stage(swarm=True, top=2),
         Stage(swarm=True, finer=True, wide=True, retry=True, top=2))
"""`align`'s stages: the start refined from the coarsest level (accepted alone from
`_SURE_QUALITY`), then from level 1 (accepted also where the two agree; it stops at level 1 where
it reaches the first's estimate, which stands: runtime.py's real pairs, MI's median 17.5 ms
instead of 20.2, benchmarks/results/runtime_settle.md), a quick search and a second one (other
seeds; one level finer where the first disagreed with the starts' best), the search, the retry
one level finer (run again with other seeds, up to `TrackConfig.retries` times, while it
disagrees with the best)."""
_COARSE_START, _FINE_START, _QUICK, _QUICK_AGAIN, _SEARCH, _RETRY = range(len(ALIGN))
TRACK = (Stage(), Stage(top=1), Stage(swarm=True, quick=True, top=2),
         Stage(swarm=True, quick=True, top=2), Stage(swarm=True, top=2), Stage(base=1),
         Stage(swarm=True, wide=True, widen=True, translation=True, top=2, base=1))
"""`track`'s stages: the start, a coarser start, a quick search and a second one (other seeds),
the search, then the recovery from the last good estimate.  The second quick search: at a jump
the first one misses now and then (tracking.py, 4 sequences × 8 keys: 3 of 64 jump frames), and
the full search then cost 1 690 evaluations, 22 ms against a 2 ms median frame; a second quick
one finds them (about 670)."""
(_T_START, _T_COARSER, _T_QUICK, _T_QUICK_AGAIN, _T_SEARCH, _T_RECOVERY_START,
 _T_RECOVERY) = range(len(TRACK))


class State(NamedTuple):
  """The stage loop's state (leading batch axis C).

  Attributes:
    stage: (C,) int32 the next stage (len(stages): done).
    best: `problem.Candidate` the best so far.
    anchor: `problem.Candidate` track: the recovery's (align does not use it).
    recovered: (C,) bool: track's recovery ran.
    searched: (C,) bool: a swarm ran.
    retries: (C,) int32 align's retries run.
    spent: (C,) int32 the evaluations of every stage run so far.
    exhausted: (C,) bool: `Knobs.max_evaluations` ended the stages early.
    seen: (C, _SEEN, 3, 3) each stage's estimate (homography), for
      `_seen_and_votes`.
    num_seen: (C,) int32 how many of `seen` are filled.
  """
  stage: jax.Array
  best: problems.Candidate
  anchor: problems.Candidate
  recovered: jax.Array
  searched: jax.Array
  retries: jax.Array
  spent: jax.Array
  exhausted: jax.Array
  seen: jax.Array
  num_seen: jax.Array


def _budgeted(state: State, following, found: problems.Candidate, knobs, done: int) -> tuple:
  """(following stage, spent, exhausted): done where the evaluations spent reach the budget."""
  spent = state.spent + jnp.where(state.stage < done, found.num_evaluations, 0)
  over = (following < done) & (spent >= knobs.max_evaluations)
  return jnp.where(over, done, following), spent, state.exhausted | over


def _column(stages, name: str, index):
  return jnp.asarray([getattr(s, name) for s in stages])[index]


def _pass(contexts: problems.Context, state: State, knobs: problems.Knobs, stages, config,
          swarm: bool) -> problems.Candidate:
  """One pass of the stage loop's body for every element: its stage's swarm, Gauss–Newton, the check.

  `swarm` (static) False leaves the swarm out of the program (the first stage has none).
  """
  stage = jnp.minimum(state.stage, len(stages) - 1)
  coarsest = contexts.template.levels - 1
  # A second quick search one level finer where the first disagreed with the
  # starts' best: the coarsest level can blur the match's basin away, and a
  # search there again with other seeds tends to miss it again (convergence.py,
  # no change, σ 20, trial 49: the quick searches, the search and two retries
  # 21.6 px off at 0.47, 12 344 evaluations; one level finer the second quick
  # search finds it at 1.000, 667 in all).  Where the first agreed (a
  # confirmation under noise) the cheaper coarsest level stays.
  finer = (_column(stages, "finer", stage)
           | (_column(stages, "finer_if_disputed", stage) & ~state.best.confirmed))
  swarm_level = jnp.maximum(coarsest - finer, 0)
  top = jnp.select([_column(stages, "top", stage) == 0, _column(stages, "top", stage) == 1],
                   [jnp.minimum(1, coarsest), coarsest], swarm_level)
  base = _column(stages, "base", stage)
  if any(s.base for s in stages):
    contexts = with_range(contexts, (state.stage < len(stages)) & (base == 1), config)
  count = state.stage.shape[0]
  dim = motion.dimension(config.motion, config.dof)
  zero = jnp.zeros(count, jnp.int32)
  u, iterations, evaluations = jnp.zeros((count, dim), jnp.float32), zero, zero
  if swarm:
    wide, quick = _column(stages, "wide", stage), _column(stages, "quick", stage)
    scale = jnp.where(wide, jnp.where(_column(stages, "retry", stage), knobs.retry_scale,
                                      knobs.recovery_scale), 1)
    iterations = jnp.where(quick, knobs.quick_iterations, knobs.max_iterations * scale)
    radius = knobs.search_radius * jnp.where(wide & _column(stages, "widen", stage), scale, 1)
    stream = jnp.uint32(_WIDE_SEED) * (state.retries.astype(jnp.uint32) + 1)
    quick_stream = jnp.uint32(_QUICK_SEED) * (stage.astype(jnp.uint32) + 1)
    stream = jnp.where(wide, stream, jnp.where(quick, quick_stream, jnp.uint32(0)))
    seeds = contexts.seed ^ stream[:, None]
    needed = (state.stage < len(stages)) & _column(stages, "swarm", stage)

    def search(_):
      def one(context, base, seed, level, radius, iterations, scale, translation):
        return problems.Problem(context, knobs, config).swarm(
            base, seed, level, radius, iterations, scale, translation)
      found = batching.each(one, contexts, base, seeds, swarm_level, radius, iterations, scale,
                            _column(stages, "translation", stage))
      return jax.tree.map(lambda a, b: jnp.where(needed.reshape((-1,) + (1,) * (a.ndim - 1)),
                                                 a, b), found, (u, zero, zero))

    u, iterations, evaluations = jax.lax.cond(jnp.any(needed), search, lambda _: (u, zero, zero),
                                              None)

  def refine_and_check(context, u, base, top, iterations, evaluations, best, settle):
    problem = problems.Problem(context, knobs, config)
    u, steps, settled = problem.descend(
        u, base, top, None if best is None else (best.homography, settle))
    found = problem.finish(u, base, iterations + steps, evaluations + steps)
    if best is None:
      return found
    # Settled: the best so far, refined at full resolution, is this stage's estimate too.
    return batching.select(settled, best._replace(num_iterations=found.num_iterations,
                                                  num_evaluations=found.num_evaluations), found)

  best = state.best if any(s.settle for s in stages) else None  # static: a settling stage
  return batching.each(refine_and_check, contexts, u, base, top, iterations, evaluations, best,
                       _column(stages, "settle", stage))


def _starts(state: State, found: problems.Candidate, contexts: problems.Context, knobs):
  """(the merged candidate, the starts' best, whether a second start follows a short first one).

  `better(state.best, found)`, and at stage 0 `found` alone; Gauss–Newton from
  the coarsest level differs from the start's (level 1) with more than two levels.
  """
  merged = better(state.best, found)
  start = batching.select(state.stage == 0, found, merged)
  second_start = jnp.isfinite(knobs.accept_quality) & (contexts.template.levels > 2)
  return merged, start, second_start


def _agrees(first: problems.Candidate, second: problems.Candidate,
            contexts: problems.Context) -> jax.Array:
  """(C,) bool: the two candidates' homographies agree within _AGREE_PX (`motion.corner_gap`)."""
  return jax.vmap(motion.corner_gap)(first.homography, second.homography,
                                     contexts.template.size) <= _AGREE_PX


def _seen_and_votes(state: State, found: problems.Candidate, best: problems.Candidate,
                    contexts: problems.Context, within: float = _AGREE_PX) -> tuple:
  """(seen, num_seen, votes (C,) int32): `found` recorded, and how many of the recorded
  estimates agree with `best` within `within` pixels (`motion.corner_gap`)."""
  slot = jnp.minimum(state.num_seen, _SEEN - 1)
  seen = state.seen.at[jnp.arange(slot.shape[0]), slot].set(found.homography)
  count = state.num_seen + 1
  gaps = jax.vmap(jax.vmap(motion.corner_gap, (0, None, None)))(seen, best.homography,
                                                                contexts.template.size)
  agree = (jnp.arange(_SEEN)[None] < jnp.minimum(count, _SEEN)[:, None]) & (gaps <= within)
  return seen, count, jnp.sum(agree, axis=1, dtype=jnp.int32)


def _advance_align(state: State, found: problems.Candidate, contexts: problems.Context,
                   knobs: problems.Knobs) -> State:
  """align's transitions: accepted start → done; else the start refined from level 1, quick
  searches, search, retry.

  After the starts, `state.best` is the better of the start's refinements: the first quick
  search is compared with it, and every later search with the best so far.
  """
  stage, done = state.stage, len(ALIGN)
  starting = stage <= _FINE_START
  merged, start, second_start = _starts(state, found, contexts, knobs)
  agree = _agrees(found, state.best, contexts)
  # The two refinements of the start confirm each other where they agree on a
  # match of at least _STARTS_AGREE_QUALITY (noise and a real change of
  # appearance lower a right alignment's quality under accept_quality, and
  # the swarm would run for nothing).
  bar = jnp.where((stage == _COARSE_START) & second_start,
                  jnp.maximum(knobs.accept_quality, _SURE_QUALITY), knobs.accept_quality)
  accepted = ((start.quality >= bar)
              | ((stage == _FINE_START) & agree & (start.quality >= _STARTS_AGREE_QUALITY)))
  searched = better(found, state.best)._replace(confirmed=agree)
  seen, num_seen, votes = _seen_and_votes(state, found, batching.select(
      stage <= _SEARCH, searched, merged), contexts, _ALIGN_VOTE_PX)
  # A search that agrees with the best so far confirms it alone only on a
  # quality of at least _MIN_REFERENCE: in 8 iterations the swarm can stay in
  # the start's wrong basin (Baker–Matthews, shading, σ 8: 3.6 px off at
  # 0.65), and the full search in a quick one's (gamma, σ 20: 22 px off at
  # 0.70); _VOTES agreeing estimates confirm it at any quality.
  settled = ((searched.quality >= knobs.retry_quality)
             | (agree & (searched.quality >= _MIN_REFERENCE)) | (votes >= _VOTES))
  # Where the best after the quick searches (and after the full search)
  # stays under hopeless_quality, the image holds no match for the
  # similarity (NCC on an inverted image): no full search and no retry
  # (`config.HOPELESS_QUALITY`).
  ended = settled | (searched.quality < knobs.hopeless_quality)
  again = ((stage == _RETRY) & (merged.quality < knobs.retry_quality) & ~agree
           & (votes < _VOTES) & (state.retries < knobs.retries))
  best = batching.select(starting, start._replace(confirmed=accepted),
                         batching.select(stage <= _SEARCH, searched, merged))
  search = jnp.where(knobs.quick_iterations > 0, _QUICK, _SEARCH)
  following = jnp.select(
      [stage == _COARSE_START, stage == _FINE_START, stage == _QUICK, stage == _QUICK_AGAIN,
       stage == _SEARCH],
      [jnp.where(accepted, done, jnp.where(second_start, _FINE_START, search)),
       jnp.where(accepted, done, search), jnp.where(settled, done, _QUICK_AGAIN),
       jnp.where(ended, done, _SEARCH), jnp.where(ended, done, _RETRY)],
      jnp.where(again, _RETRY, done))
  following, spent, exhausted = _budgeted(state, following, found, knobs, done)
  return State(following, best, state.anchor, state.recovered,
               state.searched | (stage >= _QUICK), state.retries + (stage == _RETRY), spent,
               exhausted, seen, num_seen)


def _advance_track(state: State, found: problems.Candidate, contexts: problems.Context,
                   knobs: problems.Knobs) -> State:
  """track's transitions: accepted start → done; else coarser start, quick search, search; short
  of `lost_quality`: recovery."""
  stage, done = state.stage, len(TRACK)
  # Also accepted: within _REFERENCE_MARGIN of the quality the region's last
  # search reached (noise and blur lower the right alignment's quality too),
  # unless that was under _MIN_REFERENCE (low texture: too uncertain).
  reference = contexts.reference
  merged, start, second_start = _starts(state, found, contexts, knobs)
  searched = better(found, state.best)
  quick = (stage == _T_QUICK) | (stage == _T_QUICK_AGAIN)
  quality = jnp.select([stage <= _T_COARSER, quick], [start.quality, searched.quality],
                       found.quality)  # the starts', the quick searches' or the recovery's
  steady = quality >= reference - _REFERENCE_MARGIN
  accepted = (quality >= knobs.accept_quality) | ((reference >= _MIN_REFERENCE) & steady)
  # A start that moved more than _NEAR_PX to a quality under the reference's
  # margin is accepted only where the coarser start agrees with it
  # (challenges.py, unconstrained, NCC: a shake's first frame, blurred along
  # 11.5 px; the start moved 25 px to 0.965, 6 px off, under the region's
  # 0.99; the coarser start found 0.975 at 0.8 px).
  far = ((jnp.max(jnp.abs(start.u), axis=-1) > _NEAR_PX) & ~steady
         & (reference >= _MIN_REFERENCE))
  agree = _agrees(found, state.best, contexts)
  accepted = accepted & ~((stage <= _T_COARSER) & far & ~((stage == _T_COARSER) & agree))
  # A quick search settles a frame as align's searches do, if the match is
  # not lost: _VOTES of the starts' two refinements and the quick searches
  # agreeing, or a quick search agreeing with the best so far on a
  # quality of at least _MIN_REFERENCE, spare the full search on a frame the
  # start alone did not settle (a jump, blur, the first frames before a
  # search set the reference; video.py's grass and gravel: the start 6-7 px
  # off, the coarser start and the quick search on one match at 0.87-0.91
  # under the region's 0.90-0.93, the full search 1 330 evaluations, 10-13×
  # the clip's median frame time, to find it again).
  seen, num_seen, votes = _seen_and_votes(state, found, searched, contexts)
  confirmed = (votes >= _VOTES) | (agree & (searched.quality >= _MIN_REFERENCE))
  quick_done = accepted | (confirmed & (searched.quality >= knobs.lost_quality))
  recovered = better(found, state.anchor)
  best = batching.select(stage <= _T_COARSER, start, batching.select(
      stage <= _T_SEARCH, searched, batching.select(
          stage == _T_RECOVERY_START, batching.select(accepted, merged, state.best),
          better(state.best, recovered))))
  search = jnp.where(knobs.quick_iterations > 0, _T_QUICK, _T_SEARCH)
  following = jnp.select(
      [stage == _T_START, stage == _T_COARSER, stage == _T_QUICK, stage == _T_QUICK_AGAIN,
       stage == _T_SEARCH, stage == _T_RECOVERY_START],
      [jnp.where(accepted, done, jnp.where(second_start, _T_COARSER, search)),
       jnp.where(accepted, done, search), jnp.where(quick_done, done, _T_QUICK_AGAIN),
       jnp.where(quick_done, done, _T_SEARCH),
       jnp.where(searched.quality >= knobs.lost_quality, done, _T_RECOVERY_START),
       jnp.where(accepted, done, _T_RECOVERY)], done)
  following, spent, exhausted = _budgeted(state, following, found, knobs, done)
  return State(following, best,
               batching.select(stage == _T_RECOVERY_START, found, state.anchor),
               state.recovered | (stage == _T_RECOVERY_START),
               state.searched | quick | (stage == _T_SEARCH) | (stage == _T_RECOVERY),
               state.retries, spent, exhausted, seen, num_seen)


PIPELINES = {"align": (ALIGN, _advance_align), "track": (TRACK, _advance_track)}


def _initial(count: int, config) -> State:
  """Stage 0 for `count` elements, with placeholder candidates."""
  dim = motion.dimension(config.motion, config.dof)
  zero = jnp.zeros(count, jnp.int32)
  none = problems.Candidate(u=jnp.zeros((count, dim), jnp.float32),
                            homography=jnp.broadcast_to(jnp.eye(3, dtype=jnp.float32),
                                                        (count, 3, 3)),
                            loss=jnp.full(count, jnp.inf, jnp.float32),
                            quality=jnp.full(count, -jnp.inf, jnp.float32),
                            confirmed=jnp.zeros(count, bool), base=zero, num_iterations=zero,
                            num_evaluations=zero)
  return State(zero, none, none, jnp.zeros(count, bool), jnp.zeros(count, bool), zero, zero,
               jnp.zeros(count, bool), jnp.zeros((count, _SEEN, 3, 3), jnp.float32), zero)


def _loop(contexts: problems.Context, state: State, knobs: problems.Knobs, pipeline: str,
          config) -> State:
  """The stage loop until every element is done."""
  stages, advance = PIPELINES[pipeline]

  def body(state):
    return advance(state, _pass(contexts, state, knobs, stages, config, swarm=True), contexts,
                   knobs)

  return jax.lax.while_loop(lambda s: jnp.any(s.stage < len(stages)), body, state)


def run(contexts: problems.Context, knobs: problems.Knobs, pipeline: str, config) -> State:
  """The stages of `pipeline` ("align" or "track") for a batch of registrations (leading axis R, static).

  A batch of one runs the stage loop alone, and so does every element of a
  batch on a CPU (`batching.each`: one after another, the lone element's
  computation).  On an accelerator the first stage runs for every element
  at once, then the loop only for the elements it left short
  (`batching.where_needed`), a few at a time.
  """
  count = contexts.seed.shape[0]
  if count == 1 or config.method != "pso":
    return _loop(contexts, _initial(count, config), knobs, pipeline, config)
  if batching.one_at_a_time():
    return batching.each(
        lambda context: jax.tree.map(lambda a: a[0], _loop(
            batching.as_batch(context), _initial(1, config), knobs, pipeline, config)), contexts)
  stages, advance = PIPELINES[pipeline]
  state = _initial(count, config)
  state = advance(state, _pass(contexts, state, knobs, stages, config, swarm=False), contexts,
                  knobs)
  return batching.where_needed(
      state.stage < len(stages),
      lambda indices: _loop(batching.take(contexts, indices), batching.take(state, indices), knobs,
                            pipeline, config), state)


# ---------------------------------------------------------------- contexts
def image_range(context: problems.Context, base, config) -> jax.Array:
  """(2,) MI binning range: the template's and the image's where base `base` puts it."""
  problem = problems.Problem(context, None, config)
  points, _, inside = problem._chunk(templates.FULL, 0, config.resolution)
  h = problem.homography(jnp.zeros(problem.dim, jnp.float32), base)
  values, valid = atlas.level(context.image, 0).sample(h, points)
  lo, hi = measures.intensity_range(values, valid & inside)
  return jnp.stack([jnp.minimum(lo, context.template_range[0]),
                    jnp.maximum(hi, context.template_range[1])])


def context(image: atlas.Atlas, template: templates.Template, bases, geometry, seed,
            config) -> problems.Context:
  """One registration's `problem.Context`."""
  self_loss = template.self_loss[templates.SIMILARITIES.index(config.similarity)]
  template_range = template.value_range
  quads = jnp.zeros((2, 4, 2), jnp.float32)
  if config.motion == "homography":
    quads = homography.apply_to_points(bases, motion.corners(template.size))[0]
  made = problems.Context(image, template, bases, geometry, quads, template_range,
                          jnp.zeros((2, 2), jnp.float32), self_loss, seed, jnp.float32(1.0))
  if config.similarity != "mi":
    return made
  return made._replace(image_ranges=jnp.stack([image_range(made, 0, config)] * 2))


def with_range(contexts: problems.Context, needed, config) -> problems.Context:
  """Batched contexts with the image's MI binning range at base 1 computed where `needed` (C,)."""
  if config.similarity != "mi":
    return contexts

  def compute(contexts):
    ranges = batching.each(lambda c: image_range(c, 1, config), contexts)
    return contexts._replace(image_ranges=contexts.image_ranges.at[:, 1].set(ranges))

  return jax.lax.cond(jnp.any(needed), compute, lambda c: c, contexts)
