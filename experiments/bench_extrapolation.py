"""Benchmark: how the NN surrogate's error grows beyond its trained moment range.

The policy of every command (:class:`femcal.moments.MomentPolicy`) models the surrogate's error
sd at a moment ``M`` outside the trained range ``[lo, hi]`` as a function of the log-moment
distance ``L = log(M / hi)`` above, ``log(lo / M)`` below. This benchmark measures it on our own
model: the NN surrogate (``train.large.fixed`` recipe of params.yaml, fewer members by default)
trained on a subset of the moments of the Large split, tested on the FE curves of the Test
split (64 configurations x 4 load cases) at the moments it did not see:

=============  ==========  ===========================
trained on     tested at   L
=============  ==========  ===========================
1, 2, 3 Nm     4, 5 Nm     0.29, 0.51 (above)
1, 2, 3, 4 Nm  5 Nm        0.22 (above)
3, 4, 5 Nm     2, 1 Nm     0.41, 1.10 (below)
2, 3, 4, 5 Nm  1 Nm        0.69 (below: the 1..5 Nm champion's L at 0.5 Nm)
=============  ==========  ===========================

and at its trained moments (the in-range error). Error sd = MAE * sqrt(pi / 2) (Gaussian
errors; the conversion femcal.stages.train uses for the validation error), the ratio = sd at ``M``
over the in-range sd of the same model (pooled over its trained moments). One-parameter growth
models are fitted to the ratios (least squares) on each side of the range, by the same code
for both ends, and translated to the 1..5 Nm champion, next to a colleague's measurement of the
champion on the study's held-out 0.5-10 Nm FE curves.

Writes ``extrapolation.md`` and ``extrapolation.json`` into
``experiments/results/bench_extrapolation/``.

Usage (from the project root, after ``make repro``; run it alone: torch on 2 shared cores)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_extrapolation \
        [--members 2] [--seeds 0 1]

``--select 3 --merge`` measures only the fourth experiment and keeps the others of
``experiments/results/bench_extrapolation/extrapolation.json``; ``--render`` re-analyses that file
and rewrites the report without training (``--render --champion models/surrogate-large`` measures
the champion's Test errors again first). The measured ``error_growth`` and ``max_log_ratio`` of each
side go into params.yaml's ``moments`` section by hand (the report names them).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from experiments.common import REPO, RESULTS
from experiments.extrapolation_report import markdown, notes
from femcal.config import load_params, section
from femcal.datasets import load_split
from femcal.moments import MomentPolicy, log_distance
from femcal.surrogates.nn import NeuralSurrogate
from femcal.train import ok_rows, surrogate_kwargs, validation_split

SD_PER_MAE = math.sqrt(math.pi / 2)
#: (trained moments, tested moments outside them)
EXPERIMENTS: tuple[tuple[tuple[float, ...], tuple[float, ...]], ...] = (
    ((1.0, 2.0, 3.0), (4.0, 5.0)),
    ((1.0, 2.0, 3.0, 4.0), (5.0,)),
    ((3.0, 4.0, 5.0), (2.0, 1.0)),
    ((2.0, 3.0, 4.0, 5.0), (1.0,)),
)
#: The sides of the trained range, in the order of femcal.moments.SIDES.
SIDES = ("below", "above")
#: A colleague's measurement of the 1..5 Nm champion against the study's held-out FE curves
#: (0.5-10 Nm; not available here): error in deg per moment band (0.5 Nm steps assumed).
COLLEAGUE = (
    {"band": "1-5 Nm (inside)", "moments": [1.0, 5.0], "error_deg": 0.029},
    {"band": "5.5-7.5 Nm", "moments": [5.5, 7.5], "error_deg": 0.065},
    {"band": "8-10 Nm", "moments": [8.0, 10.0], "error_deg": 0.135},
)
#: The same colleague's champion error below the range (issue 42): deg at 0.5 Nm.
COLLEAGUE_BELOW = {"band": "0.5 Nm", "moments": [0.5, 0.5], "error_deg": 0.017}
#: The champion's moments translated in the report, per side.
CHAMPION_MOMENTS = {
    "below": (0.25, 0.3, 0.4, 0.5, 0.6, 0.75, 0.9),
    "above": (5.5, 6.0, 6.5, 7.0, 7.5, 8.0, 8.3, 9.0, 10.0),
}
#: The model femcal.moments.MomentPolicy uses (see the notes).
CHOSEN = "exponential"
#: One-parameter growth models of the ratio sd(M) / sd(in range), g >= 0.
MODELS = {
    "linear": lambda L, g: 1.0 + g * L,
    "squared": lambda L, g: (1.0 + g * L) ** 2,
    "exponential": lambda L, g: np.exp(g * L),
}


def per_moment(model: NeuralSurrogate, test: pd.DataFrame, trained: tuple[float, ...]) -> list:
    """Test-set error of a fitted model at every moment of the Test split."""
    rows = test.reset_index(drop=True)
    err = np.asarray(model.predict(rows), dtype=float) - rows["rom_deg"].to_numpy()
    lo, hi = min(trained), max(trained)
    out = []
    for m in sorted(rows["moment_nm"].unique()):
        e = err[rows["moment_nm"].to_numpy() == m]
        L = float(log_distance(np.array([m]), (lo, hi))[0])
        out.append(
            {
                "moment_nm": float(m),
                "inside": bool(m in trained),
                "side": "inside" if m in trained else ("above" if m > hi else "between"),
                "L": L if m > hi or m < lo else 0.0,
                "n": int(e.size),
                "mae_deg": float(np.mean(np.abs(e))),
                "rms_deg": float(np.sqrt(np.mean(e**2))),
                "bias_deg": float(np.mean(e)),
                "sd_deg": float(np.mean(np.abs(e)) * SD_PER_MAE),
                "rom_mean_deg": float(rows.loc[rows["moment_nm"] == m, "rom_deg"].mean()),
            }
        )
    for r in out:
        if r["moment_nm"] < lo:
            r["side"] = "below"
    return out


def run_experiment(trained, tested, *, large, test, space, fixed, members, seed, val_fraction):
    data = large[large["moment_nm"].isin(list(trained))].reset_index(drop=True)
    tr, va = validation_split(data, fraction=val_fraction, seed=seed)
    nn = NeuralSurrogate(space, **surrogate_kwargs(fixed), n_members=members, seed=seed)
    t0 = time.perf_counter()
    nn.fit(tr, tr["rom_deg"].to_numpy(), X_val=va, y_val=va["rom_deg"].to_numpy())
    seconds = time.perf_counter() - t0
    rows = per_moment(nn, test, trained)
    inside = [r for r in rows if r["inside"]]
    mae_in = float(np.mean([r["mae_deg"] for r in inside]))  # equal n per moment
    sd_in = mae_in * SD_PER_MAE
    for r in rows:
        r["ratio"] = r["sd_deg"] / sd_in
    return {
        "trained_moments": list(trained),
        "tested_moments": list(tested),
        "moment_degree": int(nn.net_.architecture()["moment_degree"]),
        "seed": seed,
        "members": members,
        "epochs_per_member": [
            1 + max(h["epoch"] for h in nn.history_ if h["member"] == k) for k in range(members)
        ],
        "fit_seconds": round(seconds, 1),
        "val_mae_deg": nn.best_val_mae_deg_,
        "val_sd_deg": nn.best_val_mae_deg_ * SD_PER_MAE,
        "in_range_mae_deg": mae_in,
        "in_range_sd_deg": sd_in,
        "per_moment": rows,
    }


def fit_models(L: np.ndarray, ratio: np.ndarray, *, band_means: bool = False) -> dict:
    """Least-squares g of each growth model on log(ratio) (relative misfit), g in [0, 20].

    With ``band_means``, each ``L`` is a list of band members and the model's mean over the
    band is compared (the colleague's bands).
    """
    grid = np.linspace(0.0, 20.0, 20001)
    fits = {}
    for name, f in MODELS.items():

        def pred(g: float, f=f) -> np.ndarray:
            if band_means:
                return np.array([np.mean(f(np.asarray(b), g)) for b in L])
            return f(np.asarray(L), g)

        sse = np.array([np.sum((np.log(pred(g)) - np.log(ratio)) ** 2) for g in grid])
        g = float(grid[int(np.argmin(sse))])
        fits[name] = {
            "growth": round(g, 2),
            "rms_log_residual": float(np.sqrt(np.min(sse) / len(ratio))),
            "predicted": [float(x) for x in pred(g)],
        }
    return fits


def summarise(experiments: list[dict]) -> list[dict]:
    """Per (trained moments, extrapolated moment): the ratio over seeds (mean, min, max)."""
    groups: dict[tuple, list] = {}
    for ex in experiments:
        for r in ex["per_moment"]:
            if r["L"] > 0:
                key = (tuple(ex["trained_moments"]), r["moment_nm"])
                groups.setdefault(key, []).append((ex, r))
    out = []
    for (trained, m), items in groups.items():
        ratios = [r["ratio"] for _, r in items]
        out.append(
            {
                "trained_moments": list(trained),
                "moment_degree": items[0][0]["moment_degree"],
                "moment_nm": m,
                "side": items[0][1]["side"],
                "L": items[0][1]["L"],
                "seeds": [ex["seed"] for ex, _ in items],
                "in_range_sd_deg": float(np.mean([ex["in_range_sd_deg"] for ex, _ in items])),
                "sd_deg": float(np.mean([r["sd_deg"] for _, r in items])),
                "bias_deg": float(np.mean([r["bias_deg"] for _, r in items])),
                "ratio": float(np.exp(np.mean(np.log(ratios)))),  # geometric mean
                "ratio_min": float(min(ratios)),
                "ratio_max": float(max(ratios)),
            }
        )
    return sorted(out, key=lambda p: (p["side"], p["L"]))


def colleague_bands() -> tuple[list[list[float]], np.ndarray]:
    """The colleague's two bands beyond 5 Nm: L of their moments (0.5 Nm steps) and ratios."""
    base = COLLEAGUE[0]["error_deg"]
    Ls, ratios = [], []
    for band in COLLEAGUE[1:]:
        lo, hi = band["moments"]
        Ls.append(np.log(np.arange(lo, hi + 1e-9, 0.5) / 5.0).tolist())
        ratios.append(band["error_deg"] / base)
    return Ls, np.array(ratios)


#: The champion the report translates the policy to (a model folder, e.g. models/surrogate-large,
#: or a models:/ URI of the project's store).
CHAMPION = "models:/ivd-rom-surrogate@champion"


def champion_in_range(test: pd.DataFrame, uri: str = CHAMPION) -> dict | None:
    """The champion's Test error per moment (context)."""
    try:
        from femcal.tracking import configure_tracking, load_surrogate

        configure_tracking(store_dir=REPO / "mlruns")
        sur = load_surrogate(uri)
    except Exception as exc:  # noqa: BLE001 - context only
        print(f"champion not available: {exc}")
        return None
    rows = per_moment(sur, test, (1.0, 2.0, 3.0, 4.0, 5.0))
    return {
        "val_mae_deg": sur.best_val_mae_deg_,
        "error_deg": sur.best_val_mae_deg_ * SD_PER_MAE,
        "uri": uri,
        "moment_range": list(sur.moment_range_),
        "per_moment": rows,
        "test_mae_deg": float(np.mean([r["mae_deg"] for r in rows])),
    }


def analyse(report: dict) -> dict:
    """Fits, the chosen policy and its translation to the champion (from the raw results).

    Both ends of the trained range go through the same code: per side, ``exp(g L)`` fitted to
    that side's points, and ``max_log_ratio`` the largest ``L`` measured on that side.
    """
    points = summarise(report["experiments"])
    side_points = {side: [p for p in points if p["side"] == side] for side in SIDES}
    L = np.array([p["L"] for p in points])
    ratio = np.array([p["ratio"] for p in points])
    fits = {"all": fit_models(L, ratio)}
    for side in SIDES:
        fits[side] = fit_models(
            np.array([p["L"] for p in side_points[side]]),
            np.array([p["ratio"] for p in side_points[side]]),
        )
    bands_L, bands_ratio = colleague_bands()
    fits["colleague"] = fit_models(bands_L, bands_ratio, band_means=True)
    growth = {side: fits[side][CHOSEN]["growth"] for side in SIDES}
    lmax = {side: round(max(p["L"] for p in side_points[side]), 2) for side in SIDES}
    champ = report.get("champion_in_range")
    error_deg = champ["error_deg"] if champ else COLLEAGUE[0]["error_deg"] * SD_PER_MAE
    policy = MomentPolicy(
        (1.0, 5.0),
        error_deg,
        tuple(growth[s] for s in SIDES),
        tuple(lmax[s] for s in SIDES),
    )
    a_lo, a_hi = policy.accepted_range
    champion_rows = []
    for side in SIDES:
        ms = np.array(CHAMPION_MOMENTS[side])
        for m, Lm, f, sd in zip(
            ms, policy.log_distance(ms), policy.error_factor(ms), policy.sigma_surrogate(ms)
        ):
            champion_rows.append(
                {
                    "moment_nm": float(m),
                    "side": side,
                    "L": float(Lm),
                    "ratio": float(f),
                    "sd_deg": float(sd),
                    "accepted": bool(a_lo - 1e-9 <= m <= a_hi + 1e-9),
                }
            )
    colleague = []
    for band, Ls, r in zip(COLLEAGUE[1:], bands_L, bands_ratio):
        ms_band = 5.0 * np.exp(np.array(Ls))
        model = float(np.mean(policy.error_factor(ms_band)))
        colleague.append(
            {
                "band": band["band"],
                "L_range": [Ls[0], Ls[-1]],
                "measured_deg": band["error_deg"],
                "measured_ratio": float(r),
                "model_ratio": model,
                "model_deg_from_colleague_in_range": model * COLLEAGUE[0]["error_deg"],
                "linear_ratio": float(
                    np.mean(MODELS["linear"](np.array(Ls), fits["above"]["linear"]["growth"]))
                ),
            }
        )
    m_below = COLLEAGUE_BELOW["moments"][0]
    model_below = float(policy.error_factor(np.array([m_below]))[0])
    colleague.append(
        {
            "band": COLLEAGUE_BELOW["band"],
            "L_range": [math.log(1.0 / m_below)] * 2,
            "measured_deg": COLLEAGUE_BELOW["error_deg"],
            "measured_ratio": COLLEAGUE_BELOW["error_deg"] / COLLEAGUE[0]["error_deg"],
            "model_ratio": model_below,
            "model_deg_from_colleague_in_range": model_below * COLLEAGUE[0]["error_deg"],
            "linear_ratio": float(
                MODELS["linear"](math.log(1.0 / m_below), fits["below"]["linear"]["growth"])
            ),
        }
    )
    return {
        "points": points,
        "fits": fits,
        "chosen": {
            "model": CHOSEN,
            "formula": "sd(M) = error_deg * exp(error_growth[side] * L)",
            "error_growth": growth,
            "max_log_ratio": lmax,
            "error_deg_champion": error_deg,
            "accepted_range_champion_nm": [a_lo, a_hi],
        },
        "champion_extrapolated": champion_rows,
        "colleague": colleague,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=2, help="ensemble members per model")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--max-epochs", type=int, default=None, help="default: the recipe's")
    ap.add_argument(
        "--select",
        type=int,
        nargs="+",
        default=list(range(len(EXPERIMENTS))),
        help="indices into EXPERIMENTS to measure (default: all)",
    )
    ap.add_argument(
        "--champion",
        default=None,
        help=f"the champion to translate to: a model folder or URI (default {CHAMPION}); "
        "with --render, its Test errors are measured again",
    )
    ap.add_argument(
        "--merge",
        action="store_true",
        help="keep OUT.json's experiments of the other trained ranges (and its champion)",
    )
    ap.add_argument("--out", default=str(RESULTS / "bench_extrapolation" / "extrapolation"))
    ap.add_argument(
        "--render", action="store_true", help="re-analyse and rewrite from OUT.json (no training)"
    )
    ap.add_argument(
        "--metrics-file",
        type=Path,
        default=None,
        help="also write the chosen growth and limits here (the experiments pipeline's metrics)",
    )
    args = ap.parse_args()
    out = Path(args.out)
    if args.render:
        report = json.loads(out.with_suffix(".json").read_text())
        if args.champion:
            params = load_params(REPO / "params.yaml")
            prepared = REPO / section(params, "data", "prepared_dir")
            test = ok_rows(load_split(prepared, "test")[0])
            report["champion_in_range"] = champion_in_range(test, args.champion) or report.get(
                "champion_in_range"
            )
    else:
        report = measure(args)
        if args.merge:
            report = merged(json.loads(out.with_suffix(".json").read_text()), report)
    report["analysis"] = analyse(report)
    report["notes"] = notes(report)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(report, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown(report))
    ch = report["analysis"]["chosen"]
    if args.metrics_file is not None:
        args.metrics_file.parent.mkdir(parents=True, exist_ok=True)
        args.metrics_file.write_text(json.dumps({"chosen": ch}, indent=2) + "\n")
    print(
        f"error_growth {ch['error_growth']}, max_log_ratio {ch['max_log_ratio']}; wrote "
        f"{out.with_suffix('.md')} and {out.with_suffix('.json')}"
    )


def measure(args: argparse.Namespace) -> dict:
    torch.set_num_threads(1)
    params = load_params(REPO / "params.yaml")
    fixed = dict(section(params, "train", "large", "fixed"))
    if args.max_epochs:
        fixed["max_epochs"] = args.max_epochs
        fixed["patience"] = min(int(fixed.get("patience", 100)), args.max_epochs)
    prepared = REPO / section(params, "data", "prepared_dir")
    large, space = load_split(prepared, "large")
    test, _ = load_split(prepared, "test")
    large, test = ok_rows(large), ok_rows(test)
    val_fraction = float(section(params, "train", "val_fraction"))
    t0 = time.perf_counter()
    experiments = []
    for seed in args.seeds:
        for trained, tested in (EXPERIMENTS[i] for i in args.select):
            ex = run_experiment(
                trained,
                tested,
                large=large,
                test=test,
                space=space,
                fixed=fixed,
                members=args.members,
                seed=seed,
                val_fraction=val_fraction,
            )
            experiments.append(ex)
            print(
                f"seed {seed}, trained {trained}: in-range sd {ex['in_range_sd_deg']:.4f}; "
                + ", ".join(
                    f"{r['moment_nm']:g} Nm L={r['L']:.2f} sd {r['sd_deg']:.4f} x{r['ratio']:.2f}"
                    for r in ex["per_moment"]
                    if r["L"] > 0
                ),
                flush=True,
            )
    return {
        "members": args.members,
        "max_epochs": int(fixed["max_epochs"]),
        "machine": f"{platform.machine()}, {torch.get_num_threads()} torch thread",
        "seconds": time.perf_counter() - t0,
        "experiments": experiments,
        "champion_in_range": champion_in_range(test, args.champion or CHAMPION),
    }


def merged(old: dict, new: dict) -> dict:
    """``new``'s experiments with ``old``'s of the trained ranges ``new`` did not measure."""
    measured = {tuple(ex["trained_moments"]) for ex in new["experiments"]}
    kept = [ex for ex in old["experiments"] if tuple(ex["trained_moments"]) not in measured]
    out = dict(new, experiments=kept + new["experiments"])
    out["seconds"] = old.get("seconds", 0.0) + new["seconds"]
    out["champion_in_range"] = new.get("champion_in_range") or old.get("champion_in_range")
    return out


if __name__ == "__main__":
    main()
