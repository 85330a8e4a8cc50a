"""Outputs of :func:`femcal.diagnose.diagnose`: diagnosis.json, residual table, plots."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from femcal.calibration.report import safe_file_name
from femcal.diagnose import Diagnosis
from femcal.schema import LOAD_CASES


def residuals_frame(diag: Diagnosis) -> pd.DataFrame:
    """Disc-alone residuals of every measured point, in degrees and in units of sigma."""
    rows = []
    for s in diag.specimens:
        for j, lc in enumerate(LOAD_CASES):
            for k, m in enumerate(diag.moments):
                r = s.residuals[j, k]
                if np.isfinite(r):
                    rows.append((s.specimen, lc, m, r, r / diag.sigma_deg))
    return pd.DataFrame(
        rows, columns=["specimen", "load_case", "moment_nm", "residual_deg", "residual_sigma"]
    )


def plot_specimen(diag: Diagnosis, i: int, measured: np.ndarray, path: Path) -> None:
    """Measured vs disc-alone model with a ±2 sigma band, and the residual heat map."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = diag.specimens[i]
    model = measured - s.residuals
    fig, axes = plt.subplots(1, 5, figsize=(15, 3.0), gridspec_kw={"width_ratios": [1] * 4 + [1.2]})
    band = 2 * diag.sigma_deg
    for j, (ax, lc) in enumerate(zip(axes[:4], LOAD_CASES)):
        ok = np.isfinite(measured[j])
        ax.fill_between(
            diag.moments, model[j] - band, model[j] + band, color="C0", alpha=0.2, label="disc ± 2σ"
        )
        ax.plot(diag.moments, model[j], "-", color="C0", label="disc alone")
        ax.plot(diag.moments[ok], measured[j][ok], "o", color="black", ms=3, label="measured")
        ax.set_title(lc, fontsize=9)
        ax.set_xlabel("moment (Nm)")
    axes[0].set_ylabel("RoM (deg)")
    axes[0].legend(fontsize=7)
    ax = axes[4]
    z = s.residuals / diag.sigma_deg
    im = ax.imshow(z, cmap="RdBu_r", vmin=-4, vmax=4, aspect="auto")
    ax.set_yticks(range(4), [lc[:4] for lc in LOAD_CASES], fontsize=8)
    ax.set_xticks(range(len(diag.moments)), [f"{m:g}" for m in diag.moments], fontsize=7)
    ax.set_xlabel("moment (Nm)")
    ax.set_title("residual / σ", fontsize=9)
    fig.colorbar(im, ax=ax)
    best = next(r for r in s.ranking if r["effect"] == s.verdict)
    fig.suptitle(
        f"{s.specimen}: disc alone MAE {s.baseline_mae_deg:.3f}°, verdict "
        f"{s.verdict} (MAE {best['mae_deg']:.3f}°)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_heatmap(diag: Diagnosis, path: Path) -> None:
    """Cohort heat map: mean |residual| / sigma per load case x moment, by verdict."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    verdicts = sorted(diag.verdicts())
    fig, axes = plt.subplots(1, len(verdicts), figsize=(3.5 * len(verdicts), 3), squeeze=False)
    for ax, v in zip(axes[0], verdicts):
        z = np.stack([s.residuals for s in diag.specimens if s.verdict == v]) / diag.sigma_deg
        im = ax.imshow(np.nanmean(z, 0), cmap="RdBu_r", vmin=-4, vmax=4, aspect="auto")
        ax.set_title(f"verdict {v} (n={len(z)})", fontsize=9)
        ax.set_yticks(range(4), [lc[:4] for lc in LOAD_CASES], fontsize=8)
        ax.set_xticks(range(len(diag.moments)), [f"{m:g}" for m in diag.moments], fontsize=7)
    fig.colorbar(im, ax=axes[0].tolist())
    fig.suptitle("mean disc-alone residual / σ (measured − model)", fontsize=10)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_diagnosis(
    diag: Diagnosis,
    measured: np.ndarray,
    out_dir: Path,
    *,
    plots: bool = True,
    max_plots: int | None = None,
) -> dict:
    """Write ``diagnosis.json``, ``residuals.csv``, ``summary.md``, plots; return the summary."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    data = diag.to_dict()
    (out_dir / "diagnosis.json").write_text(json.dumps(data["specimens"], indent=2) + "\n")
    residuals_frame(diag).to_csv(out_dir / "residuals.csv", index=False)
    summary = {k: v for k, v in data.items() if k != "specimens"}
    summary["n_specimens"] = len(diag.specimens)
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    lines = [
        "# Diagnosis",
        "",
        f"Noise σ = {diag.sigma_deg:.4f}° (measurement {diag.noise_deg:.4f} ± "
        f"{diag.noise_sd_deg:.4f}°, surrogate {diag.surrogate_error_deg:.4f}°, in quadrature). "
        f"Cohort verdict: **{diag.cohort_verdict()}**; verdicts {diag.verdicts()}; "
        f"{diag.seconds:.1f} s.",
        "",
        "| specimen | verdict | disc-alone MAE (°) | with the verdict (°) | effect parameters |",
        "|---|---|---|---|---|",
    ]
    for s in diag.specimens:
        best = next(r for r in s.ranking if r["effect"] == s.verdict)
        pars = ", ".join(
            f"{k} {v['value']:.3g} ± {v['sd']:.2g} {v['unit']}"
            for k, v in best["parameters"].items()
        )
        lines.append(
            f"| {s.specimen} | {s.verdict} | {s.baseline_mae_deg:.3f} | "
            f"{best['mae_deg']:.3f} | {pars} |"
        )
    (out_dir / "summary.md").write_text("\n".join(lines) + "\n")
    if plots:
        pdir = out_dir / "plots"
        pdir.mkdir(exist_ok=True)
        n = len(diag.specimens) if max_plots is None else min(len(diag.specimens), max_plots)
        for i in range(n):
            plot_specimen(
                diag, i, measured[i], pdir / f"{safe_file_name(diag.specimens[i].specimen)}.png"
            )
        plot_heatmap(diag, out_dir / "heatmap.png")
    return summary
