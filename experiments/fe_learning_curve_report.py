"""The report of :mod:`experiments.bench_fe_learning_curve`: its figure and Markdown tables."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from femcal.schema import LOAD_CASES

#: The bands of the targets and the study's band (as in experiments.bench_fe_learning_curve).
BANDS = ("0.5-5", "5.5-10")
STUDY_BAND = ("1-5",)


def figure(figures: dict[str, Any], path: Path) -> None:
    """Log-log held-out MAE against training configurations: both recipes (mean over the
    repeats, their range shaded), both bands, the power laws and the study's curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11.5, 5.6))
    ext, curves = figures["extrapolation"], figures["curves"]
    n_hi = max(max(e["n_target"], e["n_target_last_two"]) for e in ext.values())
    grid = np.geomspace(48, 1.3 * (min(max(n_hi, 2048), 2e4) if math.isfinite(n_hi) else 2048))
    for band, colour in (("0.5-5", "tab:blue"), ("5.5-10", "tab:red")):
        for name, style in (("fe", "-o"), ("root", "--s")):
            pts = curves.get(name, {}).get(band, [])
            n, label = [p["n"] for p in pts], f"{figures['recipes'][name]['label']}, {band} Nm"
            ax.plot(n, [p["mean"] for p in pts], style, color=colour, ms=6, label=label)
            if name == "fe" and pts and max(p["repeats"] for p in pts) > 1:
                lo, hi = [p["min"] for p in pts], [p["max"] for p in pts]
                ax.fill_between(n, lo, hi, color=colour, alpha=0.15)
        e = ext[band]
        label = f"power law {band} Nm: {e['a']:.3g}·n^-{e['b']:.2f}"
        ax.plot(grid, e["a"] * grid ** -e["b"], ":", color=colour, lw=1.3, label=label)
        last = grid[grid >= curves["fe"][band][-1]["n"]]
        label = f"last doubling {band} Nm: n^-{e['b_last_two']:.2f}"
        y = e["a_last_two"] * last ** -e["b_last_two"]
        ax.plot(last, y, "-.", color=colour, lw=0.9, alpha=0.7, label=label)
        phys = figures.get("physiological", {}).get(band)
        if phys:
            label = (
                f"FE recipe, {band} Nm, the {figures['physiological']['n_configurations']} "
                f"held-out discs < {figures['physiological']['rom_deg_below']:g}°"
            )
            ax.plot(phys["n"], phys["mae_deg"], ":o", color=colour, ms=3, lw=1, label=label)
        ax.axhline(e["target_deg"], color=colour, lw=0.8, alpha=0.6)
        if e["n_target"] <= grid[-1]:
            xy = (e["n_target"], e["target_deg"])
            ax.plot(*xy, "x", color=colour, ms=9, mew=2)
            text = f"{band} Nm target {e['target_deg']:g}°: n ≈ {e['n_target']:,.0f}"
            ax.annotate(
                text,
                xy,
                textcoords="offset points",
                xytext=(-8, 6),
                ha="right",
                color=colour,
                fontsize=8,
            )
    s, fe15 = figures["study_curve"], curves["fe"]["1-5"]
    label = "reference study, 1-5 Nm (Small 128, Large 1024)"
    ax.plot([p["n"] for p in s], [p["mae_deg"] for p in s], "-^", color="0.35", label=label)
    label = "FE recipe, 1-5 Nm (the study's band)"
    ax.plot([p["n"] for p in fe15], [p["mean"] for p in fe15], "-.", color="0.35", label=label)
    ax.set(
        xscale="log",
        yscale="log",
        ylabel="held-out MAE against FE (°)",
        xlabel="training configurations (nested subsets of the FE Large split)",
    )
    ax.set_title(
        f"FE surrogate: held-out MAE on {figures['n_heldout']} FE configurations "
        f"(members: {figures['members']}; mean of {figures['repeats']} subsets)",
        fontsize=10,
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7.5, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130, bbox_inches="tight")
    plt.close(fig)


def markdown(figures: dict[str, Any]) -> str:
    """The run's tables: one row per recipe, n and repeat; the power laws."""
    lines = [
        "# The FE surrogate's learning curve",
        "",
        f"`{figures['command']}`",
        "",
        f"Held out: {figures['n_heldout']} configurations (Small + Test), "
        f"{figures['n_heldout_points']} FE points. MAE in degrees.",
        "",
        "| recipe | n (fitted + val) | repeat | 0.5-5 Nm | 5.5-10 Nm | 1-5 Nm | "
        + " | ".join(f"{c} 0.5-5 / 5.5-10" for c in LOAD_CASES)
        + " | epochs | CPU s |",
        "| --- " * (8 + len(LOAD_CASES)) + "|",
    ]
    for p in figures["points"]:
        b = p["bands"]
        cells = [
            f"{b['0.5-5']['load_cases'][c]:.3f} / {b['5.5-10']['load_cases'][c]:.3f}"
            for c in LOAD_CASES
        ]
        lines.append(
            f"| {p['recipe']} | {p['n_train']} ({p['n_fitted']} + {p['n_validation']}) | "
            f"{p.get('repeat', 0)} | {b['0.5-5']['mae_deg']:.3f} | {b['5.5-10']['mae_deg']:.3f} | "
            f"{b['1-5']['mae_deg']:.3f} | "
            + " | ".join(cells)
            + f" | {p['epochs']} | {p['cpu_seconds']:.0f} |"
        )
    lines += [
        "",
        "Mean over the repeats (min-max):",
        "",
        "| recipe | n | 0.5-5 Nm | 5.5-10 Nm | 1-5 Nm | " + " | ".join(LOAD_CASES) + " |",
        "| --- " * 9 + "|",
    ]
    for name in figures["recipes"]:
        for n in sorted({p["n_train"] for p in figures["points"] if p["recipe"] == name}):
            pts = [p for p in figures["points"] if p["recipe"] == name and p["n_train"] == n]
            v = [[p["bands"][b]["mae_deg"] for p in pts] for b in (*BANDS, *STUDY_BAND)]
            cells = [f"{np.mean(x):.3f} ({min(x):.3f}-{max(x):.3f})" for x in v[:2]]
            cells += [f"{np.mean(v[2]):.3f}"] + [
                " / ".join(
                    f"{np.mean([p['bands'][b]['load_cases'][c] for p in pts]):.3f}" for b in BANDS
                )
                for c in LOAD_CASES
            ]
            lines.append(f"| {name} | {n} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "| band | a | b | target | n at target | b, last two n | n at target, last two n |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for band, e in figures["extrapolation"].items():
        lines.append(
            f"| {band} Nm | {e['a']:.3g} | {e['b']:.3f} | {e['target_deg']:g}° | "
            f"{e['n_target']:.0f} | {e['b_last_two']:.3f} | {e['n_target_last_two']:.0f} |"
        )
    lines += [
        "",
        "| band | load case | MAE at the largest n | target (1.5 x the band's) | b | n at target "
        "| b, last two n | n at target, last two n |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for band, cases in figures["load_case_extrapolation"].items():
        for case, e in cases.items():
            lines.append(
                f"| {band} Nm | {case} | {e['mae_deg_at_largest_n']:.3f}° | "
                f"{e['target_deg']:.2f}° | {e['b']:.3f} | {e['n_target']:.0f} | "
                f"{e['b_last_two']:.3f} | {e['n_target_last_two']:.0f} |"
            )
    phys = figures.get("physiological")
    if phys:
        lines += [
            "",
            f"The {phys['n_configurations']} held-out configurations with RoM below "
            f"{phys['rom_deg_below']:g}° up to {phys['up_to_nm']:g} Nm:",
            "",
            "| band | MAE by n | b | n at target | b, last two n | n at target, last two n |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for band in BANDS:
            e = phys[band]
            maes = ", ".join(f"{n}: {v:.3f}" for n, v in zip(e["n"], e["mae_deg"]))
            lines.append(
                f"| {band} Nm | {maes} | {e['b']:.3f} | {e['n_target']:.0f} | "
                f"{e['b_last_two']:.3f} | {e['n_target_last_two']:.0f} |"
            )
    for band, w in figures.get("where", {}).items():
        rho = ", ".join(f"{k} {v:+.2f}" for k, v in w["spearman"].items() if abs(v) >= 0.25)
        lines.append(
            f"\n{band} Nm at n = {w['n_train']}: median configuration "
            f"{w['median_configuration_mae_deg']:.3f}°, worst 6 carry {w['top_6_share']:.0%}; "
            f"Spearman |rho| >= 0.25: {rho}"
        )
    return "\n".join(lines) + "\n"
