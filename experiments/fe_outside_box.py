"""FE-made discs outside the sampled box: does the diagnosis say so, or invent an element?

A disc stiffer (or softer) than every disc of the FE campaign's box is real physics the
CalculiX model simulates as readily as one inside it. This experiment draws such discs, runs
them in CalculiX (the four load cases at the campaign's moments, no posterior element), adds
Gaussian noise, and runs ``femcal diagnose`` on them with a surrogate trained on the box.

* **Discs.** ``--n-stiff`` discs whose five matrix and fibre stiffnesses (``C10Nucleus``,
  ``C01Nucleus``, ``C10Annulus``, ``K1Annulus``, ``K2Annulus``) all lie above the box, each
  drawn log-uniformly in ``[upper, --factor * upper]``, and ``--n-soft`` whose stiffnesses
  lie below it (``[lower / --factor, lower]``; ``K1Annulus`` and ``K2Annulus`` too); every
  other parameter uniform in the box (fe/params.yaml ``fe.bounds``). Seeded (``--seed``).
* **FE.** A campaign of its own (``--store``, committed, resumed when present), coarse mesh,
  one worker; a level a run does not reach is not measured. The softer discs' runs abort in
  CalculiX's fibre routine at 0-3 of 20 levels: the FE model cannot make them.
* **Scored** from ``diagnosis.json`` (``--score DIR``): the share with the out-of-box verdict
  (``outside_box.named``), and the specimens where a built-in effect has inclusion >= 0.9.

Usage (from the project root)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.fe_outside_box --out DIR
    .venv/bin/femcal diagnose --measurements DIR/measurements.csv --noise-deg 0.05 \\
        --model-uri fe/models/surrogate-large --out DIR/diagnosis
    .venv/bin/python -m experiments.fe_outside_box --score DIR
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from experiments.common import REPO
from femcal.effects.terms import parse_term

#: The stiffnesses moved beyond the box (the rest stay inside it).
STIFFNESSES = ("C10Nucleus", "C01Nucleus", "C10Annulus", "K1Annulus", "K2Annulus")
#: Built-in effects scored for confident inclusion.
BUILTIN = ("facet_contact", "ligament_tension", "neutral_zone")
LOAD_CASES = ("Flexion", "Extension", "LateralBending", "AxialRotation")


def draw(bounds: dict, n_stiff: int, n_soft: int, factor: float, seed: int) -> pd.DataFrame:
    """The discs: one row each, ``specimen``, ``side`` and the 13 parameters."""
    rng = np.random.default_rng(seed)
    rows = []
    for side, n in (("stiffer", n_stiff), ("softer", n_soft)):
        for k in range(n):
            row = {"specimen": f"{side}-{k:02d}", "side": side}
            for name, (lo, hi) in bounds.items():
                if name in STIFFNESSES:
                    a, b = (hi, hi * factor) if side == "stiffer" else (lo / factor, lo)
                    row[name] = float(np.exp(rng.uniform(np.log(a), np.log(b))))
                else:
                    row[name] = float(rng.uniform(lo, hi))
            rows.append(row)
    return pd.DataFrame(rows)


def simulate(discs: pd.DataFrame, params: dict, store: Path) -> np.ndarray:
    """CalculiX RoM (n, 4, m) of the discs at the campaign's moments (NaN: not reached)."""
    from femcal.fe.predictive import fe_outputs
    from femcal.fe.runtime import SHARED_MACHINE_TIMEOUT_S, FeRuntime

    fe = params["fe"]
    settings = {**fe["settings"], "timeout_s": SHARED_MACHINE_TIMEOUT_S}
    runtime = FeRuntime("calculix", settings, store, n_workers=1)
    names = list(fe["bounds"])
    rom, _ = fe_outputs(runtime, fe["moments"])(
        discs[names].to_numpy(float), np.arange(len(discs), dtype=np.int64)
    )
    return rom


def measurements(discs: pd.DataFrame, rom: np.ndarray, moments, noise: float, seed: int):
    """Long measurements (specimen, load_case, moment_nm, rom_deg) with Gaussian noise; a
    reading below zero (a stiff disc's first level) is written as its magnitude, as a lab
    reports a RoM."""
    rng = np.random.default_rng([seed, 1])
    noisy = np.abs(rom + rng.normal(0.0, noise, rom.shape))
    rows = [
        {"specimen": s, "load_case": lc, "moment_nm": float(m), "rom_deg": float(noisy[i, j, k])}
        for i, s in enumerate(discs["specimen"])
        for j, lc in enumerate(LOAD_CASES)
        for k, m in enumerate(moments)
        if np.isfinite(noisy[i, j, k])
    ]
    return pd.DataFrame(rows)


def score(folder: Path) -> dict:
    """The out-of-box verdicts and confident built-in effects of ``folder/diagnosis``."""
    from femcal.fe.hidden import visible_threshold

    diagnosis = json.loads((folder / "diagnosis" / "diagnosis.json").read_text())
    summary = json.loads((folder / "diagnosis" / "summary.json").read_text())
    threshold = visible_threshold(summary, summary["noise_deg"])
    rows = []
    for rec in diagnosis:
        inclusion = (rec.get("probabilities") or {}).get("inclusion") or {}
        confident = sorted(
            e for e, p in inclusion.items() if parse_term(e).effect in BUILTIN and p >= 0.9
        )
        box = rec.get("outside_box") or {}
        rows.append(
            {
                "specimen": rec["specimen"],
                "verdict": rec["verdict"],
                "outside_box": bool(box.get("named")),
                "side": box.get("side"),
                "confident_builtin": confident,
                "disc_mae_deg": float(rec["baseline_mae_deg"]),
                "visible": float(rec["baseline_mae_deg"]) > threshold,
            }
        )
    df = pd.DataFrame(rows)
    visible = df[df["visible"]]
    return {
        "n": int(len(df)),
        "visible_threshold_deg": threshold,
        "n_visible": int(len(visible)),
        "outside_box_fraction": float(df["outside_box"].mean()),
        "outside_box_fraction_visible": float(visible["outside_box"].mean()),
        "none_fraction_not_visible": float((df.loc[~df["visible"], "verdict"] == "none").mean()),
        "confident_builtin_fraction": float(df["confident_builtin"].map(bool).mean()),
        "verdicts": {str(k): int(v) for k, v in df["verdict"].value_counts().items()},
        "specimens": rows,
    }


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.fe_outside_box")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--store", type=Path, default=REPO / "experiments/fe_outside_box.jsonl.gz")
    parser.add_argument("--n-stiff", type=int, default=16)
    # softer discs: CalculiX's fibre routine aborts on them (too large a fibre extension, or
    # increments below the minimum at 0-3 of 20 levels), so the default leaves them out
    parser.add_argument("--n-soft", type=int, default=0)
    parser.add_argument("--factor", type=float, default=2.0)
    parser.add_argument("--noise-deg", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=20261202)
    parser.add_argument("--score", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.score is not None:
        figures = score(args.score)
        (args.score / "outside_box.json").write_text(json.dumps(figures, indent=2) + "\n")
        print(json.dumps({k: v for k, v in figures.items() if k != "specimens"}, indent=2))
        return
    params = yaml.safe_load((REPO / "fe" / "params.yaml").read_text())
    discs = draw(params["fe"]["bounds"], args.n_stiff, args.n_soft, args.factor, args.seed)
    rom = simulate(discs, params, args.store)
    args.out.mkdir(parents=True, exist_ok=True)
    discs.to_csv(args.out / "discs.csv", index=False)
    meas = measurements(discs, rom, params["fe"]["moments"], args.noise_deg, args.seed)
    meas.to_csv(args.out / "measurements.csv", index=False)
    print(f"{len(discs)} discs, {len(meas)} measured points: {args.out}/measurements.csv")


if __name__ == "__main__":
    main()
