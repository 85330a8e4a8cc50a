"""An FE-made cohort with hidden posterior elements: the disc alone, facets, ligaments, both.

Every specimen is one CalculiX model (:mod:`femcal.fe.calculix`): a disc whose 13 parameters
are drawn uniformly from the sampling box, joined to facet joints, ligaments, both or neither
(:mod:`femcal.fe.posterior`) whose properties are drawn around their defaults. The four
classes are balanced; the classes of the draws are shuffled, so a row's position says
nothing about its class. The jobs run through the durable campaign store
(:mod:`femcal.fe.campaign`), so a clone rebuilds the cohort from the committed store without
CalculiX.

The cohort folder holds

* ``measured/Test/``: the RoM of every specimen with Gaussian noise of ``noise_deg`` added
  (seeded), in the study's layout (row i = specimen ``i``), which ``femcal diagnose`` and
  ``femcal calibrate`` read as measurements;
* ``clean/Test/``: the same curves without noise;
* ``answers.csv``: per specimen its class, the elements present, their drawn properties and
  the disc's parameters;
* ``cohort.json``: counts per class, failures, CPU seconds, seeds.

A specimen is kept when each of its four load cases reached the last moment. Specimens whose
runs failed are replaced by new draws of the same class (at most :data:`MAX_ROUNDS` rounds).

``python -m femcal.fe.cohort`` (from ``fe/``, stage ``cohort`` of ``fe/dvc.yaml``) reads the
``fe`` and ``cohort`` sections of ``params.yaml``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from femcal.dvc_metrics import write as write_dvc_metrics
from femcal.errors import SolverError
from femcal.fe.calculix_settings import LIGAMENT_DEFAULTS, LIGAMENTS
from femcal.schema import LOAD_CASES, STATUS_OK
from femcal.settings.fe import CohortSettings

if TYPE_CHECKING:
    from femcal.fe.runtime import FeRuntime
    from femcal.space import ParameterSpace

logger = logging.getLogger(__name__)

#: The classes, in the order of the answers file: the elements each one adds to the disc.
CLASSES: dict[str, tuple[bool, bool]] = {
    "none": (False, False),
    "facets": (True, False),
    "ligaments": (False, True),
    "both": (True, True),
}
#: The diagnosis's effect names that stand for each element (femcal.effects).
CLASS_EFFECTS: dict[str, tuple[str, ...]] = {
    "none": (),
    "facets": ("facet_contact",),
    "ligaments": ("ligament_tension",),
    "both": ("facet_contact", "ligament_tension"),
}
#: First config_id of the cohort's jobs (apart from the campaign's 0..n).
FIRST_CONFIG_ID = 100_000
#: Rounds of draws at most (the first and the replacements of failed specimens).
MAX_ROUNDS = 4
#: Specimens drawn in the first round per specimen wanted (failed runs are replaced later).
FIRST_ROUND_FACTOR = 1.1
#: Bounds of a ligament's slack strain (femcal.fe.calculix_settings.LigamentSettings).
SLACK_RANGE = (-0.3, 0.5)


def _log_uniform(rng: np.random.Generator, low: float, high: float, n: int) -> np.ndarray:
    return np.exp(rng.uniform(math.log(low), math.log(high), n))


def draw_specimens(
    space: ParameterSpace,
    counts: Mapping[str, int],
    cohort: CohortSettings,
    rng: np.random.Generator,
) -> pd.DataFrame:
    """Draw specimens: disc parameters and the properties of their posterior elements.

    Parameters
    ----------
    space : ParameterSpace
        The sampling box of the disc's parameters (physical units).
    counts : mapping of str to int
        Class (a key of :data:`CLASSES`) -> specimens to draw.
    cohort : CohortSettings
        The ranges of the draws.
    rng : numpy.random.Generator

    Returns
    -------
    pandas.DataFrame, shape (sum(counts), 5 + d)
        ``class``, ``facet_gap_mm``, ``facet_stiffness_n_per_mm``,
        ``ligament_stiffness_scale``, ``ligament_slack_shift`` (NaN where the element is
        absent) and the ``d`` disc parameters, in class order.
    """
    frames = []
    lo, hi = np.asarray(space.lower, float), np.asarray(space.upper, float)
    margin = cohort.disc_margin * (hi - lo)
    for name, n in counts.items():
        if n <= 0:
            continue
        facets, ligaments = CLASSES[name]
        unit = rng.uniform(size=(n, len(space.names)))
        disc = lo + margin + unit * (hi - lo - 2 * margin)
        frame = pd.DataFrame(disc, columns=list(space.names))
        nan = np.full(n, np.nan)
        gap, stiff = cohort.facet_gap_mm, cohort.facet_stiffness_n_per_mm
        scale, shift = cohort.ligament_stiffness_scale, cohort.ligament_slack_shift
        extra = {
            "class": [name] * n,
            "facet_gap_mm": rng.uniform(gap[0], gap[1], n) if facets else nan,
            "facet_stiffness_n_per_mm": _log_uniform(rng, *stiff, n) if facets else nan,
            "ligament_stiffness_scale": _log_uniform(rng, *scale, n) if ligaments else nan,
            "ligament_slack_shift": rng.uniform(shift[0], shift[1], n) if ligaments else nan,
        }
        frames.append(pd.concat([pd.DataFrame(extra), frame], axis=1))
    return pd.concat(frames, ignore_index=True)


def posterior_of(row: Mapping[str, Any]) -> dict[str, Any] | None:
    """The ``posterior`` adapter setting of a drawn specimen (None: the disc alone).

    Parameters
    ----------
    row : mapping
        A row of :func:`draw_specimens`.

    Returns
    -------
    dict or None
        ``{"facets": {gap_mm, stiffness_n_per_mm}, "ligaments": {name: {stiffness_n_per_mm,
        slack_strain}}}`` with the elements present; every other property at its default.
    """
    facets, ligaments = CLASSES[str(row["class"])]
    if not (facets or ligaments):
        return None
    out: dict[str, Any] = {}
    if facets:
        out["facets"] = {
            "gap_mm": round(float(row["facet_gap_mm"]), 6),
            "stiffness_n_per_mm": round(float(row["facet_stiffness_n_per_mm"]), 6),
        }
    if ligaments:
        scale, shift = float(row["ligament_stiffness_scale"]), float(row["ligament_slack_shift"])
        out["ligaments"] = {}
        for name in LIGAMENTS:
            default = LIGAMENT_DEFAULTS[name]
            slack = float(np.clip(default["slack_strain"] + shift, *SLACK_RANGE))
            out["ligaments"][name] = {
                "stiffness_n_per_mm": round(default["stiffness_n_per_mm"] * scale, 6),
                "slack_strain": round(slack, 6),
            }
    return out


def adapter_settings(row: Mapping[str, Any]) -> dict[str, Any] | None:
    """The adapter settings of a drawn specimen beyond ``fe.settings`` (None: the disc alone).

    Its ``posterior`` elements (:func:`posterior_of`) and, where a ligament is pre-strained
    (slack strain < 0: taut at rest, so it turns the unloaded disc), ``neutral_step``: its RoM
    from the neutral position it settles into, as a measurement is zeroed. Elements without
    force at rest leave the neutral position where the mesh is; their jobs keep their hashes.
    """
    posterior = posterior_of(row)
    if posterior is None:
        return None
    strains = [lig["slack_strain"] for lig in posterior.get("ligaments", {}).values()]
    return {
        "posterior": posterior,
        **({"neutral_step": True} if min(strains, default=0) < 0 else {}),
    }


def complete_ids(records: pd.DataFrame, n_levels: int) -> set[int]:
    """Configurations whose four load cases all reached the last of ``n_levels`` moments."""
    if not len(records):
        return set()
    ok = records[records["status"] == STATUS_OK]
    cases = ok.groupby("config_id")["load_case"].nunique()
    return {int(c) for c, n in cases.items() if n == len(LOAD_CASES)}


def _stored(
    fe: FeRuntime, settings: Any, design: pd.DataFrame, space: ParameterSpace, moments: Sequence
) -> pd.DataFrame:
    """The records of the design's jobs already in the store (nothing runs)."""
    from femcal.fe.store import job_hash, load_records, make_jobs, records_frame, settings_hash

    jobs = make_jobs(design, space.names, load_cases=LOAD_CASES, moments=moments)
    digests = {cid: settings_hash(fe.solver, settings.of(cid)) for cid in design["config_id"]}
    hashes = [job_hash(job, digests[job.config_id]) for job in jobs]
    return records_frame(load_records(fe.store, hashes) if Path(fe.store).parent.is_dir() else [])


def _run_rounds(
    fe: FeRuntime,
    space: ParameterSpace,
    cohort: CohortSettings,
    moments: Sequence[float],
    run: bool = True,
) -> tuple[pd.DataFrame, pd.DataFrame, dict[str, Any]]:
    """Draw, run and replace failed specimens; the drawn table, the records and the counts.

    With ``run`` False nothing runs: the first round's draws and their stored records.
    """
    from femcal.fe.campaign import PerConfigSettings, run_campaign, timed_out
    from femcal.fe.runtime import SHARED_MACHINE_TIMEOUT_S

    rng = np.random.default_rng([cohort.seed, 0])
    wanted = {name: int(cohort.per_class) for name in CLASSES}
    drawn = pd.DataFrame()
    records = pd.DataFrame()
    counts: dict[str, Any] = {"rounds": 0, "jobs_run_now": 0, "jobs_from_store": 0}
    for round_ in range(MAX_ROUNDS):
        kept = _kept(drawn, records, len(moments))
        missing = {c: wanted[c] - int((kept["class"] == c).sum()) for c in CLASSES}
        if not any(v > 0 for v in missing.values()):
            break
        factor = FIRST_ROUND_FACTOR if round_ == 0 else 1.0
        todo = {c: math.ceil(v * factor) for c, v in missing.items() if v > 0}
        new = draw_specimens(space, todo, cohort, rng)
        # classes interleaved, so that a campaign stopped early holds every class alike
        new = new.iloc[rng.permutation(len(new))].reset_index(drop=True)
        new.insert(0, "config_id", FIRST_CONFIG_ID + len(drawn) + np.arange(len(new)))
        drawn = pd.concat([drawn, new], ignore_index=True)
        by_config = {
            int(r["config_id"]): s
            for r in drawn.to_dict(orient="records")
            if (s := adapter_settings(r)) is not None
        }
        base = {**fe.settings, "timeout_s": SHARED_MACHINE_TIMEOUT_S}
        settings = PerConfigSettings(base, by_config)
        if not run:
            records = _stored(fe, settings, drawn[["config_id", *space.names]], space, moments)
            counts["jobs_from_store"] = int(len(records))
            break
        result = run_campaign(
            fe.solver,
            settings,
            drawn[["config_id", *space.names]],
            fe.campaign_options(),
            store=fe.store,
            names=space.names,
            load_cases=LOAD_CASES,
            moments=moments,
            retry_failed=timed_out,
        )
        records = result.records
        counts["rounds"] = round_ + 1
        counts["jobs_run_now"] += result.n_run
        counts["jobs_from_store"] = result.n_skipped
    return drawn, records, counts


def _kept(drawn: pd.DataFrame, records: pd.DataFrame, n_levels: int) -> pd.DataFrame:
    """The first ``per_class`` complete specimens of each class, in draw order."""
    if not len(drawn):
        return pd.DataFrame({"class": []})
    done = complete_ids(records, n_levels)
    return drawn[drawn["config_id"].isin(done)]


def _with_noise(records: pd.DataFrame, noise_deg: float, seed: int) -> list[dict]:
    """The records with Gaussian noise of sd ``noise_deg`` added to every RoM value."""
    rng = np.random.default_rng([seed, 1])
    out = []
    for rec in records.sort_values(["config_id", "load_case"]).to_dict(orient="records"):
        rom = np.asarray([np.nan if v is None else v for v in rec["rom_deg"]], dtype=float)
        noisy = rom + rng.normal(0.0, noise_deg, rom.shape)
        out.append({**rec, "rom_deg": [None if np.isnan(v) else float(v) for v in noisy]})
    return out


def build_cohort(
    fe: FeRuntime,
    space: ParameterSpace,
    cohort: CohortSettings,
    moments: Sequence[float],
    *,
    partial: bool = False,
) -> dict[str, Any]:
    """Draw, simulate (or read from the store) and write the cohort (module docstring).

    Parameters
    ----------
    fe : FeRuntime
        Solver, base settings (``fe.settings``; each specimen adds its ``posterior``), the
        cohort's store and the Dask cluster.
    space : ParameterSpace
        The disc's sampling box.
    cohort : CohortSettings
        Classes' size, seed, noise, ranges and the output folder (``out_dir``).
    moments : sequence of float, shape (m,)
        Moment levels, Nm.
    partial : bool, optional
        Run nothing: write the complete specimens of the first round's draws already in the
        store, at most ``per_class`` of each class and at least one (a preview of a campaign
        still running; ``cohort.json`` says ``"complete": false``).

    Returns
    -------
    dict
        The content of ``cohort.json``.

    Raises
    ------
    SolverError
        When a class still lacks complete specimens after :data:`MAX_ROUNDS` rounds (or,
        with ``partial``, when a class has none yet).
    """
    from femcal.fe.dataset import write_dataset
    from femcal.outputs import check_destination, staged_output

    out_dir = Path(cohort.out_dir)
    check_destination(out_dir)
    drawn, records, counts = _run_rounds(fe, space, cohort, moments, run=not partial)
    done = drawn[drawn["config_id"].isin(complete_ids(records, len(moments)))]
    kept = done.groupby("class", sort=False).head(int(cohort.per_class))
    short = {c: int(cohort.per_class) - int((kept["class"] == c).sum()) for c in CLASSES}
    counts = {**counts, "complete": not any(v > 0 for v in short.values())}
    none_yet = [c for c in CLASSES if not (kept["class"] == c).any()]
    if partial and none_yet:
        raise SolverError(
            f"The store {fe.store} holds no complete specimen of the classes {none_yet} yet; "
            "a partial cohort needs one of each. Run the campaign (without --partial) longer."
        )
    if not partial and not counts["complete"]:
        raise SolverError(
            f"The cohort lacks complete specimens after {MAX_ROUNDS} rounds of draws: "
            f"{ {c: v for c, v in short.items() if v > 0} } missing (the runs' failures are in "
            f"{fe.store}). Lower cohort.per_class, or narrow the ranges in fe/params.yaml."
        )
    # Rows in config_id order, as write_dataset writes them: specimen i is row i of every
    # file (the draws' order already interleaves the classes at random).
    kept = kept.sort_values("config_id").reset_index(drop=True)
    kept.insert(0, "specimen", [str(i) for i in range(len(kept))])
    mine = records[records["config_id"].isin(set(kept["config_id"]))]
    design = kept[["config_id", *space.names]].assign(split="test")
    info = _summary(drawn, records, kept, counts, cohort)
    with staged_output(out_dir, command="fe cohort") as stage:
        for name, recs in (
            ("clean", mine.to_dict(orient="records")),
            ("measured", _with_noise(mine, cohort.noise_deg, cohort.seed)),
        ):
            write_dataset(design, recs, stage.path / name, space=space, moments=moments)
        answers = kept.drop(columns=["config_id"]).assign(
            effects=[" ".join(CLASS_EFFECTS[c]) for c in kept["class"]],
            config_id=kept["config_id"],
        )
        answers.to_csv(stage.path / "answers.csv", index=False)
        # the folder holds what the store determines; this run's own job counts stay out of it
        # (a rebuild from the store hashes as the run that made it)
        this_run = ("jobs_run_now", "jobs_from_store")
        saved = {k: v for k, v in info.items() if k not in this_run}
        (stage.path / "cohort.json").write_text(json.dumps(saved, indent=2) + "\n")
    logger.info("cohort: %s", {k: info[k] for k in ("rounds", *this_run) if k in info})
    return info


def _summary(
    drawn: pd.DataFrame,
    records: pd.DataFrame,
    kept: pd.DataFrame,
    counts: Mapping[str, Any],
    cohort: CohortSettings,
) -> dict[str, Any]:
    """The figures of ``cohort.json``."""
    failed = records[records["status"] != STATUS_OK]
    cpu = records.groupby("config_id")["cpu_seconds"].sum()
    return {
        "n_specimens": int(len(kept)),
        "classes": {c: int((kept["class"] == c).sum()) for c in CLASSES},
        "n_drawn": int(len(drawn)),
        "n_drawn_per_class": {c: int((drawn["class"] == c).sum()) for c in CLASSES},
        "n_jobs": int(len(records)),
        "n_failed_jobs": int(len(failed)),
        "failure_reasons": {str(k): int(v) for k, v in failed["reason"].value_counts().items()},
        "cpu_seconds_total": float(records["cpu_seconds"].sum()),
        "cpu_seconds_per_specimen_mean": float(cpu.mean()) if len(cpu) else float("nan"),
        "noise_deg": float(cohort.noise_deg),
        "seed": int(cohort.seed),
        **{k: v for k, v in counts.items()},
    }


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Build the cohort of ``params.yaml``'s ``cohort`` section (run from ``fe/``)."""
    from femcal.config import load_params
    from femcal.fe.runtime import fe_runtime, fe_space
    from femcal.settings import validate_params

    parser = argparse.ArgumentParser(prog="python -m femcal.fe.cohort")
    parser.add_argument("--params", type=Path, default=Path("params.yaml"))
    parser.add_argument("--metrics-file", type=Path, default=None)
    parser.add_argument("--progress", action="store_true")
    parser.add_argument(
        "--partial",
        action="store_true",
        help="run nothing; write the complete specimens already in the store",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    params = load_params(args.params)
    settings = validate_params(params, path=str(args.params), schema="fe")
    cohort = settings.cohort
    if cohort is None:
        from femcal.errors import ConfigError

        raise ConfigError(
            f"{args.params} has no cohort section; add one (fe/params.yaml shows its fields)."
        )
    fe = fe_runtime(params, {"store": cohort.store, "progress": args.progress}, "fe")
    space, moments = fe_space(params["fe"]["bounds"]), params["fe"]["moments"]
    info = build_cohort(fe, space, cohort, moments, partial=args.partial)
    # the headline; every figure in the cohort folder's cohort.json
    write_dvc_metrics(args.metrics_file, "cohort", info)
    print(json.dumps({k: info[k] for k in ("n_specimens", "classes", "n_failed_jobs")}))
    return info


if __name__ == "__main__":
    main()
