"""Benchmark: mesh presets of the CalculiX disc model (time per load case, mesh convergence).

Runs the five load cases (four pure moments at 1..5 Nm, axial compression at 300/1000/2000 N) at the
centre of the study's parameter box on each mesh preset, one job at a time, one solver thread each,
and writes ``experiments/results/bench_fe_mesh/fe_mesh.md``: CPU and wall seconds per load case, RoM
at 5 Nm, IDP under compression, and the difference of each preset to the finest one. With ``--sample
N`` it also runs the first N configurations of the study's Large design on the ``default`` preset
(four moment load cases each) and reports failures, retries and the RoM at 5 Nm next to the study's.

Usage (from the project root; needs ``ccx``, ``make install`` installs it)::

    .venv/bin/python -m experiments.bench_fe_mesh [--presets coarse default fine] [--sample 8]

Other processes on the machine slow the wall clock; CPU seconds are the solver's own.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from experiments.common import REPO, RESULTS
from femcal.fe import COMPRESSION, FEJob, simulate
from femcal.fe.calculix import CalculixDisc
from femcal.fe.geometry import MESH_PRESETS, DiscGeometry
from femcal.schema import LOAD_CASES, PARAMETER_NAMES

LARGE = REPO / "data" / "raw" / "Large"
FALLBACK_LARGE = Path("/work/shared/data/ivd-calibnn/Large")
MOMENTS = (1.0, 2.0, 3.0, 4.0, 5.0)
FORCES = (300.0, 1000.0, 2000.0)


def large_folder() -> Path:
    """The study's Large split (``data/raw/Large`` after ``make repro``, else the mirror)."""
    return LARGE if (LARGE / "ParameterBounds.csv").is_file() else FALLBACK_LARGE


def box_centre() -> dict[str, float]:
    """The centre of the study's parameter bounds (ParameterBounds.csv)."""
    bounds = pd.read_csv(large_folder() / "ParameterBounds.csv")
    return {name: float(bounds[name].mean()) for name in PARAMETER_NAMES}


def run_preset(preset: str, parameters: dict[str, float], scratch: Path) -> list[dict]:
    adapter = CalculixDisc(geometry=preset)
    mesh = adapter.mesh
    rows = []
    for case in (*LOAD_CASES, COMPRESSION):
        levels = FORCES if case == COMPRESSION else MOMENTS
        start = time.perf_counter()
        result = simulate(adapter, FEJob(0, parameters, case, levels), scratch / preset / case)
        rows.append(
            {
                "preset": preset,
                "elements": mesh.n_elements,
                "nodes": mesh.n_nodes,
                "dof": 3 * mesh.n_nodes,
                "load_case": case,
                "status": result.status,
                "attempts": result.attempts,
                "cpu_s": result.cpu_seconds,
                "wall_s": time.perf_counter() - start,
                "rom5_deg": float(result.rom_deg[-1]),
                "idp_mpa": result.idp_mpa.tolist(),
            }
        )
        print(
            f"{preset:8s} {case:15s} {result.status:6s} cpu {result.cpu_seconds:6.1f} s "
            f"RoM5 {result.rom_deg[-1]:7.3f} IDP {np.round(result.idp_mpa, 3).tolist()}",
            flush=True,
        )
    return rows


def run_sample(n: int, scratch: Path, timeout_s: float) -> list[dict]:
    """The first ``n`` configurations of the study's Large design, default preset, 4 moments."""
    folder = large_folder()
    design = pd.read_csv(folder / "MaterialConfigurations.csv")
    adapter = CalculixDisc(geometry="default", timeout_s=timeout_s)
    rows = []
    for i in range(min(n, len(design))):
        parameters = {name: float(design.loc[i, name]) for name in PARAMETER_NAMES}
        for case in LOAD_CASES:
            study = pd.read_csv(folder / f"ROM_Results_{case}_wMoment.csv").iloc[i]
            start = time.perf_counter()
            result = simulate(adapter, FEJob(i, parameters, case, MOMENTS), scratch / f"{i}-{case}")
            rows.append(
                {
                    "config": i,
                    "load_case": case,
                    "status": result.status,
                    "attempts": result.attempts,
                    "reason": result.reason,
                    "cpu_s": result.cpu_seconds,
                    "wall_s": time.perf_counter() - start,
                    "rom5_deg": float(result.rom_deg[-1]),
                    "levels_ok": int(np.isfinite(result.rom_deg).sum()),
                    "study_rom5_deg": float(study.iloc[-1]),
                }
            )
            print(
                f"sample {i:3d} {case:15s} {result.status:6s} attempts {result.attempts} "
                f"cpu {result.cpu_seconds:6.1f} s RoM5 {result.rom_deg[-1]:7.3f} "
                f"(study {study.iloc[-1]:.3f}) {result.reason[:80]}",
                flush=True,
            )
    return rows


def sample_section(rows: list[dict]) -> list[str]:
    df = pd.DataFrame(rows)
    n_jobs = len(df)
    first = ((df.status == "ok") & (df.attempts == 1)).sum()
    retried_ok = ((df.status == "ok") & (df.attempts > 1)).sum()
    failed = (df.status != "ok").sum()
    ok = df[df.status == "ok"]
    lines = [
        "",
        f"## Failures and retries: {df.config.nunique()} configurations of the study's design",
        "",
        "The first configurations of the study's Large design (MaterialConfigurations.csv), "
        '`default` preset, four moment load cases at 1..5 Nm, `kappa="scale"`, '
        "`max_attempts=3`. The study's RoM at 5 Nm (its own FE model) is shown for scale.",
        "",
        f"- {n_jobs} jobs: {first} ok at the first attempt, {retried_ok} ok after a retry "
        f"(fibre-routine abort), {failed} failed.",
        f"- CPU seconds per job: median {df.cpu_s.median():.1f}, mean {df.cpu_s.mean():.1f}, "
        f"max {df.cpu_s.max():.1f} (retries included).",
    ]
    if len(ok):
        ratio = ok.rom5_deg / ok.study_rom5_deg
        lines.append(
            f"- RoM at 5 Nm, this model / the study's: median {ratio.median():.2f} "
            f"(range {ratio.min():.2f}-{ratio.max():.2f})."
        )
    lines += [
        "",
        "| config | load case | status | attempts | CPU s | levels reached | RoM 5 Nm (deg) "
        "| study RoM 5 Nm (deg) | reason |",
        "|---:|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['config']} | {r['load_case']} | {r['status']} | {r['attempts']} | "
            f"{r['cpu_s']:.1f} | {r['levels_ok']} | {r['rom5_deg']:.2f} | "
            f"{r['study_rom5_deg']:.2f} | {r['reason'].replace('|', '/')} |"
        )
    return lines


def write_report(
    rows: list[dict], parameters: dict[str, float], path: Path, sample: list[dict]
) -> None:
    df = pd.DataFrame(rows)
    presets = list(dict.fromkeys(df["preset"]))
    finest = presets[-1]
    lines = [
        "# CalculiX disc model: mesh presets",
        "",
        "Written by `experiments/bench_fe_mesh.py` (rerun it to refresh). Model: "
        "`src/femcal/fe/calculix.py`; geometry and presets: `src/femcal/fe/geometry.py`.",
        "",
        f"Machine: {platform.machine()}, {platform.system()}, Python {platform.python_version()}; "
        "one job at a time, one solver thread (`OMP_NUM_THREADS=1`). Other processes shared "
        "the two cores, so wall seconds are inflated; CPU seconds (`wait4` of the solver "
        "process) are the cost to plan with.",
        "",
        "Parameters: centre of the study's box (ParameterBounds.csv): "
        + ", ".join(f"{k} {v:g}" for k, v in parameters.items())
        + ". Moments 1..5 Nm, compression 300/1000/2000 N.",
        "",
        "## Meshes and cost per load case",
        "",
        "| preset | mesh settings | C3D20R elements | DOF | CPU s per load case (mean, min-max) "
        "| wall s (mean) | failed |",
        "|---|---|---:|---:|---|---:|---:|",
    ]
    for preset in presets:
        sub = df[df["preset"] == preset]
        settings = ", ".join(
            f"{k.replace('elements_', '')} {v}" for k, v in MESH_PRESETS[preset].items()
        )
        lines.append(
            f"| {preset} | {settings} | {sub['elements'].iloc[0]} | {sub['dof'].iloc[0]} | "
            f"{sub['cpu_s'].mean():.1f} ({sub['cpu_s'].min():.1f}-{sub['cpu_s'].max():.1f}) | "
            f"{sub['wall_s'].mean():.1f} | {(sub['status'] != 'ok').sum()} |"
        )
    lines += [
        "",
        "CPU seconds per load case and preset:",
        "",
        "| load case | " + " | ".join(presets) + " |",
        "|---|" + "---:|" * len(presets),
    ]
    for case in (*LOAD_CASES, COMPRESSION):
        cells = [
            f"{df[(df.preset == p) & (df.load_case == case)]['cpu_s'].iloc[0]:.1f}" for p in presets
        ]
        lines.append(f"| {case} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"## Outputs and mesh convergence (difference to `{finest}`)",
        "",
        "| output | " + " | ".join(presets) + " |",
        "|---|" + "---:|" * len(presets),
    ]

    def value(preset: str, case: str, index: int | None = None) -> float:
        row = df[(df.preset == preset) & (df.load_case == case)].iloc[0]
        return row["rom5_deg"] if index is None else row["idp_mpa"][index]

    outputs = [(f"RoM {case} at 5 Nm (deg)", case, None) for case in LOAD_CASES]
    outputs += [(f"IDP at {f:g} N (MPa)", COMPRESSION, i) for i, f in enumerate(FORCES)]
    for label, case, index in outputs:
        ref = value(finest, case, index)
        cells = []
        for p in presets:
            v = value(p, case, index)
            cells.append(f"{v:.3f}" if p == finest else f"{v:.3f} ({100 * (v - ref) / ref:+.1f} %)")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if "default" in presets:
        moments = df[(df.preset == "default") & (df.load_case != COMPRESSION)]
        minutes = moments["cpu_s"].mean() * 256 / 60
        lines += [
            "",
            "A 64-configuration campaign is 256 moment jobs (4 load cases); with the `default` "
            f"preset that is about {minutes:.0f} CPU minutes (about half of it in wall time on "
            "two workers), plus retries of the jobs that abort in the fibre routine.",
        ]
    if sample:
        lines += sample_section(sample)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(MESH_PRESETS))
    parser.add_argument("--sample", type=int, default=8, help="study configurations (0: none)")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per sample run")
    parser.add_argument("--out", type=Path, default=RESULTS / "bench_fe_mesh" / "fe_mesh.md")
    args = parser.parse_args()
    for preset in args.presets:
        DiscGeometry.preset(preset)  # fail early on a typo
    parameters = box_centre()
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="bench_fe_mesh_") as tmp:
        for preset in args.presets:
            rows += run_preset(preset, parameters, Path(tmp))
        sample = run_sample(args.sample, Path(tmp) / "sample", args.timeout) if args.sample else []
    write_report(rows, parameters, args.out, sample)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
