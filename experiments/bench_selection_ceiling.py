"""How far bar (a) could go with the diagnosis' criterion: every model fitted thoroughly.

Bar (a) of issue 11 asks for >= 90 % right verdicts among the hidden specimens whose disc alone
misses by > 2σ. ``bench_diagnose.py``'s ceiling column asks of each *combination* whether the
criterion prefers it with thorough fits, and counts every single effect as preferred. This
benchmark asks it of every eligible specimen whose truth is in the library (single effects and
combinations alike), and then applies a selection rule to the thorough criteria:

    choose the model M minimising  C(M) + min_delta [|M| >= 1] + tau max(|M| - 1, 0)

``C`` the diagnosis' criterion (``chi^2 + ln n k``, ``k`` the effective number of parameters),
the lower of the thorough fit's and the diagnosis' own; ``min_delta`` (10) the gain the first
effect needs, ``tau`` the gain each further one needs (the diagnosis: 2). This is forward
selection without its path: it sees every model, fitted as well as this machine can in
reasonable time, so what it gets right bounds what a better search with this criterion could
get right. Out-of-library specimens keep the diagnosis' own verdict (the rule cannot say
``unexplained``).

Run (about 15 min per cohort on one core)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_selection_ceiling --seeds 3,4 \
        --out DIR

``--from-json A --from-json B --out DIR`` joins earlier runs into one report.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from experiments.ceiling import model_criteria, own_criteria
from experiments.common import RESULTS, reproduce_command
from experiments.diagnose_report import wilson
from experiments.diagnosis import (
    cohort_group,
    cohort_name,
    hidden_cohort,
    hidden_seeds,
    judge_cohort,
    restrict,
    run_diagnosis,
    setup,
)
from experiments.hidden_cohorts import HOLDOUT_SEEDS

#: Gains a further effect needs in the rule (the diagnosis' is 2).
TAUS = (0.0, 1.0, 2.0, 3.0, 4.0, 6.0)


def select(criteria: dict[str, float], min_delta: float, tau: float) -> tuple[str, ...]:
    """The rule's model for one specimen.

    Parameters
    ----------
    criteria : dict
        Model label (effects joined by ``+``, ``""`` the disc alone) -> criterion.
    min_delta, tau : float
        Gain the first effect and each further one need.
    """

    def score(label: str) -> float:
        k = len(label.split("+")) if label else 0
        return criteria[label] + min_delta * (k >= 1) + tau * max(k - 1, 0)

    best = min(criteria, key=score)
    return tuple(best.split("+")) if best else ()


def one_cohort(cohort: dict[str, Any], ctx: dict[str, Any]) -> dict[str, Any]:
    """Diagnose a cohort, fit every model to its eligible in-library specimens thoroughly."""
    t0 = time.perf_counter()
    diag, _, _, model, weight = run_diagnosis(cohort, ctx)
    j = judge_cohort(cohort, diag)
    ool = np.asarray(cohort["out_of_library"], dtype=bool)
    rows = np.flatnonzero(j["eligible"] & ~ool)
    sigma_m = np.asarray(diag.sigma_by_moment)
    thorough = model_criteria(cohort, ctx, model, weight, sigma_m, rows, diag)
    own = own_criteria(diag, rows)
    label = "+".join
    specimens = []
    for k, i in enumerate(rows):
        specimens.append(
            {
                "specimen": str(cohort["specimens"][i]),
                "class": str(cohort["labels"][i]),
                "truth": label(sorted(cohort["expected"][i])),
                "verdict": str(j["verdicts"][i]),
                "right": bool(j["right"][i]),
                "criteria": {label(e): float(b[k]) for e, b in thorough.items()},
                "own": {label(e): c for (kk, e), c in own.items() if kk == k},
            }
        )
    return {
        "kind": "hidden",
        "seed": cohort["seed"],
        "holdout": cohort["seed"] in HOLDOUT_SEEDS,
        "n_eligible": int(j["eligible"].sum()),
        "n_right_eligible": int(j["right"][j["eligible"]].sum()),
        "n_ool_eligible": int((j["eligible"] & ool).sum()),
        "n_ool_right": int((j["eligible"] & ool & j["right"]).sum()),
        "specimens": specimens,
        "seconds": time.perf_counter() - t0,
    }


def rule_right(row: dict[str, Any], min_delta: float, tau: float, key: str = "criteria") -> int:
    """Eligible specimens the rule names right (out-of-library ones: the diagnosis' verdict)."""
    right = row["n_ool_right"]
    for s in row["specimens"]:
        crit = s[key]
        if not crit:
            continue
        truth = tuple(s["truth"].split("+")) if s["truth"] else ()
        right += int(set(select(crit, min_delta, tau)) == set(truth))
    return right


def write(rows: list[dict[str, Any]], meta: dict[str, Any], out: Path) -> None:
    """``bench_selection_ceiling.md`` and ``.json`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_selection_ceiling.json").write_text(
        json.dumps({**meta, "rows": rows}, indent=1) + "\n"
    )
    md, taus = meta["min_delta"], meta["taus"]
    head = " | ".join(f"τ = {t:g}" for t in taus)
    lines = [
        "# Bar (a) with every model fitted thoroughly: what the criterion allows",
        "",
        "Reproduce: " + " and ".join(f"`{c}`" for c in meta["commands"]) + ".",
        "",
        "Every eligible hidden specimen (not `none`, the disc alone misses by > 2σ) whose truth "
        "is in the library is calibrated with every model the diagnosis could name (the disc, "
        "each effect, each pair, the triple) by the thorough `pgd` of `bench_diagnose.py`'s "
        "ceiling, and scored by the diagnosis' criterion (the lower of that fit's and the "
        "diagnosis' own). The rule picks the model minimising criterion + "
        f"{md:g} (the first effect's gain) + τ per further effect. Out-of-library specimens "
        "keep the diagnosis' verdict. *Own fits*: the same rule on the diagnosis' own "
        "criteria only (models it did not fit are left out).",
        "",
        f"| cohort | eligible | diagnosis | {head} | own fits, τ = 2 |",
        "|---|---|---|" + "---|" * len(taus) + "---|",
    ]
    for r in rows:
        cells = " | ".join(str(rule_right(r, md, t)) for t in taus)
        lines.append(
            f"| {cohort_name(r)} | {r['n_eligible']} | {r['n_right_eligible']} | {cells} | "
            f"{rule_right(r, md, 2.0, 'own')} |"
        )
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(cohort_group(r), []).append(r)
    if len(rows) > 1:
        lines += [
            "",
            f"| cohorts | eligible | diagnosis | {head} |",
            "|---|---|---|" + "---|" * len(taus),
        ]
        for name, rs in [*groups.items(), ("all", rows)]:
            n = sum(r["n_eligible"] for r in rs)
            d = sum(r["n_right_eligible"] for r in rs)
            cells = []
            for t in taus:
                k = sum(rule_right(r, md, t) for r in rs)
                lo, hi = wilson(k, n)
                cells.append(f"{k} ({100 * k / n:.0f} %, {100 * lo:.0f}-{100 * hi:.0f})")
            lines.append(
                f"| {name} | {n} | {d} ({100 * d / n:.0f} %) | " + " | ".join(cells) + " |"
            )
    (out / "bench_selection_ceiling.md").write_text("\n".join(lines) + "\n")


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="3,4", help="hidden cohorts' seeds")
    ap.add_argument("--holdout", action="store_true", help="allow held-out seeds")
    ap.add_argument("--max-specimens", type=int, default=None, help="per cohort (quick runs)")
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_selection_ceiling")
    ap.add_argument("--from-json", type=Path, action="append", default=[], metavar="PATH")
    args = ap.parse_args(argv)
    if args.from_json:
        rows, commands = [], []
        for p in args.from_json:
            d = json.loads(p.read_text())
            rows += d.pop("rows")
            commands += d.pop("commands")
            meta = d
        write(rows, {**meta, "commands": commands}, args.out)
        return
    seeds = hidden_seeds(ap, args.seeds, args.holdout)
    torch.manual_seed(0)
    ctx = setup()
    rows = []
    for seed in seeds:
        cohort = hidden_cohort(seed, ctx["fe_moments"], ctx["fe_rom"], ctx["plant"]["noise_deg"])
        cohort = restrict(cohort, args.max_specimens)
        print(f"hidden seed {seed}: {len(cohort['specimens'])} specimens ...", flush=True)
        rows.append(one_cohort(cohort, ctx))
        meta = {
            "commands": [reproduce_command("bench_selection_ceiling", argv)],
            "min_delta": ctx["min_delta"],
            "taus": list(TAUS),
        }
        write(rows, meta, args.out)  # after every cohort: a long run leaves what it has


if __name__ == "__main__":
    main()
