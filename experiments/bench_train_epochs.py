"""Benchmark: the surrogate recipe's Test MAE against its training length.

The train@large recipe (params.yaml ``train.large.fixed``) trains each member for
``max_epochs`` epochs under a one-cycle learning-rate schedule, which anneals over the whole
run: the validation error keeps falling until the last epochs whatever ``max_epochs`` is, so
the per-epoch curves of a run cannot say what a shorter run would reach. This benchmark trains
the recipe's ensemble (same seed, validation split and members as train@large) for each
``--epochs`` value and scores it on the study's Test split as the evaluate stage does (MAE in
degrees over every successful row), beside the wall time of the fit.

Writes ``bench_train_epochs.md`` and ``bench_train_epochs.json`` into ``--out``.

Usage (from the project root, after ``make repro``)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_train_epochs \
        [--epochs 400,600,800] [--members 5] [--learning-rate 0.0035] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from experiments.common import REPO, RESULTS, reproduce_command
from femcal.config import load_params, section
from femcal.datasets import load_split, ok_rows
from femcal.schema import STATUS_OK
from femcal.surrogates.nn import NeuralSurrogate
from femcal.train import surrogate_kwargs, validation_split


def test_mae(model: NeuralSurrogate, test) -> float:
    """MAE in degrees over the successful rows of the Test split (the evaluate stage's)."""
    rows = test[test["status"] == STATUS_OK].reset_index(drop=True)
    pred = np.asarray(model.predict(rows), dtype=float)
    return float(np.mean(np.abs(pred - rows["rom_deg"].to_numpy(dtype=float))))


def run(
    epochs: Sequence[int], members: int, learning_rate: float | None, seed: int | None = None
) -> dict[str, Any]:
    """Train the recipe for each number of epochs; Test and validation MAE, wall seconds.

    ``seed`` (default ``train.seed``) seeds the validation split and the members, as
    ``train.holdout.seed`` does for train@holdout.
    """
    params = load_params(REPO / "params.yaml")
    recipe = dict(section(params, "train", "large", "fixed"))
    if learning_rate is not None:
        recipe["learning_rate"] = learning_rate
    seed = int(section(params, "train", "seed")) if seed is None else int(seed)
    prepared = REPO / section(params, "data", "prepared_dir")
    table, space = load_split(prepared, "large")
    test, _ = load_split(prepared, "test")
    train_df, val_df = validation_split(
        ok_rows(table), fraction=float(section(params, "train", "val_fraction")), seed=seed
    )
    cols = ["config_id", "load_case", "moment_nm", *space.names]
    rows = []
    for n in epochs:
        kw = surrogate_kwargs({**recipe, "max_epochs": int(n)})
        model = NeuralSurrogate(space, **kw, n_members=members, seed=seed)
        t0 = time.perf_counter()
        model.fit(
            train_df[cols],
            train_df["rom_deg"].to_numpy(dtype=float),
            X_val=val_df[cols],
            y_val=val_df["rom_deg"].to_numpy(dtype=float),
        )
        seconds = time.perf_counter() - t0
        ran = [sum(1 for h in model.history_ if h.get("member") == k) for k in range(members)]
        rows.append(
            {
                "max_epochs": int(n),
                "epochs_run": ran,
                "val_mae_deg": float(model.best_val_mae_deg_),
                "test_mae_deg": test_mae(model, test),
                "fit_seconds": seconds,
            }
        )
        print(f"max_epochs {n}: test MAE {rows[-1]['test_mae_deg']:.5f} deg, {seconds:.0f} s")
    return {"recipe": recipe, "members": members, "seed": seed, "runs": rows}


def markdown(report: dict[str, Any]) -> str:
    """The report as a Markdown page."""
    lines = [
        "# The surrogate recipe against its training length",
        "",
        f"`{report['command']}` on {report['machine']}, {report['torch_threads']} torch "
        f"thread(s): the train@large recipe ({report['members']} members, seed "
        f"{report['seed']}, learning rate {report['recipe']['learning_rate']:.6g}), scored on "
        "the Test split as the evaluate stage scores it.",
        "",
        "| max epochs | epochs run (per member) | validation MAE (°) | Test MAE (°) | fit (s) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for r in report["runs"]:
        lines.append(
            f"| {r['max_epochs']} | {', '.join(map(str, r['epochs_run']))} | "
            f"{r['val_mae_deg']:.4f} | {r['test_mae_deg']:.4f} | {r['fit_seconds']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--epochs", default="400,600,800", help="comma-separated max_epochs values")
    ap.add_argument("--members", type=int, default=5, help="ensemble members (train@large: 5)")
    ap.add_argument(
        "--learning-rate", type=float, default=None, help="default: the recipe's (params.yaml)"
    )
    ap.add_argument("--seed", type=int, default=None, help="default: params.yaml train.seed")
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_train_epochs")
    args = ap.parse_args(argv)
    epochs = [int(e) for e in args.epochs.split(",") if e.strip()]
    torch.manual_seed(0)
    report = run(epochs, args.members, args.learning_rate, args.seed)
    report.update(
        command=reproduce_command("bench_train_epochs", argv),
        machine=platform.processor() or platform.machine(),
        torch_threads=torch.get_num_threads(),
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_train_epochs.json").write_text(json.dumps(report, indent=2) + "\n")
    (args.out / "bench_train_epochs.md").write_text(markdown(report))
    print(f"wrote {args.out / 'bench_train_epochs.md'}")


if __name__ == "__main__":
    main()
