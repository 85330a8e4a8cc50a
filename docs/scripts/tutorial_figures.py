"""The tutorial's figures and tables, from the pipeline's outputs (docs/tutorial.md).

Reads what ``dvc repro`` (or ``dvc pull``) leaves in the project:

* ``data/planted/measurements.csv`` and ``truth.csv`` (stage ``plant``);
* ``reports/diagnosis/diagnosis.json``, ``residuals.csv`` and ``plots/`` (stage ``diagnose``);
* ``reports/calibration/planted/metrics.csv`` and ``plots/`` (stage ``calibrate@planted``);

and writes into ``docs/figures/`` (``--out FOLDER`` elsewhere; not committed: they derive
from the study's data):

* ``tutorial-cohort.png``: one specimen of each planted class, four load cases;
* ``tutorial-residuals.png``: the disc model's RMS residual / sigma per specimen and load case;
* ``tutorial-specimen.png``: the diagnosis' own figure of one specimen with an effect;
* ``tutorial-calibration.png``: the recalibration's own figure of that specimen (``plots/``);
* ``tutorial-before-after.png``: each specimen's MAE, disc alone and with the found effects;
* ``tutorial-verdicts.md`` and ``tutorial-before-after.md``: the tables the page includes.

Run it from anywhere: ``.venv/bin/python docs/scripts/tutorial_figures.py [--out FOLDER]``
(a relative ``FOLDER`` starts at the current folder). Where the
pipeline's outputs are absent (a fresh clone), it says which and exits 0: the page then shows
how to make the figures instead; with ``--require`` it exits 1 (CI runs ``make repro`` first
and regenerates the figures with ``--require``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: Where the figures go without ``--out``.
OUT = ROOT / "docs" / "figures"
PLANTED = ROOT / "data" / "planted"
DIAGNOSIS = ROOT / "reports" / "diagnosis"
CALIBRATION = ROOT / "reports" / "calibration" / "planted"
NEEDED = {
    "plant": [PLANTED / "measurements.csv", PLANTED / "truth.csv"],
    "diagnose": [DIAGNOSIS / "diagnosis.json", DIAGNOSIS / "residuals.csv"],
    "calibrate@planted": [CALIBRATION / "metrics.csv"],
}
LOAD_CASES = ("Flexion", "Extension", "LateralBending", "AxialRotation")
CLASSES = ("none", "facet_contact", "ligament_tension", "neutral_zone")
COLOURS = dict(zip(CLASSES, ("0.35", "tab:blue", "tab:orange", "tab:green")))


def missing_outputs() -> list[str]:
    return [
        f"{stage}: {path.relative_to(ROOT)}"
        for stage, paths in NEEDED.items()
        for path in paths
        if not path.is_file()
    ]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def cohort_figure(measured, truth, out: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 4, figsize=(12, 3.2), sharey=False)
    for effect in CLASSES:
        specimen = truth.loc[truth["effect"] == effect, "specimen"].iloc[0]
        rows = measured[measured["specimen"] == specimen]
        for ax, lc in zip(axes, LOAD_CASES):
            r = rows[rows["load_case"] == lc].sort_values("moment_nm")
            ax.plot(r["moment_nm"], r["rom_deg"], "o-", ms=3, color=COLOURS[effect],
                    label=f"{specimen}: {effect}")
    for ax, lc in zip(axes, LOAD_CASES):
        ax.set_title(lc)
        ax.set_xlabel("moment (Nm)")
    axes[0].set_ylabel("RoM (deg)")
    axes[-1].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "tutorial-cohort.png", dpi=90)
    plt.close(fig)


def residual_figure(residuals, truth, out: Path) -> None:
    import numpy as np

    plt = _plt()
    order = truth.assign(k=truth["effect"].map({c: i for i, c in enumerate(CLASSES)}))
    order = order.sort_values(["k", "specimen"])
    rms = (
        residuals.assign(z2=residuals["residual_sigma"] ** 2)
        .groupby(["specimen", "load_case"])["z2"].mean().pow(0.5).unstack("load_case")
        .reindex(index=order["specimen"], columns=list(LOAD_CASES))
    )
    fig, ax = plt.subplots(figsize=(12, 2.8))
    im = ax.imshow(rms.to_numpy().T, aspect="auto", cmap="magma_r",
                   vmin=0, vmax=max(4.0, float(np.nanpercentile(rms.to_numpy(), 95))))
    ax.set_yticks(range(4), LOAD_CASES)
    ax.set_xticks(range(len(rms)), rms.index, rotation=90, fontsize=6)
    edges = np.cumsum(order["effect"].value_counts().reindex(CLASSES).fillna(0).to_numpy())
    start = 0
    for effect, end in zip(CLASSES, edges):
        if end > start:
            ax.axvline(end - 0.5, color="white", lw=2)
            ax.text((start + end - 1) / 2, -0.8, effect, ha="center", fontsize=8)
        start = end
    fig.colorbar(im, ax=ax, label="RMS residual / sigma")
    fig.tight_layout()
    fig.savefig(out / "tutorial-residuals.png", dpi=90)
    plt.close(fig)


def verdict_table(diagnosis, truth) -> str:
    import pandas as pd

    verdicts = pd.DataFrame({"specimen": [d["specimen"] for d in diagnosis],
                             "verdict": [d["verdict"] for d in diagnosis]})
    joined = truth[["specimen", "effect"]].merge(verdicts, on="specimen")
    table = pd.crosstab(joined["effect"], joined["verdict"]).reindex(
        [c for c in CLASSES if c in set(joined["effect"])]
    )
    cols = list(table.columns)
    lines = ["| planted effect | " + " | ".join(f"`{c}`" for c in cols) + " |",
             "| --- |" + " --- |" * len(cols)]
    for effect, row in table.iterrows():
        lines.append(f"| `{effect}` | " + " | ".join(str(int(v)) for v in row) + " |")
    right = int((joined["effect"] == joined["verdict"]).sum())
    lines += ["", f"Verdict equal to the planted effect: {right} of {len(joined)} specimens."]
    return "\n".join(lines) + "\n"


def before_after(diagnosis, metrics, truth):
    import pandas as pd

    before = pd.DataFrame({"specimen": [d["specimen"] for d in diagnosis],
                           "disc_alone": [d["baseline_mae_deg"] for d in diagnosis]})
    after = metrics[["specimen", "mae_deg"]].rename(columns={"mae_deg": "with_effects"})
    both = truth[["specimen", "effect"]].merge(before, on="specimen").merge(after, on="specimen")
    both["specimen"] = both["specimen"].astype(str)
    return both


def before_after_figure(both, out: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    for effect in CLASSES:
        rows = both[both["effect"] == effect]
        ax.scatter(rows["disc_alone"], rows["with_effects"], s=18, color=COLOURS[effect],
                   label=effect)
    top = float(max(both["disc_alone"].max(), both["with_effects"].max())) * 1.05
    ax.plot([0, top], [0, top], "k:", lw=1, label="no change")
    ax.set_xlim(0, top)
    ax.set_ylim(0, top)
    ax.set_xlabel("MAE, disc alone (deg)")
    ax.set_ylabel("MAE, disc + found effects (deg)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "tutorial-before-after.png", dpi=90)
    plt.close(fig)


def before_after_table(both) -> str:
    grouped = both.groupby("effect")[["disc_alone", "with_effects"]].mean()
    grouped = grouped.reindex([c for c in CLASSES if c in grouped.index])
    lines = ["| planted effect | specimens | MAE disc alone (°) | MAE disc + found effects (°) |",
             "| --- | --- | --- | --- |"]
    for effect, row in grouped.iterrows():
        n = int((both["effect"] == effect).sum())
        lines.append(f"| `{effect}` | {n} | {row['disc_alone']:.3f} | {row['with_effects']:.3f} |")
    return "\n".join(lines) + "\n"


def specimen_figure(diagnosis, out: Path) -> None:
    """Copy the diagnosis' figure of the first specimen given a single registered effect, and
    the recalibration's figure of the same specimen (when calibrate@planted drew it)."""
    plots = DIAGNOSIS / "plots"
    for effect in CLASSES[1:]:
        for d in diagnosis:
            path = plots / f"{d['specimen']}.png"
            if d["verdict"] == effect and path.is_file():
                shutil.copyfile(path, out / "tutorial-specimen.png")
                calibrated = CALIBRATION / "plots" / path.name
                if calibrated.is_file():
                    shutil.copyfile(calibrated, out / "tutorial-calibration.png")
                return


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out",
        type=Path,
        default=OUT,
        help=f"folder of the figures and tables (default: {OUT.relative_to(ROOT)})",
    )
    parser.add_argument(
        "--require",
        action="store_true",
        help="exit 1 when the pipeline's outputs are absent (default: say so and exit 0)",
    )
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out = args.out
    missing = missing_outputs()
    if missing:
        print("tutorial_figures: the pipeline's outputs are not here, so no figures were made:")
        for line in missing:
            print(f"  - {line}")
        print("Run `dvc repro` (or `dvc pull`) first; docs/tutorial.md builds without them.")
        return 1 if args.require else 0
    import pandas as pd

    out.mkdir(parents=True, exist_ok=True)
    measured = pd.read_csv(PLANTED / "measurements.csv", dtype={"specimen": str})
    truth = pd.read_csv(PLANTED / "truth.csv", dtype={"specimen": str})
    residuals = pd.read_csv(DIAGNOSIS / "residuals.csv", dtype={"specimen": str})
    diagnosis = json.loads((DIAGNOSIS / "diagnosis.json").read_text())
    metrics = pd.read_csv(CALIBRATION / "metrics.csv", dtype={"specimen": str})

    cohort_figure(measured, truth, out)
    residual_figure(residuals, truth, out)
    specimen_figure(diagnosis, out)
    (out / "tutorial-verdicts.md").write_text(verdict_table(diagnosis, truth))
    both = before_after(diagnosis, metrics, truth)
    before_after_figure(both, out)
    (out / "tutorial-before-after.md").write_text(before_after_table(both))
    for path in sorted(out.glob("tutorial-*")):
        print(f"tutorial_figures: {path} ({path.stat().st_size // 1024} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
