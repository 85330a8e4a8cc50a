"""Measured: how many bounds the disc-alone fit presses, and how near the box's edge the curves
lie, for discs inside the box and beyond it (issue 55, item 1; ``femcal.diagnose.box_edge``).

For each seed folder of a :mod:`experiments.bench_edges` results folder (its cohort and the
command's ``diagnosis.json``), per specimen:

* ``k``: the disc-alone parameters on a bound (``failures.on_bounds`` of ``diagnosis.json``);
* ``margin``: how far its curves lie inside the disc's envelope, in sigma
  (:func:`femcal.diagnose.box_edge.margins`, sigma the stated noise and the surrogate's error);
* the box's own answer: :data:`DRAWS` discs drawn uniformly in the box, their surrogate curves
  at the specimen's points with noise of its sd, fitted by the disc alone
  (:func:`femcal.diagnose.box_edge._box_draws`): their ``k`` and margins, and the share of
  draws with ``k_r >= k`` and ``margin_r <= margin`` (the p-value the diagnosis computes with
  more draws where it is small).

Writes ``box_edge.json`` and ``box_edge.md`` into the results folder (each seed's rows also to
``seed-<seed>/box_edge.csv``, reused when present); ``experiments.edges_report``
prints ``box_edge.md`` in that folder's section. From the project root::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.box_edge_measure \\
        --results experiments/results/bench_edges/dev-item4
"""

from __future__ import annotations

import argparse
import json
import types
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from experiments.common import REPO

#: Box draws per specimen.
DRAWS = 32
#: Groups of specimens in the tables: name -> truth classes (None: the box's own draws).
INSIDE_NONE, INSIDE_OTHER, OUTSIDE, BOX = (
    "Test discs, class none",
    "Test discs with structures",
    "discs outside the box",
    "discs drawn in the box (fitted)",
)


def _base(measurements: Path):
    """The command's surrogate on the cohort's (screened) moments, the measurements and each
    point's sd, as ``femcal diagnose --noise-deg 0.05`` builds them."""
    from femcal.calibration import SurrogateCurveModel
    from femcal.config import load_params
    from femcal.datasets import training_configurations
    from femcal.diagnose.options import DiagnoseOptions
    from femcal.jobs.diagnose import DiagnosisJob
    from femcal.measurements import read_measurements
    from femcal.moments import MomentPolicy
    from femcal.tracking import load_surrogate, open_model

    job = DiagnosisJob.from_params(
        load_params(REPO / "params.yaml"), out_dir=Path("unused"), measurements=measurements
    )
    surrogate = load_surrogate(open_model(job.model_uri))
    meas = read_measurements(measurements, noise_deg=0.05)
    policy = MomentPolicy.for_surrogate(
        surrogate, growth=job.error_growth, max_log_ratio=job.max_log_ratio
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        meas = policy.screen(meas).measurements
    base = SurrogateCurveModel(surrogate, meas.moments)
    sur = np.broadcast_to(policy.sigma_surrogate(meas.moments, meas.rom_deg), meas.rom_deg.shape)
    sigma = np.sqrt(0.05**2 + sur**2)
    bank = training_configurations(job.start_bank) if job.start_bank else None
    state = types.SimpleNamespace(
        base=base,
        specimens=list(meas.specimens),
        measured=meas.rom_deg,
        mask=np.isfinite(meas.rom_deg),
        sigma=sigma,
        weight=(sigma.min() / sigma) ** 2,
        start_bank=bank,
        options=DiagnoseOptions(),
    )
    return state


def measure_seed(seed_dir: Path) -> pd.DataFrame:
    """One row per specimen and one per box draw of ``seed_dir``'s cohort."""
    from femcal.diagnose.box_edge import _box_draws, margins
    from femcal.reachability import build_envelope

    truth = {t["specimen"]: t for t in json.loads((seed_dir / "cohort/truth.json").read_text())}
    diag = json.loads((seed_dir / "diagnosis/diagnosis.json").read_text())
    by_name = {r["specimen"]: r for r in diag}
    state = _base(seed_dir / "cohort/measurements.csv")
    env = build_envelope(state.base, sigma_model=np.zeros(state.measured.shape[2]))
    margin, side = margins(state.measured, env.lower, env.upper, state.sigma)
    rng = np.random.default_rng(int(seed_dir.name.split("-")[-1]))
    rows = []
    for i, name in enumerate(state.specimens):
        r, t = by_name[name], truth[name]
        k = len(r["failures"]["on_bounds"])
        kr, mr = _box_draws(state, i, env, rng, DRAWS)
        label = t["truth"]
        group = OUTSIDE if label == "outside_box" else INSIDE_NONE if label == "none" else None
        rows.append(
            {
                "seed": seed_dir.name.split("-")[-1],
                "specimen": name,
                "truth": label,
                "group": group or INSIDE_OTHER,
                "verdict": r["verdict"],
                "k": k,
                "margin": float(margin[i]),
                "side": side[i],
                "p_box": float((1 + np.sum((kr >= k) & (mr <= margin[i]))) / (1 + len(kr))),
                "p_box_k": float((1 + np.sum(kr >= k)) / (1 + len(kr))),
                "edge_probability": float(
                    ((r.get("outside_box") or {}).get("edge") or {}).get("probability", np.nan)
                ),
            }
        )
        rows += [
            {
                "seed": rows[-1]["seed"],
                "specimen": name,
                "group": BOX,
                "k": int(a),
                "margin": float(b),
            }
            for a, b in zip(kr, mr)
        ]
    return pd.DataFrame(rows)


def tables(t: pd.DataFrame) -> list[str]:
    """The Markdown of the measured distributions."""
    order = [BOX, INSIDE_NONE, INSIDE_OTHER, OUTSIDE]
    lines = [
        "| group | n | k: 0-2 | 3 | 4 | 5 | 6 | 7 | 8 | >= 9 | margin 10 % / 50 % / 90 % (sigma) "
        "| margin <= 2 |",
        "|---" * 11 + "|",
    ]
    for g in order:
        s = t[t["group"] == g]
        if s.empty:
            continue
        k = s["k"].to_numpy()
        shares = [np.mean(k <= 2), *(np.mean(k == v) for v in range(3, 9)), np.mean(k >= 9)]
        q = np.quantile(s["margin"], [0.1, 0.5, 0.9])
        lines.append(
            f"| {g} | {len(s)} | "
            + " | ".join(f"{100 * v:.0f} %" for v in shares)
            + f" | {q[0]:.1f} / {q[1]:.1f} / {q[2]:.1f} | {100 * np.mean(s['margin'] <= 2):.0f} % |"
        )
    spec = t[t["group"] != BOX]
    none = spec[spec["verdict"] == "none"].sort_values("p_box")
    lines += [
        "",
        "Specimens given `none`: the disc-alone fit's bounds (k), its margin, the share of the "
        f"specimen's {DRAWS} box draws pressing at least k bounds (p, k alone) and also as near "
        "the edge (p, k and margin; the diagnosis draws up to 512 where it is small) and "
        "the diagnosis' own edge probability (its p from up to 512 draws; - where it kept no "
        "reading: below 0.1 and nothing else pointing beyond the box).",
        "",
        "| seed | specimen | truth | k | margin (sigma) | side | p, k alone | p, k and margin "
        "| edge probability (diagnosis) |",
        "|---" * 9 + "|",
    ]
    for r in none.itertuples():
        prob = "-" if not np.isfinite(r.edge_probability) else f"{r.edge_probability:.2f}"
        lines.append(
            f"| {r.seed} | {r.specimen} | {r.truth} | {r.k} | {r.margin:.1f} | {r.side} | "
            f"{r.p_box_k:.2f} | {r.p_box:.2f} | {prob} |"
        )
    return lines


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--results", type=Path, required=True, help="a bench_edges results folder")
    args = ap.parse_args(argv)
    seeds = sorted(p for p in args.results.glob("seed-*") if (p / "diagnosis").exists())
    parts = []
    for seed_dir in seeds:  # each seed's rows kept beside its diagnosis, measured once
        cached = seed_dir / "box_edge.csv"
        if not cached.exists():
            measure_seed(seed_dir).to_csv(cached, index=False)
        parts.append(pd.read_csv(cached, dtype={"seed": str}))
    t = pd.concat(parts, ignore_index=True)
    (args.results / "box_edge.json").write_text(
        json.dumps(t.to_dict(orient="records"), indent=1, default=str) + "\n"
    )
    lines = ["### The disc alone at the box's edge (measured)", "", *tables(t), ""]
    (args.results / "box_edge.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
