"""Stopping rules for `align`'s stages, replayed on recorded traces.

A rule that ends `align`'s stages sooner changes only where the stage loop
stops, not what a stage finds: every stage's swarm draws its own seed. So a
rule can be judged exactly, without rerunning anything, on a record of
every stage of runs that go to their usual end.

Recording: the align transition (`register.PIPELINES["align"]`) is wrapped
in a `jax.debug.callback`. The compilation cache is off, so that the
wrapped program is the one compiled. For each stage the record holds the
stage, its estimate (homography and full-resolution quality), the best so
far and the evaluations spent. Two sets of trials are recorded:
  * convergence.py's (6 conditions × σ 2–20, `--trials` each): the
    committed seeds, and the same count on other seeds (`--holdout`
    offset); a rule chosen on the first set is checked on the second;
  * runtime.py's cases (6 cases × `--cases` trials).

Replaying: a trial stops after the first stage where the rule holds, and
keeps the best so far. `RULES` holds the rules as built, a test of the
best's quality against the other estimates' ("a peak clear of its
rivals") after the full search, two agreeing estimates at the first quick
search with the third far below (by a margin, or by a ratio), giving up
below a quality after the first or both quick searches, and smaller
evaluation budgets than the default 20 000
(`TrackConfig.max_evaluations`). Per rule the report gives the convergence trials lost and
gained against the recorded end (each set), and per runtime case the
success and median / p90 / p99 / max evaluations. Evaluations are
deterministic, so no timing is needed.

Writes results/stopping_rules.{json,md}.

Usage: python benchmarks/stopping_rules.py [--similarities mi,ncc] [--trials 100]
  [--holdout 1000] [--cases 100]
"""

from __future__ import annotations

import argparse
import os

os.environ["JAXPSO_CACHE_DIR"] = "off"  # the wrapped transition must be compiled, not loaded

import jax
import numpy as np

import common
import convergence
import jaxpso
import runtime
from jaxpso._src import align as aligning
from jaxpso._src import register

SIGMAS = (2, 4, 8, 12, 16, 20)
VOTE_PX = register._ALIGN_VOTE_PX  # align counts a vote within this many pixels
_SQUARE = np.c_[convergence.SOURCE, np.ones(4)]  # the 100×100 template's corners, homogeneous
_LOG: list = []


def _record(*values):
  _LOG.append(tuple(np.asarray(v) for v in values))


def _recording():
  """Wraps align's transition so that every stage of a lone alignment is appended to _LOG."""
  stages, advance = register.PIPELINES["align"]

  def recorded(state, found, contexts, knobs):
    after = advance(state, found, contexts, knobs)
    jax.debug.callback(_record, state.stage[0], found.quality[0], found.homography[0],
                       after.best.quality[0], after.best.homography[0], found.num_evaluations[0])
    return after

  register.PIPELINES["align"] = (stages, recorded)


def corner_gap(first, second) -> float:
  """The largest distance between the 100×100 template's corners under two homographies."""
  a, b = _SQUARE @ first.T, _SQUARE @ second.T
  return float(np.max(np.linalg.norm(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:], axis=1)))


def trace(image, template, start, key, config, error) -> dict | None:
  """One alignment's stages: (stage, quality, homography, best quality, best error, evaluations)."""
  _LOG.clear()
  try:
    result = jax.block_until_ready(jaxpso.align(image, template, start, config=config, key=key))
  except ValueError:  # a start the horizon cuts (convergence.py counts it a failure)
    return None
  jax.effects_barrier()  # every stage's callback has run
  x, y, _, _ = aligning._window(np.asarray(start, np.float64), template.shape, image.shape,
                                config.for_template(template.shape))
  shift = np.array([[1, 0, x], [0, 1, y], [0, 0, 1]], np.float64)
  stages = [(int(s), float(q), shift @ h.astype(np.float64), float(bq),
             error(shift @ bh.astype(np.float64)), int(e)) for s, q, h, bq, bh, e in _LOG]
  if sum(stage[5] for stage in stages) != int(result.num_evaluations):
    raise RuntimeError("the recorded stages do not add up to the call's evaluations")
  return {"stages": stages, "error": error(np.asarray(result.homography, np.float64)),
          "evaluations": int(result.num_evaluations)}


def record(similarity: str, trials: int, holdout: int, cases: int) -> dict:
  """{"convergence": [set][trial], "cases": {case: [trial]}} traces of `similarity`."""
  config = jaxpso.TrackConfig(similarity=similarity)
  images = {n: jaxpso.data.load_image(n) for n in ("camera", "brick")}
  sets = []
  for offset in (0, holdout):
    rows = []
    for condition in convergence.CONDITIONS:
      for sigma in SIGMAS:
        for i, origin, image, template, start in convergence.trial_images(
            images, condition, sigma, trials, offset):
          row = trace(image, template, start, i, config,
                      lambda h, o=origin: common.corner_error(h, o))
          if row is not None:
            rows.append(dict(row, cell=(condition, sigma)))
    sets.append(rows)
  photos = [common.photo(name) for name in common.PHOTOS]
  by_case = {}
  for case in ("clean", "gamma", "shading", "noise", "inverted", "real_pairs"):
    rows = [trace(image, template, start, 0, config, lambda h, t=truth: runtime._corner_rms(h, t))
            for image, template, start, truth in runtime.case_trials(case, photos, cases)]
    by_case[case] = [row for row in rows if row is not None]
  return {"convergence": sets, "cases": by_case}


# -------------------------------------------------------------------- rules
def _best_and_rival(stages):
  """(best quality, votes within VOTE_PX of the best estimate, the best rival's quality)."""
  best = max(range(len(stages)), key=lambda k: stages[k][1])
  gaps = [corner_gap(s[2], stages[best][2]) for s in stages]
  rivals = [s[1] for s, g in zip(stages, gaps) if g > VOTE_PX]
  return stages[best][1], sum(g <= VOTE_PX for g in gaps), max(rivals, default=-np.inf)


def clear_peak(margin: float, floor: float = 0.5):
  """After the full search: the best at least `floor`, every rival `margin` under it."""
  def rule(stages):
    best, _, rival = _best_and_rival(stages)
    return stages[-1][0] >= register._SEARCH and best >= floor and best - rival >= margin
  return rule


def two_votes_at_quick(margin: float):
  """At the first quick search: two estimates agree on the best, the other `margin` under it."""
  def rule(stages):
    best, votes, rival = _best_and_rival(stages)
    return (stages[-1][0] == register._QUICK and len(stages) == 3 and votes >= 2
            and best - rival >= margin)
  return rule


def clear_peak_at_quick(ratio: float):
  """At the first quick search: it agrees with the starts' best (within `register._AGREE_PX`), the
  best at least `register._STARTS_AGREE_QUALITY`, every estimate elsewhere under `ratio` × its
  quality."""
  def rule(stages):
    if stages[-1][0] != register._QUICK or len(stages) != 3:
      return False
    starts = max(stages[:2], key=lambda s: s[1])
    best, _, rival = _best_and_rival(stages)
    return (corner_gap(stages[2][2], starts[2]) <= register._AGREE_PX
            and best >= register._STARTS_AGREE_QUALITY and rival < ratio * best)
  return rule


def hopeless_after(stage: int, quality: float):
  """After `stage` (the first or the second quick search): the best under `quality` (no later
  quick search, no full search)."""
  return lambda stages: stages[-1][0] == stage and stages[-1][3] < quality


def budget(evaluations: int):
  """`TrackConfig.max_evaluations` = `evaluations`: no stage starts once that many are spent."""
  return lambda stages: sum(stage[5] for stage in stages) >= evaluations


RULES = {
    "as built": lambda stages: False,
    "clear peak after the search, margin 0.10": clear_peak(0.10),
    "clear peak after the search, margin 0.15": clear_peak(0.15),
    "two votes at the first quick search, third 0.30 under": two_votes_at_quick(0.30),
    "two votes at the first quick search, third 0.45 under": two_votes_at_quick(0.45),
    "the first quick search agrees with the starts' best, every other estimate under 0.3 × it":
        clear_peak_at_quick(0.3),
    "the first quick search agrees with the starts' best, every other estimate under 0.5 × it":
        clear_peak_at_quick(0.5),
    "give up under 0.3 after the quick searches": hopeless_after(register._QUICK_AGAIN, 0.3),
    **{f"give up under {q} after the first quick search": hopeless_after(register._QUICK, q)
       for q in (0.2, 0.3)},
    **{f"a budget of {b} evaluations": budget(b) for b in (4000, 8000, 12000)},
}


def replay(row: dict, rule) -> tuple[float, int]:
  """(error, evaluations) of one trace stopped where `rule` first holds."""
  spent = 0
  for k, stage in enumerate(row["stages"]):
    spent += stage[5]
    if k < len(row["stages"]) - 1 and rule(row["stages"][:k + 1]):
      return stage[4], spent
  return row["error"], row["evaluations"]


def summarise(traces: dict, rule) -> dict:
  """Convergence trials lost / gained (each set) and per case success and evaluations."""
  out = {"lost": [], "gained": []}
  for rows in traces["convergence"]:
    ends = [replay(row, rule)[0] for row in rows]
    out["lost"].append(sum(r["error"] <= 1 < e for r, e in zip(rows, ends)))
    out["gained"].append(sum(e <= 1 < r["error"] for r, e in zip(rows, ends)))
  out["cases"] = {}
  for case, rows in traces["cases"].items():
    ends = np.array([replay(row, rule) for row in rows], np.float64)
    out["cases"][case] = {"success": float(np.mean(ends[:, 0] <= 1)),
                          **{name: float(np.percentile(ends[:, 1], q)) for name, q in
                             (("median", 50), ("p90", 90), ("p99", 99), ("max", 100))}}
  return out


def markdown(results: dict, info: dict, args) -> str:
  lines = [
      "# Stopping rules for align, replayed on recorded stage traces", "",
      common.machine_line(info), "",
      f"Convergence: convergence.py's trials, {args.trials} per condition and σ, on the committed "
      f"seeds and on seeds offset by {args.holdout}; lost / gained: trials within 1 px at the "
      "recorded end and not at the rule's end, or the reverse.  Cases: runtime.py's, "
      f"{args.cases} trials each; success within 1 px, then evaluations at the 50th / 90th / "
      "99th percentile and the max.  See the script's docstring.", ""]
  for similarity, rules in results.items():
    cases = list(next(iter(rules.values()))["cases"])
    lines += [f"## {similarity.upper()}", "",
              "| rule | lost (seeds / other seeds) | gained (same) | "
              + " | ".join(cases) + " |",
              "|---|---|---|" + "---|" * len(cases)]
    for name, row in rules.items():
      cells = [f"{c['success']:.0%}, {c['median']:.0f} / {c['p90']:.0f} / {c['p99']:.0f} / "
               f"{c['max']:.0f}" for c in row["cases"].values()]
      lines.append(f"| {name} | {row['lost'][0]} / {row['lost'][1]} | "
                   f"{row['gained'][0]} / {row['gained'][1]} | " + " | ".join(cells) + " |")
    lines.append("")
  return "\n".join(lines)


def main():
  parser = argparse.ArgumentParser(description=__doc__,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
  parser.add_argument("--similarities", default="mi,ncc")
  parser.add_argument("--trials", type=int, default=100, help="convergence trials per σ, condition")
  parser.add_argument("--holdout", type=int, default=1000, help="seed offset of the second set")
  parser.add_argument("--cases", type=int, default=100, help="runtime.py trials per case")
  args = parser.parse_args()
  _recording()
  results = {}
  for similarity in args.similarities.split(","):
    traces = record(similarity, args.trials, args.holdout, args.cases)
    results[similarity] = {name: summarise(traces, rule) for name, rule in RULES.items()}
    print(similarity, {name: (r["lost"], r["gained"]) for name, r in results[similarity].items()},
          flush=True)
  info = common.machine()
  common.write("stopping_rules", {"machine": info, "results": results},
               markdown(results, info, args))


if __name__ == "__main__":
  main()
