"""Where the FE-made cohort's posterior elements act, measured by CalculiX.

The library's effects declare where they may act (``load_case_prior``, femcal.effects.builtin):
facets likely in extension and axial rotation, possible in lateral bending; ligaments likely in
flexion and lateral bending, possible in extension, not in axial rotation. The FE-made cohort
(``fe/data/cohort``, :mod:`femcal.fe.cohort`) has no such assignment: the elements' geometry
decides. This experiment measures it. Each element specimen runs again without one element,
in the load cases beyond the library's likely ones:

* facets removed, in lateral bending (specimens with facets);
* ligaments removed, in extension and axial rotation (specimens with ligaments); a specimen
  whose ligaments are taut at rest then has no neutral step (no force at rest, its neutral
  position is the mesh's).

The element's reach in that load case is the cohort's own curve (with it) against the run
without it: ``delta = RoM(without) - RoM(with)`` at each moment of ``fe.moments``, in degrees
(> 0: the element stiffens). Per (specimen, element, load case) it reports the MAE and the
largest ``|delta|``, the first moment where ``|delta|`` exceeds the noise (0.05 deg), and the
shape:

* ``engaging``: ``delta`` still grows over the top quarter of the moments (a gap or slack
  closed, then stiffer: what the library's laws make);
* ``saturating``: ``delta`` at the last moment within 5 % of its value at three quarters of the
  range (a taut element that goes slack: a pre-tensioned ligament unloading, whose moment at rest
  the disc takes over; no built-in law saturates in moment).

``--score DIAGNOSIS`` reads ``diagnosis.json`` of the cohort (``python -m femcal.fe.hidden``'s
``diagnosis`` folder) and adds, per row, whether the reach is visible (its MAE above 2 x the
noise plus the surrogate's error in that load case, ``sigma_parts.surrogate_by_load_case_deg``,
the loop's own visibility per load case) and the diagnosis' probability that the effect acts
there (inclusion x ``acts_in``).

Usage (from the project root; the cohort checked out: ``dvc checkout fe/dvc.yaml:cohort``)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.fe_element_reach --out DIR
    .venv/bin/python -m experiments.fe_element_reach --out DIR --score DIAGNOSIS

The CalculiX runs go to a committed store (``--store``), resumed when present: with it, no run
is repeated.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from experiments.common import REPO
from femcal.schema import LOAD_CASES

#: The element removed -> the effect that models it and the load cases run without it.
REMOVED: dict[str, tuple[str, tuple[str, ...]]] = {
    "facets": ("facet_contact", ("LateralBending",)),
    "ligaments": ("ligament_tension", ("Extension", "AxialRotation")),
}
#: Config ids of the runs without an element: this + 1000 * (position of the element in
#: REMOVED) + the specimen's number.
FIRST_ID = 300000
NOISE_DEG = 0.05


def variants(answers: pd.DataFrame) -> pd.DataFrame:
    """One row per (specimen, element removed): ``config_id``, ``specimen``, ``removed``,
    ``settings`` (the adapter settings without the element) and the 13 parameters."""
    from femcal.fe.cohort import adapter_settings

    rows = []
    for rec in answers.to_dict(orient="records"):
        own = adapter_settings(rec)
        if own is None:
            continue
        for k, element in enumerate(REMOVED):
            if element not in own["posterior"]:
                continue
            rest = {e: v for e, v in own["posterior"].items() if e != element}
            taut = own.get("neutral_step", False) and "ligaments" in rest
            settings = {"posterior": rest} if rest else {}
            settings.update({"neutral_step": True} if taut else {})
            rows.append(
                {
                    "config_id": FIRST_ID + 1000 * k + int(rec["specimen"]),
                    "specimen": str(rec["specimen"]),
                    "removed": element,
                    "settings": settings or None,
                }
            )
    return pd.DataFrame(rows)


def run(answers: pd.DataFrame, params: Mapping[str, Any], store: Path) -> pd.DataFrame:
    """The runs without each element (CalculiX, resumed from ``store``): the store's records
    of :func:`variants`, one row per job."""
    from femcal.fe.campaign import PerConfigSettings, run_campaign
    from femcal.fe.runtime import SHARED_MACHINE_TIMEOUT_S

    fe = params["fe"]
    names = list(fe["bounds"])
    table = variants(answers)
    design = table[["config_id", "specimen"]].merge(answers[["specimen", *names]], on="specimen")
    design = design[["config_id", *names]]
    base = {**fe["settings"], "timeout_s": SHARED_MACHINE_TIMEOUT_S}
    by_config = {int(c): s for c, s in zip(table["config_id"], table["settings"]) if s}
    settings = PerConfigSettings(base, by_config)
    frames = []
    for element, (_, cases) in REMOVED.items():
        part = design[table["removed"].to_numpy() == element]
        result = run_campaign(
            fe["solver"],
            settings,
            part,
            store=store,
            names=names,
            load_cases=cases,
            moments=fe["moments"],
            progress=False,
        )
        frames.append(result.records)
    records = pd.concat(frames, ignore_index=True)
    return records.merge(table[["config_id", "specimen", "removed"]], on="config_id")


def cohort_curves(cohort: Path) -> dict[tuple[str, str], np.ndarray]:
    """The cohort's noise-free curves, (specimen, load case) -> RoM (m,) in degrees: its
    ``clean/Test`` folder read as femcal reads measurements (specimen ``i`` is row ``i``, as
    in the loop's diagnosis)."""
    from femcal.measurements import read_measurements

    m = read_measurements(cohort / "clean" / "Test")
    return {
        (s, lc): m.rom_deg[i, j]
        for i, s in enumerate(m.specimens)
        for j, lc in enumerate(LOAD_CASES)
    }


def shape(delta: np.ndarray) -> str:
    """``engaging`` or ``saturating`` (module docstring) of a reach (m,); ``none`` where it
    stays within the noise."""
    d = np.abs(delta[np.isfinite(delta)])
    if len(d) < 4 or d.max() <= NOISE_DEG:
        return "none"
    late = d[(3 * len(d)) // 4 - 1]
    return "saturating" if abs(d[-1] - late) <= 0.05 * max(d[-1], 1e-12) else "engaging"


def reach(records: pd.DataFrame, cohort: Path, moments: Sequence[float]) -> pd.DataFrame:
    """Per (specimen, element, load case): ``mae_deg``, ``max_deg``, ``onset_nm``, ``shape``,
    ``levels`` (reached without the element)."""
    with_ = cohort_curves(cohort)
    rows = []
    for rec in records.itertuples(index=False):
        without = np.array([np.nan if v is None else float(v) for v in rec.rom_deg])
        delta = without - with_[(rec.specimen, rec.load_case)]
        ok = np.isfinite(delta)
        big = np.flatnonzero(ok & (np.abs(delta) > NOISE_DEG))
        rows.append(
            {
                "specimen": rec.specimen,
                "removed": rec.removed,
                "effect": REMOVED[rec.removed][0],
                "load_case": rec.load_case,
                "levels": int(ok.sum()),
                "mae_deg": float(np.abs(delta[ok]).mean()) if ok.any() else np.nan,
                "max_deg": float(np.abs(delta[ok]).max()) if ok.any() else np.nan,
                "onset_nm": float(moments[big[0]]) if len(big) else np.nan,
                "shape": shape(delta),
            }
        )
    return pd.DataFrame(rows).sort_values(["removed", "load_case", "specimen"], key=_natural)


def _natural(col: pd.Series) -> pd.Series:
    return col.map(lambda v: int(v) if str(v).isdigit() else v) if col.name == "specimen" else col


def score(table: pd.DataFrame, diagnosis: list[dict[str, Any]]) -> pd.DataFrame:
    """``table`` (:func:`reach`) with ``threshold_deg``, ``visible`` and ``p_acts`` from the
    cohort's diagnosis (module docstring)."""
    by = {str(s["specimen"]): s for s in diagnosis}
    thresholds, p_acts = [], []
    for rec in table.itertuples(index=False):
        s = by[rec.specimen]
        surrogate = s["sigma_parts"]["surrogate_by_load_case_deg"][rec.load_case]
        thresholds.append(2 * NOISE_DEG + surrogate)
        prob = s["probabilities"]
        acts = prob.get("acts_in", {}).get(rec.effect, {}).get(rec.load_case, 0.0)
        p_acts.append(prob.get("inclusion", {}).get(rec.effect, 0.0) * acts)
    out = table.assign(threshold_deg=thresholds, p_acts=p_acts)
    return out.assign(visible=out["mae_deg"] > out["threshold_deg"])


def summary(table: pd.DataFrame) -> pd.DataFrame:
    """Per (effect, load case): specimens, reach beyond the noise (max > 0.05 deg), visible,
    saturating among the visible, and among the visible the diagnosis' acting at >= 0.5."""
    rows = []
    for (effect, lc), g in table.groupby(["effect", "load_case"], sort=False):
        vis = g[g["visible"]] if "visible" in g else g.iloc[:0]
        rows.append(
            {
                "effect": effect,
                "load case": lc,
                "specimens": len(g),
                "max > noise": int((g["max_deg"] > NOISE_DEG).sum()),
                "largest max (deg)": round(float(g["max_deg"].max()), 3),
                "visible": len(vis),
                "saturating (visible)": int((vis["shape"] == "saturating").sum()),
                "named there, p >= 0.5 (visible)": int((vis["p_acts"] >= 0.5).sum())
                if "p_acts" in vis
                else 0,
            }
        )
    return pd.DataFrame(rows)


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.fe_element_reach")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cohort", type=Path, default=REPO / "fe" / "data" / "cohort")
    parser.add_argument(
        "--store", type=Path, default=REPO / "experiments" / "fe_element_reach.jsonl.gz"
    )
    parser.add_argument("--score", type=Path, default=None, help="the cohort's diagnosis folder")
    args = parser.parse_args(argv)
    params = yaml.safe_load((REPO / "fe" / "params.yaml").read_text())
    if not (args.cohort / "answers.csv").is_file():
        raise SystemExit(
            f"{args.cohort / 'answers.csv'}: not found; the FE-made cohort is a DVC output: "
            "run `dvc checkout fe/dvc.yaml:cohort` (or `dvc repro fe/dvc.yaml -s cohort`), or "
            "give its folder with --cohort"
        )
    answers = pd.read_csv(args.cohort / "answers.csv", dtype={"specimen": str})
    records = run(answers, params, args.store)
    table = reach(records, args.cohort, params["fe"]["moments"])
    if args.score is not None:
        diagnosis = json.loads((args.score / "diagnosis.json").read_text())
        table = score(table, diagnosis)
    args.out.mkdir(parents=True, exist_ok=True)
    table.to_csv(args.out / "reach.csv", index=False)
    print(summary(table).to_markdown(index=False))


if __name__ == "__main__":
    main()
