"""How honest a diagnosis' inclusion probabilities are: scored against a cohort's answers.

Every (specimen, built-in effect) pair is one forecast, the effect's inclusion probability
(summed over its forms, ``x``, ``x:split``, ``x@cases``), against whether the truth holds it:

* the **Brier score** and the **log loss** (probabilities clipped to [0.001, 0.999]), proper
  scoring rules: lower is better, and a confident wrong answer costs the most;
* **present effects at >= 0.9** and **absent effects at >= 0.9** (confidently wrong).

Run::

    .venv/bin/python -m experiments.inclusion_scores DIAGNOSIS ANSWERS [DIAGNOSIS ...]

``DIAGNOSIS`` a folder holding ``diagnosis.json`` (or the file); ``ANSWERS`` a CSV with the
columns ``specimen`` and ``effects`` (the true effects joined by spaces or ``+``), as the FE
cohort's ``answers.csv`` (``fe/data/cohort``). Prints one JSON line per diagnosis.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from experiments.bench_edges import inclusion_by_effect, inclusion_scores
from experiments.diagnosis_diff import load


def answers(path: Path) -> dict[str, set[str]]:
    """Specimen -> its true effects, from a CSV with ``specimen`` and ``effects`` columns."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or not {"specimen", "effects"} <= set(rows[0]):
        raise SystemExit(f"{path}: needs the columns specimen and effects (the true effects).")
    return {r["specimen"]: set(re.split(r"[ +]", r["effects"] or "")) - {""} for r in rows}


def scores(diagnosis: list[dict[str, Any]], truth: dict[str, set[str]]) -> dict[str, Any]:
    """Brier score, log loss and the confident counts over every (specimen, effect) pair, as
    the edge bench scores them (:func:`experiments.bench_edges.inclusion_scores`)."""
    table = pd.DataFrame(
        {
            "expected": ["+".join(sorted(truth[str(r["specimen"])])) for r in diagnosis],
            "inclusion": [json.dumps(inclusion_by_effect(r)) for r in diagnosis],
        }
    )
    got = inclusion_scores(table)
    present, absent = got["present_confident"], got["absent_confident"]
    return {
        "pairs": got["pairs"],
        "brier": round(got["brier"], 4),
        "log_loss": round(got["log_loss"], 4),
        "present_confident": f"{present['k']}/{present['n']}",
        "absent_confident": f"{absent['k']}/{absent['n']}",
    }


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("diagnosis", type=Path, help="folder holding diagnosis.json (or the file)")
    ap.add_argument("answers", type=Path, help="CSV with specimen and effects columns")
    ap.add_argument("more", type=Path, nargs="*", help="further diagnoses of the same cohort")
    args = ap.parse_args(argv)
    truth = answers(args.answers)
    for path in (args.diagnosis, *args.more):
        print(json.dumps({"diagnosis": str(path), **scores(load(path), truth)}))


if __name__ == "__main__":
    main()
