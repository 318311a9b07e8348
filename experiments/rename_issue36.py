"""Issue 36's renames, so that ``sim`` means one thing (the step's :class:`SimModel`):

* the step's static settings ``SimConfig`` -> ``StepOptions`` (beside ``SimulationConfig``, the
  user's config, the old name read as a synonym);
* the field holding them: ``SimModel.cfg`` -> ``SimModel.options``, ``Setup.sim``,
  ``FitProblem.sim``, ``Sweeper.sim`` -> ``.options``.

Mechanical and idempotent: re-run it after a merge brings in code written with the old names.
A line that contains "issue 36" is left as it is (where the old names are named on purpose).

    python experiments/rename_issue36.py            # rewrite src, tests, experiments, fit, docs (notebook too), README
    python experiments/rename_issue36.py --check    # list the files it would change
"""

from __future__ import annotations

import pathlib
import re
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
TREES = ("src", "tests", "experiments", "fit", "docs", "README.md")
SUFFIXES = {".py", ".md", ".ipynb"}
# objects whose ``.sim`` is the step's options (a Setup, a FitProblem, a Sweeper)
HOLDERS = r"setup|s|self|prob|problem|sweeper|one|hit_setup|bsetup|batch_setup|Setup|FitProblem|Sweeper|BallSweeper"
RULES = [
    (re.compile(r"\bSimConfig\b"), "StepOptions"),
    (re.compile(r"\bsim\.cfg\b"), "sim.options"),
    (re.compile(rf"\b({HOLDERS})\.sim\b(?!\w)"), r"\1.options"),
    (re.compile(r"^    (sim|cfg): (SimConfig|StepOptions)\b", re.MULTILINE), r"    options: StepOptions"),  # class fields
    (re.compile(r"(replace\(\w+), sim="), r"\1, options="),
]
SKIP = {pathlib.Path(__file__).resolve()}
KEEP = "issue 36"  # a line with this is left as it is


def files():
    for tree in TREES:
        p = ROOT / tree
        paths = [p] if p.is_file() else sorted(p.rglob("*"))
        for f in paths:
            if f.suffix in SUFFIXES and f.is_file() and f.resolve() not in SKIP and "node_modules" not in f.parts:
                yield f


def rewrite(text: str) -> str:
    """Each line by the rules, except lines that name the old names on purpose (they mention issue 36)."""
    out = []
    for line in text.splitlines(keepends=True):
        if KEEP not in line:
            for pattern, repl in RULES:
                line = pattern.sub(repl, line)
        out.append(line)
    return "".join(out)


def main(check: bool = False) -> int:
    changed = []
    for f in files():
        old = f.read_text()
        new = rewrite(old)
        if new != old:
            changed.append(f.relative_to(ROOT))
            if not check:
                f.write_text(new)
    for f in changed:
        print(f)
    return 1 if check and changed else 0


if __name__ == "__main__":
    sys.exit(main("--check" in sys.argv[1:]))
