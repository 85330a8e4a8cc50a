"""Benchmark: how honest is the FE surrogate's stated error, and what would a local one give?

The diagnosis and calibrate count the surrogate's own error as an sd at each moment
(:meth:`femcal.moments.MomentPolicy.sigma_surrogate`). This benchmark trains the FE pipeline's
recipe (fe/params.yaml ``train.large``: its ``fixed`` keywords, ``final_members`` members, the
validation split of ``femcal train``) on the campaign's Large split and compares three sds on
the held-out configurations:

* ``global``: one sd at every moment, the validation MAE times sqrt(pi / 2);
* ``profile``: the validation error by moment (``val_error_profile_``'s ``rms_deg``);
* ``relative``: the validation error relative to the RoM by moment times each point's RoM
  (``relative_rms``: what the diagnosis counts at a specimen's own curves);
* ``spread``: the members' spread at each point times a factor per moment band, the factor
  chosen on the Small split so that 95 % of its errors lie within 2 sd, scored on Test (a
  local sd: where the specimen sits in the parameter box).

For each: the share of errors within 2 sd (a calibrated sd gives 90-98 %) and the median and
mean sd per moment band (a sharper sd makes smaller effects visible).

Data as in :mod:`experiments.bench_fe_learning_curve` (the store's base splits rebuilt
without CalculiX, or ``--prepared``). Writes ``bench_fe_sigma.json`` and ``.md`` (``--out``).

Usage (from the project root; one training of ``final_members`` members, ~10 CPU-minutes)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_fe_sigma
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
import yaml

from experiments.bench_fe_learning_curve import build_prepared
from experiments.common import REPO, RESULTS, reproduce_command
from femcal.fe.sigma import BANDS, sigma_coverage
from femcal.moments import MomentPolicy
from femcal.schema import LOAD_CASES

#: The share of errors within 2 sd that the spread factor is chosen for, on the Small split.
SPREAD_COVERAGE = 0.95


def train_fe_recipe(prepared: Path) -> Any:
    """The FE recipe fitted as ``femcal train`` fits it, without MLflow."""
    from femcal.space import ParameterSpace
    from femcal.surrogates.nn import NeuralSurrogate
    from femcal.train import surrogate_kwargs, validation_split

    params = yaml.safe_load((REPO / "fe" / "params.yaml").read_text())["train"]
    space = ParameterSpace.from_dict(json.loads((prepared / "parameter_space.json").read_text()))
    table = pd.read_csv(prepared / "large.csv")
    table = table[np.isfinite(table["rom_deg"])]
    train, val = validation_split(table, fraction=params["val_fraction"], seed=params["seed"])
    cols = ["config_id", "load_case", "moment_nm", *space.names]
    large = params["large"]
    model = NeuralSurrogate(
        space,
        **surrogate_kwargs(large["fixed"]),
        n_members=int(large["final_members"]),
        seed=params["seed"],
    )
    return model.fit(
        train[cols],
        train["rom_deg"].to_numpy(float),
        X_val=val[cols],
        y_val=val["rom_deg"].to_numpy(float),
    )


def validation_profile(model: Any, prepared: Path) -> Any:
    """``model`` with its error profile measured again on the validation split of
    ``femcal train`` (a model saved without ``relative_rms``)."""
    from femcal.train import validation_split

    params = yaml.safe_load((REPO / "fe" / "params.yaml").read_text())["train"]
    table = pd.read_csv(prepared / "large.csv")
    table = table[np.isfinite(table["rom_deg"])]
    _, val = validation_split(table, fraction=params["val_fraction"], seed=params["seed"])
    pred = model.predict(val)
    return model.record_validation_error(
        val["moment_nm"].to_numpy(float), pred - val["rom_deg"].to_numpy(float), pred
    )


def errors_and_spread(model: Any, table: pd.DataFrame) -> pd.DataFrame:
    """Per reached point: moment, error (deg) and the members' sd (deg)."""
    rows = table[np.isfinite(table["rom_deg"])].reset_index(drop=True)
    lc = torch.tensor([LOAD_CASES.index(c) for c in rows["load_case"]])
    moment = torch.tensor(rows["moment_nm"].to_numpy(float), dtype=torch.float32)
    par = torch.tensor(rows[list(model.space.names)].to_numpy(float), dtype=torch.float32)
    with torch.no_grad():
        members = model.torch_module().members_degrees(lc, moment, par).double().numpy()
    return pd.DataFrame(
        {
            "moment_nm": rows["moment_nm"].to_numpy(float),
            "error_deg": members.mean(0) - rows["rom_deg"].to_numpy(float),
            "spread_deg": members.std(0, ddof=1),
        }
    )


def _in(band: tuple[float, float], moment: np.ndarray) -> np.ndarray:
    return (moment >= band[0] - 1e-9) & (moment <= band[1] + 1e-9)


def spread_sd(calibration: pd.DataFrame, scored: pd.DataFrame) -> dict[str, Any]:
    """The spread times a factor per band chosen on ``calibration``, scored on ``scored``."""
    out: dict[str, Any] = {}
    for band in BANDS:
        name = f"{band[0]:g}-{band[1]:g}"
        c = calibration[_in(band, calibration["moment_nm"].to_numpy())]
        s = scored[_in(band, scored["moment_nm"].to_numpy())]
        ratio = np.abs(c["error_deg"]) / np.maximum(c["spread_deg"], 1e-9)
        factor = float(np.quantile(ratio, SPREAD_COVERAGE) / 2.0)
        sd = factor * s["spread_deg"].to_numpy()
        out[name] = {
            "factor": factor,
            "coverage_2sigma": float(np.mean(np.abs(s["error_deg"]) <= 2 * sd)),
            "sd_median_deg": float(np.median(sd)),
            "sd_mean_deg": float(np.mean(sd)),
        }
    return out


def stated_sd(model: Any, table: pd.DataFrame, policy: MomentPolicy) -> dict[str, Any]:
    """Coverage of a policy's sd, with its median and mean per band."""
    cov = sigma_coverage(model, table, policy)
    rows = table[np.isfinite(table["rom_deg"])]
    sd = policy.sigma_surrogate(rows["moment_nm"].to_numpy(float), rows["rom_deg"].to_numpy(float))
    out = {}
    for band in BANDS:
        name = f"{band[0]:g}-{band[1]:g}"
        sel = _in(band, rows["moment_nm"].to_numpy(float))
        out[name] = {
            "coverage_2sigma": cov["coverage_2sigma"][name],
            "sd_median_deg": float(np.median(sd[sel])),
            "sd_mean_deg": float(np.mean(sd[sel])),
            "mae_deg": cov["mae_deg"][name],
        }
    return out


def measure(model: Any, tables: dict[str, pd.DataFrame]) -> dict[str, Any]:
    """The three sds on the Test split (the spread's factor from Small)."""
    root = yaml.safe_load((REPO / "fe" / "params.yaml").read_text())["moments"]
    keywords = {"growth": root["error_growth"], "max_log_ratio": root["max_log_ratio"]}
    profile = MomentPolicy.for_surrogate(model, **keywords)
    relative = MomentPolicy(
        profile.trained_range,
        profile.error_deg,
        profile.growth,
        profile.max_log_ratio,
        profile.profile,
        model.val_error_profile_["relative_rms"],
    )
    profile = MomentPolicy(
        profile.trained_range,
        profile.error_deg,
        profile.growth,
        profile.max_log_ratio,
        profile.profile,
    )
    flat = MomentPolicy.for_surrogate(
        model, **keywords, error_deg=model.best_val_mae_deg_ * math.sqrt(math.pi / 2)
    )
    test = errors_and_spread(model, tables["test"])
    figures = {
        "global": stated_sd(model, tables["test"], flat),
        "profile": stated_sd(model, tables["test"], profile),
        "relative": stated_sd(model, tables["test"], relative),
        "spread": spread_sd(errors_and_spread(model, tables["small"]), test),
        "val_mae_deg": model.best_val_mae_deg_,
        "val_error_profile": model.val_error_profile_,
    }
    for band in BANDS:
        name = f"{band[0]:g}-{band[1]:g}"
        err = np.abs(test["error_deg"].to_numpy())[_in(band, test["moment_nm"].to_numpy())]
        figures.setdefault("test_abs_error_deg", {})[name] = {
            "median": float(np.median(err)),
            "q90": float(np.quantile(err, 0.9)),
            "q95": float(np.quantile(err, 0.95)),
            "rms": float(np.sqrt(np.mean(err**2))),
        }
    return figures


def markdown(figures: dict[str, Any], command: str) -> str:
    lines = [
        "| sd | band (Nm) | within 2 sd (Test) | sd median (deg) | sd mean (deg) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for kind in ("global", "profile", "relative", "spread"):
        for name, row in figures[kind].items():
            lines.append(
                f"| {kind} | {name} | {row['coverage_2sigma']:.3f} | "
                f"{row['sd_median_deg']:.3f} | {row['sd_mean_deg']:.3f} |"
            )
    lines += [
        "",
        "| band (Nm) | median abs error | q90 | q95 | rms |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, e in figures["test_abs_error_deg"].items():
        lines.append(
            f"| {name} | {e['median']:.3f} | {e['q90']:.3f} | {e['q95']:.3f} | {e['rms']:.3f} |"
        )
    lines += ["", f"Reproduce: `{command}`", ""]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.bench_fe_sigma")
    parser.add_argument("--campaign", type=Path, default=REPO / "fe/data/campaign/runs.jsonl.gz")
    parser.add_argument("--prepared", type=Path, default=None)
    parser.add_argument(
        "--model", type=Path, default=None, help="a NeuralSurrogate folder trained as above"
    )
    parser.add_argument("--out", type=Path, default=RESULTS / "bench_fe_sigma")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as work:
        prepared = args.prepared or build_prepared(args.campaign, Path(work))
        tables = {s: pd.read_csv(prepared / f"{s}.csv") for s in ("small", "test")}
        if args.model is None:
            model = train_fe_recipe(prepared)
        else:
            from femcal.surrogates.nn import NeuralSurrogate

            model = validation_profile(NeuralSurrogate.load(args.model), prepared)
    figures = measure(model, tables)
    command = reproduce_command("bench_fe_sigma", argv)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_fe_sigma.json").write_text(json.dumps(figures, indent=2) + "\n")
    (args.out / "bench_fe_sigma.md").write_text(markdown(figures, command))
    print(markdown(figures, command))


if __name__ == "__main__":
    main()
