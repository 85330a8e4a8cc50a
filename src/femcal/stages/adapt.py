"""Stage ``adapt`` (fe/dvc.yaml): adaptive sampling, a challenger, and the champion's folder.

Rounds of FE runs where the target specimens' calibrations land and where the ensemble
disagrees, with fine-tuning (:func:`femcal.fe.adaptive.adapt_surrogate`). The fine-tuned
surrogate is logged to MLflow and registered as a new version of ``mlflow.model_name`` with
the alias ``challenger``; ``champion`` moves to it only when its MAE on the held-out FE
configurations (which no round trains on) beats the surrogate it started from. The winner's
files become ``adapt.out_model``, the folder the later stages calibrate with.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from femcal.dvc_metrics import split_run
from femcal.fe.options import AdaptOptions
from femcal.fe.runtime import FeRuntime
from femcal.stages.common import StageSettings, path_setting, typed, write_metrics
from femcal.stages.simulate import fe_runtime
from femcal.stages.store import tracking

#: The alias of the adapted surrogate's registered version.
CHALLENGER_ALIAS = "challenger"


@dataclass(frozen=True)
class AdaptSettings(StageSettings):
    """The ``adapt`` and ``fe`` sections of fe/params.yaml."""

    model_uri: str
    targets: Path
    train: Path
    heldout: Path
    out_model: Path
    out_dir: Path
    fe: FeRuntime
    options: AdaptOptions
    model_name: str

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> AdaptSettings:
        cfg = typed(params, "adapt")
        return cls(
            model_uri=cfg.model_uri,
            targets=path_setting(params, "adapt", "targets"),
            train=path_setting(params, "adapt", "train"),
            heldout=path_setting(params, "adapt", "heldout"),
            out_model=path_setting(params, "adapt", "out_model"),
            out_dir=path_setting(params, "adapt", "out_dir"),
            fe=fe_runtime(params, args, "adapt"),
            options=AdaptOptions(**cfg.options()),
            model_name=typed(params, "mlflow").model_name,
            metrics_file=args.get("metrics_file"),
            params=params,
        )


def run(settings: AdaptSettings) -> dict[str, Any]:
    """Adapt, register the challenger, promote it if it wins; returns the figures."""
    tracking(settings.params)
    figures = run_adapt(settings)
    # the headline; every figure in its details file (details_path), which validate reads
    write_metrics(settings.metrics_file, figures, "adapt", details=True)
    return figures


def describe(figures: Mapping[str, Any]) -> list[str]:
    errs = ", ".join(f"{v:.4f}" for v in figures["error_at_solutions_deg"])
    verdict = (
        "the challenger is the new champion"
        if figures["promoted"]
        else "the champion stays (the challenger did not beat it on held-out FE)"
    )
    bands = ", ".join(
        f"{band} Nm {figures['champion_heldout_mae_deg_by_band'][band]:.4f} -> {v:.4f}"
        for band, v in figures["challenger_heldout_mae_deg_by_band"].items()
    )
    return [
        f"adaptive sampling: {figures['n_rounds']} rounds, {figures['n_new_configurations']} "
        f"new FE configurations; surrogate error at the calibrated solutions, round by round: "
        f"{errs} deg",
        f"held-out FE MAE: champion {figures['champion_heldout_mae_deg']:.4f} deg, challenger "
        f"{figures['challenger_heldout_mae_deg']:.4f} deg: {verdict} (version "
        f"{figures['challenger_version']}); by moment band: {bands} deg",
        f"outputs: {figures['out_model']} (the champion's files), {figures['out_dir']}",
    ]


def _table_rows(path: Path, space: Any) -> tuple[Any, np.ndarray]:
    """A prepared table's usable rows: the configurations (load case, moment, id, parameters)
    and their RoM in degrees."""
    from femcal.datasets import ok_rows
    from femcal.tidy import load_tidy

    table = ok_rows(load_tidy(path, space))
    columns = ["load_case", "moment_nm", "config_id", *space.names]
    return table[columns], table["rom_deg"].to_numpy(dtype=float)


def run_adapt(settings: AdaptSettings) -> dict[str, Any]:
    """Adaptive sampling from the surrogate at ``model_uri``; MLflow; the champion's folder.

    ``settings`` (:class:`AdaptSettings`) holds the fields named below.

    ``targets`` are measurements (any layout ``femcal calibrate`` reads), ``train`` and
    ``heldout`` prepared tidy tables (``data/prepared/large.csv``, ``small.csv``). Writes
    ``out_dir/rounds.csv``, ``out_dir/runs.csv`` and ``out_dir/adapt.json``, and
    ``out_model``: the challenger's files when it won, else the starting model's. The FE
    runs go through ``fe`` (solver, settings, campaign store, Dask cluster); ``options``
    (:class:`~femcal.fe.options.AdaptOptions`) sets the rounds, the exploration, the
    fine-tuning, the calibrations and the seed, and the new runs are numbered after the
    training table's configurations.
    """
    import mlflow
    from mlflow import MlflowClient

    from femcal.datasets import SPACE_FILE
    from femcal.fe.adaptive import adapt_surrogate, band_mae
    from femcal.measurements import read_measurements
    from femcal.outputs import check_destination
    from femcal.space import ParameterSpace
    from femcal.tracking import export_model, load_surrogate, log_surrogate, open_model

    s = settings
    model_uri, targets, train, heldout = s.model_uri, s.targets, s.train, s.heldout
    out_model, out_dir = s.out_model, s.out_dir
    rounds, n_explore = s.options.rounds, s.options.n_explore
    model_name = s.model_name
    check_destination(out_dir)
    meas = read_measurements(targets)
    source = open_model(model_uri)
    surrogate = load_surrogate(source)
    space = ParameterSpace.from_json(Path(train).parent / SPACE_FILE)

    train_rows, heldout_rows = _table_rows(train, space), _table_rows(heldout, space)
    first_id = int(train_rows[0]["config_id"].max()) + 1
    result = adapt_surrogate(
        surrogate,
        meas.rom_deg,
        meas.moments.tolist(),
        s.fe.curves(meas.moments.tolist()),
        train_rows,
        heldout_rows,
        s.options,
        first_id=first_id,
    )
    champion_mae = result.heldout_mae_start
    challenger_mae = float(result.rounds["heldout_mae_deg"].iloc[-1])
    promoted = bool(np.isfinite(challenger_mae) and challenger_mae < champion_mae)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    result.rounds.to_csv(out_dir / "rounds.csv", index=False)
    result.runs.to_csv(out_dir / "runs.csv", index=False)
    with mlflow.start_run(run_name="adapt") as run:
        mlflow.set_tag("femcal.stage", "adapt")
        mlflow.log_params(
            {
                "model_uri": model_uri,
                "model_sha256": source.sha256,
                "rounds": rounds,
                "n_explore": n_explore,
                "targets": str(targets),
                "heldout": str(heldout),
            }
        )
        for row in result.rounds.itertuples(index=False):
            mlflow.log_metrics(
                {
                    "error_at_solutions_deg": float(row.error_at_solutions_deg),
                    "heldout_mae_deg": float(row.heldout_mae_deg),
                    "fe_calibration_mae_deg": float(row.fe_calibration_mae_deg),
                },
                step=int(row.round),
            )
        mlflow.log_metrics(
            {"champion_heldout_mae_deg": champion_mae, "challenger_heldout_mae_deg": challenger_mae}
        )
        info = log_surrogate(result.surrogate, result.surrogate.space)
        mv = mlflow.register_model(info.model_uri, model_name)
        client = MlflowClient()
        client.set_model_version_tag(model_name, mv.version, "heldout_fe_mae_deg", challenger_mae)
        client.set_registered_model_alias(model_name, CHALLENGER_ALIAS, mv.version)
        if promoted:
            client.set_registered_model_alias(model_name, "champion", mv.version)
        mlflow.set_tag("promoted", str(promoted).lower())
        if Path(out_model).exists():
            shutil.rmtree(out_model)
        if promoted:
            export_model(
                info.model_uri,
                out_model,
                record={"registered_model": model_name, "version": mv.version, "promoted": True},
                run={
                    "tracking_uri": mlflow.get_tracking_uri(),
                    "run_id": run.info.run_id,
                    "model_uri": info.model_uri,
                },
            )
        else:
            shutil.copytree(source.path, out_model)
        figures = {
            **result.summary(),
            # the held-out FE error in the study's moment range and beyond it, both models
            "champion_heldout_mae_deg_by_band": band_mae(surrogate, *heldout_rows),
            "challenger_heldout_mae_deg_by_band": band_mae(result.surrogate, *heldout_rows),
            "champion_heldout_mae_deg": champion_mae,
            "challenger_heldout_mae_deg": challenger_mae,
            "challenger_version": str(mv.version),
            "promoted": promoted,
            "out_model": str(out_model),
            "out_dir": str(out_dir),
            "mlflow_run_id": run.info.run_id,
        }
        computed = split_run(figures)[0]  # the run id is the run's: the run record holds it
        (out_dir / "adapt.json").write_text(json.dumps(computed, indent=2) + "\n")
        mlflow.log_artifacts(str(out_dir), artifact_path="adapt")
    return figures
