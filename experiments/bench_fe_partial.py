"""Benchmark: what limits the FE surrogate at 5.5-10 Nm, and what the failed runs' levels buy.

The FE surrogate (``fe/dvc.yaml`` ``train@large``) misses the 5.5-10 Nm bar of issue 54 while it
meets the 0.5-5 Nm one. This benchmark decomposes its held-out error and trains the fixed
recipe on variants of the same Large split to measure what moves that band.

* **Data.** The FE pipeline's prepared folder (``--prepared``, default ``fe/data/prepared``):
  a failed CalculiX job keeps the levels it reached (``status`` ``ok``, the RoM it reached) and
  only its unreached levels are ``failed`` (NaN); training rows are the ``ok`` rows
  (:func:`femcal.datasets.ok_rows`), the loss a mean over them (the padded rows of a
  configuration's block are masked out: :mod:`femcal.surrogates.romnet_training`).
* **Held out.** The Test split (what ``python -m femcal.fe.heldout`` scores) and Small + Test
  (64 configurations), each at every level FE reached and on the complete curves only (the
  curves of jobs that reached 10 Nm), so that variants compare like with like.
* **Decomposition** (``--model``, a saved surrogate; default ``fe/models/surrogate-large``): MAE
  by band and load case, by moment, by the held-out disc's softness (its FE RoM at 5 Nm, mean
  over the load cases), by the failed jobs around it (the failed fraction of the same load
  case among its ``--k`` nearest Large configurations in the unit box), by whether its own job
  completed, and relative to the RoM; the share of the error the worst configurations carry.
* **Variants** (``--variants``), each :class:`femcal.surrogates.nn.NeuralSurrogate` fitted as
  ``femcal train`` fits its final model (``train.large.fixed``, ``train.large.final_members``
  members, seed ``--seed``; one validation split of the configurations drawn on the whole
  table, the same for every variant):

  - ``reached``: every level FE reached (what ``femcal train`` learns);
  - ``complete``: the curves FE completed only (the reached levels of failed jobs left out);
  - ``minus-soft``, ``minus-stiff``: ``reached`` less ``--n-drop`` training configurations
    drawn at random among those softer (stiffer) than the median RoM at 5 Nm: the value of
    the data's density in each half of the box.

Writes ``bench_fe_partial.json`` (``--out``); ``--from-json`` prints its tables again.

Usage (from the project root; one fit at a time, about 5 CPU-minutes each)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_fe_partial
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from experiments.common import REPO, RESULTS, reproduce_command
from femcal.schema import LOAD_CASES, STATUS_OK

#: Moment bands, (lo, hi] in Nm: those of issue 54's bars.
BANDS = {"0.5-5": (0.0, 5.0), "5.5-10": (5.0, 10.0)}
#: The variants :func:`variant_rows` knows.
VARIANTS = ("reached", "complete", "minus-soft", "minus-stiff")
FEATURES = ["config_id", "load_case", "moment_nm"]
_EPS = 1e-9


# ---------------------------------------------------------------------------------- data
def load_tables(prepared: Path) -> tuple[dict[str, pd.DataFrame], Any]:
    """The prepared splits (every row, failed ones included) and the parameter space; each
    row carries ``complete``: whether its job reached the last moment."""
    from femcal.datasets import load_split

    tables = {}
    for split in ("large", "small", "test"):
        table, space = load_split(prepared, split)
        failed = (
            (table["status"] != STATUS_OK)
            .groupby([table["config_id"], table["load_case"]])
            .transform("any")
        )
        tables[split] = table.assign(complete=~failed.to_numpy())
    return tables, space


def softness(table: pd.DataFrame) -> pd.Series:
    """Per configuration: its FE RoM at 5 Nm (deg), mean over the load cases that reached it;
    +inf for a configuration none of whose jobs reached 5 Nm (the softest)."""
    ok = table[(table["status"] == STATUS_OK) & np.isclose(table["moment_nm"], 5.0)]
    rom5 = ok.groupby("config_id")["rom_deg"].mean()
    return rom5.reindex(np.unique(table["config_id"])).fillna(np.inf)


def failed_nearby(large: pd.DataFrame, heldout: pd.DataFrame, space: Any, k: int) -> pd.Series:
    """Per held-out (config_id, load_case): the failed fraction of the same load case's jobs
    among the ``k`` Large configurations nearest to it in the unit box (Euclidean)."""
    names = list(space.names)
    lx = large.groupby("config_id")[names].first()
    failed = (large["status"] != STATUS_OK).groupby([large["config_id"], large["load_case"]]).any()
    hx = heldout.groupby("config_id")[names].first()
    ul, uh = space.to_unit(lx.to_numpy(float)), space.to_unit(hx.to_numpy(float))
    dist = np.linalg.norm(uh[:, None, :] - ul[None, :, :], axis=2)
    near = lx.index.to_numpy()[np.argsort(dist, axis=1)[:, :k]]  # (n_heldout, k)
    out = {}
    for i, cid in enumerate(hx.index):
        for lc in LOAD_CASES:
            out[(cid, lc)] = float(np.mean([failed.get((c, lc), False) for c in near[i]]))
    return pd.Series(out)


def joined_heldout(tables: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """Small and Test as one table, Test's config ids after Small's, with ``split``."""
    small, test = tables["small"], tables["test"]
    test = test.assign(config_id=test["config_id"] + int(small["config_id"].max()) + 1)
    return pd.concat([small.assign(split="small"), test.assign(split="test")], ignore_index=True)


# ------------------------------------------------------------------------------- scoring
def scored_rows(model: Any, heldout: pd.DataFrame, space: Any) -> pd.DataFrame:
    """The held-out rows FE reached with the model's absolute error ``err`` (deg), relative
    error ``rel`` and ``band``."""
    rows = heldout[heldout["status"] == STATUS_OK].reset_index(drop=True)
    pred = np.asarray(model.predict(rows[[*FEATURES, *space.names]]), dtype=float)
    rom = rows["rom_deg"].to_numpy(float)
    m = rows["moment_nm"].to_numpy(float)
    band = np.where(m <= BANDS["0.5-5"][1] + _EPS, "0.5-5", "5.5-10")
    return rows.assign(err=np.abs(pred - rom), rel=np.abs(pred - rom) / rom, band=band)


def band_table(rows: pd.DataFrame) -> dict[str, Any]:
    """MAE (deg) by band, with its load cases, points, relative MAE and mean FE RoM."""
    out = {}
    for band, sub in rows.groupby("band"):
        out[band] = {
            "mae_deg": float(sub["err"].mean()),
            "n_points": len(sub),
            "relative_mae": float(sub["rel"].mean()),
            "mean_rom_deg": float(sub["rom_deg"].mean()),
            "load_cases": {lc: float(g["err"].mean()) for lc, g in sub.groupby("load_case")},
        }
    return out


def scores(rows: pd.DataFrame) -> dict[str, Any]:
    """:func:`band_table` on Test and on Small + Test, each at every reached level and on the
    complete curves only."""
    out = {}
    for name, sel in (("test", rows["split"] == "test"), ("small+test", rows["split"] != "")):
        sub = rows[sel]
        out[name] = {
            "reached": band_table(sub),
            "complete": band_table(sub[sub["complete"]]),
        }
    return out


def by_bins(rows: pd.DataFrame, column: str, edges: Sequence[float]) -> list[dict[str, Any]]:
    """The 5.5-10 Nm rows grouped by ``column`` in ``edges`` (right-closed): points, MAE,
    relative MAE, mean FE RoM and the bin's share of the band's summed error."""
    hi = rows[rows["band"] == "5.5-10"]
    total = float(hi["err"].sum())
    cut = pd.cut(hi[column], bins=list(edges), include_lowest=True)
    out = []
    for interval, sub in hi.groupby(cut, observed=True):
        out.append(
            {
                "bin": str(interval),
                "n_points": len(sub),
                "n_configurations": int(sub["config_id"].nunique()),
                "mae_deg": float(sub["err"].mean()),
                "relative_mae": float(sub["rel"].mean()),
                "mean_rom_deg": float(sub["rom_deg"].mean()),
                "error_share": float(sub["err"].sum() / total),
            }
        )
    return out


def decompose(rows: pd.DataFrame, near: pd.Series, soft: pd.Series) -> dict[str, Any]:
    """Where the held-out error sits (module docstring), on Small + Test."""
    rows = rows.assign(
        failed_nearby=[near[(c, lc)] for c, lc in zip(rows["config_id"], rows["load_case"])],
        rom_5nm=soft.reindex(rows["config_id"]).to_numpy(),
        completed=rows["complete"].astype(float),
    )
    quart = np.quantile(soft[np.isfinite(soft)], [0.25, 0.5, 0.75])
    by_moment = {
        f"{m:g}": {
            "mae_deg": float(g["err"].mean()),
            "relative_mae": float(g["rel"].mean()),
            "n_points": len(g),
            "mae_deg_complete": float(g.loc[g["complete"], "err"].mean()),
        }
        for m, g in rows.groupby("moment_nm")
    }
    per_config = rows[rows["band"] == "5.5-10"].groupby("config_id")["err"].mean()
    worst = np.sort(per_config.to_numpy())[::-1]
    hi = rows[rows["band"] == "5.5-10"]
    return {
        "by_moment": by_moment,
        "by_softness": by_bins(rows, "rom_5nm", [0.0, *quart, np.inf]),
        "softness_quartiles_deg": quart.tolist(),
        "by_failed_nearby": by_bins(rows, "failed_nearby", [-0.01, 0.0, 0.1, 0.3, 1.0]),
        "by_own_job": by_bins(rows, "completed", [-0.5, 0.5, 1.5]),
        "by_rom_deg": by_bins(rows, "rom_deg", [0.0, 5.0, 10.0, 20.0, 40.0, np.inf]),
        "load_case_x_failed_nearby": {
            lc: by_bins(g, "failed_nearby", [-0.01, 0.1, 1.0])
            for lc, g in rows.groupby("load_case")
        },
        "worst_configurations_5_10": {
            "n": int(worst.size),
            "top_4_share": float(worst[:4].sum() / worst.sum()),
            "top_8_share": float(worst[:8].sum() / worst.sum()),
            "median_mae_deg": float(np.median(worst)),
        },
        "spearman_5_10": _spearman(hi, per_config),
    }


def _spearman(hi: pd.DataFrame, per_config: pd.Series) -> dict[str, float]:
    """Spearman correlation of a configuration's 5.5-10 Nm MAE with its covariates."""
    from scipy.stats import spearmanr

    cov = hi.groupby("config_id")[["rom_5nm", "failed_nearby", "completed"]].mean()
    cov = cov.loc[per_config.index]
    return {
        c: float(spearmanr(cov[c], per_config.to_numpy(), nan_policy="omit").statistic)
        for c in cov.columns
    }


# ------------------------------------------------------------------------------- variants
def variant_rows(
    name: str, train: pd.DataFrame, soft: pd.Series, n_drop: int, seed: int
) -> pd.DataFrame:
    """The training rows of a variant (module docstring) from the fitted rows ``train``."""
    if name == "reached":
        return train
    if name == "complete":
        return train[train["complete"]]
    if name in ("minus-soft", "minus-stiff"):
        ids = np.unique(train["config_id"])
        s = soft.reindex(ids).to_numpy()
        median = np.median(s[np.isfinite(s)])
        pool = ids[s > median] if name == "minus-soft" else ids[s <= median]
        drop = np.random.default_rng(seed).choice(pool, size=min(n_drop, pool.size), replace=False)
        return train[~train["config_id"].isin(drop)]
    raise ValueError(f"unknown variant {name!r}; choose from {', '.join(VARIANTS)}")


def fit_variant(
    name: str,
    large: pd.DataFrame,
    space: Any,
    fixed: dict[str, Any],
    options: dict[str, Any],
) -> tuple[Any, dict[str, Any]]:
    """One variant fitted as ``femcal train`` fits its final model; the model and its facts.

    ``options``: ``members``, ``seed``, ``val_fraction``, ``n_drop``, ``soft`` (a
    :func:`softness` series of ``large``).
    """
    import torch

    from femcal.datasets import ok_rows
    from femcal.surrogates.nn import NeuralSurrogate
    from femcal.train import surrogate_kwargs, validation_split

    torch.set_num_threads(1)
    seed = int(options["seed"])
    tr, va = validation_split(ok_rows(large), fraction=options["val_fraction"], seed=seed)
    tr = variant_rows(name, tr, options["soft"], int(options["n_drop"]), seed)
    cols = [*FEATURES, *space.names]
    model = NeuralSurrogate(
        space, **surrogate_kwargs(fixed), n_members=int(options["members"]), seed=seed
    )
    t0, w0 = time.process_time(), time.perf_counter()
    model.fit(tr[cols], tr["rom_deg"].to_numpy(float), X_val=va[cols], y_val=va["rom_deg"])
    facts = {
        "variant": name,
        "seed": seed,
        "n_fitted_configurations": int(tr["config_id"].nunique()),
        "n_fitted_rows": len(tr),
        "n_fitted_rows_5_10": int((tr["moment_nm"] > 5.0 + _EPS).sum()),
        "n_validation_configurations": int(va["config_id"].nunique()),
        "best_val_mae_deg": float(model.best_val_mae_deg_),
        "cpu_seconds": round(time.process_time() - t0, 1),
        "wall_seconds": round(time.perf_counter() - w0, 1),
    }
    return model, facts


# ------------------------------------------------------------------------------- report
def markdown(figures: dict[str, Any]) -> str:
    """The figures as Markdown tables."""
    lines = [
        "| variant | seed | fitted configs / rows at 5.5-10 Nm | held out | points | "
        "0.5-5 Nm | 5.5-10 Nm | Flex / Ext / LB / AR at 5.5-10 | CPU s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for fit in figures.get("fits", []):
        for held in ("test", "small+test"):
            for which in ("reached", "complete"):
                b = fit["scores"][held][which]
                hi = b["5.5-10"]
                cases = " / ".join(f"{hi['load_cases'][lc]:.3f}" for lc in LOAD_CASES)
                lines.append(
                    f"| {fit['variant']} | {fit['seed']} | {fit['n_fitted_configurations']} / "
                    f"{fit['n_fitted_rows_5_10']} | {held} | {which} | "
                    f"{b['0.5-5']['mae_deg']:.4f} | {hi['mae_deg']:.4f} | {cases} | "
                    f"{fit['cpu_seconds']} |"
                )
    dec = figures.get("decomposition")
    if dec:
        lines += ["", "```", json.dumps(dec, indent=1), "```"]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> None:
    """Command line (module docstring)."""
    p = argparse.ArgumentParser(prog="python -m experiments.bench_fe_partial", description=__doc__)
    p.add_argument("--prepared", type=Path, default=REPO / "fe" / "data" / "prepared")
    p.add_argument("--params", type=Path, default=REPO / "fe" / "params.yaml")
    p.add_argument("--model", default=str(REPO / "fe" / "models" / "surrogate-large"))
    p.add_argument("--variants", default="", help="comma-separated, of " + ", ".join(VARIANTS))
    p.add_argument("--seeds", default="0", help="comma-separated training seeds")
    p.add_argument("--n-drop", type=int, default=128)
    p.add_argument("--k", type=int, default=10)
    p.add_argument("--out", type=Path, default=RESULTS / "bench_fe_partial")
    p.add_argument("--from-json", action="store_true")
    args = p.parse_args(argv)
    out_json = args.out / "bench_fe_partial.json"
    if args.from_json:
        print(markdown(json.loads(out_json.read_text())))
        return
    args.out.mkdir(parents=True, exist_ok=True)
    figures = json.loads(out_json.read_text()) if out_json.exists() else {"fits": []}
    figures["command"] = reproduce_command("bench_fe_partial", argv)
    tables, space = load_tables(args.prepared)
    heldout = joined_heldout(tables)
    soft_large = softness(tables["large"])
    if args.model:
        from femcal.tracking import load_surrogate, open_model

        model = load_surrogate(open_model(args.model))
        rows = scored_rows(model, heldout, space)
        near = failed_nearby(tables["large"], heldout, space, args.k)
        figures["decomposition"] = {
            "model": args.model,
            "scores": scores(rows),
            **decompose(rows, near, softness(heldout)),
        }
    params = yaml.safe_load(args.params.read_text())
    section = params["train"]["large"]
    options = {
        "members": section.get("final_members", 3),
        "val_fraction": params["train"].get("val_fraction", 0.15),
        "n_drop": args.n_drop,
        "soft": soft_large,
    }
    for seed in [int(s) for s in args.seeds.split(",") if s]:
        for name in [v for v in args.variants.split(",") if v]:
            model, facts = fit_variant(
                name, tables["large"], space, dict(section["fixed"]), {**options, "seed": seed}
            )
            facts["scores"] = scores(scored_rows(model, heldout, space))
            figures["fits"] = [
                f for f in figures["fits"] if (f["variant"], f["seed"]) != (name, seed)
            ] + [facts]
            out_json.write_text(json.dumps(figures, indent=1) + "\n")
            print(json.dumps({k: v for k, v in facts.items() if k != "scores"}))
    out_json.write_text(json.dumps(figures, indent=1) + "\n")
    print(markdown(figures))


if __name__ == "__main__":
    main()
