"""Benchmark: `dvc repro` from a fresh clone with the default params, then again, then after
changing one training parameter. Writes experiments/results/bench_pipeline/bench_pipeline.md.

Usage (from the project root, after `make install`)::

    FEMCAL_DATA_MIRROR=../shared/data/ivd-calibnn .venv/bin/python -m experiments.bench_pipeline

The clone is made in a temporary folder; its MLflow store and Optuna storage are its own.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from experiments.common import REPO, RESULTS

BIN = Path(sys.executable).parent


def run(args: list[str], cwd: Path, env: dict) -> tuple[float, str]:
    t0 = time.perf_counter()
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"{' '.join(args)} failed:\n{proc.stdout}\n{proc.stderr}")
    return seconds, proc.stdout


def stages_run(stdout: str) -> list[str]:
    return [ln.split("'")[1] for ln in stdout.splitlines() if ln.startswith("Running stage")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(RESULTS / "bench_pipeline" / "bench_pipeline.md"))
    parser.add_argument("--keep", action="store_true", help="keep the temporary clone")
    args = parser.parse_args()
    if not os.environ.get("FEMCAL_DATA_MIRROR"):
        print("note: FEMCAL_DATA_MIRROR unset: the fetch stage downloads from the internet")
    tmp = Path(tempfile.mkdtemp(prefix="femcal-bench-"))
    clone = tmp / "femcal"
    env = {k: v for k, v in os.environ.items() if k not in ("MLFLOW_TRACKING_URI",)}
    env["PATH"] = f"{BIN}{os.pathsep}{env['PATH']}"
    env.pop("FEMCAL_OPTUNA_STORAGE", None)
    subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
    rows = []
    t, out = run([str(BIN / "dvc"), "repro"], clone, env)
    rows.append(("first `dvc repro` (fresh clone, default params)", t, stages_run(out)))
    t, out = run([str(BIN / "dvc"), "repro"], clone, env)
    rows.append(("second `dvc repro`, nothing changed", t, stages_run(out)))
    params = yaml.safe_load((clone / "params.yaml").read_text())
    params["train"]["small"]["fixed"]["patience"] += 1
    (clone / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    t, out = run([str(BIN / "dvc"), "repro"], clone, env)
    rows.append(("after changing `train.small.fixed.patience`", t, stages_run(out)))
    surrogates = json.loads((clone / "reports" / "surrogates.json").read_text())
    lines = [
        "# Pipeline benchmark",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python "
        f"{platform.python_version()}; measured {time.strftime('%Y-%m-%d')}.",
        "",
        "| run | wall time (s) | stages run |",
        "|---|---|---|",
    ]
    for what, seconds, stages in rows:
        lines.append(f"| {what} | {seconds:.0f} | {', '.join(stages) or 'none'} |")
    nn = surrogates["trained_on_large"]["nn@large"]
    small = surrogates["trained_on_small"]["nn@small"]
    lines += [
        "",
        f"Test MAE of the NN surrogate: {nn['mae']:.4f}° (Large), {small['mae']:.4f}° (Small); "
        f"mean R² {nn['r2_mean']:.5f} (Large).",
        "",
    ]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines))
    for what, seconds, stages in rows:
        print(f"{seconds:8.0f} s  {what}: {', '.join(stages) or 'no stage'}")
    if not args.keep:
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        print(f"clone kept at {clone}")


if __name__ == "__main__":
    main()
