"""The loop on the FE-made cohort: diagnose what the FE added, then calibrate with it.

``python -m femcal.fe.hidden`` runs, with the project's ``params.yaml``, the jobs a user runs
(:mod:`femcal.jobs`, in this process), both starting from the FE campaign's own training
configurations (``--start-bank``, :data:`FE_START_BANK`: pgd's starts and the reachability
envelope's FE curves) rather than ``params.yaml``'s ``calibrate.start_bank`` (the root
pipeline's prepared split, another FE model's curves):

1. the diagnosis (``femcal diagnose``) of the cohort's noisy curves (``measured/Test``) with
   the disc-only surrogate: a verdict per specimen, without the answers;
2. the calibration (``femcal calibrate``) of every specimen with the disc alone, and of the
   specimens of each verdict with its model's terms;
3. the verdicts and errors against ``answers.csv``: ``hidden.json``.

The figures (:func:`score`), each over all specimens and over the visible ones:

*visible*
    the disc alone misses the specimen by more than ``2 noise + sd_surrogate``: its fit's MAE
    above twice the measurement noise plus the surrogate's own error sd at the specimen's
    moments (the diagnosis' summary: ``sigma_by_moment`` with the noise taken out), so an
    element whose effect stays within the noise and the surrogate's error is not counted;
``right_fraction_visible``, ``right_fraction_all``
    the fraction whose verdict names exactly the class's elements (facets: ``facet_contact``;
    ligaments: ``ligament_tension``; every term of an effect, split or acting in other load
    cases, counts as its effect);
``none_given_element_fraction_visible``, ``none_given_element_fraction_all``
    among the specimens with an element, the fraction with the verdict ``none``;
``none_false_alarms``
    the specimens of the ``none`` class given an effect (of ``n_none``);
``error_ratio_max``
    the largest, over the classes, of the mean MAE after calibrating with the found effects
    over the disc-only floor: the mean MAE of the disc alone's calibration on the ``none``
    class (noise and surrogate error; every MAE against the noisy curves).
"""

from __future__ import annotations

import argparse
import json
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.effects.terms import parse_term
from femcal.errors import ConfigError
from femcal.fe.cohort import CLASS_EFFECTS, CLASSES
from femcal.jobs.calibrate import CalibrationJob, run_calibration
from femcal.jobs.diagnose import DiagnosisJob, run_diagnosis

#: Misfit of the disc alone beyond which an element is visible: this many noise sds, plus the
#: surrogate's own error sd.
VISIBLE_NOISE_SDS = 2.0


#: Where the calibrations and the diagnosis of :func:`run_hidden` say their noise comes from.
NOISE_SOURCE = "python -m femcal.fe.hidden --noise-deg"

#: The FE pipeline's prepared Large split (``fe/dvc.yaml`` stage ``prepare``), relative to the
#: working directory: the configurations the FE surrogate was trained on, the jobs' start bank.
FE_START_BANK = Path("fe/data/prepared/large.csv")


def start_bank_of(path: Path | None) -> dict[str, Path]:
    """The jobs' ``start_bank`` keyword: ``{"start_bank": path}`` (resolved), or ``{}`` for
    ``params.yaml``'s ``calibrate.start_bank`` when ``path`` is None.

    Raises
    ------
    ConfigError
        ``path`` is not a file.
    """
    if path is None:
        return {}
    path = Path(path)
    if not path.is_file():
        raise ConfigError(
            f"The start bank {path} is not a file; give the FE campaign's prepared Large split "
            f"(--start-bank, default {FE_START_BANK}: run `dvc repro fe/dvc.yaml -s prepare` to "
            "make it), or --start-bank '' for params.yaml's calibrate.start_bank."
        )
    return {"start_bank": path.resolve()}


def portable_path(path: str | Path, root: Path) -> str:
    """``path`` as ``hidden.json`` records it: relative to the project ``root`` (POSIX) where
    it lies inside it, so that the report reads alike from every clone; a ``models:/`` URI or
    a path outside the root as given."""
    from femcal.tracking import is_local_model

    text = str(path)
    if not is_local_model(text) or text.startswith("file:"):  # a URI: as given
        return text
    full, base = Path(text).resolve(), Path(root).resolve()
    return full.relative_to(base).as_posix() if full.is_relative_to(base) else text


def found_effects(effects: Sequence[str]) -> tuple[str, ...]:
    """The registered effects a verdict's terms name (:func:`femcal.effects.terms.parse_term`:
    split or not, in whichever load cases), sorted and unique."""
    return tuple(sorted({parse_term(str(e)).effect for e in effects}))


def visible_threshold(summary: Mapping[str, Any], noise_deg: float) -> float:
    """``2 noise + sd_surrogate`` in degrees, from the diagnosis' ``summary.json``.

    ``sd_surrogate`` is the mean over the diagnosed moments of the surrogate's error sd,
    ``sqrt(sigma_by_moment^2 - noise^2)`` (``sigma_deg`` when no moment profile is given).
    """
    noise = float(noise_deg)
    by_moment = summary.get("sigma_by_moment") or [summary["sigma_deg"]]
    sigma = np.asarray(by_moment, dtype=float)
    surrogate = np.sqrt(np.clip(sigma**2 - noise**2, 0.0, None))
    return VISIBLE_NOISE_SDS * noise + float(np.mean(surrogate))


def _fraction(flags: pd.Series) -> float:
    return float(flags.mean()) if len(flags) else float("nan")


def score(
    diagnosis: Sequence[Mapping[str, Any]],
    answers: pd.DataFrame,
    visible_deg: float,
    mae_disc: Mapping[str, float],
    mae_after: Mapping[str, float],
) -> dict[str, Any]:
    """The figures of ``hidden.json`` (module docstring).

    Parameters
    ----------
    diagnosis : sequence of mapping
        ``diagnosis.json`` of ``femcal diagnose``: per specimen ``specimen``, ``effects``,
        ``baseline_mae_deg`` (the disc alone's fit).
    answers : pandas.DataFrame
        ``answers.csv``: ``specimen``, ``class``.
    visible_deg : float
        The disc-alone MAE beyond which a specimen is visible (:func:`visible_threshold`), deg.
    mae_disc, mae_after : mapping of str to float
        Specimen -> MAE of the calibration with the disc alone, and with the found effects
        (the disc alone where none is found), deg.

    Returns
    -------
    dict
    """
    truth = dict(zip(answers["specimen"].astype(str), answers["class"]))
    config = dict(
        zip(answers["specimen"].astype(str), answers.get("config_id", answers["specimen"]))
    )
    rows = []
    for rec in diagnosis:
        name = str(rec["specimen"])
        cls = truth[name]
        found = found_effects(rec.get("effects") or [])
        rows.append(
            {
                "specimen": name,
                "config_id": int(config[name]) if str(config[name]).isdigit() else None,
                "class": cls,
                "found": " ".join(found) or "none",
                "right": found == tuple(sorted(CLASS_EFFECTS[cls])),
                "visible": float(rec["baseline_mae_deg"]) > visible_deg,
                "diagnosis_disc_mae_deg": float(rec["baseline_mae_deg"]),
                "disc_mae_deg": float(mae_disc.get(name, np.nan)),
                "after_mae_deg": float(mae_after.get(name, np.nan)),
            }
        )
    df = pd.DataFrame(rows)
    floor = float(df.loc[df["class"] == "none", "disc_mae_deg"].mean())
    element = df["class"] != "none"
    visible = df["visible"]
    classes = {}
    for cls in CLASSES:
        part = df[df["class"] == cls]
        classes[cls] = {
            "n": int(len(part)),
            "right": int(part["right"].sum()),
            "n_visible": int(part["visible"].sum()),
            "right_where_visible": int(part.loc[part["visible"], "right"].sum()),
            "verdicts": {str(k): int(v) for k, v in part["found"].value_counts().items()},
            "disc_mae_deg": float(part["disc_mae_deg"].mean()),
            "after_mae_deg": float(part["after_mae_deg"].mean()),
            "error_ratio": float(part["after_mae_deg"].mean() / floor),
            "error_ratio_disc_alone": float(part["disc_mae_deg"].mean() / floor),
        }
    none_class = df[~element]
    return {
        "n_specimens": int(len(df)),
        "visible_threshold_deg": float(visible_deg),
        "n_visible": int(visible.sum()),
        "right_fraction_visible": _fraction(df.loc[visible, "right"]),
        "right_fraction_all": _fraction(df["right"]),
        "none_given_element_fraction_visible": _fraction(
            df.loc[element & visible, "found"] == "none"
        ),
        "none_given_element_fraction_all": _fraction(df.loc[element, "found"] == "none"),
        "none_false_alarms": int((none_class["found"] != "none").sum()),
        "n_none": int(len(none_class)),
        "disc_only_floor_mae_deg": floor,
        "error_ratio_max": max(c["error_ratio"] for c in classes.values()),
        "classes": classes,
        "specimens": rows,
    }


def calibration_job(
    measurements: Path, out_dir: Path, effects: Sequence[str], options: Mapping
) -> CalibrationJob:
    """The calibration job of :func:`run_hidden`: ``options["params"]``'s ``calibrate``
    settings with the terms ``effects``, the surrogate ``options["model_uri"]``, the noise
    ``options["noise_deg"]`` and the start bank ``options["start_bank"]`` (None: params.yaml's);
    no held-out surrogate, no figures."""
    return CalibrationJob.from_params(
        options["params"],
        measurements=measurements,
        out_dir=out_dir,
        model_uri=options["model_uri"],
        holdout_uri=None,
        plots="none",
        effects=tuple(effects),
        noise_deg=float(options["noise_deg"]),
        noise_source=NOISE_SOURCE,
        **start_bank_of(options.get("start_bank")),
    )


def _calibrate(
    long: pd.DataFrame,
    names: Sequence[str],
    effects: Sequence[str],
    folder: Path,
    options: Mapping,
) -> dict[str, float]:
    """The calibration with the terms ``effects`` of the specimens ``names`` (params.yaml's
    ``calibrate`` settings, no held-out surrogate, no figures); specimen -> MAE."""
    folder.mkdir(parents=True, exist_ok=True)
    subset = folder / "measurements.csv"
    long[long["specimen"].astype(str).isin(names)].to_csv(subset, index=False)
    result = folder / "calibration"
    run_calibration(calibration_job(subset, result, effects, options))
    metrics = pd.read_csv(result / "metrics.csv", dtype={"specimen": str})
    return dict(zip(metrics["specimen"], metrics["mae_deg"].astype(float)))


def _calibrate_groups(
    measured: Path, diagnosis: Sequence[Mapping[str, Any]], out_dir: Path, options: Mapping
) -> tuple[dict[str, float], dict[str, float]]:
    """MAE per specimen of the disc alone and of the disc with its verdict's effects, deg."""
    from femcal.measurements import read_measurements

    long = read_measurements(measured).to_long()
    names = [str(rec["specimen"]) for rec in diagnosis]
    disc = _calibrate(long, names, (), out_dir / "disc-alone", options)
    groups: dict[tuple[str, ...], list[str]] = {}
    for rec in diagnosis:  # the diagnosed model's terms: tied or split, where each acts
        terms = rec.get("model") or rec.get("effects") or []
        groups.setdefault(tuple(terms), []).append(str(rec["specimen"]))
    after: dict[str, float] = {}
    # the folders found-<i> numbered in the order of the terms' comma-separated lists
    ordered = sorted(groups.items(), key=lambda item: ",".join(item[0]))
    for i, (effects, members) in enumerate(ordered):
        if not effects:
            after.update({name: disc[name] for name in members})
            continue
        after.update(_calibrate(long, members, effects, out_dir / f"found-{i}", options))
    return disc, after


def run_hidden(
    cohort_dir: Path,
    model_uri: str,
    out_dir: Path,
    noise_deg: float,
    root: Path,
    start_bank: Path | None = FE_START_BANK,
) -> dict[str, Any]:
    """Diagnose and calibrate the cohort; write and return the figures (module docstring).

    Parameters
    ----------
    cohort_dir : Path
        The cohort folder (:mod:`femcal.fe.cohort`): ``measured/Test`` and ``answers.csv``.
    model_uri : str
        The disc-only surrogate (a model folder, relative to the working directory, or a
        ``models:/`` URI).
    out_dir : Path
        Folder of the diagnosis, the calibrations and ``hidden.json``.
    noise_deg : float
        Measurement noise sd given to both jobs, deg.
    root : Path
        The project root: its ``params.yaml`` gives both jobs' other settings, its MLflow
        store and its user effects (:func:`femcal.jobs.common.use_project`), its git commit
        is recorded.
    start_bank : Path or None
        The prepared split whose configurations both jobs start from (and whose FE curves
        bound the reachability envelope); None: ``params.yaml``'s ``calibrate.start_bank``.

    Returns
    -------
    dict
        ``hidden.json``.
    """
    from femcal.config import load_params
    from femcal.jobs.common import use_project

    cohort_dir, out_dir = Path(cohort_dir).resolve(), Path(out_dir).resolve()
    measured = cohort_dir / "measured" / "Test"
    diagnosis_dir = out_dir / "diagnosis"
    bank = start_bank_of(start_bank)  # a missing bank is the first error, not the last
    params = load_params(Path(root) / "params.yaml")
    use_project(params)
    job = DiagnosisJob.from_params(
        params,
        measurements=measured,
        out_dir=diagnosis_dir,
        model_uri=model_uri,
        noise_deg=float(noise_deg),
        noise_source=NOISE_SOURCE,
        **bank,
    )
    run_diagnosis(job)
    diagnosis = json.loads((diagnosis_dir / "diagnosis.json").read_text())
    summary = json.loads((diagnosis_dir / "summary.json").read_text())
    threshold = visible_threshold(summary, noise_deg)
    answers = pd.read_csv(cohort_dir / "answers.csv", dtype={"specimen": str})
    options = {
        "model_uri": model_uri,
        "noise_deg": noise_deg,
        "params": params,
        "start_bank": bank.get("start_bank"),
    }
    disc, after = _calibrate_groups(measured, diagnosis, out_dir, options)
    figures = score(diagnosis, answers, threshold, disc, after)
    commit = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True
    ).stdout.strip()
    figures.update(
        model_uri=portable_path(model_uri, root),
        noise_deg=float(noise_deg),
        cohort=portable_path(cohort_dir, root),
        commit=commit,
        start_bank=portable_path(job.start_bank, root),
    )
    info = cohort_dir / "cohort.json"
    if info.is_file():  # the cohort's own figures: complete or a partial preview, its jobs
        figures["cohort_info"] = json.loads(info.read_text())
    (out_dir / "hidden.json").write_text(json.dumps(figures, indent=2) + "\n")
    return figures


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command line of :func:`run_hidden` (see the module docstring)."""
    from femcal.threads import limit_threads

    parser = argparse.ArgumentParser(prog="python -m femcal.fe.hidden")
    parser.add_argument("--cohort", type=Path, default=Path("fe/data/cohort"))
    parser.add_argument("--model-uri", default=str(Path("fe/models/surrogate-large").resolve()))
    parser.add_argument("--out", type=Path, default=Path("fe/reports/hidden"))
    parser.add_argument("--noise-deg", type=float, default=0.05)
    parser.add_argument("--root", type=Path, default=Path("."))
    parser.add_argument("--metrics-file", type=Path, default=None)
    parser.add_argument(
        "--start-bank",
        default=str(FE_START_BANK),
        help="prepared split of the jobs' starts; '' for params.yaml's calibrate.start_bank",
    )
    args = parser.parse_args(argv)
    limit_threads()  # as femcal's command line: the cores free now, before torch starts
    bank = Path(args.start_bank) if args.start_bank else None
    figures = run_hidden(args.cohort, args.model_uri, args.out, args.noise_deg, args.root, bank)
    if args.metrics_file:
        headline = {k: v for k, v in figures.items() if k != "specimens"}
        args.metrics_file.write_text(json.dumps(headline, indent=2) + "\n")
    keys = ("right_fraction_visible", "right_fraction_all", "error_ratio_max")
    print(json.dumps({k: figures[k] for k in keys}))
    return figures


if __name__ == "__main__":
    main()
