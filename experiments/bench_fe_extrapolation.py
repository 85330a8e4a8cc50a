"""Benchmark: the surrogate's error beyond its trained moments, on the open CalculiX model.

The moment policy (:class:`femcal.moments.MomentPolicy`, ``moments`` in params.yaml) counts
the surrogate's larger error beyond its trained range as an sd that grows with the log-moment
distance ``L = log(M / hi)``; ``experiments/bench_extrapolation.py`` measured that growth on the
study's data (1..5 Nm). This benchmark measures it on the open FE model's campaign, which
reaches 10 Nm: held-out configurations of the campaign store (``--n-heldout``), a surrogate
(the FE pipeline's recipe) trained on the others at 0.5..5 Nm only, and one trained on every
moment (the in-range reference), both tested on the held-out curves at every moment.

Reports per moment: both models' MAE, the ratio of the 0.5..5 Nm model's sd at ``M`` to its
in-range sd, and the ratio the policy predicts (``exp(error_growth * L)``).

Writes ``bench_fe_extrapolation.md`` and ``bench_fe_extrapolation.json`` into
``experiments/results/bench_fe_extrapolation/``.

Usage (from the project root)::

    .venv/bin/python -m experiments.bench_fe_extrapolation [--n-heldout 16] [--members 2]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import yaml

from experiments.bench_fe_refine import campaign_curves_table, recipe_surrogate
from experiments.common import REPO, RESULTS
from femcal.fe.adaptive import curves_to_rows
from femcal.schema import PARAMETER_NAMES
from femcal.space import ParameterSpace
from femcal.surrogates.nn import NeuralSurrogate

SD = math.sqrt(math.pi / 2)  # Gaussian errors: sd = MAE * sqrt(pi / 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--campaign", default="fe/data/campaign/runs.jsonl.gz")
    ap.add_argument("--n-heldout", type=int, default=16)
    ap.add_argument("--members", type=int, default=2)
    ap.add_argument("--max-epochs", type=int, default=600)
    ap.add_argument("--trained-max", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--out", default=str(RESULTS / "bench_fe_extrapolation" / "bench_fe_extrapolation")
    )
    args = ap.parse_args()

    fe_params = yaml.safe_load((REPO / "fe" / "params.yaml").read_text())
    root_params = yaml.safe_load((REPO / "params.yaml").read_text())
    growth = float(root_params["moments"]["error_growth"])
    fe = fe_params["fe"]
    moments = np.array([float(m) for m in fe["moments"]])
    bounds = fe["bounds"]
    space = ParameterSpace(
        list(PARAMETER_NAMES),
        [bounds[n][0] for n in PARAMETER_NAMES],
        [bounds[n][1] for n in PARAMETER_NAMES],
    )
    x_all, curves_all = campaign_curves_table(REPO / args.campaign, moments.tolist())
    order = np.random.default_rng(args.seed).permutation(len(x_all))
    ho, tr = order[: args.n_heldout], order[args.n_heldout :]
    recipe = fe_params["train"]["large"]["fixed"]

    def fit(keep: np.ndarray) -> tuple[NeuralSurrogate, float]:
        X, y = curves_to_rows(
            x_all[tr][:, :], curves_all[tr][:, :, keep], moments[keep], space.names
        )
        t0 = time.perf_counter()
        model = recipe_surrogate(space, recipe, args.members, args.max_epochs, args.seed)
        model.fit(X, y)
        return model, time.perf_counter() - t0

    X_ho, y_ho = curves_to_rows(x_all[ho], curves_all[ho], moments, space.names)
    m_ho = X_ho["moment_nm"].to_numpy()
    inside = moments <= args.trained_max + 1e-9
    low, low_s = fit(inside)
    full, full_s = fit(np.ones_like(inside))
    err_low = np.abs(low.predict(X_ho) - y_ho)
    err_full = np.abs(full.predict(X_ho) - y_ho)
    in_sd = SD * float(err_low[m_ho <= args.trained_max + 1e-9].mean())
    rows = []
    for m in moments:
        sel = np.isclose(m_ho, m)
        sd_m = SD * float(err_low[sel].mean())
        L = max(0.0, math.log(m / args.trained_max))
        rows.append(
            {
                "moment_nm": float(m),
                "n_points": int(sel.sum()),
                "mae_trained_to_5nm_deg": float(err_low[sel].mean()),
                "mae_trained_to_10nm_deg": float(err_full[sel].mean()),
                "L": L,
                "ratio": sd_m / in_sd,
                "policy_ratio": math.exp(growth * L),
            }
        )
    figures = {
        "campaign": args.campaign,
        "n_configurations": int(len(x_all)),
        "n_training": int(len(tr)),
        "n_heldout": int(len(ho)),
        "members": args.members,
        "fit_seconds": [round(low_s, 1), round(full_s, 1)],
        "in_range_sd_deg": in_sd,
        "error_growth_policy": growth,
        "per_moment": rows,
    }
    out = REPO / args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{out}.json").write_text(json.dumps(figures, indent=2) + "\n")
    lines = [
        "# The surrogate's error beyond its trained moments, on the open CalculiX model",
        "",
        f"`experiments/bench_fe_extrapolation.py` on {len(x_all)} finished configurations of "
        f"`{args.campaign}`: {len(tr)} train, {len(ho)} held out (4 load cases each). Two "
        f"{args.members}-member surrogates (the FE pipeline's recipe): one trained at 0.5..5 Nm, "
        "one at 0.5..10 Nm. sd = MAE x sqrt(pi/2); ratio = the 0.5..5 Nm model's sd at M over its "
        f"in-range sd ({in_sd:.4f}°); the policy's ratio is exp({growth:g} L), L = log(M / 5 Nm).",
        "",
        "| M (Nm) | MAE, trained to 5 Nm | MAE, trained to 10 Nm | L | measured ratio "
        "| policy ratio |",
        "| --- | --- | --- | --- | --- | --- |",
        *(
            f"| {r['moment_nm']:g} | {r['mae_trained_to_5nm_deg']:.4f}° | "
            f"{r['mae_trained_to_10nm_deg']:.4f}° | {r['L']:.2f} | {r['ratio']:.2f} | "
            f"{r['policy_ratio']:.2f} |"
            for r in rows
        ),
        "",
    ]
    Path(f"{out}.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
