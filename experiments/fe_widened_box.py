"""The remedy for discs outside the box, run on the CalculiX model: widen, simulate, retrain.

The out-of-box reading of ``femcal diagnose`` (experiments/fe_outside_box.py: 16 CalculiX
discs whose five stiffnesses lie above the FE campaign's box) asks for a wider box. This
experiment runs that remedy and measures whether the error falls.

* **Widened box** (:func:`widened_bounds`): fe/params.yaml ``fe.bounds`` with the upper
  bounds of ``C10Nucleus``, ``C01Nucleus``, ``C10Annulus``, ``K1Annulus``, ``K2Annulus``
  times ``--factor`` (the outside discs' factor, 2).
* **Widened campaign** (``campaign``): a seeded Latin hypercube of ``--n-new`` configurations
  over the widened box, those outside the old box kept (:func:`added_design`), run in CalculiX
  with fe/params.yaml's ``fe.settings``, load cases and moments (0.5..10 Nm) on 2 Dask workers;
  its own store (``--store``, committed, resumed when present).
* **New surrogate** (``train``): fe/params.yaml's ``train.large.fixed`` recipe trained with
  femcal's training API on the FE campaign's Large split plus the added configurations.
* **Scored** (``score``): the held-out error inside the old box (the FE Test split, 0.5-5 and
  5.5-10 Nm) of the old and the new surrogate, and the disc-alone MAE and verdicts of the 16
  outside discs (``femcal diagnose`` and ``femcal calibrate --effects ''`` with each
  surrogate), and the added campaign's CalculiX CPU time.

Usage (from the project root; FE tables of the campaign in ``PREP``, e.g.
/tmp/ferun/fe/data/prepared; the outside discs' folder ``OUT`` from
``python -m experiments.fe_outside_box --out OUT``; the old surrogate ``OLD``, e.g.
fe/models/surrogate-large; ``MLFLOW_TRACKING_URI`` set for the training run)::

    nice -n 10 .venv/bin/python -m experiments.fe_widened_box campaign
    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m experiments.fe_widened_box train \\
        --prepared PREP --members 3 --out DIR
    # for M, D, C in (OLD, OUT/diagnosis-old, OUT/calibration-old), (DIR/surrogate,
    # DIR/diagnosis, DIR/calibration):
    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/femcal diagnose --measurements OUT/measurements.csv \\
        --noise-deg 0.05 --plots false --model-uri M --out D
    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/femcal calibrate --effects '' --no-holdout \\
        --plots none --measurements OUT/measurements.csv --noise-deg 0.05 --model-uri M --out C
    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.fe_widened_box score --prepared PREP \\
        --out DIR --old-model OLD --old-diagnosis OUT/diagnosis-old \\
        --old-calibration OUT/calibration-old

``score`` writes ``DIR/widened_box.json``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from experiments.common import REPO
from experiments.fe_outside_box import STIFFNESSES

#: Added configurations are numbered from here (the campaign's splits number theirs from 0).
ID_OFFSET = 100_000


def widened_bounds(bounds: Mapping[str, Sequence[float]], factor: float) -> dict:
    """The box the out-of-box reading asks for: ``bounds`` with the upper bound of every
    stiffness in :data:`STIFFNESSES` times ``factor``, every other bound unchanged.

    Parameters
    ----------
    bounds : mapping of str to [lower, upper]
        fe/params.yaml ``fe.bounds`` (physical units).
    factor : float
        Widening of the stiffnesses' upper bounds (> 1).

    Returns
    -------
    dict of str to [float, float]
    """
    return {
        name: [float(lo), float(hi) * (factor if name in STIFFNESSES else 1.0)]
        for name, (lo, hi) in bounds.items()
    }


def outside(x: np.ndarray, names: Sequence[str], bounds: Mapping[str, Sequence[float]]):
    """Whether each row of ``x`` (shape (n, d), columns ``names``) lies outside ``bounds``
    (some parameter below its lower or above its upper bound); shape (n,), bool."""
    lo = np.array([bounds[n][0] for n in names], dtype=float)
    hi = np.array([bounds[n][1] for n in names], dtype=float)
    return np.any((x < lo) | (x > hi), axis=1)


def added_design(bounds: Mapping[str, Sequence[float]], factor: float, n: int, seed: int):
    """The widened campaign's added configurations: a Latin hypercube of ``n`` points over
    :func:`widened_bounds` (``default_rng(seed)``), the points outside the old box kept.

    Returns
    -------
    pandas.DataFrame, shape (k, 1 + d), k <= n
        ``config_id`` (``ID_OFFSET`` + index in the hypercube) and the parameters.
    """
    from femcal.fe.design import latin_hypercube
    from femcal.fe.runtime import fe_space

    wide = widened_bounds(bounds, factor)
    space = fe_space(wide)
    x = space.clip(latin_hypercube(space, n, np.random.default_rng(seed)))
    keep = outside(x, list(space.names), bounds)
    df = pd.DataFrame(x[keep], columns=list(space.names))
    df.insert(0, "config_id", ID_OFFSET + np.flatnonzero(keep).astype(np.int64))
    return df


def run_added(params: Mapping, design_df: pd.DataFrame, store: Path, n_workers: int):
    """Run (or resume from ``store``) the added configurations in CalculiX: fe.settings, the
    four load cases at fe.moments; returns the :class:`~femcal.fe.campaign.CampaignResult`."""
    from femcal.fe.runtime import FeRuntime

    fe = params["fe"]
    runtime = FeRuntime(fe["solver"], dict(fe["settings"]), store, n_workers=n_workers)
    return runtime.campaign(
        design_df,
        names=list(fe["bounds"]),
        load_cases=list(fe["load_cases"]),
        moments=[float(m) for m in fe["moments"]],
    )


def cmd_campaign(args: argparse.Namespace, params: Mapping) -> None:
    design_df = added_design(params["fe"]["bounds"], args.factor, args.n_new, args.seed)
    print(f"{len(design_df)} of {args.n_new} hypercube points outside the old box", flush=True)
    result = run_added(params, design_df, args.store, args.workers)
    status = result.records["status"].value_counts().to_dict()
    print(
        json.dumps(
            {
                "n_configs": len(design_df),
                "n_jobs": result.n_jobs,
                "n_run": result.n_run,
                "n_skipped": result.n_skipped,
                "status": {str(k): int(v) for k, v in status.items()},
                "errors": len(result.errors),
                "wall_s": result.wall_seconds,
            },
            indent=2,
        )
    )


def added_table(records: Sequence[Mapping], names: Sequence[str]) -> pd.DataFrame:
    """The added configurations' store records as a tidy table (the prepared tables' columns).

    Each job gives one row per moment level; a level is ``ok`` while the curve is reached (the
    leading run of finite positive RoM values, as the FE dataset reads a run), ``failed``
    after it (RoM left empty).

    Parameters
    ----------
    records : sequence of mapping
        Store records (:func:`femcal.fe.store.load_records`): ``config_id``, ``load_case``,
        ``levels`` (Nm, shape (m,)), ``rom_deg`` and ``idp_mpa`` (shape (m,), None where not
        reached) and ``parameters``.
    names : sequence of str
        The parameter columns.

    Returns
    -------
    pandas.DataFrame, shape (sum of m over jobs, 3 + d + 3)
        ``config_id``, ``load_case``, ``moment_nm``, the parameters, ``rom_deg``, ``idp_mpa``,
        ``status``.
    """
    rows = []
    for rec in records:
        reached = True
        for j, moment in enumerate(rec["levels"]):
            rom = rec["rom_deg"][j] if j < len(rec["rom_deg"] or []) else None
            idp = rec["idp_mpa"][j] if j < len(rec["idp_mpa"] or []) else None
            reached = reached and rom is not None and np.isfinite(rom) and rom > 0.0
            rows.append(
                {
                    "config_id": int(rec["config_id"]),
                    "load_case": rec["load_case"],
                    "moment_nm": float(moment),
                    **{n: float(rec["parameters"][n]) for n in names},
                    "rom_deg": float(rom) if reached else np.nan,
                    "idp_mpa": float(idp) if reached and idp is not None else np.nan,
                    "status": "ok" if reached else "failed",
                }
            )
    return pd.DataFrame(rows)


def complete_configs(table: pd.DataFrame, n_load_cases: int) -> pd.DataFrame:
    """The rows of the configurations whose every load case is in ``table`` (a campaign
    stopped early leaves some with fewer)."""
    cases = table.groupby("config_id")["load_case"].nunique()
    return table[table["config_id"].isin(cases[cases == n_load_cases].index)]


def cmd_train(args: argparse.Namespace, params: Mapping) -> None:
    import mlflow

    from femcal.fe.runtime import fe_space
    from femcal.fe.store import load_records
    from femcal.stages.store import export_folder
    from femcal.train import train_surrogate

    names = list(params["fe"]["bounds"])
    old = pd.read_csv(args.prepared / "large.csv", keep_default_na=False, na_values=[""])
    added = complete_configs(
        added_table(load_records(args.store), names), len(params["fe"]["load_cases"])
    )
    table = pd.concat([old, added[old.columns]], ignore_index=True)
    space = fe_space(widened_bounds(params["fe"]["bounds"], args.factor))
    mlflow.set_experiment("femcal-fe-widened-box")
    train = params["train"]
    result = train_surrogate(
        table,
        space,
        final_members=args.members,
        val_fraction=float(train["val_fraction"]),
        run_name="train-widened-box",
        study_name="fe-widened-box",
        fixed=dict(train["large"]["fixed"]),
        n_trials=0,
        seed=int(train["seed"]),
    )
    args.out.mkdir(parents=True, exist_ok=True)
    export_folder(result, args.out / "surrogate", None)
    figures = {
        "n_configs_old": int(old["config_id"].nunique()),
        "n_configs_added": int(added["config_id"].nunique()),
        "members": args.members,
        "val_mae_deg": result.val_mae_deg,
        "seconds": result.seconds,
    }
    (args.out / "train.json").write_text(json.dumps(figures, indent=2) + "\n")
    print(json.dumps(figures, indent=2))


def disc_alone(diagnosis_dir: Path) -> pd.DataFrame:
    """Per specimen of ``diagnosis_dir`` (a ``femcal diagnose`` output): the disc-alone MAE
    (deg), the verdict and whether the out-of-box reading is named."""
    rows = [
        {
            "specimen": rec["specimen"],
            "disc_mae_deg": float(rec["baseline_mae_deg"]),
            "verdict": rec["verdict"],
            "outside_box": bool((rec.get("outside_box") or {}).get("named")),
        }
        for rec in json.loads((diagnosis_dir / "diagnosis.json").read_text())
    ]
    return pd.DataFrame(rows).set_index("specimen")


def cmd_score(args: argparse.Namespace, params: Mapping) -> None:
    from femcal.fe.heldout import heldout_errors
    from femcal.fe.hidden import visible_threshold
    from femcal.fe.store import load_records
    from femcal.tracking import load_surrogate

    test = pd.read_csv(args.prepared / "test.csv", keep_default_na=False, na_values=[""])
    large = pd.read_csv(args.prepared / "large.csv", keep_default_na=False, na_values=[""])
    figures: dict = {"heldout": {}}
    for label, uri in (("old", args.old_model), ("new", args.out / "surrogate")):
        errors = heldout_errors(load_surrogate(uri), test, large)
        figures["heldout"][label] = {
            k: errors[k] for k in ("heldout_mae_deg_0_5", "heldout_mae_deg_5_10")
        }
    old, new = disc_alone(args.old_diagnosis), disc_alone(args.out / "diagnosis")
    summary = json.loads((args.old_diagnosis / "summary.json").read_text())
    visible = old["disc_mae_deg"] > visible_threshold(summary, summary["noise_deg"])
    table = old.add_suffix("_old").join(new.add_suffix("_new")).assign(visible_old=visible)
    for label, folder in (("old", args.old_calibration), ("new", args.out / "calibration")):
        metrics = pd.read_csv(folder / "metrics.csv").set_index("specimen")
        table[f"calibrate_mae_deg_{label}"] = metrics["mae_deg"]
        table[f"beyond_noise_{label}"] = metrics["flag"].astype(str).str.contains("beyond noise")
        figures[f"calibrate_mae_all_{label}"] = float(metrics["mae_deg"].mean())
    figures["discs"] = table.reset_index().to_dict(orient="records")
    figures["mae_all_old"] = float(table["disc_mae_deg_old"].mean())
    figures["mae_all_new"] = float(table["disc_mae_deg_new"].mean())
    figures["outside_box_old"] = int(table["outside_box_old"].sum())
    figures["outside_box_new"] = int(table["outside_box_new"].sum())
    records = load_records(args.store)
    figures["campaign"] = {
        "jobs": len(records),
        "configs": len({r["config_id"] for r in records}),
        "failed_jobs": sum(r["status"] != "ok" for r in records),
        "ccx_cpu_hours": sum(float(r.get("cpu_seconds") or 0.0) for r in records) / 3600,
        "worker_cpu_hours": sum(float(r.get("worker_cpu_seconds") or 0.0) for r in records) / 3600,
    }
    (args.out / "widened_box.json").write_text(json.dumps(figures, indent=2) + "\n")
    print(table.to_string())
    print(json.dumps({k: v for k, v in figures.items() if k != "discs"}, indent=2))


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.fe_widened_box")
    parser.add_argument("command", choices=["campaign", "train", "score"])
    parser.add_argument("--store", type=Path, default=REPO / "experiments/fe_widened_box.jsonl.gz")
    parser.add_argument("--factor", type=float, default=2.0)
    parser.add_argument("--n-new", type=int, default=128)
    parser.add_argument("--seed", type=int, default=20261203)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--prepared", type=Path, default=Path("/tmp/ferun/fe/data/prepared"))
    parser.add_argument("--out", type=Path, default=Path("/tmp/W/widened"))
    parser.add_argument("--members", type=int, default=3)
    parser.add_argument(
        "--old-model", type=Path, default=Path("/tmp/ferun/fe/models/surrogate-large")
    )
    parser.add_argument("--old-diagnosis", type=Path, default=Path("/tmp/W/outside/diagnosis-old"))
    parser.add_argument(
        "--old-calibration", type=Path, default=Path("/tmp/W/outside/calibration-old")
    )
    args = parser.parse_args(argv)
    params = yaml.safe_load((REPO / "fe" / "params.yaml").read_text())
    {"campaign": cmd_campaign, "train": cmd_train, "score": cmd_score}[args.command](args, params)


if __name__ == "__main__":
    main()
