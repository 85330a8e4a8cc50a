"""The DVC metrics files: one narrow row per stage in ``dvc metrics show``.

``dvc metrics show`` prints one table for the whole repository: a row per metrics file of every
``dvc.yaml`` (the root pipeline, ``fe/`` and ``experiments/``), a column per key that any of
them holds. Each metrics file therefore holds keys of one shared vocabulary only
(:data:`VOCABULARY`): the stage's figures mapped onto it (:data:`SOURCES`), flat and scalar, so
that the table stays within :data:`MAX_WIDTH` characters. A stage's other figures (nested
tables, lists, names, run ids, hyperparameters) go to a plain output beside the metrics file,
``<name>.details.json`` (:func:`details_path`; the FE pipeline keeps its metrics files in
``reports/metrics/`` and each stage's report at ``reports/<name>.json``), or stay where the
stage writes them whole
(``summary.json`` of calibrate and diagnose, ``reports/surrogates_table.json`` of evaluate).

What describes the run rather than what it computed (:data:`RUN_KEYS`: wall time, MLflow run
id) stays out of both, which DVC hashes: it goes to the run record ``reports/<name>.run.json``
(:func:`run_path`; not versioned), to the stage's MLflow run and to the console. So a stage
rebuilt from the same inputs writes the files ``dvc.lock`` names.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from femcal.errors import FemcalError

#: Widest line ``dvc metrics show`` may print (characters), for every pipeline at once.
MAX_WIDTH = 200

#: The keys a DVC metrics file may hold, and what each means (one column each).
VOCABULARY: dict[str, str] = {
    "mae_deg": "the stage's main error, deg (validation, Test, fit, FE or predictive MAE)",
    "ref_mae_deg": "the error of what the stage compares with, deg (the best baseline, the "
    "held-out surrogate, the champion before adapt, the surrogate against FE)",
    "mae_mpa": "the intradiscal-pressure error, MPa",
    "r2": "mean R²",
    "coverage": "share of held-out errors within 2 stated sd (the worst moment band)",
    "n": "items: trials, Test rows, specimens, configurations",
    "flagged": "specimens flagged for a look (R² < 0, outside the envelope, beyond the noise, "
    "unexplained)",
    "failed": "failures (FE jobs; calibrated parameters at a bound)",
    "version": "the registered model version",
    "promoted": "whether the model became the champion",
    "seconds": "the FE campaign's wall time from its store, s (to 0.1 s)",
}

#: Figures of the run, not of what it computed: kept out of the metrics file and the report
#: (:func:`write` puts them in the run record, :func:`run_path`).
RUN_KEYS: tuple[str, ...] = ("seconds", "mlflow_run_id")

Source = tuple[str, ...] | Callable[[Mapping[str, Any]], Any]


def _total(*keys: str) -> Callable[[Mapping[str, Any]], Any]:
    def total(figures: Mapping[str, Any]) -> Any:
        values = [_lookup(figures, k) for k in keys]
        present = [v for v in values if v is not None]
        return sum(int(v) for v in present) if present else None

    return total


def _worst_band(figures: Mapping[str, Any]) -> Any:
    bands = figures.get("coverage_2sigma")
    return min(bands.values()) if isinstance(bands, Mapping) and bands else None


#: Per kind of stage: vocabulary key -> the figure it takes (the first of the dotted paths
#: present, or a function of the figures).
SOURCES: dict[str, dict[str, Source]] = {
    "train": {
        "mae_deg": ("val_mae_deg", "val_rom_mae_deg"),
        "mae_mpa": ("val_mae_mpa",),
        "n": ("n_trials",),
        "version": ("registered_version",),
        "promoted": ("promoted",),
    },
    "evaluate": {
        "mae_deg": ("nn_large_mae_deg",),
        "ref_mae_deg": ("best_baseline_large_mae_deg",),
        "r2": ("nn_large_r2_mean",),
        "n": ("n_test_rows",),
    },
    "calibrate": {
        "mae_deg": ("mae_deg",),
        "ref_mae_deg": ("holdout_mae_deg",),
        "r2": ("r2_mean",),
        "n": ("n_specimens",),
        "flagged": _total("n_r2_negative", "n_outside_envelope", "n_beyond_noise"),
        "failed": ("n_outside_bounds",),
    },
    "diagnose": {
        "n": ("n_specimens",),
        "flagged": ("effects.unexplained", "n_unexplained"),
    },
    "simulate": {
        "n": ("n_configurations",),
        "failed": ("n_failed",),
        "seconds": ("campaign_wall_seconds",),
    },
    "cohort": {"n": ("n_specimens",), "failed": ("n_failed_jobs",)},
    "adapt": {
        "mae_deg": ("challenger_heldout_mae_deg", "heldout_mae_deg"),
        "ref_mae_deg": ("champion_heldout_mae_deg",),
        "n": ("n_new_configurations",),
        "version": ("challenger_version",),
        "promoted": ("promoted",),
    },
    "validate": {
        "mae_deg": ("fe_mae_deg",),
        "ref_mae_deg": ("surrogate_mae_deg",),
        "mae_mpa": ("idp_head.mae_mpa",),
        "n": ("n_specimens",),
        "failed": ("n_fe_failed_jobs",),
    },
    "predictive": {
        "mae_deg": ("fe_predictive_mae_deg", "clean.predict_mae_deg"),
        "n": ("n_specimens",),
    },
    "sigma": {"coverage": _worst_band},
}


class MetricsFileError(FemcalError, ValueError):
    """A DVC metrics file would hold a key outside :data:`VOCABULARY`, or an unknown kind."""


def _lookup(figures: Mapping[str, Any], dotted: str) -> Any:
    value: Any = figures
    for part in dotted.split("."):
        if not isinstance(value, Mapping) or part not in value:
            return None
        value = value[part]
    return value


def _scalar(key: str, value: Any) -> Any:
    """A JSON scalar, short in the table: seconds to 0.1 s, NaN and infinities None."""
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if key == "seconds" and isinstance(value, (int, float)):
        return round(float(value), 1)
    return value


def headline(kind: str, figures: Mapping[str, Any]) -> dict[str, Any]:
    """The metrics file of a stage of ``kind``: its figures on the shared vocabulary.

    Parameters
    ----------
    kind : str
        A key of :data:`SOURCES` (``train``, ``evaluate``, ``calibrate``, ...).
    figures : mapping
        The stage's figures, possibly nested (dotted paths reach inside).

    Returns
    -------
    dict
        Vocabulary key -> scalar, for the figures present (in :data:`VOCABULARY`'s order).

    Raises
    ------
    MetricsFileError
        ``kind`` is unknown, or a value is not a scalar.
    """
    if kind not in SOURCES:
        raise MetricsFileError(
            f"No DVC metrics mapping for stage kind {kind!r}; known: {sorted(SOURCES)}. Add "
            "one to femcal.dvc_metrics.SOURCES, on the keys of VOCABULARY."
        )
    out: dict[str, Any] = {}
    for key in VOCABULARY:
        source = SOURCES[kind].get(key)
        if source is None:
            continue
        if callable(source):
            value = source(figures)
        else:
            value = next((v for v in (_lookup(figures, s) for s in source) if v is not None), None)
        value = _scalar(key, value)
        if value is None:
            continue
        if isinstance(value, (Mapping, list, tuple)):
            raise MetricsFileError(
                f"{kind}: the figure for {key!r} is a {type(value).__name__}, not a number; "
                "map a scalar onto it in femcal.dvc_metrics.SOURCES."
            )
        out[key] = value
    return out


def details_path(path: str | Path) -> Path:
    """The plain output of a metrics file's stage: ``reports/x.json`` ->
    ``reports/x.details.json`` beside it; a metrics file in a folder named ``metrics``
    (``reports/metrics/x.json``, the FE pipeline's layout) -> ``reports/x.json``, the stage's
    report under its own name."""
    path = Path(path)
    if path.parent.name == "metrics":
        return path.parent.parent / path.name
    return path.with_name(f"{path.stem}.details.json")


def run_path(path: str | Path) -> Path:
    """The run record of a metrics file's stage: ``reports/x.json`` and
    ``reports/metrics/x.json`` -> ``reports/x.run.json`` (ignored by git, not a DVC output)."""
    path = Path(path)
    folder = path.parent.parent if path.parent.name == "metrics" else path.parent
    return folder / f"{path.stem}.run.json"


def split_run(figures: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``figures`` without :data:`RUN_KEYS`, and those keys alone (top level only)."""
    computed = {k: v for k, v in figures.items() if k not in RUN_KEYS}
    run = {k: v for k, v in figures.items() if k in RUN_KEYS}
    return computed, run


def write_run(path: str | Path, run: Mapping[str, Any]) -> None:
    """Write the run record (:func:`run_path`) of the metrics file ``path``, when ``run`` holds
    anything."""
    if run:
        from femcal.outputs import write_text_atomic

        text = json.dumps(dict(run), indent=2, default=str) + "\n"
        write_text_atomic(run_path(path), text)


def write(
    path: str | Path | None, kind: str, figures: Mapping[str, Any], *, details: bool = False
) -> dict[str, Any] | None:
    """Write a stage's DVC metrics file (its :func:`headline`), and with ``details`` every
    figure to :func:`details_path` (each written whole or not at all); :data:`RUN_KEYS` go to
    the run record (:func:`write_run`) instead. Nothing when ``path`` is None. Returns the
    headline."""
    if not path:
        return None
    from femcal.outputs import write_text_atomic

    computed, run = split_run(figures)
    head = headline(kind, computed)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    if details:
        text = json.dumps(computed, indent=2, default=str) + "\n"
        write_text_atomic(details_path(path), text)
    write_text_atomic(path, json.dumps(head, indent=2) + "\n")
    write_run(path, run)
    return head
