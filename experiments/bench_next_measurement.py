"""Benchmark: follow *what to measure next*, and see whether it settles the question.

Issue 11, item 6: where two explanations are close, the diagnosis names the measurement that
would settle it, and how many measurements there (``next_measurement``: load case, moment,
``repeats_to_settle``). This benchmark takes the diagnosis at its word on the hidden cohorts of
:mod:`experiments.hidden_cohorts` (laws unlike femcal's): for every specimen whose suggestion
needs at most ``--max-repeats`` measurements, it draws that many from the hidden truth at that
point (the generator's own laws at that moment, Gaussian noise of the cohort's sd, seeded per
specimen), adds them to the specimen's measurements as ``femcal``'s reader does with repeated
rows (their mean, of weight ``k``), and diagnoses the specimen again, alone, with and without
them (alone both times: a batch of other specimens changes the fits' floating-point
reductions).

Per specimen it reports the criterion gap between the two models (the rival's minus the
chosen's) before and after, whether the question is settled (the two ``min_delta`` apart, or
one of them no longer among the models fitted), whether the model the data then prefer is the
truth, and the verdict before and after.

Writes ``bench_next_measurement.md`` and ``.json`` into ``--out`` (default
``experiments/results/bench_next_measurement/``).

Usage (from the project root, after ``make repro``)::

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_next_measurement \\
        --seeds 0,1,2025,4711 [--holdout] [--max-repeats 10]
"""

from __future__ import annotations

import argparse
import json
import platform
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from experiments.common import RESULTS, reproduce_command
from experiments.diagnosis import (
    hidden_cohort,
    hidden_seeds,
    judge,
    named_effects,
    named_effects_of,
    run_diagnosis,
    setup,
)
from experiments.hidden_cohorts import COMPONENTS, make_hidden_cohort, specimen_curves
from femcal.diagnose.report import PRACTICAL_REPEATS
from femcal.schema import LOAD_CASES


def components_of(row: pd.Series) -> dict[str, dict[str, float | str]]:
    """A hidden specimen's components (law and parameters) from its truth row."""
    out: dict[str, dict[str, float | str]] = {}
    for c in COMPONENTS[row["class"]]:
        out[c] = {
            k[len(c) + 1 :]: v
            for k, v in row.items()
            if k.startswith(c + "_") and not (isinstance(v, float) and np.isnan(v))
        }
    return out


def one_specimen(cohort: dict[str, Any], i: int, extra: tuple[int, float, float, int] | None):
    """Specimen ``i`` of ``cohort`` alone, with ``extra`` = (load case, moment, mean of the
    new measurements, their number) added as one point of that weight."""
    moments = cohort["moments"]
    rom = cohort["rom_deg"][i : i + 1]
    weight = np.ones_like(rom)
    if extra is not None:
        j, m, value, k = extra
        moments = np.union1d(moments, [m])
        col = int(np.searchsorted(moments, m))
        grow = np.full((1, 4, len(moments)), np.nan)
        keep = np.searchsorted(moments, cohort["moments"])
        grow[..., keep] = rom
        if np.isfinite(grow[0, j, col]):  # the point was measured already: pool them
            value = (grow[0, j, col] + k * value) / (k + 1)
            k += 1
        grow[0, j, col] = value
        rom = grow
        weight = np.ones_like(rom)
        weight[0, j, col] = k
    keep = np.isfinite(rom).any(axis=(0, 1))
    return {
        **cohort,
        "specimens": [cohort["specimens"][i]],
        "moments": moments[keep],
        "rom_deg": rom[..., keep],
        "point_weight": weight[..., keep],
    }


def gap_between(diag, pair: Sequence[str]) -> float | None:
    """The criterion of ``pair[1]`` minus that of ``pair[0]`` in the specimen's ranking (None
    when one of them was not fitted)."""
    crit = {r["effect"]: r["criterion"] for r in diag.specimens[0].ranking}
    if pair[0] not in crit or pair[1] not in crit:
        return None
    return float(crit[pair[1]] - crit[pair[0]])


def is_right(diag, expected: frozenset[str], out_of_library: bool) -> bool:
    """Is the verdict of a one-specimen diagnosis right (bar (a)'s judgement)?"""
    one = diag.specimens[0]
    return bool(judge(one.verdict, named_effects(one), expected, out_of_library)[0])


def follow(
    seed: int, ctx: dict[str, Any], max_repeats: int, repeats: int | None = None
) -> list[dict[str, Any]]:
    """Every specimen of hidden cohort ``seed`` with a suggestion of at most ``max_repeats``
    measurements: the diagnosis alone before and after taking them. With ``repeats``, every
    specimen with a suggestion, that many measurements at its point (whatever the
    suggestion's own count: does "no practical measurement settles it" hold?)."""
    fe_moments, fe_rom = ctx["fe_moments"], ctx["fe_rom"]
    noise = float(ctx["plant"]["noise_deg"])
    cohort = hidden_cohort(seed, fe_moments, fe_rom, noise)
    clean = make_hidden_cohort(fe_moments, fe_rom, seed=seed, noise_deg=noise).clean_deg
    diag, *_ = run_diagnosis(cohort, ctx)
    rows = []
    for i, s in enumerate(diag.specimens):
        n = s.next_measurement
        promised = None if not n else n.get("repeats_to_settle")
        k = promised if repeats is None or not n else repeats
        if k is None or (repeats is None and k > max_repeats):
            continue
        truth = cohort["truth"].iloc[i]
        comps = components_of(truth)
        cfg = int(truth["config_id"])
        # the truth rebuilt from the truth table reproduces the cohort's own curves
        ok = np.isfinite(clean[i])
        again = specimen_curves(comps, fe_moments, fe_rom[cfg], cohort["moments"])
        assert np.allclose(again[ok], clean[i][ok], atol=1e-6), (seed, s.specimen)
        j, m = LOAD_CASES.index(n["load_case"]), float(n["moment_nm"])
        true_value = float(specimen_curves(comps, fe_moments, fe_rom[cfg], np.array([m]))[j, 0])
        draws = true_value + np.random.default_rng([seed, i]).normal(0.0, noise, k)
        before, *_ = run_diagnosis(one_specimen(cohort, i, None), ctx)
        after, *_ = run_diagnosis(one_specimen(cohort, i, (j, m, float(draws.mean()), k)), ctx)
        pair = n["between"]
        expected, ool = cohort["expected"][i], bool(cohort["out_of_library"][i])
        g0, g1 = gap_between(before, pair), gap_between(after, pair)
        settled = g1 is None or abs(g1) >= ctx["min_delta"]
        preferred = None if g1 is None else pair[0] if g1 > 0 else pair[1]
        rows.append(
            {
                "seed": seed,
                "specimen": s.specimen,
                "class": str(cohort["labels"][i]),
                "protocol": str(cohort["protocol"][i]),
                "between": list(pair),
                "truth_in_pair": (not ool)
                and any(set(named_effects_of(p)) == set(expected) for p in pair),
                "load_case": n["load_case"],
                "moment_nm": m,
                "repeats": int(k),
                "repeats_to_settle": promised,
                "difference_sigma": float(n["difference_sigma"]),
                "gap_cohort": float(n["criterion_gap"]),
                "gap_before": g0,
                "gap_after": g1,
                "settled": bool(settled),
                "preferred_after": preferred,
                "preferred_is_truth": preferred is not None
                and not ool
                and set(named_effects_of(preferred)) == set(expected),
                "verdict_cohort": s.verdict,
                "verdict_before": before.specimens[0].verdict,
                "verdict_after": after.specimens[0].verdict,
                "right_before": is_right(before, expected, ool),
                "right_after": is_right(after, expected, ool),
            }
        )
        print(
            f"  {s.specimen} ({rows[-1]['class']}): {pair[0]} vs {pair[1]}, {k}x "
            f"{n['load_case']} at {m:.3g} Nm: gap {g0} -> {g1}",
            flush=True,
        )
    return rows


def write(rows: list[dict[str, Any]], meta: dict[str, Any], out: Path) -> None:
    """``bench_next_measurement.md`` / ``.json`` (with ``--repeats N``:
    ``bench_next_measurement_repeats-N``)."""
    out.mkdir(parents=True, exist_ok=True)
    name = "bench_next_measurement" + (
        f"_repeats-{meta['repeats']}" if meta["repeats"] is not None else ""
    )
    (out / f"{name}.json").write_text(json.dumps({**meta, "specimens": rows}, indent=2) + "\n")

    def fmt(g: float | None) -> str:
        return "not fitted" if g is None else f"{g:+.1f}"

    def settled(g: float | None) -> bool:
        return g is not None and abs(g) >= meta["min_delta"]

    def prefers_truth(r: dict[str, Any], gap: float | None) -> bool:
        """Is the model of the pair that ``gap`` prefers the true one?"""
        if gap is None:
            return False
        preferred = r["between"][0] if gap > 0 else r["between"][1]
        return set(named_effects_of(preferred)) == set(named_effects_of(r["class"]))

    def toward_truth(r: dict[str, Any]) -> bool | None:
        """Did the new points move the gap towards the true model of the pair?"""
        if not r["truth_in_pair"] or r["gap_before"] is None or r["gap_after"] is None:
            return None
        chosen_is_truth = set(named_effects_of(r["between"][0])) == set(
            named_effects_of(r["class"])
        )
        moved = r["gap_after"] - r["gap_before"]
        return moved > 0 if chosen_is_truth else moved < 0

    how = (
        f"{meta['repeats']} measurements at every suggested point, whatever the diagnosis "
        "said of them"
        if meta["repeats"] is not None
        else f"suggestions of at most {meta['max_repeats']} measurements, as many as they say"
    )
    lines = [
        "# What to measure next, followed (issue 11, item 6)",
        "",
        f"Reproduce: `{meta['command']}`. Surrogate {meta['surrogate']}; noise "
        f"{meta['noise_deg']}°; `min_delta` {meta['min_delta']:g}; {how}; hidden cohorts "
        f"{meta['seeds']}.",
        "",
        "The measurements were drawn from the hidden truth at the suggested point and the "
        "specimen diagnosed again, alone, with them (their mean, of weight k, as femcal reads "
        "repeated rows) and without. Gap: the rival's criterion minus the chosen model's "
        "(positive: the chosen is preferred); settled: the two at least `min_delta` apart "
        "afterwards (or the rival no longer fitted).",
        "",
        "| what the diagnosis said | followed | settled before (alone) | settled after | "
        "pair holds the truth | gap moved towards it | the truth preferred, before → after | "
        "verdict right before → after |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    groups = {
        "settles within its count": [r for r in rows if r["repeats_to_settle"] is not None],
        "no number of measurements settles it": [r for r in rows if r["repeats_to_settle"] is None],
    }
    for label, rs in groups.items():
        if not rs:
            continue
        pair = [r for r in rs if r["truth_in_pair"]]
        lines.append(
            f"| {label} | {len(rs)} | "
            f"{sum(settled(r['gap_before']) for r in rs)} | "
            f"{sum(r['settled'] for r in rs)} | {len(pair)} | "
            f"{sum(bool(toward_truth(r)) for r in pair)} | "
            f"{sum(prefers_truth(r, r['gap_before']) for r in pair)} → "
            f"{sum(prefers_truth(r, r['gap_after']) for r in pair)} | "
            f"{sum(r['right_before'] for r in rs)} → {sum(r['right_after'] for r in rs)} |"
        )
    lines += [
        "",
        "| cohort | specimen | truth | chosen vs rival | measure | it said | gap in the cohort | "
        "alone, before | after | settled | preferred after | verdict before → after |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        said = "never" if r["repeats_to_settle"] is None else f"{r['repeats_to_settle']}x"
        lines.append(
            f"| {r['seed']} | {r['specimen']} | {r['class']} | {r['between'][0]} vs "
            f"{r['between'][1]} | {r['repeats']}x {r['load_case']} at {r['moment_nm']:.3g} Nm "
            f"({r['difference_sigma']:.1f}σ) | {said} | {r['gap_cohort']:+.1f} | "
            f"{fmt(r['gap_before'])} | {fmt(r['gap_after'])} | "
            f"{'yes' if r['settled'] else 'no'} | "
            f"{r['preferred_after'] or '-'}{' (truth)' if r['preferred_is_truth'] else ''} | "
            f"{r['verdict_before']} → {r['verdict_after']} |"
        )
    (out / f"{name}.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / name}.md")


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="0,1,2025,4711", help="hidden cohorts")
    ap.add_argument("--holdout", action="store_true", help="allow the held-out seeds")
    ap.add_argument(
        "--max-repeats",
        type=int,
        default=PRACTICAL_REPEATS,
        help="follow suggestions of at most this many measurements (default: the practical "
        f"number of femcal.diagnose.report, {PRACTICAL_REPEATS})",
    )
    ap.add_argument(
        "--repeats",
        type=int,
        default=None,
        help="take this many measurements at every suggested point instead (also where the "
        "diagnosis says no number of them settles it): is that so?",
    )
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_next_measurement")
    ap.add_argument(
        "--from-json",
        type=Path,
        action="append",
        default=[],
        metavar="PATH",
        help="join earlier runs' JSON files (repeatable, same settings) into one report",
    )
    args = ap.parse_args(argv)
    if args.from_json:
        runs = [json.loads(f.read_text()) for f in args.from_json]
        meta = {k: v for k, v in runs[0].items() if k != "specimens"}
        meta["command"] = "` and `".join(r["command"] for r in runs)
        meta["seeds"] = [s for r in runs for s in r["seeds"]]
        write([row for r in runs for row in r["specimens"]], meta, args.out)
        return
    seeds = hidden_seeds(ap, args.seeds, args.holdout)
    torch.manual_seed(0)
    ctx = setup()
    rows = []
    for seed in seeds:
        print(f"hidden seed {seed} ...", flush=True)
        rows += follow(seed, ctx, args.max_repeats, args.repeats)
    command = reproduce_command("bench_next_measurement", argv)
    meta = {
        "command": command,
        "machine": platform.processor() or platform.machine(),
        "surrogate": ctx["surrogate_name"],
        "noise_deg": ctx["plant"]["noise_deg"],
        "min_delta": ctx["min_delta"],
        "max_repeats": args.max_repeats,
        "repeats": args.repeats,
        "seeds": seeds,
    }
    write(rows, meta, args.out)


if __name__ == "__main__":
    main()
