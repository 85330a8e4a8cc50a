"""How far the out-of-box evidence can go on the edge cohorts: each score as a decision rule.

Issue 55 asks that at least 75 % of the discs outside the box get the out-of-box verdict. The
diagnosis decides with its out-of-box probability (``outside_box.probability`` of
``diagnosis.json``); the evidence under it is the disc-alone fit pressing the box (the number
of disc parameters on a bound) and the disc alone's miss. This script takes the bench's
scored specimens (``specimens.csv`` of ``python -m experiments.bench_edges``) and reads each
score as a rule "outside the box where the score reaches t", for every threshold t:

* **hits**: the discs outside the box it names, over all of them and over the visible ones
  (the disc alone misses the data by more than 2 x the true noise rms);
* **false alarms**: the discs inside the box it names (every other class);
* **the verdict**: the diagnosis' own answers (``box_said``: the out-of-box verdict, or
  ``unexplained`` naming the box) on the same two sets.

The ceiling of a score is its largest hit rate at no more false alarms than the verdict's.
A disc outside the box that the disc alone explains within the noise (not visible) shows the
box only through the parameters its fit presses, which discs inside the box at its edge press
too. Run::

    .venv/bin/python -m experiments.outside_box_roc RESULTS [RESULTS ...]

``RESULTS``: ``specimens.csv`` files or folders holding one. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

OUTSIDE = "outside_box"
#: Issue 55's bar: the share of the discs outside the box given the out-of-box verdict.
BAR = 0.75
#: The scores read as rules: column of specimens.csv -> what it is, in the table.
SCORES = {
    "box_probability": "out-of-box probability",
    "bounds_pressed": "disc parameters on a bound",
}


def load(paths: Sequence[Path]) -> pd.DataFrame:
    """The scored specimens of every ``specimens.csv`` (a folder: the file inside it)."""
    files = [p / "specimens.csv" if p.is_dir() else p for p in paths]
    return pd.concat([pd.read_csv(f) for f in files], ignore_index=True)


def rates(table: pd.DataFrame, named: np.ndarray) -> dict[str, float]:
    """Hit rates (all, visible) and false-alarm rate of the rule that names ``named`` (bool,
    one per row of ``table``)."""
    out = (table["truth"] == OUTSIDE).to_numpy()
    visible = out & table["visible"].astype(bool).to_numpy()
    return {
        "hits": named[out].mean(),
        "hits_visible": named[visible].mean() if visible.any() else np.nan,
        "false_alarms": named[~out].mean(),
    }


def ceilings(table: pd.DataFrame, bar: float = BAR) -> list[dict[str, object]]:
    """The verdict's rates, then per score: its best rule at no more false alarms than the
    verdict's and at none (the largest threshold reaching the best hit rate), and the rule
    with the fewest false alarms that names at least ``bar`` of the discs outside."""
    verdict = rates(table, table["box_said"].astype(bool).to_numpy())
    rows: list[dict[str, object]] = [{"rule": "the verdict", "threshold": "", **verdict}]
    budget = verdict["false_alarms"] + 1e-12
    most_hits = lambda tr: (tr[1]["hits"], tr[0])  # noqa: E731 (then the largest t)
    fewest_alarms = lambda tr: (-tr[1]["false_alarms"], tr[0])  # noqa: E731
    for column, words in SCORES.items():
        score = table[column].fillna(-np.inf).to_numpy(dtype=float)
        rules = [(t, rates(table, score >= t)) for t in np.unique(score[np.isfinite(score)])]
        picks = (
            (
                "false alarms at most the verdict's",
                lambda r: r["false_alarms"] <= budget,
                most_hits,
            ),
            ("no false alarm", lambda r: r["false_alarms"] == 0, most_hits),
            (f"at least {bar:.0%} named", lambda r: r["hits"] >= bar - 1e-12, fewest_alarms),
        )
        for label, allowed, rank in picks:
            ok = [(t, r) for t, r in rules if allowed(r)]
            if ok:
                t, r = max(ok, key=rank)
                rows.append({"rule": f"{words} >= t, {label}", "threshold": f"{t:.3g}", **r})
    return rows


def markdown(table: pd.DataFrame, rows: list[dict[str, object]]) -> str:
    """The rows as a Markdown table, with the counts they are rates of."""
    out = table["truth"] == OUTSIDE
    n, n_visible, n_in = int(out.sum()), int((out & table["visible"]).sum()), int((~out).sum())
    head = (
        f"| rule | t | hits of {n} outside | of the {n_visible} visible | "
        f"false alarms of {n_in} inside |\n| --- | --- | --- | --- | --- |\n"
    )

    def pct(x: float, of: int) -> str:
        return "n/a" if np.isnan(x) else f"{round(x * of)}/{of} ({100 * x:.0f} %)"

    body = "".join(
        f"| {r['rule']} | {r['threshold']} | {pct(r['hits'], n)} | "
        f"{pct(r['hits_visible'], n_visible)} | {pct(r['false_alarms'], n_in)} |\n"
        for r in rows
    )
    return head + body


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("results", type=Path, nargs="+", help="specimens.csv files or folders")
    args = ap.parse_args(argv)
    table = load(args.results)
    print(markdown(table, ceilings(table)))


if __name__ == "__main__":
    main()
