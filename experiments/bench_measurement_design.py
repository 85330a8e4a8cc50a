"""Benchmark: could measurements at several points settle what one point cannot?

``next_measurement`` asks how many measurements at *one* point would settle a close call, and
on the hidden cohorts the answer is always "none would" (docs/diagnosis-benchmark.md, "Is that
so?"): the rival bends to new points at a cost ``delta^2 / v``, so repeats at one point
saturate at ``delta^2 / (s^2 + v)``. But a rival bends along the few directions its parameters
leave free: points whose differences do not lie along them add up. By the diagnosis' own
arithmetic, the criteria of two models part by ``delta_P^T (N / k + S + V_P)^-1 delta_P`` for
``k`` measurements at each point of a set ``P`` (``N``: the noise variance, ``S``: the
surrogate's, independent per point as the diagnosis counts them; ``V_P``: both models'
prediction covariance there, from their Jacobians and parameter covariances).

For every close call of the hidden cohorts (the chosen model and the rival
``next_measurement`` names), this benchmark builds a design greedily from the moments the
policy accepts (add the point that raises that gain most, up to ``--points``, ``--repeats``
measurements each) and reports whether it would settle the question (gain >= ``min_delta`` +
the criterion gap). Nothing is measured: it asks whether building such designs into the
diagnosis could pay at all.

Usage (from the project root, after ``make repro``)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_measurement_design --seeds 0,1
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

import femcal.diagnose.assemble as assemble
from experiments.common import RESULTS, reproduce_command
from experiments.diagnosis import hidden_cohort, hidden_seeds, run_diagnosis, setup
from femcal.effects.composite import EffectModel


def _curves_jacobian(dense_base, effects, fit, pos):
    """Curves (4q,) and Jacobian (4q, d) of one fitted model on the probe grid."""
    model = dense_base if not effects else EffectModel(dense_base, list(effects))
    curves, jac = model.curves_jacobian(fit.v[pos : pos + 1])
    c = curves.detach().double().numpy()[0].reshape(-1)
    j = jac.detach().double().numpy()[0]
    return c, j.reshape(-1, j.shape[-1])


def greedy_design(
    delta: np.ndarray,
    point_var: np.ndarray,
    j_a: np.ndarray,
    c_a: np.ndarray,
    j_b: np.ndarray,
    c_b: np.ndarray,
    points: int,
) -> tuple[list[int], list[float]]:
    """Greedy design: the point indices chosen and the gain after each.

    ``delta`` (p,) the two models' difference, ``point_var`` (p,) the variance of one design
    point (noise^2 / k + surrogate^2), ``j_*`` (p, d_*) and ``c_*`` (d_*, d_*) the models'
    Jacobians and parameter covariances.
    """
    ok = np.flatnonzero(np.isfinite(delta) & np.isfinite(point_var))
    chosen: list[int] = []
    gains: list[float] = []
    for _ in range(points):
        best, best_gain = None, -np.inf
        for q in ok:
            if q in chosen:
                continue
            p = [*chosen, q]
            v = j_a[p] @ c_a @ j_a[p].T + j_b[p] @ c_b @ j_b[p].T
            m = v + np.diag(point_var[p])
            d = delta[p]
            g = float(d @ np.linalg.solve(m, d))
            if g > best_gain:
                best, best_gain = q, g
        if best is None:
            break
        chosen.append(int(best))
        gains.append(best_gain)
    return chosen, gains


def analyse(
    seed: int, ctx: dict[str, Any], points: int, repeats: int, surrogate_scale: float = 1.0
) -> list[dict[str, Any]]:
    """Every close call of hidden cohort ``seed``: the greedy design's gain, point by point."""
    noise = float(ctx["plant"]["noise_deg"])
    cohort = hidden_cohort(seed, ctx["fe_moments"], ctx["fe_rom"], noise)
    rows: list[dict[str, Any]] = []
    original = assemble.next_measurement

    def wrapped(ranking, fits, dense_base, dense, sigma_dense, min_delta, chosen, *a, **kw):
        out = original(ranking, fits, dense_base, dense, sigma_dense, min_delta, chosen, *a, **kw)
        if not out or dense_base is None:
            return out
        models = {str(m): m for m in fits}  # a ranking's entry names its model
        rival = models[out["between"][1]]
        best = chosen
        fa, pa = fits[best]
        fb, pb = fits[rival]
        if fa.cov is None or fb.cov is None:
            return out
        ca, ja = _curves_jacobian(dense_base, best, fa, pa)
        cb, jb = _curves_jacobian(dense_base, rival, fb, pb)
        s2 = np.tile(sigma_dense**2 - min(noise, float(sigma_dense.min())) ** 2, 4)
        per_point = noise**2 / repeats + surrogate_scale**2 * s2
        picked, gains = greedy_design(ca - cb, per_point, ja, fa.cov[pa], jb, fb.cov[pb], points)
        needed = min_delta + float(out["criterion_gap"])
        rows.append(
            {
                "seed": seed,
                "between": out["between"],
                "needed": needed,
                "gains": gains,
                "settles_with": next((k + 1 for k, g in enumerate(gains) if g >= needed), None),
                "points": [(int(q // len(dense)), float(dense[q % len(dense)])) for q in picked],
            }
        )
        return out

    assemble.next_measurement = wrapped
    try:
        run_diagnosis(cohort, ctx)
    finally:
        assemble.next_measurement = original
    return rows


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1", help="hidden cohorts")
    ap.add_argument("--holdout", action="store_true", help="allow the held-out seeds")
    ap.add_argument("--points", type=int, default=4, help="design points at the most")
    ap.add_argument("--repeats", type=int, default=10, help="measurements at each point")
    ap.add_argument(
        "--surrogate-error-scale",
        type=float,
        default=1.0,
        help="an ablation: the surrogate's error at the design points times this (0: a perfect "
        "surrogate), to see what limits the gain",
    )
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_measurement_design")
    args = ap.parse_args(argv)
    seeds = hidden_seeds(ap, args.seeds, args.holdout)
    torch.manual_seed(0)
    ctx = setup()
    rows = []
    for seed in seeds:
        print(f"hidden seed {seed} ...", flush=True)
        rows += analyse(seed, ctx, args.points, args.repeats, args.surrogate_error_scale)
    command = reproduce_command("bench_measurement_design", argv)
    n = len(rows)
    by_points = [
        sum(r["settles_with"] is not None and r["settles_with"] <= k for r in rows)
        for k in range(1, args.points + 1)
    ]
    lines = [
        "# Could several points settle what one cannot? (issue 11, item 6)",
        "",
        f"Reproduce: `{command}`. Hidden cohorts {seeds}; {args.repeats} measurements "
        f"at each design point; greedy designs of up to {args.points} points over the moments "
        "the policy accepts (see the module docstring of "
        "`experiments/bench_measurement_design.py`). Nothing is measured: the gain is the "
        "diagnosis' own arithmetic, ``delta^T (N / k + S + V)^-1 delta``.",
        "",
        f"Close calls: {n}. Settled (gain >= `min_delta` + gap) with "
        + ", ".join(
            f"{k} point{'s' if k > 1 else ''} ({k * args.repeats} measurements): {c}"
            for k, c in enumerate(by_points, 1)
        )
        + ".",
        "",
        "| gain / needed, quantiles | 1 point | "
        + " | ".join(f"{k} points" for k in range(2, args.points + 1))
        + " |",
        "|---|" + "---|" * args.points,
    ]
    for q in (0.5, 0.9, 1.0):
        cells = []
        for k in range(args.points):
            vals = [r["gains"][k] / r["needed"] for r in rows if len(r["gains"]) > k]
            cells.append(f"{np.quantile(vals, q):.2f}" if vals else "")
        lines.append(f"| {q:.0%} | " + " | ".join(cells) + " |")
    args.out.mkdir(parents=True, exist_ok=True)
    name = "bench_measurement_design"
    if (args.points, args.repeats) != (4, 10):  # another design beside the default's report
        name += f"_points-{args.points}_repeats-{args.repeats}"
    if args.surrogate_error_scale != 1.0:
        name += f"_surrogate-{args.surrogate_error_scale:g}"
    (args.out / f"{name}.md").write_text("\n".join(lines) + "\n")
    (args.out / f"{name}.json").write_text(
        json.dumps({"command": command, "rows": rows}, indent=2) + "\n"
    )
    print("\n".join(lines))


if __name__ == "__main__":
    main()
