"""How far each wrong verdict lies from the right one, in the diagnosis' own scores: an oracle.

For every specimen whose verdict names another set of effects than the truth, the score of
its most probable model against the best-scoring model fitted to it that holds exactly the true
effects (any form: tied, split, in any load cases). A model's score is its criterion
(``chi^2 + k ln n``, from ``diagnosis.json``'s ranking) plus the prior cost the probabilities
add (:func:`femcal.diagnose.probabilities.model_prior_cost`, with the options' ``min_delta``
and ``min_delta_inadequate``). Lower is better. What each row says:

* ``true set best, left out``: the true set scores best but is not among the probabilities'
  models (an effect in a load case beyond its likely ones that does not engage there, or an
  idle effect: :func:`femcal.diagnose.decide._probabilities`);
* ``within the prior's resolution``: the true set scores worse by less than
  ``min_delta_inadequate`` (the evidence a further effect or a split form needs), so the two
  fit about equally and the probabilities share them;
* ``the fits prefer another set``: worse by more than that;
* ``true set not fitted``: the search never fitted it.

With the best fits the search found, it bounds what any decision rule on these scores can
name right: the rows of the first two kinds. Run::

    .venv/bin/python -m experiments.verdict_margins DIAGNOSIS ANSWERS [--hidden HIDDEN_JSON]

``DIAGNOSIS`` a folder holding ``diagnosis.json`` (or the file); ``ANSWERS`` a CSV with the
columns ``specimen`` and ``effects`` (:func:`experiments.inclusion_scores.answers`);
``HIDDEN_JSON`` the loop's ``hidden.json`` (``python -m femcal.fe.hidden``), whose ``visible``
flags restrict the rows to the visible specimens. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from experiments.diagnosis_diff import load
from experiments.inclusion_scores import answers
from femcal.diagnose import DiagnoseOptions
from femcal.diagnose.probabilities import model_prior_cost
from femcal.effects.base import available_effects
from femcal.effects.terms import DISC_ALONE, Model

LEFT_OUT = "true set best, left out"
WITHIN = "within the prior's resolution"
PREFERRED = "the fits prefer another set"
NOT_FITTED = "true set not fitted"


def margins(
    specimen: dict[str, Any], truth: set[str], options: DiagnoseOptions
) -> dict[str, Any] | None:
    """One specimen's row: None where its verdict names the true effects; else its most
    probable model, the best true-set model, their scores and the reading (module docstring)."""
    verdict = set(specimen["effects"])
    if verdict == truth:
        return None
    kept = specimen["probabilities"]["models"]
    scored = []
    for entry in specimen["ranking"]:
        model = Model.parse(entry["effect"])
        cost = model_prior_cost(model, options.min_delta, options.min_delta_inadequate)
        scored.append((entry["criterion"] + cost, entry["effect"], set(model.effects)))
    scored.sort(key=lambda s: s[0])
    chosen = "+".join(specimen["model"]) or DISC_ALONE
    chosen_score = next((s for s, label, _ in scored if label == chosen), scored[0][0])
    true_set = [(s, label) for s, label, effects in scored if effects == truth]
    row = {
        "specimen": str(specimen["specimen"]),
        "truth": "+".join(sorted(truth)) or DISC_ALONE,
        "verdict": specimen["verdict"],
        "chosen": chosen,
        "chosen_score": round(chosen_score, 2),
        "true_model": None,
        "true_score": None,
        "gap": None,
        "reading": NOT_FITTED,
    }
    if not true_set:
        return row
    score, label = true_set[0]
    gap = score - chosen_score
    if gap <= 0 and label not in kept:
        reading = LEFT_OUT
    elif gap < options.min_delta_inadequate:
        reading = WITHIN
    else:
        reading = PREFERRED
    return {
        **row,
        "true_model": label,
        "true_score": round(score, 2),
        "gap": round(gap, 2),
        "reading": reading,
    }


def table(rows: list[dict[str, Any]]) -> str:
    """The rows as a Markdown table, with a count of each reading below."""
    columns = (
        "specimen",
        "truth",
        "verdict",
        "its score",
        "best true-set model",
        "its score",
        "gap",
        "reading",
    )
    lines = ["| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]
    for r in rows:
        true = f"`{r['true_model']}`" if r["true_model"] else "-"
        cells = [
            r["specimen"],
            f"`{r['truth']}`",
            f"`{r['verdict']}`",
            r["chosen_score"],
            true,
            r["true_score"] if r["true_score"] is not None else "-",
            r["gap"] if r["gap"] is not None else "-",
            r["reading"],
        ]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    counts = {
        k: sum(r["reading"] == k for r in rows) for k in (LEFT_OUT, WITHIN, PREFERRED, NOT_FITTED)
    }
    lines.append("")
    lines.append("; ".join(f"{k}: {n}" for k, n in counts.items()))
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("diagnosis", type=Path, help="folder holding diagnosis.json (or the file)")
    ap.add_argument("answers", type=Path, help="CSV with specimen and effects columns")
    ap.add_argument("--hidden", type=Path, help="the loop's hidden.json: visible specimens only")
    args = ap.parse_args(argv)
    available_effects()  # the built-in effects and the plugins, registered
    truth = answers(args.answers)
    visible = None
    if args.hidden:
        visible = {
            s["specimen"] for s in json.loads(args.hidden.read_text())["specimens"] if s["visible"]
        }
    options, rows = DiagnoseOptions(), []
    for specimen in load(args.diagnosis):
        name = str(specimen["specimen"])
        if visible is not None and name not in visible:
            continue
        row = margins(specimen, truth[name], options)
        if row is not None:
            rows.append(row)
    print(table(rows))


if __name__ == "__main__":
    main()
