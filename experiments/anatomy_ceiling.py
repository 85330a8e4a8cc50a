"""How far a better search could go on the anatomy cohorts: the misses refitted thoroughly.

For every visible single-effect specimen the diagnosis did not name strictly right, the true
effect (tied and split) and the diagnosis' own model are calibrated again with a thorough
``pgd`` (32 starts, the start bank, 5 rounds of fresh effect starts over 32 shape starts) and
scored as the diagnosis scores them: the criterion ``chi^2 + k ln n`` (``k`` the effective
number of parameters) plus the prior cost of the model (10 for the first effect, 2 for each
further effect or split form), the lower of the thorough fit's and the diagnosis' own.

* **search miss**: the truth scores lower than the verdict's model: a search that fitted
  every model as well as this would have named it;
* **library**: the verdict's model scores lower (or within 2, a tie the data cannot break):
  with these laws and this criterion no search names the truth; the ceiling of the
  strict rate is what the diagnosis got right plus the search misses.

With ``--pairs``, the visible facet-and-ligament specimens not named strictly right are
judged the same way: the pair's four forms (each effect tied or split) against the verdict's
model.

Run on the output of ``bench_anatomy`` (its ``seed-*/cohort`` and ``seed-*/diagnosis``)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.anatomy_ceiling --bench DIR --out FILE
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from experiments.common import screened_cohort
from experiments.diagnosis import THOROUGH

REPO = Path(__file__).resolve().parents[1]
FIRST, FURTHER = 10.0, 2.0
#: Criterion differences within this are ties the data cannot break.
TIE = 2.0


def prior(model: tuple[str, ...]) -> float:
    """The diagnosis' prior cost of a model (:func:`femcal.diagnose.probabilities.prior_cost`)."""
    from femcal.diagnose.probabilities import prior_cost
    from femcal.effects.terms import Model

    return prior_cost(Model.parse("+".join(model)), FIRST, FURTHER)


def thorough_scores(
    cohort: Path, specimens: list[str], models: list[tuple[str, ...]]
) -> dict[tuple[str, ...], np.ndarray]:
    """Criterion (r,) of each model for the specimens, thorough ``pgd`` fits, the diagnosis'
    noise (0.05 deg and the surrogate's own error at each moment)."""

    from femcal.calibration import SurrogateCurveModel, calibrate
    from femcal.datasets import training_configurations
    from femcal.diagnose.fits import Fit, chi_square
    from femcal.effects.composite import EffectModel

    params, sur, policy, meas = screened_cohort(cohort / "measurements.csv")
    idx = np.array([meas.specimens.index(s) for s in specimens])
    rom = meas.rom_deg[idx]
    sigma = np.broadcast_to(np.sqrt(0.05**2 + policy.sigma_surrogate(meas.moments) ** 2), rom.shape)
    weight = np.array((sigma.min() / sigma) ** 2)
    base = SurrogateCurveModel(sur, meas.moments)
    mask = np.isfinite(rom)
    cost = np.log(np.maximum(mask.reshape(len(idx), -1).sum(1), 2.0))
    bank = training_configurations(REPO / params["calibrate"]["start_bank"])
    out = {}
    for model in models:
        m = EffectModel(base, list(model)) if model else base
        res = calibrate(
            m, rom, weight=weight, method="pgd", options={**THOROUGH, "start_bank": bank}, seed=0
        )
        chi2 = chi_square(torch.as_tensor(res.prediction), rom, sigma)
        fit = Fit(model, m, m.from_physical(np.asarray(res.x)), np.arange(len(idx)), None, chi2, 0)
        out[model] = np.array([fit.criterion(k, cost[k], mask, sigma) for k in range(len(idx))])
    return out


def misses(bench: Path) -> pd.DataFrame:
    """The visible single-effect specimens not named strictly right (``specimens.csv``)."""
    table = pd.read_csv(bench / "specimens.csv", dtype={"expected": str}).fillna({"model": ""})
    single = table["expected"].fillna("").str.count(r"\+").eq(0) & table["expected"].notna()
    return table[table["visible"] & ~table["strict"].astype(bool) & single]


def judge_misses(bench: Path) -> list[dict[str, Any]]:
    """Per miss: the truth's best thorough score, the verdict model's, and which is lower."""
    rows = []
    for seed, group in misses(bench).groupby("seed"):
        root = bench / f"seed-{seed}"
        own = {
            d["specimen"]: d for d in json.loads((root / "diagnosis/diagnosis.json").read_text())
        }
        for _, r in group.iterrows():
            truth = str(r["expected"])
            verdict_model = tuple(sorted(m for m in str(r["model"]).split("+") if m))
            candidates = [(truth,), (truth + ":split",)]
            models = [*candidates, *([verdict_model] if verdict_model not in candidates else [])]
            scores = thorough_scores(root / "cohort", [r["specimen"]], models)
            ranking = {
                tuple(sorted(x["effects"])): x["criterion"] for x in own[r["specimen"]]["ranking"]
            }
            best = {m: min(float(scores[m][0]), ranking.get(m, np.inf)) + prior(m) for m in models}
            truth_score = min(best[m] for m in candidates)
            rows.append(
                {
                    "seed": int(seed),
                    "specimen": r["specimen"],
                    "truth": truth,
                    "verdict": r["verdict"],
                    "truth_score": round(truth_score, 1),
                    "verdict_score": round(best[verdict_model], 1) if verdict_model else None,
                    "search_miss": bool(verdict_model) and truth_score < best[verdict_model] - TIE,
                }
            )
    return rows


#: The facet and the ligament, each tied or split: the four forms of the pair class.
PAIR_FORMS = [
    ("facet_contact", "ligament_tension"),
    ("facet_contact:split", "ligament_tension:split"),
    ("facet_contact:split", "ligament_tension"),
    ("facet_contact", "ligament_tension:split"),
]


def judge_pairs(bench: Path) -> list[dict[str, Any]]:
    """Per visible facet-and-ligament specimen not named strictly right: the best thorough
    score of the pair's four forms against the verdict model's (the lower of its thorough and
    its own fit), and whether the pair wins by more than a tie."""
    table = pd.read_csv(bench / "specimens.csv", dtype={"expected": str}).fillna({"model": ""})
    table = table[(table["expected"] == "facet_contact+ligament_tension") & table["visible"]]
    table = table[~table["strict"].astype(bool)]
    rows = []
    for seed, group in table.groupby("seed"):
        root = bench / f"seed-{seed}"
        own = {
            d["specimen"]: d for d in json.loads((root / "diagnosis/diagnosis.json").read_text())
        }
        verdicts = {tuple(sorted(m for m in str(v).split("+") if m)) for v in group["model"]}
        models = PAIR_FORMS + sorted(v for v in verdicts if v and v not in PAIR_FORMS)
        scores = thorough_scores(root / "cohort", list(group["specimen"]), models)
        for k, (_, r) in enumerate(group.iterrows()):
            ranking = {
                tuple(sorted(x["effects"])): x["criterion"] for x in own[r["specimen"]]["ranking"]
            }

            def best(m: tuple[str, ...], k: int = k, ranking: dict = ranking, s=scores) -> float:
                mine = float(s[m][k]) if m in s else np.inf
                return min(mine, ranking.get(tuple(sorted(m)), np.inf)) + prior(m)

            verdict_model = tuple(sorted(m for m in str(r["model"]).split("+") if m))
            pair = min(PAIR_FORMS, key=best)
            rows.append(
                {
                    "seed": int(seed),
                    "specimen": r["specimen"],
                    "verdict": r["verdict"],
                    "verdict_score": round(best(verdict_model), 1),
                    "pair": "+".join(pair),
                    "pair_score": round(best(pair), 1),
                    "search_miss": best(pair) < best(verdict_model) - TIE,
                }
            )
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bench", type=Path, required=True, help="a bench_anatomy output folder")
    ap.add_argument("--out", type=Path, required=True, help="JSON file to write")
    ap.add_argument(
        "--pairs", action="store_true", help="judge the facet-and-ligament misses instead"
    )
    args = ap.parse_args(argv)
    if args.pairs:
        rows = judge_pairs(args.bench)
        summary = {"pair_misses": len(rows), "search_misses": sum(r["search_miss"] for r in rows)}
        args.out.write_text(json.dumps({**summary, "misses": rows}, indent=2) + "\n")
        print(json.dumps(summary))
        return
    rows = judge_misses(args.bench)
    table = pd.read_csv(args.bench / "specimens.csv")
    single = table["expected"].notna() & ~table["expected"].fillna("").str.contains(r"\+")
    visible = table[table["visible"] & single & table["expected"].notna()]
    right = int(visible["strict"].astype(bool).sum())
    n = len(visible)
    searchable = sum(r["search_miss"] for r in rows)
    summary = {
        "n_visible_single": n,
        "strict_right": right,
        "search_misses": searchable,
        "ceiling": (right + searchable) / n if n else None,
        "misses": rows,
    }
    args.out.write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps({k: v for k, v in summary.items() if k != "misses"}))


if __name__ == "__main__":
    main()
