"""Benchmark: wall time of a whole ``femcal calibrate`` of the 64 Test specimens (the real CLI).

Runs ``femcal calibrate --measurements data/raw/Test --out <tmp>/out-<i> [options]`` in a
subprocess from the project root, with ``MLFLOW_TRACKING_URI`` pointing at a temporary SQLite
store and ``--out`` at a temporary folder, so nothing of the project (``mlruns/``,
``reports/``) is touched. Per variant (a set of options): one untimed warm-up run (it creates
the store: MLflow's migrations are a one-off cost), then ``--repeats`` timed runs.

Where the time goes, once per label: ``python -X importtime`` (heavy packages) and ``cProfile``
(cumulative time of the CLI's phases: tracking setup, reading, model loading, reachability,
calibration, tables and plots, MLflow logging) of the default command. Profiled times are
longer than plain ones (the profiler's overhead), so read them as shares.

Writes ``bench_cli_calibrate.json`` into ``experiments/results/bench_cli_calibrate/`` (each label's
figures, merged with the file's other labels) and ``bench_cli_calibrate.md`` (every label in the
file); ``--results DIR`` writes them into DIR instead. ``experiments/timeline_cli_calibrate.py``
gives the timeline of one run (each process' phases and its garbage collector's time).

``--src <worktree>/src`` runs an earlier commit's code (``git worktree add /tmp/before <rev>``)
with this project's data and models; ``--baseline-src <worktree>/src`` adds that code as one
more variant, timed round-robin with the others (before and after under the same load).

Usage (from the project root, after ``dvc repro`` or ``dvc pull``)::

    nice -n 19 env OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_cli_calibrate \
        --label after --variant "plots all=" --variant "plots none=--plots none"

The machine's load average is recorded before and after each run: on a shared machine the
figures move with it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import pstats
import re
import resource
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from experiments.common import REPO, RESULTS

FEMCAL = Path(sys.executable).parent / "femcal"
MEASUREMENTS = "data/raw/Test"
JSON_PATH = RESULTS / "bench_cli_calibrate" / "bench_cli_calibrate.json"
MD_PATH = RESULTS / "bench_cli_calibrate" / "bench_cli_calibrate.md"

#: Phases of the profile: label -> (file suffix, function name) whose cumulative times add up.
PHASES = {
    "whole CLI (main)": [("femcal/cli.py", "main")],
    "tracking setup (mlflow import, store, killed runs)": [("femcal/stages/store.py", "tracking")],
    "start the MLflow process (the setup above in parallel)": [
        ("femcal/stages/tracking_process.py", "__init__")
    ],
    "waiting for the MLflow process (setup, run, tables, artifacts)": [
        ("femcal/stages/tracking_process.py", "_receive")
    ],
    "read measurements": [
        ("femcal/measurements.py", "read_measurements"),
        ("femcal/measurements/__init__.py", "read_measurements"),
    ],
    "load models (with torch/Lightning imports)": [("femcal/tracking.py", "load_surrogate")],
    "reachability check": [("femcal/reachability/__init__.py", "assess_reachability")],
    "calibrate (pgd)": [("femcal/calibration/base.py", "calibrate")],
    "write outputs (tables + plots)": [("femcal/calibration/report.py", "write_outputs")],
    "per-specimen plots": [
        ("femcal/calibration/report.py", "plot_specimen"),
        ("femcal/calibration/report.py", "plot_specimens"),
    ],
    "summary plot": [("femcal/calibration/report.py", "plot_summary")],
    "MLflow artifacts": [("femcal/jobs/mlflow_steps.py", "log_artifacts")],
    "MLflow tables": [("mlflow/tracking/fluent.py", "log_table")],
    "compare with previous run": [("femcal/jobs/mlflow_steps.py", "compare_with_previous")],
}
#: Packages whose import time is reported (cumulative, where first imported).
PACKAGES = (
    "torch",
    "pytorch_lightning",
    "mlflow",
    "matplotlib",
    "matplotlib.pyplot",
    "pandas",
    "sklearn",
    "scipy",
    "tqdm",
)


def load_average() -> float:
    return os.getloadavg()[0]


def command(out: Path) -> list[str]:
    return [str(FEMCAL), "-q", "calibrate", "--measurements", MEASUREMENTS, "--out", str(out)]


def _children_cpu() -> float:
    """CPU seconds (user + system) of the ended child processes waited for so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run(args: list[str], env: dict[str, str]) -> dict:
    """One run of ``args``: its wall time and CPU time (user + system, the command's own
    process and every process it started), the load before and after, its output."""
    load_before = load_average()
    cpu_before = _children_cpu()
    start = time.perf_counter()
    proc = subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    cpu = _children_cpu() - cpu_before
    if proc.returncode != 0:
        raise SystemExit(f"{shlex.join(args)} failed ({proc.returncode}):\n{proc.stderr}")
    seconds = re.search(r"in ([0-9.]+) s:", proc.stdout)
    return {
        "wall_s": round(wall, 3),
        "cpu_s": round(cpu, 3),
        "calibration_s": float(seconds.group(1)) if seconds else None,
        "load_before": round(load_before, 2),
        "load_after": round(load_average(), 2),
        "stdout": proc.stdout.strip(),
    }


def bench_variants(
    specs: dict[str, tuple[list[str], dict[str, str]]], repeats: int
) -> dict[str, dict]:
    """Time every variant (name -> (extra options, environment)), round-robin.

    Each variant has its own temporary store, created by an untimed warm-up run; then the
    timed runs alternate between the variants (a, b, c, a, b, c, ...), so that a change of the
    machine's load falls on all of them alike.
    """
    with tempfile.TemporaryDirectory(prefix="bench-cli-calibrate-") as tmp:
        tmp_path = Path(tmp)
        envs, warm, runs = {}, {}, {name: [] for name in specs}
        for k, (name, (extra, env)) in enumerate(specs.items()):
            store = tmp_path / f"store-{k}"
            store.mkdir()
            envs[name] = {**env, "MLFLOW_TRACKING_URI": f"sqlite:///{store / 'mlflow.db'}"}
            warm[name] = run(command(store / "out-warmup") + extra, envs[name])
        for i in range(repeats):
            for k, (name, (extra, _)) in enumerate(specs.items()):
                out = tmp_path / f"store-{k}" / f"out-{i}"
                runs[name].append(run(command(out) + extra, envs[name]))
        counts = {}
        for k, name in enumerate(specs):
            last = tmp_path / f"store-{k}" / f"out-{repeats - 1}"
            counts[name] = (
                len(list(last.rglob("*.png"))),
                len([p for p in last.rglob("*") if p.is_file()]),
            )
    out = {}
    for name, (extra, env) in specs.items():
        walls = [r["wall_s"] for r in runs[name]]
        argv = ["femcal", "-q", "calibrate", "--measurements", MEASUREMENTS, "--out", "<tmp>/out"]
        out[name] = {
            "args": extra,
            "command": shlex.join([*argv, *extra]),
            "pythonpath": env.get("PYTHONPATH", ""),
            "warmup_wall_s": warm[name]["wall_s"],
            "runs": runs[name],
            "wall_s_median": round(statistics.median(walls), 3),
            "cpu_s_median": round(statistics.median(r["cpu_s"] for r in runs[name]), 3),
            "wall_s_min": min(walls),
            "wall_s_max": max(walls),
            "png_files": counts[name][0],
            "files": counts[name][1],
        }
    return out


def import_times(env: dict[str, str]) -> dict[str, float]:
    """Cumulative import time (s) of the heavy packages in one default run (-X importtime)."""
    with tempfile.TemporaryDirectory(prefix="bench-cli-calibrate-") as tmp:
        tmp_path = Path(tmp)
        run_env = {**env, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}
        args = [
            sys.executable,
            "-X",
            "importtime",
            "-m",
            "femcal",
            "-q",
            "calibrate",
            "--measurements",
            MEASUREMENTS,
            "--out",
            str(tmp_path / "out"),
        ]
        proc = subprocess.run(args, cwd=REPO, env=run_env, capture_output=True, text=True)
    found: dict[str, float] = {}
    top_total = 0.0
    for line in proc.stderr.splitlines():
        m = re.match(r"import time:\s+(\d+) \|\s+(\d+) \|( *)(\S+)", line)
        if not m:
            continue
        cumulative, indent, name = int(m.group(2)) / 1e6, len(m.group(3)), m.group(4)
        if indent == 1:
            top_total += cumulative
        if name in PACKAGES and name not in found:
            found[name] = round(cumulative, 3)
    found["all imports (sum of top-level)"] = round(top_total, 3)
    return found


#: What the command's own process does before calibrating: the calibration's imports and the
#: surrogate loaded from its folder (MLflow works in a child process meanwhile).
FLOOR_CODE = (
    "import femcal.effects.composite, femcal.calibration, femcal.reachability, pandas; "
    "from femcal.tracking import load_surrogate; load_surrogate('models/surrogate-large')"
)
#: What the MLflow process imports: femcal's MLflow glue and MLflow's SQL store.
MLFLOW_FLOOR_CODE = (
    "import femcal.tracking; from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore"
)


def import_floor(env: dict[str, str], repeats: int, code: str = FLOOR_CODE) -> dict:
    """Wall time of a Python process that only runs ``code`` (a part of the command)."""
    walls = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, check=True)
        walls.append(round(time.perf_counter() - start, 3))
    return {"code": code, "walls_s": walls, "wall_s_median": statistics.median(walls)}


def profile(env: dict[str, str]) -> dict[str, float | None]:
    """Cumulative seconds per phase of one default run under cProfile."""
    with tempfile.TemporaryDirectory(prefix="bench-cli-calibrate-") as tmp:
        tmp_path = Path(tmp)
        run_env = {**env, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}
        prof = tmp_path / "calibrate.prof"
        args = [
            sys.executable,
            "-m",
            "cProfile",
            "-o",
            str(prof),
            "-m",
            "femcal",
            "-q",
            "calibrate",
            "--measurements",
            MEASUREMENTS,
            "--out",
            str(tmp_path / "out"),
        ]
        proc = subprocess.run(args, cwd=REPO, env=run_env, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"profiled run failed:\n{proc.stderr}")
        stats = pstats.Stats(str(prof)).stats  # type: ignore[attr-defined]
    out: dict[str, float | None] = {}
    for label, funcs in PHASES.items():
        total, hit = 0.0, False
        for (file, _line, name), (_cc, _nc, _tt, ct, _callers) in stats.items():
            if name in {f for _, f in funcs} and any(
                file.replace(os.sep, "/").endswith(s) and name == f for s, f in funcs
            ):
                total += ct
                hit = True
        out[label] = round(total, 3) if hit else None
    return out


def markdown(data: dict) -> str:
    lines = [
        "# `femcal calibrate` of the 64 Test specimens: wall time of the whole CLI call",
        "",
        "Generated by `experiments/bench_cli_calibrate.py` (see its docstring): the real CLI in a "
        "subprocess, a temporary MLflow store (`MLFLOW_TRACKING_URI=sqlite:///<tmp>/mlflow.db`) "
        "and output folder; one untimed warm-up run per variant (it creates the store), then the "
        "timed runs, round-robin between the variants of a label. CPU is user + system time of "
        "the command and every process it started. `load` is the 1-minute load average before "
        "each run: the machine (2 cores) was shared with other benchmarks and "
        "test runs, so the figures move with it; compare variants of one label.",
        "",
    ]
    for label, entry in data.items():
        meta = entry["meta"]
        lines += [
            f"## {label}",
            "",
            f"{meta['when']}, commit {meta['commit']}, {meta['machine']}, "
            f"{meta['cpus']} CPUs, {meta['threads']}, run under `{meta['nice']}`.",
            "",
            "| variant | command | median wall (s) | min | max | median CPU (s) | calibration (s) "
            "| load | PNGs | files |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for name, v in entry["variants"].items():
            loads = ", ".join(f"{r['load_before']:.1f}" for r in v["runs"])
            cal = ", ".join(f"{r['calibration_s']:.2f}" for r in v["runs"])
            cpu = f"{v['cpu_s_median']:.2f}" if "cpu_s_median" in v else "-"
            lines.append(
                f"| {name} | `{v['command']}` | {v['wall_s_median']:.2f} | {v['wall_s_min']:.2f} "
                f"| {v['wall_s_max']:.2f} | {cpu} | {cal} | {loads} | {v['png_files']} "
                f"| {v['files']} |"
            )
        if entry.get("floor") and entry.get("mlflow_floor"):
            f, g = entry["floor"], entry["mlflow_floor"]
            lines += [
                "",
                "Floors: the command's own process up to the calibration, MLflow aside (`python -c "
                f'"{f["code"]}"`): median {f["wall_s_median"]:.2f} s '
                f"({', '.join(f'{w:.2f}' for w in f['walls_s'])}); its MLflow process's imports, "
                f'in parallel on the other core (`python -c "{g["code"]}"`): median '
                f"{g['wall_s_median']:.2f} s ({', '.join(f'{w:.2f}' for w in g['walls_s'])}).",
            ]
        elif entry.get("floor"):
            f = entry["floor"]
            lines += [
                "",
                f"Floor: a Python process that only imports what the command needs (`python -c "
                f'"{f["code"]}"`): median {f["wall_s_median"]:.2f} s '
                f"({', '.join(f'{w:.2f}' for w in f['walls_s'])}).",
            ]
        if entry.get("profile"):
            lines += [
                "",
                "Where the time goes (one default run under cProfile, cumulative seconds; the "
                "profiler slows Python code down, so read these as shares):",
                "",
                "| phase | seconds |",
                "|---|---|",
            ]
            for phase, s in entry["profile"].items():
                lines.append(f"| {phase} | {'-' if s is None else f'{s:.2f}'} |")
        if entry.get("imports"):
            lines += [
                "",
                "Import time (`python -X importtime`, cumulative where first imported; nested "
                "packages are counted in their importer"
                + (
                    "; the MLflow process, forked from the command, logs its imports too: a "
                    "package both import counts where either reported it first"
                    if entry.get("mlflow_floor")
                    else ""
                )
                + "):",
                "",
                "| package | seconds |",
                "|---|---|",
            ]
            for pkg, s in entry["imports"].items():
                lines.append(f"| {pkg} | {s:.2f} |")
        if entry.get("note"):
            lines += ["", entry["note"]]
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--label", required=True, help="e.g. before, after")
    parser.add_argument(
        "--variant",
        action="append",
        metavar="NAME=OPTIONS",
        help="a named set of extra calibrate options, e.g. 'plots none=--plots none' "
        "(repeatable; default: 'default=' , the command as the README gives it)",
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-profile", action="store_true", help="skip importtime and cProfile")
    parser.add_argument("--note", default="", help="a sentence added under the label's tables")
    parser.add_argument(
        "--results",
        type=Path,
        default=JSON_PATH.parent,
        help="the folder of bench_cli_calibrate.json and .md (default: the experiments "
        "pipeline's output, experiments/results/bench_cli_calibrate)",
    )
    parser.add_argument(
        "--src",
        type=Path,
        help="run femcal from this source folder instead (PYTHONPATH), e.g. a `git worktree` "
        "of an earlier commit's src/, to measure before and after under the same load",
    )
    parser.add_argument(
        "--baseline-src",
        type=Path,
        help="also time an earlier commit's src/ (a `git worktree`), round-robin with the "
        "variants: before and after under the same load",
    )
    args = parser.parse_args(argv)
    env = dict(os.environ)
    if args.src:
        env["PYTHONPATH"] = str(args.src.resolve())
    specs: dict[str, tuple[list[str], dict[str, str]]] = {}
    if args.baseline_src:
        base_env = {**env, "PYTHONPATH": str(args.baseline_src.resolve())}
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=args.baseline_src.resolve().parent,
            capture_output=True,
            text=True,
        ).stdout.strip()
        specs[f"before ({rev}, default)"] = ([], base_env)
    for spec in args.variant or ["default="]:
        name, _, opts = spec.partition("=")
        specs[name] = (shlex.split(opts), env)
    variants = bench_variants(specs, args.repeats)
    for name, v in variants.items():
        print(f"{name}: median {v['wall_s_median']:.2f} s", flush=True)
    src_repo = args.src.resolve().parent if args.src else REPO
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=src_repo, capture_output=True, text=True
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--", "src"], cwd=src_repo, capture_output=True, text=True
    ).stdout.strip()
    threads = env.get("OMP_NUM_THREADS")
    entry = {
        "meta": {
            "when": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "commit": commit + (" (src/ modified)" if dirty else ""),
            "machine": platform.machine(),
            "cpus": os.cpu_count(),
            "threads": f"OMP_NUM_THREADS={threads}" if threads else "OMP_NUM_THREADS unset",
            "nice": f"nice -n {os.nice(0)}",
        },
        "variants": variants,
    }
    entry["floor"] = import_floor(env, args.repeats)
    entry["mlflow_floor"] = import_floor(env, args.repeats, MLFLOW_FLOOR_CODE)
    if not args.no_profile:
        entry["imports"] = import_times(env)
        entry["profile"] = profile(env)
    if args.note:
        entry["note"] = args.note
    json_path, md_path = args.results / JSON_PATH.name, args.results / MD_PATH.name
    data = json.loads(json_path.read_text()) if json_path.exists() else {}
    data[args.label] = entry
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(data, indent=2) + "\n")
    md_path.write_text(markdown(data))
    print(f"wrote {json_path}, {md_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
