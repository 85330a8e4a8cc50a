"""The headline figures of each stage: what its DVC metrics file holds.

``dvc metrics show`` prints one table for the whole repository, one row per metrics file and one
column per key of any of them; a stage's metrics file therefore holds its figures on the shared
vocabulary of :mod:`femcal.dvc_metrics` (chosen from at most :data:`MAX_KEYS` flat figures),
and its tables go to plain outputs beside it:

* evaluate: ``reports/surrogates.json`` (:func:`surrogate_headline`); every model x training
  set x load case in ``reports/surrogates_table.json`` and ``reports/surrogates.md``;
* calibrate: ``reports/calibrate-<name>.json`` (:func:`calibration_headline`); the MAE per load
  case and the per-parameter "determined" fractions in
  ``reports/calibration/<name>/summary.json``;
* diagnose: ``reports/diagnose.json`` (:func:`diagnosis_headline`); verdict and effect counts
  and sigma per moment in ``reports/diagnosis/summary.json``.

The train stages write their own small summaries (``femcal.train.write_summary``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from femcal.errors import FemcalError

#: Most keys a metrics file may hold (``dvc metrics show`` should fit a terminal).
MAX_KEYS = 15

#: The calibration figures kept as headlines, in this order (when present).
CALIBRATION_KEYS = (
    "method",
    "n_specimens",
    "mae_deg",
    "mae_deg_median",
    "mae_deg_max",
    "r2_mean",
    "holdout_mae_deg",
    "holdout_r2_mean",
    "n_outside_bounds",
    "n_r2_negative",
    "n_outside_envelope",
    "n_beyond_noise",
    "range_width_mean",
    "seconds",
)

#: The diagnosis figures kept as they are, in this order (when present).
DIAGNOSIS_KEYS = (
    "n_specimens",
    "sigma_deg",
    "noise_deg",
    "noise_sd_deg",
    "surrogate_error_deg",
    "alpha",
    "cohort_verdict",
    "seconds",
)


class HeadlineError(FemcalError, ValueError):
    """A stage's figures lack what its headline needs, or the headline is too wide."""


def _scalar(value: Any) -> Any:
    """A JSON scalar (NaN and infinities become None: ``dvc metrics show`` prints "-")."""
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _checked(headline: dict[str, Any], what: str, kind: str) -> dict[str, Any]:
    """``headline`` checked (flat, at most :data:`MAX_KEYS`) and mapped onto the DVC metrics
    vocabulary of a stage of ``kind`` (:func:`femcal.dvc_metrics.headline`); the run's own
    figures (:data:`femcal.dvc_metrics.RUN_KEYS`) are carried as they are, for the run record
    (:func:`femcal.stages.common.write_metrics`)."""
    from femcal.dvc_metrics import RUN_KEYS
    from femcal.dvc_metrics import headline as on_vocabulary

    nested = [k for k, v in headline.items() if isinstance(v, (dict, list, tuple))]
    if nested or len(headline) > MAX_KEYS:
        raise HeadlineError(
            f"The {what} headline must be flat with at most {MAX_KEYS} keys; got "
            f"{len(headline)} keys, nested: {nested}. Move tables to a plain output under "
            "reports/ (see femcal.headlines)."
        )
    run = {k: headline[k] for k in RUN_KEYS if k in headline}
    return {**on_vocabulary(kind, headline), **run}


def _require(figures: Mapping[str, Any], keys: Sequence[str], what: str) -> None:
    missing = [k for k in keys if k not in figures]
    if missing:
        raise HeadlineError(
            f"The {what} figures lack {missing}; got keys {sorted(figures)}. Pass the figures "
            "the stage computed (e.g. run_calibration's or run_diagnosis' second result)."
        )


def calibration_headline(figures: Mapping[str, Any]) -> dict[str, Any]:
    """The headline of a calibration (``reports/calibrate-<name>.json``).

    Parameters
    ----------
    figures : mapping
        The batch's figures (``femcal.calibration.report.summary_figures`` plus what
        ``run_calibration`` adds), as written whole to ``<out_dir>/summary.json``.

    Returns
    -------
    dict
        On the DVC metrics vocabulary (:data:`femcal.dvc_metrics.SOURCES` ``calibrate``), of
        :data:`CALIBRATION_KEYS` that are present and ``determined_mean``: the mean over the
        parameters of the share of specimens whose identifiability range is narrow
        (``figures["determined"]``, which stays in ``summary.json`` per parameter).
    """
    _require(figures, ("n_specimens", "mae_deg", "r2_mean"), "calibration")
    out = {k: _scalar(figures[k]) for k in CALIBRATION_KEYS if k in figures}
    determined = figures.get("determined")
    if isinstance(determined, Mapping) and determined:
        out["determined_mean"] = round(
            sum(float(v) for v in determined.values()) / len(determined), 4
        )
    return _checked(out, "calibration", "calibrate")


def diagnosis_headline(summary: Mapping[str, Any]) -> dict[str, Any]:
    """The headline of a diagnosis (``reports/diagnose.json``).

    Parameters
    ----------
    summary : mapping
        ``run_diagnosis``' summary (as in ``<out_dir>/summary.json``): ``verdicts`` (count per
        verdict), ``effects`` (count per effect and ``unexplained``), ``found_effects``...

    Returns
    -------
    dict
        On the DVC metrics vocabulary (:data:`femcal.dvc_metrics.SOURCES` ``diagnose``), of
        :data:`DIAGNOSIS_KEYS` that are present, and the counts: ``n_none`` (the disc alone
        explains the specimen), ``n_with_effects`` (at least one effect named),
        ``n_unexplained`` (not explained within the noise), ``n_effects_found`` and
        ``found_effects`` (the effects named, most frequent first, joined by "+").
    """
    _require(summary, ("n_specimens", "verdicts", "effects"), "diagnosis")
    verdicts: Mapping[str, int] = summary["verdicts"] or {}
    effects: Mapping[str, int] = summary["effects"] or {}
    found = list(summary.get("found_effects") or [])
    out = {k: _scalar(summary[k]) for k in DIAGNOSIS_KEYS if k in summary}
    out["n_none"] = int(verdicts.get("none", 0))
    out["n_with_effects"] = int(
        sum(n for v, n in verdicts.items() if v not in ("none", "unexplained"))
    )
    out["n_unexplained"] = int(effects.get("unexplained", 0))
    out["n_effects_found"] = len(found)
    out["found_effects"] = "+".join(found)
    return _checked(out, "diagnosis", "diagnose")


def surrogate_headline(
    table: Mapping[str, Mapping[str, Mapping[str, Any]]],
) -> dict[str, Any]:
    """The headline of the Test-set evaluation (``reports/surrogates.json``).

    Parameters
    ----------
    table : mapping
        ``reports/surrogates_table.json``: section (``trained_on_large``,
        ``trained_on_small``, ``interpolation``) -> ``model@split`` -> row (``model``,
        ``mae``, ``r2_mean``, ``r2_curve_mean``, ``n_rows``...).

    Returns
    -------
    dict
        On the DVC metrics vocabulary (:data:`femcal.dvc_metrics.SOURCES` ``evaluate``), of:
        per training set (``large``, ``small``), the network's ``nn_<set>_mae_deg``,
        ``nn_<set>_r2_mean`` and the best baseline's name and MAE; the network's MAE at unseen
        moments (``interpolation_nn_mae_deg``) and the number of Test rows.
    """
    out: dict[str, Any] = {}
    for split in ("large", "small"):
        rows = table.get(f"trained_on_{split}")
        if not rows:
            continue
        nn = [r for r in rows.values() if r.get("model") == "nn"]
        if not nn:
            raise HeadlineError(
                f"Section trained_on_{split} of the evaluation has no 'nn' row; got "
                f"{sorted(rows)}. Evaluate models/surrogate-{split} with the baselines."
            )
        out[f"nn_{split}_mae_deg"] = _scalar(nn[0]["mae"])
        out[f"nn_{split}_r2_mean"] = _scalar(nn[0]["r2_mean"])
        if split == "large":
            out["nn_large_r2_curve_mean"] = _scalar(nn[0].get("r2_curve_mean"))
            out["n_test_rows"] = int(nn[0]["n_rows"])
        others = [r for r in rows.values() if r.get("model") != "nn"]
        if others:
            best = min(others, key=lambda r: float(r["mae"]))
            out[f"best_baseline_{split}"] = best["model"]
            out[f"best_baseline_{split}_mae_deg"] = _scalar(best["mae"])
    interp = [r for r in (table.get("interpolation") or {}).values() if r.get("model") == "nn"]
    if interp:
        out["interpolation_nn_mae_deg"] = _scalar(interp[0]["mae"])
        out["interpolation_nn_r2_mean"] = _scalar(interp[0]["r2_mean"])
    return _checked(out, "evaluation", "evaluate")
