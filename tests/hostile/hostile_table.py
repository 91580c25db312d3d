"""Run the large form of the hostile-input suite and write its table into docs/reference/hostile-inputs.md.

Usage (from the repository root)::

    OMP_NUM_THREADS=1 python tests/hostile/hostile_table.py             # run `pytest -m hostile`, then write
    python tests/hostile/hostile_table.py --results outcomes.jsonl      # only write, from a run's outcomes

The table replaces the text between the ``hostile-table`` markers of the page: per category, the cases, how
many ended in each outcome (see ``hostile_harness``), and the largest peak resident memory and input.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
PAGE = ROOT / "docs" / "reference" / "hostile-inputs.md"
START, END = "<!-- hostile-table:start -->", "<!-- hostile-table:end -->"
ORDER = ["CLI arguments", "checkpoints", "reward models", "nuScenes labels", "map rasters", "ScenarioNet pickles",
         "feedback databases", "HTTP requests"]
COMMAND = "OMP_NUM_THREADS=1 python tests/hostile/hostile_table.py"

sys.path.insert(0, str(HERE))
from hostile_harness import OUTCOMES, PEAK_LIMIT_MB, RESULTS_ENV  # noqa: E402


def run_large_form(results: Path) -> int:
    """``pytest -m hostile tests/hostile`` with every outcome appended to ``results``; returns pytest's exit code."""
    env = {**os.environ, RESULTS_ENV: str(results), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "hostile", str(HERE)]
    return subprocess.run(command, cwd=ROOT, env=env, check=False).returncode


def _size(num_bytes: int) -> str:
    for unit, scale in (("MB", 2**20), ("kB", 2**10)):
        if num_bytes >= scale:
            return f"{num_bytes / scale:.1f} {unit}"
    return f"{num_bytes} B"


def table(rows: list[dict]) -> str:
    """The markdown table of ``rows`` (one per case outcome)."""
    by_category: dict[str, list[dict]] = defaultdict(list)
    for row in rows:
        by_category[row["category"]].append(row)
    names = [c for c in ORDER if c in by_category] + sorted(set(by_category) - set(ORDER))
    header = ["category", "cases", *OUTCOMES, f"over {PEAK_LIMIT_MB} MB", "max peak RSS", "largest input"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for name in names + ["all"]:
        group = rows if name == "all" else by_category[name]
        counts = [sum(r["kind"] == kind for r in group) for kind in OUTCOMES]
        over = sum(r["peak_mb"] >= PEAK_LIMIT_MB for r in group)
        peak = max((r["peak_mb"] for r in group), default=0.0)
        largest = max((r.get("input_bytes", 0) for r in group), default=0)
        cells = [f"**{name}**" if name == "all" else name, str(len(group)), *map(str, counts), str(over),
                 f"{peak:.0f} MB", _size(largest)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_page(rows: list[dict]) -> None:
    """Replace the table between the markers of :data:`PAGE`."""
    text = PAGE.read_text(encoding="utf-8")
    if START not in text or END not in text:
        raise SystemExit(f"{PAGE} has no {START} ... {END} markers")
    before, rest = text.split(START, 1)
    _, after = rest.split(END, 1)
    body = (f"{START}\n\nRegenerate with `{COMMAND}` (the large form, a few minutes on one core).\n\n"
            f"{table(rows)}\n\n{END}")
    PAGE.write_text(before + body + after, encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, help="outcomes (JSON lines) of a finished run; skips the run")
    args = parser.parse_args(argv)
    code = 0
    if args.results is None:
        with tempfile.NamedTemporaryFile(suffix=".jsonl", delete=False) as f:
            results = Path(f.name)
        code = run_large_form(results)
    else:
        results = args.results
    rows = [json.loads(line) for line in results.read_text(encoding="utf-8").splitlines() if line.strip()]
    if not rows:
        raise SystemExit(f"no outcomes in {results}")
    write_page(rows)
    print(table(rows))
    print(f"{len(rows)} cases; table written to {PAGE.relative_to(ROOT)} (pytest exit code {code})")
    return 0 if code in (0, 1) else code


if __name__ == "__main__":
    raise SystemExit(main())
