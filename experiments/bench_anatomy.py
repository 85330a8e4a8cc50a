"""Benchmark: the real ``femcal diagnose`` command on anatomy cohorts (issue 42, item 4).

For each seed, :mod:`experiments.anatomy_cohorts` writes a cohort (held-out FE curves plus
physics with per-load-case parameters) to ``<out>/seed-<seed>/cohort``; the command

    femcal diagnose --measurements <cohort>/measurements.csv --noise-deg 0.05 --out <diagnosis>

runs as a user would run it (its wall time is timed), and its ``diagnosis.json`` is scored
against ``answers.csv``:

* **visible**: the disc alone misses by more than 2 sigma, i.e. the diagnosis' disc-alone MAE
  (``baseline_mae_deg``) exceeds twice the noise; the disc-alone chi-square test
  (``adequacy.disc_alone.p_chi2`` below ``alpha``) is reported beside it;
* **strict**: the exact effect set and no ``+unexplained`` (``none`` for the ``none`` class,
  a bare ``unexplained`` for the out-of-library class);
* **known exact**: the exact effect set, ``+unexplained`` allowed;
* **no wrong, one right**: the effects named are a non-empty subset of the true ones;
* **out-of-library right**: a non-``none`` verdict naming no wrong effect (for that class every
  registered effect is wrong, so a bare ``unexplained``);
* **none given an effect**: a specimen with physics (a library effect or the out-of-library
  one) whose verdict is ``none``; **false alarm**: a ``none`` specimen whose verdict is not;
* per class and per protocol; with per-specimen ``probabilities`` (``inclusion``: effect -> p,
  ``outside_library``: p) a 5-bin reliability table over every effect x specimen pair, and
  the share of visible single-effect specimens whose true effect has inclusion >= 0.5;
* **MAE over the none floor**: the mean ``final_mae_deg`` (the diagnosis' own fit with the
  effects it found for each specimen) of a class over that of the ``none`` class. It is the
  diagnosis' per-specimen fit, not a cohort recalibration with ``femcal calibrate --effects``.

Writes ``bench_anatomy.md``, ``bench_anatomy.json`` and ``specimens.csv`` to ``--out``
(default ``/tmp/femcal-bench-anatomy``). Run one diagnosis at a time::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_anatomy --seeds 12345 \
        [--protocols "1-5 Nm x 0.5,1.25-5 Nm x 1.25"] [--out DIR] [--reuse]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from experiments import anatomy_cohorts as ac
from femcal.effects.terms import parse_term
from femcal.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = Path("/tmp/femcal-bench-anatomy")
SINGLE = ("facet_contact", "ligament_tension", "neutral_zone")
BINS = np.linspace(0.0, 1.0, 6)
METRICS = ("strict", "known_exact", "no_wrong_one_right", "ool_right", "none_given_effect")


# ------------------------------------------------------------------------------ the command
def femcal_command(
    measurements: Path, out_dir: Path, noise_deg: float, model_uri: str | None = None
) -> list[str]:
    """The ``femcal diagnose`` command line for one cohort."""
    exe = Path(sys.executable).with_name("femcal")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "femcal"]
    cmd += ["diagnose", "--measurements", str(measurements), "--noise-deg", f"{noise_deg:g}"]
    cmd += ["--out", str(out_dir)]
    return cmd + (["--model-uri", model_uri] if model_uri else [])


def run_command(cmd: Sequence[str]) -> dict[str, Any]:
    """Run ``cmd`` from the repository root (one thread per library unless set); returns its
    return code, wall seconds and the tails of stdout and stderr."""
    env = dict(os.environ)
    env.setdefault("OMP_NUM_THREADS", "1")
    t0 = time.perf_counter()
    proc = subprocess.run(list(cmd), cwd=REPO, env=env, capture_output=True, text=True)
    return {
        "command": shlex.join(cmd),
        "returncode": proc.returncode,
        "wall_s": time.perf_counter() - t0,
        "stdout": proc.stdout[-3000:],
        "stderr": proc.stderr[-3000:],
    }


# ------------------------------------------------------------------------------- judging
def judge(
    verdict: str, effects: Sequence[str], expected: frozenset[str], out_of_library: bool
) -> dict[str, bool | None]:
    """Every verdict criterion for one specimen (None where a criterion does not apply).

    Parameters
    ----------
    verdict : str
        ``none``, ``unexplained``, ``a+b`` or ``a+b+unexplained``.
    effects : sequence of str
        The registered effects the verdict names.
    expected : frozenset of str
        The true registered effects (empty for ``none`` and the out-of-library class).
    out_of_library : bool
        The specimen's physics is outside femcal's library.
    """
    named = set(effects)
    flagged = ac.UNEXPLAINED in verdict.split("+")
    has_physics = bool(expected) or out_of_library
    if not has_physics:
        right = verdict == ac.NONE
        return {
            "strict": right,
            "known_exact": not named,
            "no_wrong_one_right": None,
            "ool_right": None,
            "none_given_effect": None,
            "false_alarm": not right,
        }
    ool_right = verdict != ac.NONE and not named if out_of_library else None
    return {
        "strict": (ool_right if out_of_library else named == expected and not flagged),
        "known_exact": named == set(expected),
        "no_wrong_one_right": None if out_of_library else bool(named) and named <= expected,
        "ool_right": ool_right,
        "none_given_effect": verdict == ac.NONE,
        "false_alarm": None,
    }


def score_specimens(
    answers: pd.DataFrame, diagnosis: list[dict[str, Any]], noise_deg: float, alpha: float
) -> pd.DataFrame:
    """One row per specimen: truth, verdict, the criteria of :func:`judge`, visibility, MAEs
    and (when the diagnosis gives them) the inclusion probabilities.

    Raises
    ------
    ConfigError
        The diagnosis misses specimens of the answers.
    """
    by_name = {str(s["specimen"]): s for s in diagnosis}
    missing = [s for s in answers["specimen"].astype(str) if s not in by_name]
    if missing:
        raise ConfigError(
            f"diagnosis.json has no verdict for {len(missing)} specimens of answers.csv "
            f"(e.g. {missing[:3]}); score a diagnosis of the same cohort."
        )
    rows = []
    for a in answers.itertuples(index=False):
        s = by_name[str(a.specimen)]
        named = [parse_term(str(e)).effect for e in s.get("effects") or []]  # a term's effect
        expected = frozenset(e for e in str(a.expected_effects or "").split("+") if e)
        if a.expected_effects != a.expected_effects:  # NaN from an empty CSV cell
            expected = frozenset()
        probs = s.get("probabilities") or {}
        disc = (s.get("adequacy") or {}).get("disc_alone") or {}
        rows.append(
            {
                "specimen": a.specimen,
                "truth": a.truth,
                "protocol": a.protocol,
                "expected": "+".join(sorted(expected)),
                "verdict": s["verdict"],
                "effects": "+".join(named),
                "model": "+".join(s.get("model") or []),
                **judge(s["verdict"], named, expected, bool(a.out_of_library)),
                "visible": float(s["baseline_mae_deg"]) > 2.0 * noise_deg,
                "disc_rejected": float(disc.get("p_chi2", np.nan)) < alpha,
                "baseline_mae_deg": float(s["baseline_mae_deg"]),
                "final_mae_deg": float(s.get("final_mae_deg", np.nan)),
                "effect_rms_deg": float(a.effect_rms_deg),
                "inclusion": json.dumps(probs.get("inclusion")) if probs else "",
                "outside_library": float(probs.get("outside_library", np.nan)),
            }
        )
    return pd.DataFrame(rows)


# ------------------------------------------------------------------------------- summaries
def _rate(flags: pd.Series) -> dict[str, Any]:
    """``k`` true of ``n`` applicable (None entries do not count), and ``k / n``."""
    ok = flags.dropna().astype(bool)
    return {"k": int(ok.sum()), "n": int(ok.size), "rate": float(ok.mean()) if ok.size else None}


def grouped_rates(table: pd.DataFrame, by: str) -> list[dict[str, Any]]:
    """Per value of ``by``: specimens, visible ones, and each criterion over the visible
    specimens with physics (over all ``none`` specimens for ``strict`` and false alarms)."""
    out = []
    for key, g in table.groupby(by, sort=False):
        physics = g["truth"] != ac.NONE
        seen = g[(physics & g["visible"]) | ~physics]
        row = {by: key, "n": len(g), "visible": int((physics & g["visible"]).sum())}
        for m in (*METRICS, "false_alarm"):
            row[m] = _rate(seen[m])
        out.append(row)
    return out


def headline(table: pd.DataFrame) -> dict[str, dict[str, Any]]:
    """The issue's bars, each as k / n: single effects strict where visible, all effect
    classes 'no wrong, one right' where visible, out-of-library right, none given an effect,
    false alarms."""
    vis = table[table["visible"]]
    single = vis[vis["truth"].isin(SINGLE)]
    effect = vis[~vis["truth"].isin((ac.NONE, ac.UNEXPLAINED))]
    ool = table[table["truth"] == ac.UNEXPLAINED]
    physics = table[table["truth"] != ac.NONE]
    return {
        "single_strict_visible": _rate(single["strict"]),
        "single_known_exact_visible": _rate(single["known_exact"]),
        "effects_no_wrong_one_right_visible": _rate(effect["no_wrong_one_right"]),
        "effects_strict_visible": _rate(effect["strict"]),
        "ool_right": _rate(ool["ool_right"]),
        "ool_right_visible": _rate(ool[ool["visible"]]["ool_right"]),
        "none_given_effect_visible": _rate(physics[physics["visible"]]["none_given_effect"]),
        "none_given_effect_all": _rate(physics["none_given_effect"]),
        "false_alarm": _rate(table[table["truth"] == ac.NONE]["false_alarm"]),
    }


def reliability(table: pd.DataFrame) -> dict[str, Any] | None:
    """Calibration of the inclusion probabilities over every effect x specimen pair (5 bins;
    the effects are those any specimen's probabilities or truth name, absent ones count as 0),
    of ``outside_library`` against the out-of-library truth, and the share of visible
    single-effect specimens whose true effect has inclusion >= 0.5; None without
    probabilities."""
    have = table[table["inclusion"].astype(bool)]
    if have.empty:
        return None
    included = [json.loads(r) or {} for r in have["inclusion"]]
    truths = [set(e.split("+")) - {""} for e in have["expected"]]
    library = sorted(set().union(*included, *truths))  # an effect never fitted has p = 0
    pairs = [(float(inc.get(e, 0.0)), e in t) for inc, t in zip(included, truths) for e in library]
    pred, obs = np.array([p for p, _ in pairs]), np.array([o for _, o in pairs], dtype=float)
    ool = have[np.isfinite(have["outside_library"])]

    def bins(p: np.ndarray, o: np.ndarray) -> list[dict[str, Any]]:
        idx = np.clip(np.digitize(p, BINS[1:-1]), 0, len(BINS) - 2)
        return [
            {
                "bin": f"{BINS[b]:.1f}-{BINS[b + 1]:.1f}",
                "n": int((idx == b).sum()),
                "predicted": float(p[idx == b].mean()) if (idx == b).any() else None,
                "observed": float(o[idx == b].mean()) if (idx == b).any() else None,
            }
            for b in range(len(BINS) - 1)
        ]

    single = have[have["truth"].isin(SINGLE) & have["visible"]]
    hits = [json.loads(r.inclusion).get(r.expected, 0.0) >= 0.5 for r in single.itertuples()]
    return {
        "inclusion": bins(pred, obs),
        "outside_library": bins(
            ool["outside_library"].to_numpy(), (ool["truth"] == ac.UNEXPLAINED).to_numpy(float)
        ),
        "true_effect_inclusion_ge_half": _rate(pd.Series(hits, dtype=object)),
        "n_specimens": len(have),
        "effects": library,
    }


def mae_ratios(table: pd.DataFrame) -> dict[str, Any] | None:
    """Mean final MAE of each class over that of the ``none`` class (the floor), with the
    disc-alone MAE beside it; None without final MAEs."""
    if not np.isfinite(table["final_mae_deg"]).any():
        return None
    means = table.groupby("truth", sort=False)[["final_mae_deg", "baseline_mae_deg"]].mean()
    floor = float(means.loc[ac.NONE, "final_mae_deg"]) if ac.NONE in means.index else np.nan
    return {
        "floor_deg": floor,
        "classes": {
            c: {
                "final_mae_deg": float(r.final_mae_deg),
                "disc_alone_mae_deg": float(r.baseline_mae_deg),
                "ratio": float(r.final_mae_deg / floor) if floor > 0 else None,
            }
            for c, r in means.iterrows()
        },
    }


def summarize(table: pd.DataFrame) -> dict[str, Any]:
    """Every figure of the report for one table of scored specimens."""
    return {
        "n_specimens": len(table),
        "headline": headline(table),
        "by_class": grouped_rates(table, "truth"),
        "by_protocol": grouped_rates(table, "protocol"),
        "reliability": reliability(table),
        "mae": mae_ratios(table),
    }


# ---------------------------------------------------------------------------------- report
BARS = {
    "single_strict_visible": ("single effects, strict, visible", ">= 90 %"),
    "single_known_exact_visible": ("single effects, known effects exact, visible", ""),
    "effects_strict_visible": ("all effect classes, strict, visible", ""),
    "effects_no_wrong_one_right_visible": (
        "all effect classes, no wrong + one right, visible",
        ">= 85 %",
    ),
    "ool_right": ("out-of-library right (bare `unexplained`)", ">= 85 %"),
    "ool_right_visible": ("out-of-library right, visible", ""),
    "none_given_effect_visible": ("`none` given an effect, visible", "<= 10 %"),
    "none_given_effect_all": ("`none` given an effect, all", ""),
    "false_alarm": ("false alarm (truth `none`, verdict not `none`)", ""),
}


def _fmt(r: dict[str, Any] | None) -> str:
    if not r or not r["n"]:
        return "-"
    return f"{r['k']}/{r['n']} ({100 * r['rate']:.0f} %)"


def _rate_table(rows: list[dict[str, Any]], key: str) -> list[str]:
    head = f"| {key} | n | visible | " + " | ".join((*METRICS, "false_alarm")) + " |"
    lines = [head, "|" + "---|" * (3 + len(METRICS) + 1)]
    for r in rows:
        cells = " | ".join(_fmt(r[m]) for m in (*METRICS, "false_alarm"))
        lines.append(f"| {r[key]} | {r['n']} | {r['visible']} | {cells} |")
    return lines


def _reliability_lines(rel: dict[str, Any] | None) -> list[str]:
    if rel is None:
        return ["diagnosis.json gives no per-specimen `probabilities`: no reliability table."]
    lines = [
        f"{rel['n_specimens']} specimens with probabilities. True effects with inclusion >= 0.5"
        f" among visible single-effect specimens: {_fmt(rel['true_effect_inclusion_ge_half'])}.",
        "",
        "| bin | inclusion n | predicted | observed | outside_library n | predicted | observed |",
        "|---|---|---|---|---|---|---|",
    ]

    def f(x: float | None) -> str:
        return "-" if x is None else f"{x:.2f}"

    for a, b in zip(rel["inclusion"], rel["outside_library"]):
        lines.append(
            f"| {a['bin']} | {a['n']} | {f(a['predicted'])} | {f(a['observed'])} | {b['n']} | "
            f"{f(b['predicted'])} | {f(b['observed'])} |"
        )
    return lines


def write_report(runs: list[dict[str, Any]], pooled: dict[str, Any] | None, meta: dict, out: Path):
    """Write ``bench_anatomy.md`` and ``bench_anatomy.json`` into ``out``."""
    scored = [r for r in runs if r.get("summary")]
    lines = [
        "# `femcal diagnose` on anatomy cohorts",
        "",
        f"Command: `{meta['command']}`. Cohorts from `experiments/anatomy_cohorts.py` (seeds "
        f"{meta['seeds']}, {meta['n_per_class']} per class, protocols {meta['protocols']}, "
        f"noise sd {meta['noise_deg']} deg); fresh seeds, nothing tuned on them. Visible: the "
        "disc-alone MAE of the diagnosis exceeds 2 x noise.",
        "",
        "## Headline",
        "",
        "| "
        + " | ".join(["criterion", *(f"seed {r['seed']}" for r in scored), "pooled", "bar"])
        + " |",
        "|---" * (len(scored) + 3) + "|",
    ]
    for key, (label, bar) in BARS.items():
        cells = [_fmt(r["summary"]["headline"][key]) for r in scored]
        pool = _fmt(pooled["headline"][key]) if pooled else "-"
        lines.append("| " + " | ".join([label, *cells, pool, bar]) + " |")
    lines += ["", "## Wall time of the whole command", ""]
    for r in runs:
        status = "ok" if r["returncode"] == 0 else f"failed (exit {r['returncode']})"
        lines.append(
            f"- seed {r['seed']}: {r['wall_s']:.1f} s for {r['n_specimens']} specimens, {status}"
        )
        if r["returncode"] != 0:
            last = (r["stderr"].strip().splitlines() or [""])[-1]
            lines.append(f"  - stderr: `{last}`")
    if pooled:
        lines += ["", "## Per class (pooled; criteria over visible specimens, `none` over all)", ""]
        lines += _rate_table(pooled["by_class"], "truth")
        lines += ["", "## Per protocol (pooled)", ""]
        lines += _rate_table(pooled["by_protocol"], "protocol")
        lines += ["", "## Inclusion probabilities", ""] + _reliability_lines(pooled["reliability"])
        lines += ["", "## Final MAE over the `none` floor (pooled)", ""]
        mae = pooled["mae"]
        if mae is None:
            lines.append("diagnosis.json gives no final MAE: left out.")
        else:
            lines += [
                f"Floor (class `none`, final MAE): {mae['floor_deg']:.4f} deg. The final MAE is "
                "the diagnosis' own fit with the effects it found per specimen (bar: <= 1.5 x for "
                "the classes the library covers).",
                "",
                "| class | disc-alone MAE (deg) | final MAE (deg) | ratio |",
                "|---|---|---|---|",
            ]
            for c, v in mae["classes"].items():
                ratio = "-" if v["ratio"] is None else f"{v['ratio']:.2f}"
                lines.append(
                    f"| {c} | {v['disc_alone_mae_deg']:.4f} | {v['final_mae_deg']:.4f} | {ratio} |"
                )
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_anatomy.md").write_text("\n".join(lines) + "\n")
    payload = {"meta": meta, "runs": runs, "pooled": pooled}
    (out / "bench_anatomy.json").write_text(json.dumps(payload, indent=2, default=str) + "\n")


# ------------------------------------------------------------------------------------ main
def one_seed(seed: int, args: argparse.Namespace, curves: tuple[np.ndarray, np.ndarray]) -> dict:
    """Write one cohort, diagnose it with the real command (or reuse its diagnosis) and score
    it; the run's record with its scored specimens (``table``) and summary."""
    root = args.out / f"seed-{seed}"
    cohort = ac.make_cohort(
        *curves, seed=seed, n_per_class=args.n_per_class, protocols=args.protocols
    )
    measurements = ac.write_cohort(cohort, root / "cohort", source=str(args.raw_dir))
    diag_dir = root / "diagnosis"
    cmd = femcal_command(measurements, diag_dir, args.noise_deg, args.model_uri)
    if (diag_dir / "diagnosis.json").exists() and args.reuse:
        run = {"command": shlex.join(cmd), "returncode": 0, "wall_s": float("nan"), "stdout": ""}
        run["stderr"] = "reused an earlier diagnosis (wall time not measured)"
    elif diag_dir.exists():
        raise ConfigError(
            f"{diag_dir} exists: pass a fresh --out, or --reuse to score its diagnosis again."
        )
    else:
        run = run_command(cmd)
    run.update(seed=seed, n_specimens=len(cohort.answers))
    if run["returncode"] != 0:
        return run
    diagnosis = json.loads((diag_dir / "diagnosis.json").read_text())
    summary_path = diag_dir / "summary.json"
    alpha = (
        json.loads(summary_path.read_text()).get("alpha", 0.01) if summary_path.exists() else 0.01
    )
    table = score_specimens(cohort.answers, diagnosis, args.noise_deg, float(alpha))
    table.insert(0, "seed", seed)
    run.update(table=table, summary=summarize(table))
    return run


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", required=True, help="comma-separated cohort seeds (fresh ones)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="report and cohort folder")
    ap.add_argument("--raw-dir", type=Path, default=None, help="folder holding the study's Test/")
    ap.add_argument("--n-per-class", type=int, default=9)
    ap.add_argument("--protocols", default=",".join(ac.PROTOCOLS), help="comma-separated keys")
    ap.add_argument("--noise-deg", type=float, default=ac.NOISE_DEG)
    ap.add_argument("--model-uri", default=None, help="passed to femcal diagnose")
    ap.add_argument("--reuse", action="store_true", help="score an existing diagnosis again")
    args = ap.parse_args(argv)
    args.raw_dir = args.raw_dir or ac.default_raw_dir(REPO)
    args.protocols = [p for p in args.protocols.split(",") if p]
    seeds = [int(s) for s in args.seeds.split(",") if s]
    curves = ac.read_heldout_curves(args.raw_dir)
    runs = []
    for seed in seeds:  # one diagnosis at a time
        runs.append(one_seed(seed, args, curves))
        r = runs[-1]
        print(f"seed {seed}: exit {r['returncode']}, {r['wall_s']:.1f} s", flush=True)
    tables = [r.pop("table") for r in runs if "table" in r]
    pooled = summarize(pd.concat(tables, ignore_index=True)) if tables else None
    if tables:
        args.out.mkdir(parents=True, exist_ok=True)
        pd.concat(tables, ignore_index=True).to_csv(args.out / "specimens.csv", index=False)
    meta = {
        "command": shlex.join(
            ["python", "-m", "experiments.bench_anatomy", *(argv or sys.argv[1:])]
        ),
        "seeds": seeds,
        "n_per_class": args.n_per_class,
        "protocols": args.protocols,
        "noise_deg": args.noise_deg,
        "raw_dir": str(args.raw_dir),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS", "1 (set by the runner)"),
    }
    write_report(runs, pooled, meta, args.out)
    print(f"wrote {args.out / 'bench_anatomy.md'}")


if __name__ == "__main__":
    main()
