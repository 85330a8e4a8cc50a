"""Before and after: compare a calibration with the previous one of the same measurements.

When a user adds a physical effect to the model (``calibrate.effects`` in params.yaml) and
reruns the pipeline, the calibrate stage looks up the latest earlier calibrate run of the same
measurement file whose model differs (other effects, other surrogate version) in the MLflow
store, and writes the side-by-side table: overall and per-load-case MAE, R², the held-out
surrogate's MAE. The two runs are also comparable in the MLflow UI (same metric names).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from femcal.schema import LOAD_CASES

logger = logging.getLogger(__name__)

#: Metrics compared, in table order (names as logged by the calibrate stage).
COMPARED: tuple[str, ...] = (
    "mae_deg",
    *(f"mae_deg_{lc}" for lc in LOAD_CASES),
    "mae_deg_max",
    "r2_mean",
    "holdout_mae_deg",
)


def previous_calibration(
    *, measurements: str, effects: str, exclude_run_id: str | None = None
) -> Any | None:
    """The latest calibrate run of ``measurements`` in the active experiment with other effects.

    Parameters
    ----------
    measurements : str
        The ``measurements`` parameter of the runs (the file calibrated).
    effects : str
        This run's ``effects`` parameter; runs with the same value are not "before".
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
            f"and params.effects != '{effects}'"
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

    ``before`` and ``after`` describe the two runs (run id, effects, model version).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    lines = [
        "# Before and after",
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
    md = out_dir / "comparison.md"
    md.write_text("\n".join(lines) + "\n")
    js = out_dir / "comparison.json"
    js.write_text(
        json.dumps(
            {"before": dict(before), "after": dict(after), "metrics": frame.to_dict("records")},
            indent=2,
        )
    )
    return [md, js]
