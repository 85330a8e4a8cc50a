"""The timeline of one ``femcal calibrate``: when each phase of each process starts and ends.

Runs ``femcal -q calibrate --measurements data/raw/Test --out <tmp>/out`` (the real CLI, in a
subprocess, from the project root, with a temporary SQLite MLflow store created by an untimed
first run) under a small wrapper (``--wrapped``): before femcal is imported it installs an
import hook that wraps the phases' functions (:data:`PHASES`) once their module is imported,
so no import moves; every process (the command, its MLflow process, the figures' workers,
all forked) appends ``(pid, phase, start, end, its CPU so far)`` to a JSON-lines file, and
on leaving (``os._exit``) its CPU time and the time Python's cyclic garbage collector took
in it. Times are seconds since the wrapper started (the interpreter's own start, about
0.05 s, comes before).

Usage (from the project root)::

    nice -n 10 env OMP_NUM_THREADS=1 .venv/bin/python -m experiments.timeline_cli_calibrate \
        --src /tmp/before/src --out /tmp/timeline-before.md

``--src`` runs an earlier commit's code (a ``git worktree``); the table goes to ``--out``
(markdown) and beside it as JSON.
"""

from __future__ import annotations

import argparse
import functools
import gc
import importlib.abc
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from experiments.common import REPO

#: module -> functions whose calls are phases of the timeline.
PHASES = {
    "femcal.stages.calibrate": ["run", "leave_a_core_to_mlflow"],
    "femcal.stages.tracking_process": ["_serve_tracking", "tracking"],
    "femcal.jobs.calibrate": ["run_calibration", "_write_and_log"],
    "femcal.measurements": ["read_measurements"],
    "femcal.tracking": ["load_surrogate", "ensure_experiment"],
    "femcal.reachability": ["assess_reachability"],
    "femcal.calibration": ["calibrate"],
    "femcal.calibration.report": ["write_outputs", "plot_specimens", "plot_summary"],
    "femcal.calibration.plots": ["_draw"],
}
#: Modules whose import is a phase of its own.
IMPORTS = ("pandas", "torch", "mlflow", "mlflow.store.tracking.sqlalchemy_store", "matplotlib")
#: The MLflow process' calls (femcal.jobs.mlflow_steps.TRACKING_CALLS) are phases too.
STEPS = "femcal.jobs.mlflow_steps"


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


class _Recorder:
    """The spans and garbage-collector time of the processes of one run (JSON lines)."""

    def __init__(self, path: Path) -> None:
        self.path, self.t0, self.role = path, time.time(), "command"
        self.gc_s, self.gc_n, self._gc_start = 0.0, 0, 0.0

    def write(self, row: dict[str, Any]) -> None:
        with open(self.path, "a", encoding="utf-8") as fh:
            fh.write(json.dumps({"pid": os.getpid(), "role": self.role, **row}) + "\n")

    def span(self, name: str, start: float) -> None:
        self.write(
            {
                "phase": name,
                "start": round(start - self.t0, 3),
                "end": round(time.time() - self.t0, 3),
                "cpu": round(_cpu(), 3),
            }
        )

    def wrap(self, fn: Any, name: str) -> Any:
        @functools.wraps(fn)
        def timed(*args: Any, **kwargs: Any) -> Any:
            start = time.time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.span(name, start)

        return timed

    def on_gc(self, phase: str, _info: dict) -> None:
        if phase == "start":
            self._gc_start = time.process_time()
        else:
            self.gc_s += time.process_time() - self._gc_start
            self.gc_n += 1

    def forked(self) -> None:
        self.role, self.gc_s, self.gc_n = "forked", 0.0, 0

    def leaving(self) -> None:
        self.write(
            {"phase": "(end)", "end": round(time.time() - self.t0, 3), "cpu": round(_cpu(), 3)}
            | {"gc_s": round(self.gc_s, 3), "gc_runs": self.gc_n}
        )


def _patch(rec: _Recorder, module: Any) -> None:
    for attr in PHASES.get(module.__name__, []):
        if hasattr(module, attr):
            setattr(module, attr, rec.wrap(getattr(module, attr), f"{module.__name__}.{attr}"))
    if module.__name__ == STEPS:  # the run's steps, found by name in the MLflow process
        for name, fn in list(module.TRACKING_CALLS.items()):
            module.TRACKING_CALLS[name] = rec.wrap(fn, f"MLflow step {name}")
            setattr(module, name, module.TRACKING_CALLS[name])


class _Hook(importlib.abc.MetaPathFinder):
    """Wraps the phases of a module once it is imported; times the heavy imports."""

    def __init__(self, rec: _Recorder) -> None:
        self.rec = rec

    def find_spec(self, name: str, path: Any, target: Any = None) -> Any:
        if name not in PHASES and name not in IMPORTS and name != STEPS:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(name, path, target)
            if spec is not None:
                break
        else:
            return None
        run_module, rec = spec.loader.exec_module, self.rec

        def exec_module(module: Any) -> None:
            start = time.time()
            run_module(module)
            if name in IMPORTS:
                rec.span(f"import {name}", start)
            _patch(rec, module)

        spec.loader.exec_module = exec_module
        return spec


def wrapped(path: Path, argv: list[str]) -> int:
    """Run ``femcal argv`` in this process, recording into ``path``."""
    rec = _Recorder(path)
    gc.callbacks.append(rec.on_gc)
    os.register_at_fork(after_in_child=rec.forked)
    leave = os._exit

    def exit_(code: int) -> None:
        rec.leaving()
        leave(code)

    os._exit = exit_  # every process ends here: femcal's exit_now, multiprocessing's children
    sys.meta_path.insert(0, _Hook(rec))
    from femcal.cli import run_command

    code = run_command(argv)
    exit_(code)
    return code  # pragma: no cover - exit_ does not return


def timeline(src: Path | None) -> list[dict[str, Any]]:
    """The rows of one default run (after an untimed one that creates the store)."""
    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = str(src.resolve())
    with tempfile.TemporaryDirectory(prefix="timeline-calibrate-") as tmp:
        tmp_path = Path(tmp)
        env["MLFLOW_TRACKING_URI"] = f"sqlite:///{tmp_path / 'mlflow.db'}"
        rows_path = tmp_path / "rows.jsonl"
        for k in range(2):
            rows_path.write_text("")
            out = tmp_path / f"out-{k}"
            args = ["-q", "calibrate", "--measurements", "data/raw/Test", "--out", str(out)]
            cmd = [sys.executable, "-m", "experiments.timeline_cli_calibrate", "--wrapped"]
            subprocess.run(
                [*cmd, str(rows_path), "--", *args],
                cwd=REPO,
                env=env,
                check=True,
                text=True,
                capture_output=True,
            )
        return [json.loads(line) for line in rows_path.read_text().splitlines()]


def markdown(rows: list[dict[str, Any]], title: str) -> str:
    """The spans by start time (P0 the command, P1.. the processes it forked, in order)."""
    names: dict[int, str] = {}
    for row in rows:
        names.setdefault(row["pid"], "P0" if row["role"] == "command" else f"P{len(names)}")
    lines = [f"## {title}", "", "| process | phase | start (s) | end (s) | CPU so far (s) |"]
    lines.append("|---|---|---|---|---|")
    for row in sorted((r for r in rows if r["phase"] != "(end)"), key=lambda r: r["start"]):
        lines.append(
            f"| {names[row['pid']]} | {row['phase']} | {row['start']:.2f} | {row['end']:.2f} "
            f"| {row['cpu']:.2f} |"
        )
    lines += ["", "| process | ends at (s) | CPU (s) | of which cyclic GC (s) | GC runs |"]
    lines.append("|---|---|---|---|---|")
    for row in (r for r in rows if r["phase"] == "(end)"):
        lines.append(
            f"| {names[row['pid']]} | {row['end']:.2f} | {row['cpu']:.2f} | {row['gc_s']:.2f} "
            f"| {row['gc_runs']} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--wrapped"]:
        return wrapped(Path(argv[1]), argv[3:])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--src", type=Path, help="run femcal from this source folder")
    parser.add_argument("--out", type=Path, required=True, help="the markdown table")
    parser.add_argument("--title", default="timeline")
    args = parser.parse_args(argv)
    rows = timeline(args.src)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")
    args.out.write_text(markdown(rows, args.title))
    print(args.out.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
