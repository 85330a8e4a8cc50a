"""Benchmark: the FE surrogate's learning curve, its held-out error against the configurations.

The FE pipeline's surrogate (``fe/dvc.yaml`` ``train@large``) learns from the Large split of the
CalculiX campaign. This benchmark measures how its error on FE configurations it never saw
falls as the Large split grows, to say what lowers it: more FE runs, where, or another network.

* **Data.** The campaign store (``--campaign``, default ``fe/data/campaign/runs.jsonl.gz``) is
  copied into a work folder and the FE pipeline's dataset is rebuilt from the copy
  (``femcal simulate`` with fe/params.yaml's splits and ``batches: []``, then ``femcal
  prepare``), without CalculiX: the build stops with an error if any job of the design is
  missing from the store. With ``--prepared`` an already prepared folder is used instead.
* **Held out.** Every configuration of the Small and Test splits (64 on the 576-configuration
  campaign), at the points FE reached (a failed job keeps the levels it reached; the rest of
  its curve is not scored).
* **Training sets.** Nested random subsets of Large (one permutation of its configurations):
  the first 64, 128, 256, 512 (``--sizes``); ``--repeats`` permutations (seeds ``--seed`` + r),
  each with the training seed ``train.seed`` + r. As in ``femcal train``, 15 % of a subset's
  configurations (``train.val_fraction``) are the validation set of early stopping and keeping
  the best epoch, the rest are fitted.
* **Recipes.** ``fe``: fe/params.yaml ``train.large.fixed`` (width 128, depth 3, batch 16,
  degree 6 in log-moment); ``root``: the root params.yaml ``train.large.fixed`` (width 256,
  depth 4, batch 64, the study's measured recipe), with the FE recipe's ``moment_degree`` (the
  0.5..10 Nm curves need degree 6: ``experiments/bench_fe_curve_form.py``), at ``--root-sizes``.
  One member each (``--members``), :class:`femcal.surrogates.nn.NeuralSurrogate` fitted
  directly, without MLflow.
* **Figures.** Held-out MAE in degrees per moment band (0.5-5 and 5.5-10 Nm, and the study's
  1-5 Nm) and load case; a power law ``MAE = a n^-b`` per band (and per load case) fitted to
  the FE recipe's means (least squares in log-log) and over its last two n, solved for the
  configurations that reach ``--targets`` (0.04 and 0.08 deg; 1.5 times those per load case);
  where the error sits (the worst configurations' share, Spearman correlations with the
  parameters and the RoM), and the curve on the held-out discs with RoM below 20 deg up to
  7.5 Nm.

Writes ``bench_fe_learning_curve.json`` and ``.md`` (``--out``) and the figure
``docs/figures/fe-learning-curve.png`` (``--figure``; docs/benchmarks/fe.md shows it), both
by :mod:`experiments.fe_learning_curve_report`.
``--from-json`` redraws the figure and tables from a written JSON without training.

Usage (from the project root; one training at a time: 18 fits, about 7 CPU-minutes)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_fe_learning_curve
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from experiments.common import REPO, RESULTS, reproduce_command
from experiments.fe_learning_curve_report import figure, markdown
from femcal.schema import LOAD_CASES

#: The moment bands scored, (lo, hi] in Nm: the two of the targets, and the study's 1..5 Nm.
BANDS = {"0.5-5": (0.0, 5.0), "5.5-10": (5.0, 10.0)}
STUDY_BAND = {"1-5": (0.75, 5.0)}
#: The reference study's learning curve (its 1..5 Nm Test MAE, degrees, by training set).
STUDY_CURVE = [
    {"n": 128, "mae_deg": 0.22, "label": "Small"},
    {"n": 1024, "mae_deg": 0.023, "label": "Large"},
]
FEATURES = ["config_id", "load_case", "moment_nm"]
#: The held-out configurations within reach of a lumbar segment: RoM below 20 deg in every load
#: case up to 7.5 Nm (as docs/benchmarks/fe.md's stated-error section restricts them).
PHYSIOLOGICAL = (20.0, 7.5)


# ---------------------------------------------------------------------------------- data
def build_prepared(campaign: Path, work: Path) -> Path:
    """The FE pipeline's prepared tables of the campaign's base splits, rebuilt without FE.

    ``campaign`` is copied into ``work``; ``femcal simulate`` (fe/params.yaml, ``batches: []``,
    the copy as its store) and ``femcal prepare`` write ``work/dataset`` and
    ``work/prepared``. Running a CalculiX job is refused: a job missing from the store raises.

    Returns
    -------
    Path
        The prepared folder (``large.csv``, ``small.csv``, ``test.csv``,
        ``parameter_space.json``).
    """
    import shutil

    import femcal.fe.campaign as campaign_mod
    from femcal.cli import main as femcal_main

    work.mkdir(parents=True, exist_ok=True)
    store = work / "runs.jsonl.gz"
    shutil.copyfile(campaign, store)
    params = yaml.safe_load((REPO / "fe" / "params.yaml").read_text())
    params["fe"]["batches"] = []
    params["fe"]["store"] = str(store)
    params["fe"]["out_dir"] = str(work / "dataset")
    params["fe"]["n_workers"] = 1
    params["data"]["raw_dir"] = str(work / "dataset")
    params["data"]["prepared_dir"] = str(work / "prepared")
    params["mlflow"]["store_dir"] = str(work / "mlruns")
    params["train"]["storage"] = f"sqlite:///{work / 'optuna.db'}"
    for name in ("cohort", "adapt", "validate"):  # paths of stages not run here
        params.pop(name, None)
    params_file = work / "params.yaml"
    params_file.write_text(yaml.safe_dump(params, sort_keys=False))

    def refuse(*args: Any, **kwargs: Any) -> Any:
        todo = args[1] if len(args) > 1 else kwargs.get("todo", [])
        raise RuntimeError(
            f"{len(todo)} jobs of the design are not in {campaign}; this benchmark runs no FE."
        )

    run_jobs = campaign_mod._run_jobs
    campaign_mod._run_jobs = refuse
    try:
        for argv in (["simulate", "--store", str(store)], ["prepare"]):
            if femcal_main(["--params", str(params_file), *argv]) != 0:
                raise RuntimeError(f"femcal {argv[0]} failed (see above)")
    finally:
        campaign_mod._run_jobs = run_jobs
    return work / "prepared"


def load_tables(prepared: Path) -> tuple[dict[str, pd.DataFrame], Any]:
    """The prepared splits (all rows, failed ones included) and the parameter space."""
    from femcal.datasets import load_split

    tables = {}
    for split in ("large", "small", "test"):
        tables[split], space = load_split(prepared, split)
    return tables, space


def joined_heldout(tables: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """Small and Test as one table; Test's config ids (counted within its split) follow
    Small's."""
    small, test = tables["small"], tables["test"]
    test = test.assign(config_id=test["config_id"] + int(small["config_id"].max()) + 1)
    return pd.concat([small, test], ignore_index=True)


# ------------------------------------------------------------------------------- training
def recipe(name: str, fe_params: dict, root_params: dict) -> dict[str, Any]:
    """NeuralSurrogate keywords of a recipe (``fe`` or ``root``), ``width``/``depth`` as given."""
    fixed = dict(fe_params["train"]["large"]["fixed"])
    if name == "root":
        fixed = dict(root_params["train"]["large"]["fixed"]) | {
            "moment_degree": fixed["moment_degree"]
        }
    return fixed


def fit_and_score(
    train: pd.DataFrame,
    heldout: pd.DataFrame,
    space: Any,
    fixed: dict[str, Any],
    *,
    members: int,
    seed: int,
    val_fraction: float,
    max_epochs: int | None,
) -> dict[str, Any]:
    """One surrogate fitted as ``femcal train`` fits its final model, scored on ``heldout``."""
    import torch

    from femcal.datasets import ok_rows
    from femcal.surrogates.nn import NeuralSurrogate
    from femcal.train import surrogate_kwargs, validation_split

    torch.set_num_threads(1)
    data = ok_rows(train)
    tr, va = validation_split(data, fraction=val_fraction, seed=seed)
    cols = [*FEATURES, *space.names]
    kw = surrogate_kwargs(fixed)
    if max_epochs is not None:
        kw["max_epochs"] = min(int(kw["max_epochs"]), max_epochs)
    model = NeuralSurrogate(space, **kw, n_members=members, seed=seed)
    t0 = time.process_time()
    w0 = time.perf_counter()
    model.fit(tr[cols], tr["rom_deg"].to_numpy(float), X_val=va[cols], y_val=va["rom_deg"])
    cpu_s, wall_s = time.process_time() - t0, time.perf_counter() - w0
    ho = ok_rows(heldout)
    err = np.abs(model.predict(ho[cols]) - ho["rom_deg"].to_numpy(float))
    m = ho["moment_nm"].to_numpy(float)
    lc = ho["load_case"].astype(str).to_numpy()
    out: dict[str, Any] = {
        "n_fitted": int(tr["config_id"].nunique()),
        "n_validation": int(va["config_id"].nunique()),
        "epochs": int(max(r["epoch"] for r in model.history_)) + 1,
        "max_epochs": int(kw["max_epochs"]),
        "best_val_mae_deg": float(model.best_val_mae_deg_),
        "cpu_seconds": round(cpu_s, 1),
        "wall_seconds": round(wall_s, 1),
        "mae_deg": float(err.mean()),
        "n_points": int(err.size),
        "bands": {},
    }
    for band, (lo, hi) in BANDS.items():
        sel = (m > lo + 1e-9) & (m <= hi + 1e-9)
        out["bands"][band] = {
            "mae_deg": float(err[sel].mean()),
            "n_points": int(sel.sum()),
            "load_cases": {c: float(err[sel & (lc == c)].mean()) for c in LOAD_CASES},
        }
    for band, (lo, hi) in STUDY_BAND.items():
        sel = (m > lo + 1e-9) & (m <= hi + 1e-9)
        out["bands"][band] = {"mae_deg": float(err[sel].mean()), "n_points": int(sel.sum())}
    out["load_cases"] = {c: float(err[lc == c].mean()) for c in LOAD_CASES}
    # per held-out configuration: where the error sits
    rel = err / ho["rom_deg"].to_numpy(float)
    frame = pd.DataFrame({"config_id": ho["config_id"].to_numpy(), "err": err, "rel": rel})
    frame["band"] = np.where(m <= 5.0 + 1e-9, "0.5-5", "5.5-10")
    for band in BANDS:
        sub = frame[frame["band"] == band]
        per = sub.groupby("config_id")["err"].mean()
        out["bands"][band]["relative_mae"] = float(sub["rel"].mean())
        out["bands"][band]["per_configuration_mae_deg"] = {
            str(int(k)): round(float(v), 5) for k, v in per.items()
        }
    return out


# ------------------------------------------------------------------------------ power law
def power_law(ns: Sequence[float], maes: Sequence[float]) -> dict[str, float]:
    """``MAE = a n^-b`` by least squares in log-log: ``a``, ``b`` and the rms log residual."""
    x, y = np.log(np.asarray(ns, float)), np.log(np.asarray(maes, float))
    slope, intercept = np.polyfit(x, y, 1)
    resid = y - (intercept + slope * x)
    return {
        "a": float(math.exp(intercept)),
        "b": float(-slope),
        "rms_log_residual": float(np.sqrt(np.mean(resid**2))),
    }


def n_for(a: float, b: float, target: float) -> float:
    """Configurations at which ``a n^-b`` reaches ``target`` (inf when it does not fall)."""
    return (a / target) ** (1.0 / b) if b > 0 else math.inf


def curve(figures: dict[str, Any], recipe_name: str, band: str) -> list[dict[str, float]]:
    """Mean, min and max over the repeats of a recipe's held-out MAE in ``band``, by n."""
    by_n: dict[int, list[float]] = {}
    for p in figures["points"]:
        if p["recipe"] == recipe_name:
            by_n.setdefault(p["n_train"], []).append(p["bands"][band]["mae_deg"])
    return [
        {
            "n": n,
            "mean": float(np.mean(v)),
            "min": float(min(v)),
            "max": float(max(v)),
            "repeats": len(v),
        }
        for n, v in sorted(by_n.items())
    ]


def summarise(figures: dict[str, Any], targets: Sequence[float]) -> dict[str, Any]:
    """Adds the curves (mean over repeats), the power law of the FE recipe's curve per band
    fitted to every n, and its local slope over the last two n, each solved for the target."""
    figures["curves"] = {
        name: {band: curve(figures, name, band) for band in (*BANDS, *STUDY_BAND)}
        for name in figures["recipes"]
    }
    ext = {}
    for band, target in zip(BANDS, targets):
        pts = figures["curves"]["fe"][band]
        ns, maes = [p["n"] for p in pts], [p["mean"] for p in pts]
        fit = power_law(ns, maes)
        last = power_law(ns[-2:], maes[-2:])
        ext[band] = fit | {
            "target_deg": float(target),
            "n_target": n_for(fit["a"], fit["b"], target),
            "b_last_two": last["b"],
            "a_last_two": last["a"],
            "n_target_last_two": n_for(last["a"], last["b"], target),
        }
    figures["extrapolation"] = ext
    figures["load_case_extrapolation"] = load_case_laws(figures, targets)
    if "heldout_configurations" in figures:
        figures["where"] = where(figures)
        figures["physiological"] = physiological(figures, targets)
    s = figures["study_curve"]
    figures["study_power_law"] = power_law([p["n"] for p in s], [p["mae_deg"] for p in s])
    return figures


def heldout_covariates(heldout: pd.DataFrame, names: Sequence[str]) -> dict[str, dict]:
    """Per held-out configuration: its parameters, its mean FE RoM at 5 Nm over the load
    cases, and the FE points its failed jobs did not reach."""
    ok = heldout[heldout["status"] == "ok"]
    rom5 = ok[np.isclose(ok["moment_nm"], 5.0)].groupby("config_id")["rom_deg"].mean()
    lost = (heldout["status"] != "ok").groupby(heldout["config_id"]).sum()
    rom_max = ok[ok["moment_nm"] <= PHYSIOLOGICAL[1]].groupby("config_id")["rom_deg"].max()
    first = heldout.groupby("config_id")[list(names)].first()
    m = ok["moment_nm"].to_numpy()
    counts = {
        band: ok[(m > lo + 1e-9) & (m <= hi + 1e-9)].groupby("config_id").size()
        for band, (lo, hi) in BANDS.items()
    }
    return {
        str(int(i)): {
            **row.to_dict(),
            "rom_deg_5nm": float(rom5.get(i, np.nan)),
            "n_points_lost": int(lost.get(i, 0)),
            "rom_deg_max_7_5nm": float(rom_max.get(i, np.nan)),
            **{f"n_points_{b}": int(c.get(i, 0)) for b, c in counts.items()},
        }
        for i, row in first.iterrows()
    }


def where(figures: dict[str, Any], top: int = 6) -> dict[str, dict]:
    """Per band, at the FE recipe's largest n (mean over repeats): the share of the error the
    ``top`` worst held-out configurations carry, and the Spearman correlation of a
    configuration's error with each covariate (:func:`heldout_covariates`)."""
    from scipy.stats import spearmanr

    cov = pd.DataFrame(figures["heldout_configurations"]).T
    cov = cov[[c for c in cov.columns if not c.startswith(("n_points_0", "n_points_5"))]]
    n = max(p["n_train"] for p in figures["points"] if p["recipe"] == "fe")
    pts = [p for p in figures["points"] if p["recipe"] == "fe" and p["n_train"] == n]
    out = {}
    for band in BANDS:
        err = pd.DataFrame([p["bands"][band]["per_configuration_mae_deg"] for p in pts]).mean()
        worst = np.sort(err.to_numpy())[::-1]
        x = cov.loc[err.index].astype(float)
        out[band] = {
            "n_train": n,
            "median_configuration_mae_deg": float(np.median(worst)),
            f"top_{top}_share": float(worst[:top].sum() / worst.sum()),
            "spearman": {
                c: float(spearmanr(x[c], err.to_numpy(), nan_policy="omit").statistic)
                for c in x.columns
            },
        }
    return out


def physiological(figures: dict[str, Any], targets: Sequence[float]) -> dict[str, Any]:
    """The FE recipe's curve scored on the held-out configurations of :data:`PHYSIOLOGICAL`
    only (points pooled as in the band MAE), its power law and the n at each target."""
    cov = figures["heldout_configurations"]
    keep = {k for k, v in cov.items() if v["rom_deg_max_7_5nm"] < PHYSIOLOGICAL[0]}
    out: dict[str, Any] = {
        "n_configurations": len(keep),
        "rom_deg_below": PHYSIOLOGICAL[0],
        "up_to_nm": PHYSIOLOGICAL[1],
    }
    for band, target in zip(BANDS, targets):
        by_n: dict[int, list[float]] = {}
        for p in figures["points"]:
            if p["recipe"] == "fe":
                per = p["bands"][band]["per_configuration_mae_deg"]
                w = {k: cov[k][f"n_points_{band}"] for k in per if k in keep}
                mae = sum(per[k] * w[k] for k in w) / sum(w.values())
                by_n.setdefault(p["n_train"], []).append(mae)
        ns = sorted(by_n)
        maes = [float(np.mean(by_n[n])) for n in ns]
        fit, last = power_law(ns, maes), power_law(ns[-2:], maes[-2:])
        out[band] = {
            "n": ns,
            "mae_deg": maes,
            **fit,
            "b_last_two": last["b"],
            "n_target": n_for(fit["a"], fit["b"], target),
            "n_target_last_two": n_for(last["a"], last["b"], target),
        }
    return out


def load_case_laws(
    figures: dict[str, Any], targets: Sequence[float], factor: float = 1.5
) -> dict[str, dict[str, dict[str, float]]]:
    """Per band and load case: the FE recipe's power law (all n, and the last two n) and
    the configurations at which it reaches ``factor`` times the band's target."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for band, target in zip(BANDS, targets):
        out[band] = {}
        for case in LOAD_CASES:
            by_n: dict[int, list[float]] = {}
            for p in figures["points"]:
                if p["recipe"] == "fe":
                    by_n.setdefault(p["n_train"], []).append(p["bands"][band]["load_cases"][case])
            ns = sorted(by_n)
            maes = [float(np.mean(by_n[n])) for n in ns]
            fit, last = power_law(ns, maes), power_law(ns[-2:], maes[-2:])
            out[band][case] = {
                "mae_deg_at_largest_n": maes[-1],
                "target_deg": factor * target,
                "b": fit["b"],
                "n_target": n_for(fit["a"], fit["b"], factor * target),
                "b_last_two": last["b"],
                "n_target_last_two": n_for(last["a"], last["b"], factor * target),
            }
    return out


# ----------------------------------------------------------------------------------- main
def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--campaign", default="fe/data/campaign/runs.jsonl.gz")
    ap.add_argument("--prepared", help="an already prepared folder (skips the rebuild)")
    ap.add_argument("--work", help="folder of the rebuilt dataset (default: a temp folder)")
    ap.add_argument("--sizes", default="64,128,256,512", help="training configurations, FE recipe")
    ap.add_argument("--root-sizes", default="256,512", help="training configurations, root recipe")
    ap.add_argument("--members", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3, help="subsets (and seeds) per n")
    ap.add_argument("--max-epochs", type=int, help="cap on the recipes' max_epochs")
    ap.add_argument("--targets", default="0.04,0.08", help="MAE targets of the two bands, deg")
    ap.add_argument("--seed", type=int, default=0, help="repeat r permutes Large with seed + r")
    ap.add_argument(
        "--out", default=str(RESULTS / "bench_fe_learning_curve" / "bench_fe_learning_curve")
    )
    ap.add_argument("--figure", default="docs/figures/fe-learning-curve.png")
    ap.add_argument("--from-json", help="redraw the figure and tables from this JSON")
    args = ap.parse_args(argv)
    targets = [float(t) for t in args.targets.split(",")]
    out = REPO / args.out
    out.parent.mkdir(parents=True, exist_ok=True)

    if args.from_json:
        figures = json.loads(Path(args.from_json).read_text())
        if args.prepared:  # held-out covariates of a JSON written without them
            tables, space = load_tables(Path(args.prepared))
            figures["heldout_configurations"] = heldout_covariates(
                joined_heldout(tables), space.names
            )
        figures = summarise(figures, targets)
    else:
        os.environ.setdefault("MLFLOW_TRACKING_URI", f"file://{tempfile.mkdtemp()}/mlruns")
        fe_params = yaml.safe_load((REPO / "fe" / "params.yaml").read_text())
        root_params = yaml.safe_load((REPO / "params.yaml").read_text())
        if args.prepared:
            prepared = Path(args.prepared)
        else:
            work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="fe-lc-"))
            prepared = build_prepared(REPO / args.campaign, work)
        tables, space = load_tables(prepared)
        large = tables["large"]
        heldout = joined_heldout(tables)
        ids = np.unique(large["config_id"].to_numpy())
        tr_seed = int(fe_params["train"]["seed"])
        val_fraction = float(fe_params["train"]["val_fraction"])
        plan = [("fe", int(n)) for n in args.sizes.split(",") if n]
        plan += [("root", int(n)) for n in args.root_sizes.split(",") if n]
        figures = {
            "command": reproduce_command("bench_fe_learning_curve", argv),
            "campaign": args.campaign,
            "n_large": int(ids.size),
            "n_heldout": int(heldout["config_id"].nunique()),
            "n_heldout_points": int((heldout["status"] == "ok").sum()),
            "seed": args.seed,
            "repeats": args.repeats,
            "members": args.members,
            "max_epochs_cap": args.max_epochs,
            "torch_threads": 1,
            "targets_deg": dict(zip(BANDS, targets)),
            "study_curve": STUDY_CURVE,
            "recipes": {
                "fe": {"label": "FE recipe (128x3, batch 16)", **recipe("fe", fe_params, {})},
                "root": {
                    "label": "root recipe (256x4, batch 64)",
                    **recipe("root", fe_params, root_params),
                },
            },
            "heldout_configurations": heldout_covariates(heldout, space.names),
            "points": [],
        }
        for rep in range(args.repeats):
            # nested subsets: the first n of one permutation; each repeat its own permutation
            # and training seed
            order = np.random.default_rng(args.seed + rep).permutation(ids)
            for name, n in plan:
                keep = set(order[:n].tolist())
                train = large[large["config_id"].isin(keep)].reset_index(drop=True)
                point = fit_and_score(
                    train,
                    heldout,
                    space,
                    recipe(name, fe_params, root_params),
                    members=args.members,
                    seed=tr_seed + rep,
                    val_fraction=val_fraction,
                    max_epochs=args.max_epochs,
                )
                figures["points"].append({"recipe": name, "n_train": n, "repeat": rep, **point})
                b = point["bands"]
                print(
                    f"repeat {rep} {name} n={n}: 0.5-5 {b['0.5-5']['mae_deg']:.4f}, 5.5-10 "
                    f"{b['5.5-10']['mae_deg']:.4f} deg ({point['epochs']} epochs, "
                    f"{point['cpu_seconds']:.0f} CPU s, {point['wall_seconds']:.0f} s)",
                    flush=True,
                )
                Path(f"{out}.json").write_text(json.dumps(figures, indent=2) + "\n")
        figures = summarise(figures, targets)
    Path(f"{out}.json").write_text(json.dumps(figures, indent=2) + "\n")
    text = markdown(figures)
    Path(f"{out}.md").write_text(text)
    figure(figures, REPO / args.figure)
    print(text)


if __name__ == "__main__":
    main()
