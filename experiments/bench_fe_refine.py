"""Benchmark: FE-in-the-loop refinement of calibrations, confirmed by CalculiX.

Takes the finished configurations of an FE campaign store (default: the 0.5..10 Nm campaign,
``fe/data/campaign/runs.jsonl.gz``, complete or not), holds ``--n-heldout`` of them out as
specimens (their FE curves are the measurements, no noise), trains a surrogate on the others
(the FE pipeline's recipe, ``--members`` members), calibrates the held-out curves through it
(pgd) and refines each calibration with CalculiX in the loop
(:func:`femcal.fe.refine.refine_with_fe`, up to ``--max-fe-runs`` runs per specimen, stop at
``--tol-deg``). Reports, per specimen and on average:

* the surrogate's own error on the held-out configurations, in 0.5..5 and 5.5..10 Nm;
* the FE-evaluated error of the plain calibration (the first FE run);
* the FE-confirmed error after refinement and the FE runs it took.

Writes ``bench_fe_refine.md`` and ``bench_fe_refine.json`` into
``experiments/results/bench_fe_refine/``; the refinement's FE runs go to ``--store`` (resumable).

Usage (from the project root)::

    .venv/bin/python -m experiments.bench_fe_refine [--n-heldout 16] [--max-fe-runs 5]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import yaml

from experiments.common import REPO, RESULTS
from femcal.calibration import SurrogateCurveModel, calibrate
from femcal.fe.adaptive import band_mae, curves_to_rows
from femcal.fe.refine import campaign_curves, refine_with_fe
from femcal.fe.store import CampaignStore
from femcal.schema import LOAD_CASES, PARAMETER_NAMES
from femcal.space import ParameterSpace
from femcal.surrogates.nn import NeuralSurrogate


def campaign_curves_table(store: Path, moments: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """Parameters (N, 13) and curves (N, 4, m) of the configurations with all four load cases."""
    by_config: dict[int, dict] = {}
    for rec in CampaignStore(store).finished().values():
        if rec["load_case"] not in LOAD_CASES or not np.allclose(rec["levels"], moments):
            continue
        c = by_config.setdefault(int(rec["config_id"]), {"params": rec["parameters"]})
        c[rec["load_case"]] = [np.nan if v is None else float(v) for v in rec["rom_deg"]]
    ids = sorted(k for k, v in by_config.items() if all(lc in v for lc in LOAD_CASES))
    x = np.array([[by_config[i]["params"][n] for n in PARAMETER_NAMES] for i in ids])
    curves = np.array([[by_config[i][lc] for lc in LOAD_CASES] for i in ids])
    return x, curves


def recipe_surrogate(
    space: ParameterSpace, recipe: dict, members: int, max_epochs: int, seed: int
) -> NeuralSurrogate:
    """An unfitted surrogate of the FE pipeline's recipe (fe/params.yaml train.large.fixed)."""
    return NeuralSurrogate(
        space,
        hidden=[recipe["width"]] * recipe["depth"],
        activation=recipe["activation"],
        log_target=recipe["log_target"],
        log_params=recipe["log_params"],
        loss=recipe["loss"],
        batch_size=recipe["batch_size"],
        max_epochs=max_epochs,
        patience=recipe["patience"],
        learning_rate=recipe["learning_rate"],
        n_members=members,
        seed=seed,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--campaign", default="fe/data/campaign/runs.jsonl.gz")
    ap.add_argument("--store", default="fe/data/refine-bench/runs.jsonl")
    ap.add_argument("--n-heldout", type=int, default=16)
    ap.add_argument("--members", type=int, default=3)
    ap.add_argument("--max-epochs", type=int, default=600)
    ap.add_argument("--max-fe-runs", type=int, default=5)
    ap.add_argument("--tol-deg", type=float, default=0.05)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(RESULTS / "bench_fe_refine" / "bench_fe_refine"))
    args = ap.parse_args()

    params = yaml.safe_load((REPO / "fe" / "params.yaml").read_text())
    fe = params["fe"]
    moments = [float(m) for m in fe["moments"]]
    bounds = fe["bounds"]
    space = ParameterSpace(
        list(PARAMETER_NAMES),
        [bounds[n][0] for n in PARAMETER_NAMES],
        [bounds[n][1] for n in PARAMETER_NAMES],
    )
    x_all, curves_all = campaign_curves_table(REPO / args.campaign, moments)
    rng = np.random.default_rng(args.seed)
    order = rng.permutation(len(x_all))
    ho, tr = order[: args.n_heldout], order[args.n_heldout :]
    X, y = curves_to_rows(x_all[tr], curves_all[tr], moments, list(PARAMETER_NAMES))
    X_ho, y_ho = curves_to_rows(x_all[ho], curves_all[ho], moments, list(PARAMETER_NAMES))
    recipe = params["train"]["large"]["fixed"]
    t0 = time.perf_counter()
    surrogate = recipe_surrogate(space, recipe, args.members, args.max_epochs, args.seed)
    surrogate.fit(X, y)
    train_s = time.perf_counter() - t0
    bands = band_mae(surrogate, X_ho, y_ho)
    model = SurrogateCurveModel(surrogate, moments)
    measured = curves_all[ho]
    names = [f"cfg{int(i)}" for i in ho]
    cal = calibrate(
        model,
        measured,
        specimens=names,
        seed=args.seed,
        options=params["calibrate"]["options"]["pgd"] | {"ranges": False},
    )
    x0 = cal.parameters_frame()[list(PARAMETER_NAMES)].to_numpy()
    fe_fn = campaign_curves(fe["solver"], fe["settings"], store=REPO / args.store, moments=moments)
    t0 = time.perf_counter()
    res = refine_with_fe(
        model,
        measured,
        x0,
        fe_fn,
        specimens=names,
        max_fe_runs=args.max_fe_runs,
        tol_deg=args.tol_deg,
    )
    refine_s = time.perf_counter() - t0
    s = res.summary()
    figures = {
        "campaign": args.campaign,
        "n_training_configurations": int(len(tr)),
        "n_heldout": int(len(ho)),
        "moments": moments,
        "surrogate_members": args.members,
        "surrogate_train_seconds": round(train_s, 1),
        "surrogate_heldout_mae_deg_by_band": bands,
        "calibration_surrogate_mae_deg": float(np.mean(cal.mae_deg)),
        **s,
        "refine_wall_seconds": round(refine_s, 1),
    }
    out = REPO / args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{out}.json").write_text(json.dumps(figures, indent=2) + "\n")
    table = res.table()[["specimen", "fe_mae_deg_start", "fe_mae_deg", "fe_runs", "confirmed"]]
    lines = [
        "# FE-in-the-loop refinement, confirmed by CalculiX",
        "",
        f"`experiments/bench_fe_refine.py` on {len(x_all)} finished configurations of "
        f"`{args.campaign}` ({moments[0]:g}..{moments[-1]:g} Nm, {len(moments)} levels): "
        f"{len(tr)} train a {args.members}-member surrogate ({train_s:.0f} s), {len(ho)} are "
        "the specimens (their FE curves, no noise).",
        "",
        "| | |",
        "| --- | --- |",
        f"| surrogate on the held-out configurations, 0.5..5 Nm | {bands['0-5']:.4f}° |",
        f"| surrogate on the held-out configurations, 5.5..10 Nm | {bands['5-10']:.4f}° |",
        f"| calibration, through the surrogate | {figures['calibration_surrogate_mae_deg']:.4f}° |",
        f"| calibration, through CalculiX (FE run 1) | {s['fe_mae_deg_start']:.4f}° |",
        f"| **after refinement, FE-confirmed** | **{s['fe_confirmed_mae_deg']:.4f}°** "
        f"(worst {s['fe_confirmed_mae_deg_max']:.4f}°) |",
        f"| specimens within {args.tol_deg:g}° | {s['n_confirmed']} of {s['n_specimens']} |",
        f"| FE runs per specimen | at most {s['fe_runs_per_specimen_max']}, mean "
        f"{s['fe_runs_per_specimen_mean']:.1f} |",
        f"| refinement wall time (2 workers) | {refine_s:.0f} s |",
        "",
        "| specimen | FE MAE, calibration | FE MAE, refined | FE runs | confirmed |",
        "| --- | --- | --- | --- | --- |",
        *(
            f"| {r.specimen} | {r.fe_mae_deg_start:.4f}° | {r.fe_mae_deg:.4f}° | {r.fe_runs} "
            f"| {'yes' if r.confirmed else 'no'} |"
            for r in table.itertuples()
        ),
        "",
    ]
    Path(f"{out}.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
