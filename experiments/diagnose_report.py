"""The reports of :mod:`experiments.bench_diagnose`: the full report, the timing report, the
bars pooled per group of cohorts, and the merge of earlier runs.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.stats import binomtest

from experiments.diagnosis import BAR_SECONDS, cohort_group, cohort_name
from experiments.hidden_cohorts import (
    HOLDOUT_SEEDS,
    PROTOCOLS,
    TUNING_SEEDS,
)
from femcal.diagnose.report import PRACTICAL_REPEATS
from femcal.effects.planted import NONE
from femcal.schema import LOAD_CASES


def _pct(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{x:.0%}"


def _ok(flag: bool) -> str:
    return "yes" if flag else "**no**"


def wilson(k: int, n: int) -> tuple[float, float]:
    """Wilson score 95 % interval of a proportion ``k / n`` (SciPy); (nan, nan) if n = 0."""
    if n <= 0:
        return float("nan"), float("nan")
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


def pooled(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Bars (a) and (b) pooled per group of cohorts (three-class; hidden tuning, fresh, held
    out), with Wilson 95 % intervals: one cohort's 34-41 eligible specimens put a rate's
    interval about +-10 points wide."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(cohort_group(r), []).append(r)
    out = []
    for name, rs in groups.items():
        k = sum(int(r["n_right_eligible"]) for r in rs)
        n = sum(int(r["n_eligible"]) for r in rs)
        kp = sum(int(r.get("n_truth_preferred", r["n_eligible"])) for r in rs)
        kb = sum(int(r["n_none_given_effect"]) for r in rs)
        nb = sum(int(r["n_none"]) for r in rs)
        out.append(
            {
                "group": name,
                "seeds": [r["seed"] for r in rs],
                "a_right": k,
                "a_eligible": n,
                "a_interval": wilson(k, n),
                "ceiling": kp / n if n else float("nan"),
                "b_none_given_effect": kb,
                "b_none": nb,
                "b_interval": wilson(kb, nb),
                # right, or the true model is the rival next_measurement names
                "a_right_or_rival": sum(int(r["n_right_or_rival_eligible"]) for r in rs)
                if all("n_right_or_rival_eligible" in r for r in rs)
                else None,
            }
        )
    return out


def merge_reports(paths: Sequence[Path]) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The cohorts of several ``bench_diagnose.json`` files and their shared settings.

    Raises
    ------
    ValueError
        The files were written with other surrogates, noise or diagnose options: their rates
        are not comparable side by side.
    """
    rows: list[dict[str, Any]] = []
    metas = []
    for path in paths:
        data = json.loads(Path(path).read_text())
        rows += data.pop("cohorts")
        metas.append(data)
    keys = ("surrogate", "noise_deg", "diagnose_options", "surrogate_error_in_range")
    for key in (*keys, "max_specimens"):
        seen = {json.dumps(m.get(key), sort_keys=True) for m in metas}
        if len(seen) > 1:
            raise ValueError(
                f"--from-json: the reports differ in {key!r} ({', '.join(sorted(seen))}); "
                "merge only runs of the same surrogate, noise and options."
            )
    commands = []
    for m in metas:
        commands += m.get("commands") or [m["command"]]
    meta = {**metas[0], "commands": commands}
    meta.pop("command", None)
    return rows, meta


def write_timing(rows: list[dict[str, Any]], meta: dict[str, Any], out: Path) -> None:
    """Write ``bench_diagnose_timing.md`` and ``.json`` into ``out`` (bar (e), and bars (a)
    and (b) per cohort and pooled per group); with more than one torch thread
    ``bench_diagnose_timing_<n>threads.md``, with diagnose options
    ``bench_diagnose_timing_<key>-<value>.md`` (and ``.json``)."""
    out.mkdir(parents=True, exist_ok=True)
    threads = int(meta["torch_threads"])
    name = "bench_diagnose_timing" + (f"_{threads}threads" if threads > 1 else "")
    # an ablation (--diagnose-option) writes beside the default's report, never over it
    name += "".join(f"_{k}-{v}" for k, v in sorted(meta["diagnose_options"].items()))
    if meta.get("surrogate_error_in_range") is not None:
        name += f"_surrogate-in-range-{meta['surrogate_error_in_range']:g}"
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    lines = [
        "# Missing-effect search: the diagnosis' time per 50 specimens (bar (e), <= 60 s)",
        "",
        "Reproduce: "
        + " and ".join(f"`{c}`" for c in meta.get("commands") or [meta["command"]])
        + " (on a quiet machine: nothing else running).",
        "",
        f"Machine: {meta['machine']}, {os.cpu_count()} cores, {meta['torch_threads']} torch "
        f"threads; load average after the run {', '.join(f'{v:.2f}' for v in load or ())}. "
        "Only `femcal.diagnose.diagnose` is timed, exactly as in `bench_diagnose.md` (same "
        "cohorts, options and seeds: the verdicts are the same); the recalibrations and the "
        "visibility checks of the full benchmark are not run. Options of "
        f"`femcal.diagnose.diagnose` beyond the defaults: {meta['diagnose_options'] or 'none'}"
        + (
            ""
            if meta.get("surrogate_error_in_range") is None
            else "; the surrogate's error inside its trained moments counted as "
            f"{meta['surrogate_error_in_range']:g}° (its growth beyond them kept)"
        )
        + ". "
        "Bars (a) and (b) as in `bench_diagnose.md` (eligible: not `none`, the disc alone "
        "misses by > 2σ). Where the verdict is wrong, the rival that `next_measurement` names "
        "(the close model the fewest measurements settle) may be the true model: counted, and "
        f"in parentheses where at most {PRACTICAL_REPEATS} measurements at the point it names "
        "would settle it; this does not count towards bar (a).",
        "",
        "| cohort | specimens | (a) right / eligible | wrong, the rival named is right "
        "(practical) | (b) `none` given an effect | wall | CPU "
        "| wall per 50 specimens | CPU per 50 | <= 60 s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        a = f"{r['n_right_eligible']}/{r['n_eligible']}" if "n_eligible" in r else "-"
        b = f"{r['n_none_given_effect']}/{r['n_none']}" if "n_none" in r else "-"
        w = (
            f"{r['n_wrong_rival_right']} ({r['n_wrong_rival_right_practical']})"
            if "n_wrong_rival_right" in r
            else "-"
        )
        lines.append(
            f"| {cohort_name(r)} | {r['n_specimens']} | {a} | {w} | {b} | {r['seconds']:.1f} s | "
            f"{r['cpu_seconds']:.1f} s | "
            f"{r['wall_per_50']:.1f} s | {r['cpu_per_50']:.1f} s | "
            f"{_ok(r['wall_per_50'] <= BAR_SECONDS)} |"
        )
    if all("n_eligible" in r for r in rows):
        lines += [
            "",
            "| cohorts | (a) right / eligible | 95 % interval | right, or the rival named is "
            "| (b) `none` given an effect |",
            "|---|---|---|---|---|",
        ]
        for g in pooled(rows):
            k, n = g["a_right"], g["a_eligible"]
            lo, hi = g["a_interval"]
            kr = g["a_right_or_rival"]
            lines.append(
                f"| {g['group']} | {k}/{n} = {_pct(k / n if n else np.nan)} | "
                f"{_pct(lo)}-{_pct(hi)} | "
                f"{'-' if kr is None else f'{kr}/{n} = {_pct(kr / n if n else np.nan)}'} | "
                f"{g['b_none_given_effect']}/{g['b_none']} |"
            )
    (out / f"{name}.md").write_text("\n".join(lines) + "\n")
    (out / f"{name}.json").write_text(
        json.dumps({**meta, "load_average": load, "cohorts": rows}, indent=2) + "\n"
    )
    print(f"wrote {out / name}.md")


def _header(meta: dict[str, Any]) -> list[str]:
    """The title, the commands, the settings and the bars table's head."""
    sur = meta["surrogate_error_deg"]
    pol = meta["moment_policy"]
    return [
        "# Missing-effect search: closed-world and open-world cohorts",
        "",
        "Reproduce: "
        + ", then ".join(f"`{c}`" for c in meta.get("commands") or [meta["command"]])
        + (
            " (this report joins their JSON: `experiments/bench_diagnose.py --from-json ...`)"
            if len(meta.get("commands") or []) > 1
            else ""
        ),
        "",
        f"Machine: {meta['machine']}, {meta['torch_threads']} torch threads. Surrogate: "
        f"{meta['surrogate']}, its error {sur:.4f} deg (sd) in range"
        + (
            f", growing as exp({pol['growth']} L) beyond 1..5 Nm (moment policy)"
            if pol
            else " (one value at every moment)"
        )
        + f", added to the noise ({meta['noise_deg']} deg) in quadrature. "
        + (
            f"Quick run: at most {meta['max_specimens']} specimens per cohort. "
            if meta["max_specimens"]
            else ""
        )
        + (
            f"Ablation: diagnose({', '.join(f'{k}={v!r}' for k, v in opts.items())}). "
            if (opts := meta.get("diagnose_options"))
            else ""
        )
        + "`three` = femcal.effects.planted.make_cohort (femcal's own formulas, 1..5 Nm); "
        "`hidden` = experiments/hidden_cohorts.py (other laws, combinations, an out-of-library "
        "softening, 1..5 / 1.25..5 / 1.25..7.5 Nm protocols); seeds "
        f"{', '.join(map(str, TUNING_SEEDS))} tune, "
        f"seeds {', '.join(map(str, HOLDOUT_SEEDS))} are held out. "
        "`experiments/bench_diagnose.py` wrote this file.",
        "",
        "## The issue's bars",
        "",
        "| cohort | specimens | (a) right where the disc alone misses > 2σ (>= 90 %) | "
        "of which `+unexplained` | (b) `none` given an effect (<= 10 %) | "
        "(d) worst covered class MAE / `none` MAE (<= 1.5) | "
        "(e) diagnosis wall (CPU), per 50 specimens (<= 60 s) | "
        "(a') of (a), where each component of a combination would also be visible alone | "
        "(a'') of (a), where each effect of a combination shows beyond the others | "
        "(a*) of (a), where the true combination is the preferred model | "
        "ceiling of (a): share of (a) where it is |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]


def _bar_rows(rows: list[dict[str, Any]]) -> list[str]:
    """One row of the bars table per cohort."""
    lines: list[str] = []
    for r in rows:
        b, ok = r["bars"], r["bars"]["pass"]
        name = cohort_name(r)
        nan_note = (
            f" ({r['n_recalibrated_nan']} recalibrations NaN)" if r["n_recalibrated_nan"] else ""
        )
        lines.append(
            f"| {name} | {r['n_specimens']} | {r['n_right_eligible']}/{r['n_eligible']} = "
            f"{_pct(b['a_right_eligible'])} {_ok(ok['a'])} | {r['n_extra_unexplained']} | "
            f"{r['n_none_given_effect']}/{r['n_none']} = {_pct(b['b_none_given_effect'])} "
            f"{_ok(ok['b'])} | {b['d_worst_ratio']:.2f}{nan_note} {_ok(ok['d'])} | "
            f"{r['seconds']:.1f} s ({r['cpu_seconds']:.1f} s), {b['e_wall_per_50']:.1f} s "
            f"({b['e_cpu_per_50']:.1f} s) {_ok(ok['e'])} | "
            f"{r['n_right_each_visible']}/{r['n_each_visible']} = "
            f"{_pct(b['a_right_each_visible'])} | "
            f"{r['n_right_identifiable']}/{r['n_identifiable']} = "
            f"{_pct(b['a_right_identifiable'])} | "
            + (
                f"{r['n_right_truth_preferred']}/{r['n_truth_preferred']} = "
                f"{_pct(b['a_right_truth_preferred'])} | "
                f"{r['n_truth_preferred']}/{r['n_eligible']} = {_pct(b['a_ceiling'])} |"
                if "n_truth_preferred" in r
                else "- | - |"
            )
        )
    return lines


def _pooled(rows: list[dict[str, Any]]) -> list[str]:
    """The bars pooled per group of cohorts."""
    lines: list[str] = []
    lines += [
        "",
        "Pooled per group of cohorts, with Wilson 95 % intervals (one cohort's 34-41 eligible "
        "specimens give an interval about ±10 points wide; near ties between a combination and "
        "its stronger effect flip with float rounding, see docs/diagnosis-benchmark.md):",
        "",
        "| cohorts | seeds | (a) right / eligible | 95 % interval | ceiling of (a) | "
        "(b) `none` given an effect | 95 % interval |",
        "|---|---|---|---|---|---|---|",
    ]
    for g in pooled(rows):
        lo, hi = g["a_interval"]
        blo, bhi = g["b_interval"]
        lines.append(
            f"| {g['group']} | {', '.join(map(str, g['seeds']))} | "
            f"{g['a_right']}/{g['a_eligible']} = {_pct(g['a_right'] / max(g['a_eligible'], 1))} | "
            f"{_pct(lo)}-{_pct(hi)} | {_pct(g['ceiling'])} | "
            f"{g['b_none_given_effect']}/{g['b_none']} = "
            f"{_pct(g['b_none_given_effect'] / max(g['b_none'], 1))} | {_pct(blo)}-{_pct(bhi)} |"
        )
    return lines


def _readings() -> list[str]:
    """What the columns (a'), (a'') and (a*) mean."""
    lines: list[str] = []
    lines += [
        "",
        "(a') is not the issue's bar; it separates what the data cannot show from what the "
        "diagnosis misses. A combination's component counts as visible when the disc alone, "
        "calibrated to the specimen's disc with that component only (same noise draw), misses "
        "by > 2σ. Where one component is not visible on its own, disc + the other effect "
        "usually explains the data within the noise and the smaller model wins any criterion.",
        "(a'') is not the issue's bar either: a combination counts only when the library's model "
        "with the other true effects, calibrated to the specimen's own data, still misses by "
        "> 2σ for each of its effects (the eligibility of (a), applied to what the other effects "
        "leave).",
        "(a*) is not the issue's bar either, but it is the ceiling the data allow any criterion "
        "that prefers the better model by the diagnosis' criterion (BIC `chi^2 + k ln n` by "
        "default, AIC `chi^2 + 2k` with `criterion='aic'`): every model the "
        "diagnosis could name (the disc alone, each effect, each pair, the triple) is "
        "calibrated to each combination specimen with a thorough `pgd` (`THOROUGH`: 32 nearest "
        "starts, every effect start kept to the end, 5 rounds, 40 iterations) and scored "
        "by that criterion with the same σ; a combination counts only where it scores the "
        "lowest. The last column is the share of the eligible specimens where that holds "
        "(every single effect and out-of-library specimen counts): bar (a) cannot pass where it "
        "is below 90 %, whatever the search.",
        "",
    ]
    return lines


def _per_class(rows: list[dict[str, Any]]) -> list[str]:
    """Per cohort and class: verdicts and errors; the found effects."""
    lines: list[str] = []
    lines += [
        "## Per class: verdicts, disc-alone MAE, MAE recalibrated with the found effects",
        "",
        "Recalibrated = `calibrate(EffectModel(base, found))` over the whole cohort, found = every "
        "registered effect named by any verdict of the cohort; ratio = the class' recalibrated "
        "MAE over that of `none` (bar (d) on the classes the library covers); discrepancy = MAE "
        "of the diagnosis' final model + its GP discrepancy (reported for the out-of-library "
        "class).",
        "",
        "| cohort | class | n | eligible (> 2σ) | right (eligible) | right (each component "
        "visible) | right (all) | disc alone MAE | recalibrated MAE | ratio to `none` | "
        "discrepancy fit MAE |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        for c, v in r["per_class"].items():
            ratio = f"{v['ratio_to_none']:.2f}" + ("" if v["covered"] or c == NONE else " (n/c)")
            dm = "–" if v["discrepancy_mae"] is None else f"{v['discrepancy_mae']:.4f}"
            lines.append(
                f"| {r['kind']} {r['seed']} | {c} | {v['n']} | {v['n_eligible']} | "
                f"{v['right_eligible']}/{v['n_eligible']} | "
                f"{v['right_each_visible']}/{v['n_each_visible']} | {v['right']}/{v['n']} | "
                f"{v['disc_mae']:.4f} | {v['recalibrated_mae']:.4f}"
                + (f" ({v['recalibrated_nan']} NaN)" if v["recalibrated_nan"] else "")
                + f" | {ratio} | {dm} |"
            )
    lines += [
        "",
        "Found effects per cohort: "
        + "; ".join(
            f"{r['kind']} {r['seed']}: {', '.join(r['found_effects']) or 'none'}" for r in rows
        ),
        "",
    ]
    return lines


def _confusion(rows: list[dict[str, Any]]) -> list[str]:
    """Per cohort: truth against verdict."""
    lines: list[str] = []
    lines += ["## Confusion (rows truth, columns verdict)", ""]
    for r in rows:
        verdicts = sorted({v for row in r["confusion"].values() for v in row})
        lines += [
            f"Cohort {r['kind']} {r['seed']}:",
            "",
            "| truth \\ verdict | " + " | ".join(verdicts) + " |",
            "|---" * (len(verdicts) + 1) + "|",
        ]
        for t, row in r["confusion"].items():
            lines.append(f"| {t} | " + " | ".join(str(row.get(v, 0)) for v in verdicts) + " |")
        lines.append("")
    return lines


def _per_protocol(rows: list[dict[str, Any]]) -> list[str]:
    """Per hidden cohort and protocol: bars (a) and (b)."""
    lines: list[str] = []
    if any(r["kind"] == "hidden" for r in rows):
        lines += [
            "## Per protocol (hidden cohorts)",
            "",
            "| cohort | protocol | right (eligible) | `none` given an effect |",
            "|---|---|---|---|",
        ]
        for r in rows:
            if r["kind"] != "hidden":
                continue
            for p in PROTOCOLS:
                if p in r["per_protocol"]:
                    v = r["per_protocol"][p]
                    lines.append(
                        f"| {r['seed']} | {p} | {v['right_eligible']}/{v['n_eligible']} | "
                        f"{v['none_given_effect']}/{v['n_none']} |"
                    )
        lines.append("")
    return lines


def _per_load_case(rows: list[dict[str, Any]]) -> list[str]:
    """Per cohort and model: the error per load case."""
    lines: list[str] = []
    lines += ["## Error per load case (whole cohort)", ""]
    lines += ["| cohort | model | " + " | ".join(LOAD_CASES) + " |", "|---|---" + "|---" * 4 + "|"]
    for r in rows:
        for name, vals in r["per_load_case"].items():
            lines.append(
                f"| {r['kind']} {r['seed']} | {name} | "
                + " | ".join(f"{vals[lc]:.4f}" for lc in LOAD_CASES)
                + " |"
            )
    return lines


def _parameters(rows: list[dict[str, Any]]) -> list[str]:
    """Effect parameters against the planted truth (three-class cohorts)."""
    lines: list[str] = []
    lines += ["", "## Effect parameters +- sd (three-class cohorts, right verdicts)", ""]
    lines += [
        "| cohort | parameter | n | within 2 sd | median sd | median abs. error |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        pf = pd.DataFrame(r["parameters"])
        if not len(pf):
            continue
        for name, g in pf.groupby("parameter", sort=False):
            lines.append(
                f"| {r['kind']} {r['seed']} | {name} ({g['unit'].iloc[0]}) | {len(g)} | "
                f"{g['within_2sd'].mean():.0%} | {g['sd'].median():.3g} | "
                f"{(g['value'] - g['truth']).abs().median():.3g} |"
            )
    return lines


def write(rows: list[dict[str, Any]], meta: dict[str, Any], out: Path) -> None:
    """Write ``bench_diagnose.md`` and ``bench_diagnose.json`` into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    lines = _header(meta) + _bar_rows(rows) + _pooled(rows) + _readings()
    lines += _per_class(rows) + _confusion(rows) + _per_protocol(rows)
    lines += _per_load_case(rows) + _parameters(rows)
    (out / "bench_diagnose.md").write_text("\n".join(lines) + "\n")
    (out / "bench_diagnose.json").write_text(
        json.dumps({**meta, "cohorts": rows}, indent=2, default=float)
    )
    print("\n".join(lines))
