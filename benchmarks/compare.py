"""Two runs of one benchmark side by side: before and after a change, the same trials.

`python benchmarks/compare.py NAME BEFORE.json AFTER.json [--label TEXT]`
reads two results files of benchmark NAME ("convergence", "tracking" or
"batch", written by those scripts into results/) and appends a markdown
table of their rows, matched by the rows' keys, to results/NAME_before_after.md.
"""

from __future__ import annotations

import argparse
import json
import os

HERE = os.path.dirname(os.path.abspath(__file__))

# name → (the keys matching rows, [(column title, field, format)])
SCHEMAS = {
    "convergence": (("condition", "method", "sigma"),
                    [("success", "success", "{:.0%}"), ("median error px", "median_error_px", "{:.2f}"),
                     ("median ms", "median_ms", "{:.1f}")]),
    "tracking": (("seed", "case"),
                 [("within 5 px", "within_5px", "{:.1%}"), ("median px", "median_error_px", "{:.2f}"),
                  ("max px", "max_error_px", "{:.1f}"), ("lost", "lost", "{}"),
                  ("ms/frame", "ms_per_frame", "{:.1f}")]),
    "batch": (("batch",),
              [("t·f/s", "templates_frames_per_s", "{:.0f}"), ("within 2 px", "within_2px", "{:.1%}"),
               ("lost", "lost", "{}"), ("regions × frames swarmed", "swarm_regions", "{:.1%}")]),
}


def table(name: str, before: dict, after: dict) -> list[str]:
  keys, columns = SCHEMAS[name]
  index = {tuple(row[k] for k in keys): row for row in before["rows"]}
  head = " | ".join(keys) + " | " + " | ".join(f"{title} before | after" for title, *_ in columns)
  lines = [f"| {head} |", "|" + "---|" * (len(keys) + 2 * len(columns))]
  for row in after["rows"]:
    old = index.get(tuple(row[k] for k in keys))
    cells = [str(row[k]) for k in keys]
    for _, field, fmt in columns:
      cells.append(fmt.format(old[field]) if old is not None and field in old else "–")
      cells.append(fmt.format(row[field]))
    lines.append("| " + " | ".join(cells) + " |")
  return lines


def main():
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("name", choices=sorted(SCHEMAS))
  parser.add_argument("before")
  parser.add_argument("after")
  parser.add_argument("--label", default="", help="what the two runs are (one line above the table)")
  args = parser.parse_args()
  with open(args.before) as f:
    before = json.load(f)
  with open(args.after) as f:
    after = json.load(f)
  machine = after["machine"]
  lines = [f"## {args.label or args.name}", "",
           f"Before: `{before['machine']['command']}` ({before['machine']['date']}); after:"
           f" `{machine['command']}` ({machine['date']}); {machine['cpu']}, {machine['cores']}"
           " cores.", ""] + table(args.name, before, after) + [""]
  path = os.path.join(HERE, "results", f"{args.name}_before_after.md")
  with open(path, "a") as f:
    f.write("\n".join(lines) + "\n")
  print("\n".join(lines))


if __name__ == "__main__":
  main()
