"""Before and after: compare a calibration with an earlier one.

When a user adds a physical effect to the model (``calibrate.effects`` in params.yaml,
``--effects``) and calibrates again, the calibrate stage writes the side-by-side table
(``comparison.md``, ``comparison.json``): overall and per-load-case MAE, R², the held-out
surrogate's MAE. The earlier run ("before") is

* the one ``--compare-to`` names: an output folder of an earlier ``femcal calibrate`` or
  ``femcal diagnose`` (its ``summary.json``), or an MLflow run id;
* else the one :data:`BASELINE_RULE` picks in the MLflow store: the disc alone, so that every
  run with effects is measured against the same baseline. A run of the disc alone has no
  default baseline and writes no comparison.

``comparison.md`` and the log say which run or folder was compared with and how it was chosen.
The two runs are also comparable in the MLflow UI (same metric names).
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES

if TYPE_CHECKING:
    import pandas as pd

logger = logging.getLogger(__name__)

#: Metrics compared, in table order (names as logged by the calibrate stage).
COMPARED: tuple[str, ...] = (
    "mae_deg",
    *(f"mae_deg_{lc}" for lc in LOAD_CASES),
    "mae_deg_max",
    "r2_mean",
    "holdout_mae_deg",
)


#: How "before" is chosen when ``--compare-to`` is not given (stated in comparison.md and the log).
BASELINE_RULE = (
    "the latest earlier finished calibrate run of the same measurement file with the disc alone "
    "(effects: none), in the MLflow store"
)

#: The effects parameter of a run of the disc alone (``params.effects``).
DISC_ALONE = "none"

#: What an MLflow run id looks like (``--compare-to`` that is not a folder).
_RUN_ID = re.compile(r"^[0-9a-f]{32}$")


def check_compare_to(value: str | None) -> str | None:
    """``--compare-to``, checked before any work: an output folder with a ``summary.json``, or
    an MLflow run id (32 hexadecimal digits). Returns the folder's resolved path, or the id.

    Raises
    ------
    ConfigError
        The value names neither such a folder nor a run id.
    """
    if value is None:
        return None
    path = Path(value).expanduser()
    if path.is_dir():
        if not (path / "summary.json").is_file():
            raise ConfigError(
                f"--compare-to {value}: the folder has no summary.json, so it is no output "
                "folder of femcal calibrate or femcal diagnose. Give the --out folder of an "
                "earlier calibration (or its MLflow run id)."
            )
        return str(path.resolve())
    if _RUN_ID.match(value):
        return value
    raise ConfigError(
        f"--compare-to {value}: no such folder, and not an MLflow run id (32 hexadecimal "
        "digits). Give the --out folder of an earlier calibration, e.g. --compare-to "
        "reports/calibration/planted, or the run id the MLflow UI shows."
    )


def resolve_baseline(
    compare_to: str | None, *, measurements: str, effects: str, exclude_run_id: str | None
) -> dict[str, Any] | None:
    """The "before" of a comparison: what ``--compare-to`` names, else :data:`BASELINE_RULE`.

    Parameters
    ----------
    compare_to : str or None
        An output folder of an earlier calibrate or diagnose, or an MLflow run id
        (:func:`check_compare_to`); None applies :data:`BASELINE_RULE`.
    measurements, effects : str
        This run's ``measurements`` and ``effects`` parameters.
    exclude_run_id : str, optional
        This run.

    Returns
    -------
    dict or None
        ``source`` (what was compared with: ``run <id>`` or ``folder <path>``), ``chosen`` (how),
        ``run_id``, ``effects``, ``model`` and ``metrics``; None when the rule finds no run (or
        this run is the disc alone).

    Raises
    ------
    ConfigError
        ``compare_to`` names a run that is not in the store.
    """
    if compare_to is not None and Path(compare_to).is_dir():
        return _folder_baseline(Path(compare_to))
    if compare_to is not None:
        run = _get_run(compare_to)
        if run is None:
            raise ConfigError(
                f"--compare-to {compare_to}: no MLflow run with this id in the tracking store "
                f"{_tracking_uri()}. Give the id of a run there, or the --out folder of the "
                "earlier calibration."
            )
        return _run_baseline(run, chosen="given by --compare-to")
    if effects == DISC_ALONE:
        return None
    run = previous_calibration(
        measurements=measurements, effects=DISC_ALONE, exclude_run_id=exclude_run_id
    )
    return None if run is None else _run_baseline(run, chosen=f"the default: {BASELINE_RULE}")


def _tracking_uri() -> str:
    import mlflow

    return mlflow.get_tracking_uri()


def _get_run(run_id: str) -> Any | None:
    import mlflow
    from mlflow.exceptions import MlflowException

    try:
        return mlflow.get_run(run_id)
    except MlflowException:
        return None


def _run_baseline(run: Any, *, chosen: str) -> dict[str, Any]:
    return {
        "source": f"run {run.info.run_id}",
        "chosen": chosen,
        "run_id": run.info.run_id,
        "effects": run.data.params.get("effects", ""),
        "model": run.data.params.get("model_version", ""),
        "metrics": dict(run.data.metrics),
    }


def _folder_baseline(folder: Path) -> dict[str, Any]:
    """A baseline from an output folder: its ``summary.json``, its marker's run id and, when
    that run is in the store, its effects and model."""
    from femcal.outputs import read_marker

    summary = json.loads((folder / "summary.json").read_text())
    metrics = {
        k: float(v)
        for k, v in summary.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool)
    }
    marker = read_marker(folder) or {}
    run_id = marker.get("mlflow_run_id") or ""
    run = _get_run(run_id) if run_id else None
    command = marker.get("command", "")
    return {
        "source": f"folder {folder}" + (f" (femcal {command})" if command else ""),
        "chosen": "given by --compare-to",
        "run_id": run_id,
        "effects": run.data.params.get("effects", "") if run else summary.get("effects", ""),
        "model": run.data.params.get("model_version", "") if run else "",
        "metrics": metrics,
    }


def previous_calibration(
    *, measurements: str, effects: str, exclude_run_id: str | None = None
) -> Any | None:
    """The latest finished calibrate run of ``measurements`` in the active experiment with
    ``effects``.

    Parameters
    ----------
    measurements : str
        The ``measurements`` parameter of the runs (the file calibrated).
    effects : str
        The ``effects`` parameter of the runs sought (``"none"``: the disc alone).
    exclude_run_id : str, optional
        This run.

    Returns
    -------
    mlflow.entities.Run or None
    """
    import mlflow

    experiment = mlflow.get_experiment_by_name(_active_experiment_name())
    if experiment is None:
        return None
    quoted = measurements.replace("'", "\\'")
    runs = mlflow.search_runs(
        experiment_ids=[experiment.experiment_id],
        filter_string=(
            f"tags.`femcal.stage` = 'calibrate' and params.measurements = '{quoted}' "
            f"and params.effects = '{effects}'"
        ),
        order_by=["attributes.start_time DESC"],
        max_results=5,
        output_format="list",
    )
    runs = [r for r in runs if r.info.run_id != exclude_run_id and r.info.status == "FINISHED"]
    return runs[0] if runs else None


def _active_experiment_name() -> str:
    import mlflow

    run = mlflow.active_run()
    if run is not None:
        return mlflow.get_experiment(run.info.experiment_id).name
    from mlflow.tracking.fluent import _get_experiment_id

    return mlflow.get_experiment(_get_experiment_id()).name


def comparison_frame(
    before: Mapping[str, float], after: Mapping[str, float], metrics: tuple[str, ...] = COMPARED
) -> pd.DataFrame:
    """One row per metric: before, after, change (after - before) and ratio (after / before).

    Metrics missing from either side are left out.
    """
    import pandas as pd

    rows = []
    for name in metrics:
        if name in before and name in after:
            b, a = float(before[name]), float(after[name])
            rows.append(
                {
                    "metric": name,
                    "before": b,
                    "after": a,
                    "change": a - b,
                    "ratio": a / b if b else float("nan"),
                }
            )
    return pd.DataFrame(rows, columns=["metric", "before", "after", "change", "ratio"])


def write_comparison(
    frame: pd.DataFrame,
    out_dir: Path,
    *,
    before: Mapping[str, Any],
    after: Mapping[str, Any],
) -> list[Path]:
    """Write ``comparison.md`` and ``comparison.json`` into ``out_dir``.

    ``before`` and ``after`` describe the two runs (run id, effects, model version);
    ``before`` also says what was compared with (``source``: a run or a folder) and how it was
    chosen (``chosen``), both written on the page's first lines. With no metric in common
    (e.g. a diagnosis folder), the page says so.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    source = before.get("source") or f"run {before.get('run_id', '')}"
    lines = [
        "# Before and after",
        "",
        f"Compared with {source}, {before.get('chosen', 'given by --compare-to')}.",
        "",
        f"- before: run `{before.get('run_id', '')}`, effects: {before.get('effects', '')}, "
        f"model {before.get('model', '')}",
        f"- after: run `{after.get('run_id', '')}`, effects: {after.get('effects', '')}, "
        f"model {after.get('model', '')}",
        "",
        "| metric | before | after | change | after / before |",
        "|---|---|---|---|---|",
    ]
    for row in frame.itertuples():
        lines.append(
            f"| {row.metric} | {row.before:.4f} | {row.after:.4f} | {row.change:+.4f} | "
            f"{row.ratio:.2f} |"
        )
    if frame.empty:
        lines += [
            "",
            f"No metric in common: the earlier output holds none of {', '.join(COMPARED)}. "
            "Compare with the output folder or run of an earlier calibration.",
        ]
    md = out_dir / "comparison.md"
    md.write_text("\n".join(lines) + "\n")
    js = out_dir / "comparison.json"
    js.write_text(
        json.dumps(
            {
                "before": {k: v for k, v in before.items() if k != "metrics"},
                "after": dict(after),
                "metrics": frame.to_dict("records"),
            },
            indent=2,
        )
    )
    return [md, js]
