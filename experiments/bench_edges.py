"""Benchmark: the real ``femcal diagnose`` command on edge cohorts (issue 55's closing figures).

For each seed, :mod:`experiments.edge_cohorts` writes a cohort to ``<out>/seed-<seed>/cohort``
and the command runs as a user runs it, timed by ``/usr/bin/time -v``::

    femcal diagnose --measurements <cohort>/measurements.csv --noise-deg 0.05 --out <diagnosis>

Its ``diagnosis.json`` is scored against ``truth.json``:

* **visible**: the disc alone misses, i.e. the diagnosis' disc-alone MAE
  (``baseline_mae_deg``) exceeds :data:`VISIBLE_FACTOR` x the specimen's true noise RMS (the
  truth's, not the stated noise), and every structure of the specimen shows: in a load case it
  acts in, the RMS of what it adds at the measured points (``contribution_rms_deg`` of the
  truth: the RoM with every structure less the RoM without it) exceeds the same threshold. A
  structure beyond the old assignment is visible there where the disc alone misses and its
  contribution in that load case exceeds the threshold.
* **outside the box**: the verdict names ``outside_box`` (or the reading's ``named``), or it
  says ``unexplained`` and its out-of-box reading has probability >= :data:`BOX_REPORTED` (the
  summary names the box beside it); and the specimens where a built-in effect has inclusion
  >= :data:`CONFIDENT`.
  Beside the verdict: the discs outside the box whose out-of-box reading is reported (its
  probability >= :data:`BOX_REPORTED`, under any verdict), and the box said of discs inside it
  (the class ``none``, and every class but ``outside_box``: the Test discs).
* **beyond the old assignment**: facets acting in LateralBending and ligaments acting in
  Extension, where that load case's contribution is visible: the right effect named (among
  others) and the exact, strict verdict.
* **confidently wrong**: an effect absent from the truth with inclusion >= :data:`CONFIDENT`
  (inclusion summed over an effect's forms, ``x`` and ``x:split``), over all specimens.
* **combinations**: facet + ligament and facet + neutral zone, strict (the exact effect set,
  neither ``unexplained`` nor ``outside_box``), where each member is visible.
* **kept**: single effects strict where visible; ``none`` given to a visible specimen with
  structures; false alarms (truth ``none``, verdict not ``none``); out-of-library right (no
  effect named, ``unexplained`` said); the final MAE of each class over the ``none`` class's.
* **time**: wall and CPU (user + sys, children included) seconds of the whole command, and per
  50 specimens.

Writes ``bench_edges.json`` and ``specimens.csv`` to ``--out``; ``experiments.edges_report``
turns one or more such folders into ``docs/benchmarks/edges.md``. One diagnosis at a time::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_edges --seeds 101,102 \\
        --label dev --out experiments/results/bench_edges/dev
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from experiments import edge_cohorts as ec
from experiments.common import REPO, reproduce_command
from femcal.effects.terms import parse_term

#: The femcal effect a structure should be named as (None: outside femcal's library).
EFFECT_OF: dict[str, str | None] = {
    "facets": "facet_contact",
    "ligaments": "ligament_tension",
    "laxity": "neutral_zone",
    "softening": None,
}
#: The load cases femcal's built-in effects were declared for when issue 55 was filed; a
#: structure acting elsewhere acts beyond that assignment.
BUILTIN_ASSIGNMENT: dict[str, tuple[str, ...]] = {
    "facets": ("Extension", "AxialRotation"),
    "ligaments": ("Flexion", "LateralBending"),
    "laxity": ec.LOAD_CASES,
    "softening": ec.LOAD_CASES,
}
BUILTIN = ("facet_contact", "ligament_tension", "neutral_zone")
SINGLE = ("facets", "ligaments", "neutral_zone")
COMBOS = ("facets+ligaments", "facets+neutral_zone")
VISIBLE_FACTOR = 2.0
CONFIDENT = 0.9
#: An out-of-box reading this probable is reported beside a verdict that does not name the box
#: (femcal.diagnose.outside.REPORTED).
BOX_REPORTED = 0.1
OUTSIDE_BOX, UNEXPLAINED = "outside_box", "unexplained"


# ------------------------------------------------------------------------------ the command
def femcal_command(measurements: Path, out_dir: Path, noise_deg: float) -> list[str]:
    """``/usr/bin/time -v femcal diagnose ...`` with the running interpreter's ``femcal``."""
    exe = Path(sys.executable).with_name("femcal")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "femcal"]
    cmd += ["diagnose", "--measurements", str(measurements), "--noise-deg", f"{noise_deg:g}"]
    return ["/usr/bin/time", "-v", *cmd, "--out", str(out_dir)]


def parse_time(stderr: str) -> dict[str, float]:
    """User, system and wall seconds and the peak RSS (MB) of ``/usr/bin/time -v``'s report."""
    out: dict[str, float] = {}
    for key, pattern in (
        ("user_s", r"User time \(seconds\): ([\d.]+)"),
        ("sys_s", r"System time \(seconds\): ([\d.]+)"),
        ("max_rss_mb", r"Maximum resident set size \(kbytes\): (\d+)"),
    ):
        m = re.search(pattern, stderr)
        out[key] = float(m.group(1)) if m else float("nan")
    out["max_rss_mb"] /= 1024.0
    m = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)", stderr)
    if m:
        parts = [float(x) for x in m.group(1).split(":")]
        out["time_wall_s"] = sum(v * 60.0**k for k, v in enumerate(reversed(parts)))
    out["cpu_s"] = out["user_s"] + out["sys_s"]
    return out


def run_command(cmd: Sequence[str]) -> dict[str, Any]:
    """Run ``cmd`` from the repository root (one thread per library unless set)."""
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")
    t0 = time.perf_counter()
    proc = subprocess.run(list(cmd), cwd=REPO, env=env, capture_output=True, text=True)
    return {
        "command": shlex.join(cmd),
        "returncode": proc.returncode,
        "wall_s": time.perf_counter() - t0,
        **parse_time(proc.stderr),
        "stderr": proc.stderr[-3000:],
    }


# ------------------------------------------------------------------------------- judging
def inclusion_by_effect(record: dict) -> dict[str, float]:
    """Inclusion probability per registered effect, its terms (``x``, ``x:split``, ``x@cases``)
    summed."""
    inc = (record.get("probabilities") or {}).get("inclusion") or {}
    out: dict[str, float] = {}
    for key, p in inc.items():
        base = parse_term(key).effect
        out[base] = min(1.0, out.get(base, 0.0) + float(p))
    return out


def score_specimen(truth: dict, record: dict) -> dict[str, Any]:
    """Every criterion for one specimen (None where it does not apply)."""
    label = truth["truth"]
    noise = float(truth["noise"]["rms_deg"])
    threshold = VISIBLE_FACTOR * noise
    contrib = truth["contribution_rms_deg"]
    expected = {EFFECT_OF[s] for s in truth["structures"]} - {None}
    seen = {s: max(v.values(), default=0.0) > threshold for s, v in contrib.items()}
    beyond = {
        s: [lc for lc in v if lc not in BUILTIN_ASSIGNMENT[s] and v[lc] > threshold]
        for s, v in contrib.items()
    }
    parts = str(record["verdict"]).split("+")
    named = {parse_term(str(e)).effect for e in record.get("effects") or []}
    inclusion = inclusion_by_effect(record)
    box = record.get("outside_box") or {}
    box_named = OUTSIDE_BOX in parts or bool(box.get("named"))
    flagged = UNEXPLAINED in parts
    box_said = box_named or (flagged and float(box.get("probability") or 0.0) >= BOX_REPORTED)
    exact = named == expected and not flagged and not box_named
    baseline = float(record["baseline_mae_deg"])
    missed = baseline > threshold  # the disc alone misses the data
    visible = missed and (label == "outside_box" or (bool(seen) and all(seen.values())))
    return {
        "specimen": truth["specimen"],
        "truth": label,
        "protocol": truth["protocol"],
        "noise_kind": truth["noise"]["kind"],
        "noise_rms_deg": noise,
        "expected": "+".join(sorted(expected)),
        "verdict": record["verdict"],
        "effects": "+".join(sorted(named)),
        "visible": visible,
        "strict": {
            "none": record["verdict"] == "none",
            "unexplained": flagged and not named and not box_named,
            "outside_box": box_said,
        }.get(label, exact),
        "right_named": bool(expected) and expected <= named,
        "box_said": box_said,
        "box_probability": float(box.get("probability") or 0.0),
        "box_reported": float(box.get("probability") or 0.0) >= BOX_REPORTED,
        "bounds_pressed": len((record.get("failures") or {}).get("on_bounds") or []),
        "edge_probability": float((box.get("edge") or {}).get("probability", np.nan)),
        "confident_wrong": "+".join(
            sorted(e for e, p in inclusion.items() if p >= CONFIDENT and e not in expected)
        ),
        "confident_builtin": "+".join(
            sorted(e for e, p in inclusion.items() if p >= CONFIDENT and e in BUILTIN)
        ),
        "facets_lb_visible": missed and "LateralBending" in beyond.get("facets", []),
        "ligaments_ext_visible": missed and "Extension" in beyond.get("ligaments", []),
        "facet_named": "facet_contact" in named,
        "ligament_named": "ligament_tension" in named,
        "baseline_mae_deg": baseline,
        "final_mae_deg": float(record.get("final_mae_deg", np.nan)),
        "inclusion": json.dumps(inclusion),
    }


def score_cohort(truth: list[dict], diagnosis: list[dict]) -> pd.DataFrame:
    """One row per specimen of ``truth`` (:func:`score_specimen`)."""
    by_name = {str(r["specimen"]): r for r in diagnosis}
    missing = [t["specimen"] for t in truth if t["specimen"] not in by_name]
    if missing:
        raise KeyError(
            f"diagnosis.json has no verdict for {len(missing)} specimens of truth.json (e.g. "
            f"{missing[:3]}); score the diagnosis of the same cohort."
        )
    return pd.DataFrame([score_specimen(t, by_name[t["specimen"]]) for t in truth])


# ------------------------------------------------------------------------------- summaries
def _rate(flags: pd.Series) -> dict[str, Any]:
    ok = flags.dropna().astype(bool)
    return {"k": int(ok.sum()), "n": int(ok.size), "rate": float(ok.mean()) if ok.size else None}


def headline(t: pd.DataFrame) -> dict[str, dict[str, Any]]:
    """The issue's bars, each as k of n."""
    vis = t[t["visible"]]
    box = t[t["truth"] == "outside_box"]
    physics = vis[~vis["truth"].isin(("none", "outside_box"))]
    facets_lb, lig_ext = t[t["facets_lb_visible"]], t[t["ligaments_ext_visible"]]
    return {
        "box_said": _rate(box["box_said"]),
        "box_said_visible": _rate(box[box["visible"]]["box_said"]),
        "box_confident_builtin": _rate(box["confident_builtin"].astype(bool)),
        "box_reported": _rate(box["box_reported"]),
        "box_false_none": _rate(t[t["truth"] == "none"]["box_said"]),
        "box_reported_none": _rate(t[t["truth"] == "none"]["box_reported"]),
        "box_false_inside": _rate(t[t["truth"] != "outside_box"]["box_said"]),
        "beyond_right_named": _rate(
            pd.concat([facets_lb["facet_named"], lig_ext["ligament_named"]], ignore_index=True)
        ),
        "facets_lb_right_named": _rate(facets_lb["facet_named"]),
        "facets_lb_strict": _rate(facets_lb[facets_lb["truth"] == "facets"]["strict"]),
        "ligaments_ext_right_named": _rate(lig_ext["ligament_named"]),
        "ligaments_ext_strict": _rate(lig_ext[lig_ext["truth"] == "ligaments"]["strict"]),
        "confident_wrong": _rate(t["confident_wrong"].astype(bool)),
        "combos_strict_visible": _rate(vis[vis["truth"].isin(COMBOS)]["strict"]),
        "facets_ligaments_strict_visible": _rate(vis[vis["truth"] == COMBOS[0]]["strict"]),
        "facets_nz_strict_visible": _rate(vis[vis["truth"] == COMBOS[1]]["strict"]),
        "single_strict_visible": _rate(vis[vis["truth"].isin(SINGLE)]["strict"]),
        "none_given_effect_visible": _rate(physics["verdict"] == "none"),
        "false_alarm": _rate(t[t["truth"] == "none"]["verdict"] != "none"),
        "unexplained_right_visible": _rate(vis[vis["truth"] == "unexplained"]["strict"]),
    }


def by_group(t: pd.DataFrame, key: str) -> list[dict[str, Any]]:
    """Per value of ``key``: specimens, visible ones, strict (visible), confidently wrong (all),
    verdict ``none`` (visible), out-of-box said (all)."""
    rows = []
    for value, g in t.groupby(key, sort=False):
        vis = g[g["visible"]]
        rows.append(
            {
                key: value,
                "n": len(g),
                "visible": len(vis),
                "strict_visible": _rate(vis["strict"]),
                "confident_wrong": _rate(g["confident_wrong"].astype(bool)),
                "verdict_none_visible": _rate(vis["verdict"] == "none"),
                "box_said": _rate(g["box_said"]),
            }
        )
    return rows


def mae_ratios(t: pd.DataFrame) -> dict[str, Any]:
    """Mean final MAE per class over the ``none`` class's (the floor), disc-alone MAE beside."""
    means = t.groupby("truth", sort=False)[["final_mae_deg", "baseline_mae_deg"]].mean()
    floor = float(means.loc["none", "final_mae_deg"]) if "none" in means.index else np.nan
    return {
        "floor_deg": floor,
        "classes": {
            str(c): {
                "final_mae_deg": float(r.final_mae_deg),
                "disc_alone_mae_deg": float(r.baseline_mae_deg),
                "ratio": float(r.final_mae_deg / floor) if floor > 0 else None,
            }
            for c, r in means.iterrows()
        },
    }


def inclusion_scores(t: pd.DataFrame) -> dict[str, Any]:
    """The inclusion probabilities of the built-in effects scored against the truth, over every
    (specimen, effect) pair: the Brier score, the log loss (probabilities clipped to
    [0.001, 0.999]) and how many present and absent effects have inclusion >= CONFIDENT."""
    p, y = [], []
    for inc, expected in zip(t["inclusion"], t["expected"]):
        got, present = json.loads(inc or "{}"), set(str(expected or "").split("+"))
        for effect in sorted(BUILTIN):
            p.append(float(got.get(effect, 0.0)))
            y.append(effect in present)
    prob, truth = np.clip(np.array(p), 1e-3, 1 - 1e-3), np.array(y, dtype=bool)
    loss = -np.log(np.where(truth, prob, 1 - prob))
    return {
        "pairs": len(p),
        "brier": float(np.mean((prob - truth) ** 2)) if p else np.nan,
        "log_loss": float(np.mean(loss)) if p else np.nan,
        "present_confident": _rate(pd.Series(prob[truth] >= CONFIDENT)),
        "absent_confident": _rate(pd.Series(prob[~truth] >= CONFIDENT)),
    }


def summarize(t: pd.DataFrame) -> dict[str, Any]:
    """Every figure of the report for one table of scored specimens."""
    return {
        "n_specimens": len(t),
        "headline": headline(t),
        "inclusion_scores": inclusion_scores(t),
        "by_class": by_group(t, "truth"),
        "by_noise": by_group(t, "noise_kind"),
        "by_protocol": by_group(t, "protocol"),
        "verdicts_by_class": {
            str(c): g["verdict"].value_counts().to_dict() for c, g in t.groupby("truth", sort=False)
        },
        "mae": mae_ratios(t),
    }


# ------------------------------------------------------------------------------------ main
def _timed_before(out: Path, seed: int) -> dict[str, Any]:
    """The command and times of ``seed``'s run in ``out/bench_edges.json`` (empty if none)."""
    path = out / "bench_edges.json"
    if not path.exists():
        return {}
    before = [r for r in json.loads(path.read_text())["runs"] if r.get("seed") == seed]
    keys = ("command", "wall_s", "user_s", "sys_s", "cpu_s", "time_wall_s", "max_rss_mb")
    return {k: before[0][k] for k in keys if before and k in before[0]}


def diagnose_seed(seed: int, args: argparse.Namespace, discs: tuple) -> dict[str, Any]:
    """Write one cohort and diagnose it with the real command (or reuse its diagnosis); the
    run's record with the cohort (``cohort_obj``) kept for scoring."""
    root = args.out / f"seed-{seed}"
    opts = ec.CohortOptions(n_per_class=args.n_per_class, stated_noise_deg=args.noise_deg)
    cohort = ec.make_cohort(discs[0], discs[1], seed, opts)
    measurements = ec.write_cohort(cohort, root / "cohort")
    diag = root / "diagnosis"
    cmd = femcal_command(measurements, diag, args.noise_deg)
    if args.reuse and (diag / "diagnosis.json").exists():
        run: dict[str, Any] = {"command": shlex.join(cmd), "returncode": 0}
        run.update(_timed_before(args.out, seed), reused=True)
    elif diag.exists():
        raise FileExistsError(f"{diag} exists: pass a fresh --out, or --reuse to score it again.")
    else:
        run = run_command(cmd)
    n = cohort.meta["n_specimens"]
    run.update(seed=seed, n_specimens=n, cohort=cohort.meta, cohort_obj=cohort)
    for key in ("time_wall_s", "cpu_s"):
        if key in run:
            run[key.replace("_s", "_s_per_50")] = run[key] * 50.0 / n
    print(f"seed {seed}: exit {run['returncode']}, {run.get('time_wall_s', np.nan):.1f} s")
    return run


def score_run(run: dict[str, Any], out: Path) -> dict[str, Any]:
    """Score a finished run against its cohort's truth (adds ``table`` and ``summary``)."""
    cohort = run.pop("cohort_obj")
    if run["returncode"] != 0:
        return run
    diag = out / f"seed-{run['seed']}" / "diagnosis" / "diagnosis.json"
    table = score_cohort(cohort.truth, json.loads(diag.read_text()))
    table.insert(0, "seed", run["seed"])
    run.update(table=table, summary=summarize(table))
    return run


def library_state() -> dict[str, str]:
    """Where ``femcal`` is imported from (a ``PYTHONPATH`` snapshot runs before the editable
    install), the repository's commit and whether its src/femcal differs from it."""

    def git(*a: str) -> str:
        p = subprocess.run(["git", *a], cwd=REPO, capture_output=True, text=True)
        return p.stdout.strip()

    probe = subprocess.run(
        [sys.executable, "-c", "import femcal; print(femcal.__file__)"],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    return {
        "femcal_imported_from": probe.stdout.strip(),
        "pythonpath": os.environ.get("PYTHONPATH", ""),
        "commit": git("rev-parse", "HEAD"),
        "subject": git("log", "-1", "--format=%s"),
        "committed_at": git("log", "-1", "--format=%cI"),
        "src_femcal_changes": git("status", "--porcelain", "src/femcal"),
    }


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--seeds", required=True, help="comma-separated cohort seeds")
    ap.add_argument("--label", default="dev", help="what the seeds are (dev, fresh, ...)")
    ap.add_argument("--note", default="", help="a sentence the report prints under the label")
    ap.add_argument("--out", type=Path, required=True, help="results folder")
    ap.add_argument("--raw-dir", type=Path, default=None, help="folder holding the study's Test/")
    ap.add_argument("--store", type=Path, default=ec.STORE, help="discs outside the box")
    ap.add_argument("--n-per-class", type=int, default=ec.CohortOptions.n_per_class)
    ap.add_argument("--noise-deg", type=float, default=ec.STATED_NOISE_DEG)
    ap.add_argument("--reuse", action="store_true", help="score existing diagnoses again")
    ap.add_argument(
        "--jobs", type=int, default=1, help="diagnoses run at once (times: 1, one at a time)"
    )
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s]
    discs = (
        ec.read_test_curves(args.raw_dir or ec.default_raw_dir()),
        ec.read_outside_store(args.store),
    )
    meta = {
        "command": (
            f"PYTHONPATH={os.environ['PYTHONPATH']} " if os.environ.get("PYTHONPATH") else ""
        )
        + reproduce_command("bench_edges", argv),
        "label": args.label,
        "note": args.note,
        "seeds": seeds,
        "n_per_class": args.n_per_class,
        "noise_deg": args.noise_deg,
        "jobs": args.jobs,
        "library": library_state(),
        "started_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    previous = args.out / "bench_edges.json"
    if args.reuse and previous.exists():  # the diagnoses' run, scored again now
        before = json.loads(previous.read_text())["meta"]
        meta["rescore_command"] = meta["command"]
        meta.update(
            {k: before[k] for k in ("command", "started_at", "library", "jobs") if k in before}
        )
        meta["rescored_at"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:  # --jobs diagnoses at a time
        done = list(pool.map(lambda seed: diagnose_seed(seed, args, discs), seeds))
    runs = [score_run(r, args.out) for r in done]
    tables = [r.pop("table") for r in runs if "table" in r]
    pooled = summarize(pd.concat(tables, ignore_index=True)) if tables else None
    args.out.mkdir(parents=True, exist_ok=True)
    if tables:
        pd.concat(tables, ignore_index=True).to_csv(args.out / "specimens.csv", index=False)
    payload = {"meta": meta, "runs": runs, "pooled": pooled}
    (args.out / "bench_edges.json").write_text(json.dumps(payload, indent=2, default=str) + "\n")
    print(f"wrote {args.out / 'bench_edges.json'}")


if __name__ == "__main__":
    main()
