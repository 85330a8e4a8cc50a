"""Outputs of :func:`femcal.diagnose.diagnose`: diagnosis.json, residual table, plots."""

from __future__ import annotations

import json
import multiprocessing
import warnings
from collections.abc import Collection, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.calibration.report import figure_names
from femcal.diagnose.balance import flat_note
from femcal.diagnose.outside import REPORTED
from femcal.diagnose.result import NONE, Diagnosis, SpecimenDiagnosis
from femcal.dvc_metrics import split_run
from femcal.figures import LOAD_CASE_LABELS, free_cores
from femcal.schema import LOAD_CASES

#: Load-case names in plots (the calibration's figures name them alike).
LABELS = LOAD_CASE_LABELS
#: ``summary.md`` calls a suggested measurement practical when this many repeats there (or
#: fewer) settle the question (``next_measurement.repeats_to_settle``).
PRACTICAL_REPEATS = 10


def residuals_frame(diag: Diagnosis) -> pd.DataFrame:
    """Residuals of every measured point, disc alone and final model, in degrees and sigma."""
    rows = []
    sig = diag.sigma_by_moment if diag.sigma_by_moment is not None else None
    for s in diag.specimens:
        final = s.final_residuals if s.final_residuals is not None else s.residuals
        for j, lc in enumerate(LOAD_CASES):
            for k, m in enumerate(diag.moments):
                r = s.residuals[j, k]
                if np.isfinite(r):
                    sk = (
                        float(s.sigma[j, k])
                        if s.sigma is not None
                        else float(sig[k])
                        if sig is not None
                        else diag.sigma_deg
                    )
                    rows.append(
                        (s.specimen, lc, m, r, r / sk, final[j, k], final[j, k] / sk, s.verdict)
                    )
    return pd.DataFrame(
        rows,
        columns=[
            "specimen",
            "load_case",
            "moment_nm",
            "residual_deg",
            "residual_sigma",
            "final_residual_deg",
            "final_residual_sigma",
            "verdict",
        ],
    )


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def practical_next(s: SpecimenDiagnosis) -> dict[str, Any] | None:
    """``next_measurement`` when a practical number of measurements (at most
    :data:`PRACTICAL_REPEATS`) at its point settles the question, else ``None``. (Its point
    within the protocol, when it has one, differs less, so it never settles sooner.)"""
    n = s.next_measurement
    return n if n and _settles(n) else None


def _mark_next_measurement(s: SpecimenDiagnosis, axes) -> str | None:
    """Dotted lines where ``next_measurement`` says to measure, when that is practical (and
    at its point within the protocol too, when that is practical as well); returns the
    sentence saying so."""
    n = practical_next(s)
    if n is None:
        return None
    inner = n.get("within_protocol")
    points = [n] + ([inner] if inner and _settles(inner) else [])
    for p in points:
        ax = axes[LOAD_CASES.index(p["load_case"])]
        ax.axvline(p["moment_nm"], ls=":", color="C1", lw=1.4)
        ax.text(
            p["moment_nm"],
            0.03,
            "measure next ",
            transform=ax.get_xaxis_transform(),
            rotation=90,
            ha="right",
            va="bottom",
            fontsize=8,
            color="C1",
        )

    def where(p: dict[str, Any]) -> str:
        k = p["repeats_to_settle"]
        return (
            f"{LABELS.get(p['load_case'], p['load_case'])} at {p['moment_nm']:.2g} Nm "
            f"({p['difference_deg']:+.3f}°, {p['difference_sigma']:.1f}σ, "
            f"{k} measurement{'s' if k > 1 else ''})"
        )

    text = f"Measure next to tell {n['between'][0]} from {n['between'][1]}: {where(n)}" + (
        ", beyond the protocol" if n.get("within_measured_range") is False else ""
    )
    return text + (f"; within the protocol: {where(inner)}" if len(points) > 1 else "") + "."


def plot_specimen(diag: Diagnosis, i: int, measured: np.ndarray, path: Path) -> None:
    """Measured points and continuous model curves (disc alone, with the verdict's effects),
    residuals against the ±2σ band, and the discrepancy estimate with its band."""
    s = diag.specimens[i]
    sig = (
        diag.sigma_by_moment
        if diag.sigma_by_moment is not None
        else np.full(len(diag.moments), diag.sigma_deg)
    )
    curves = s.curves or {}
    dense = curves.get("moments")
    # Fixed margins, no layout engine and no tight box: each would lay the eight axes out
    # again (drawing is most of a diagnosis' wall time). The notes get their own band below.
    fig, axes = _specimen_figure()
    # The final model's curve, where the verdict is the model as fitted (with an out-of-box
    # verdict that drops stand-ins, only the disc alone is drawn).
    final_label = s.final_label if dense is None or s.final_label in curves else NONE
    sig_dense = None if dense is None else np.interp(np.log(dense), np.log(diag.moments), sig)
    for j, lc in enumerate(LOAD_CASES):
        ax, rx = axes[0, j], axes[1, j]
        ok = np.isfinite(measured[j])
        if dense is not None:
            disc = curves[NONE][j]
            ax.fill_between(
                dense,
                disc - 2 * sig_dense,
                disc + 2 * sig_dense,
                color="C0",
                alpha=0.15,
                lw=0,
                label="disc alone ± 2σ",
            )
            ax.plot(dense, disc, "-", color="C0", lw=1.6, label="disc alone")
            if final_label != NONE:
                ax.plot(
                    dense,
                    curves[final_label][j],
                    "-",
                    color="C3",
                    lw=1.8,
                    label=f"disc + {final_label}",
                )
        ax.plot(diag.moments[ok], measured[j][ok], "o", color="black", ms=4, label="measured")
        # At the axes' top (y=1): the position matplotlib would find, as no tick or label
        # lies above the axes, without measuring every tick label of the figure to find it.
        ax.set_title(LABELS.get(lc, lc), fontsize=11, y=1.0)
        # Residuals: disc alone and final model, with the noise band.
        rx.fill_between(diag.moments, -2 * sig, 2 * sig, color="0.85", lw=0, label="± 2σ noise")
        rx.axhline(0.0, color="0.5", lw=0.8)
        rx.plot(diag.moments[ok], s.residuals[j][ok], "o", color="C0", ms=4, label="disc alone")
        if final_label != NONE and s.final_residuals is not None:
            rx.plot(
                diag.moments[ok],
                s.final_residuals[j][ok],
                "s",
                color="C3",
                ms=4,
                mfc="none",
                label=f"disc + {final_label}",
            )
        if s.discrepancy is not None and dense is not None:
            mu, sd = s.discrepancy["mean"][j], s.discrepancy["sd"][j]
            rx.fill_between(dense, mu - 2 * sd, mu + 2 * sd, color="C2", alpha=0.25, lw=0)
            rx.plot(
                dense,
                mu,
                "-",
                color="C2",
                lw=1.6,
                label=f"discrepancy of {s.discrepancy['model']} (± 2 sd)",
            )
        rx.set_xlabel("moment (Nm)", fontsize=10)
    measure_next = _mark_next_measurement(s, axes[0])
    axes[0, 0].set_ylabel("RoM (deg)", fontsize=10)
    axes[1, 0].set_ylabel("measured − model (deg)", fontsize=10)
    axes[0, 0].legend(fontsize=8, loc="upper left")
    axes[1, 0].legend(fontsize=8, loc="upper left", framealpha=0.8)
    title = (
        f"{s.specimen}: verdict {s.verdict}; MAE disc alone {s.baseline_mae_deg:.3f}°"
        + (f", with {final_label} {s.final_mae_deg:.3f}°" if final_label != NONE else "")
        + (
            f", with the discrepancy {s.discrepancy['mae_deg']:.3f}°"
            if s.discrepancy is not None
            else ""
        )
    )
    fig.suptitle(title, fontsize=11)
    notes = list(s.discrepancy["description"]) if s.discrepancy is not None else []
    if (box := outside_box_note(s)) is not None:
        notes.insert(0, box)
    if (flat := flat_note(s.probabilities or {})) is not None:
        notes.append(flat)
    if measure_next:
        notes.append(measure_next)
    _place_notes(fig, notes)
    fig.savefig(path, dpi=100)


#: The per-specimen figure of this process and its (2, 4) axes, drawn again for each specimen:
#: building eight axes and their ticks anew costs about as much as drawing them.
_FIGURE: tuple[Any, np.ndarray] | None = None


def _specimen_figure() -> tuple[Any, np.ndarray]:
    """This process's per-specimen figure and axes, emptied of the last specimen's artists,
    titles, legends and notes, with their data limits to be set anew (as on new axes)."""
    global _FIGURE
    if _FIGURE is None:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(_WIDTH_IN, _AXES_HEIGHT_IN))
        _FIGURE = fig, fig.subplots(2, 4, sharex=True)
        return _FIGURE
    fig, axes = _FIGURE
    for ax in axes.flat:
        for artist in [*ax.lines, *ax.collections, *ax.texts, *ax.patches]:
            artist.remove()
        if ax.get_legend() is not None:
            ax.get_legend().remove()
        ax.set_title("")
        ax.set_xlabel("")
        ax.set_ylabel("")
        ax.ignore_existing_data_limits = True
        ax.set_autoscale_on(True)
    for text in list(fig.texts):
        text.remove()
    return fig, axes


#: Per-specimen figure: width and the height of its axes (inches); each note line below the
#: axes adds ``_NOTE_LINE_IN``; notes wrap at ``_NOTE_CHARS`` characters (monospace 8.5 pt).
_WIDTH_IN, _AXES_HEIGHT_IN, _NOTE_LINE_IN, _NOTE_CHARS = 15.0, 6.6, 0.15, 190


def _place_notes(fig, notes: list[str]) -> None:
    """Fixed margins around the axes of a per-specimen figure, and ``notes`` (wrapped) in a
    band below them that grows the figure by the lines it holds."""
    import textwrap

    lines = [w for note in notes for w in textwrap.wrap(note, _NOTE_CHARS) or [""]]
    band = len(lines) * _NOTE_LINE_IN + (0.15 if lines else 0.0)
    height = _AXES_HEIGHT_IN + band
    fig.set_size_inches(_WIDTH_IN, height)
    fig.subplots_adjust(
        left=0.05,
        right=0.99,
        bottom=(0.55 + band) / height,
        top=1.0 - 0.6 / height,
        wspace=0.22,
        hspace=0.1,
    )
    if lines:
        fig.text(
            0.01,
            (band - 0.05) / height,
            "\n".join(lines),
            fontsize=8.5,
            va="top",
            family="monospace",
        )


def plot_heatmap(diag: Diagnosis, path: Path) -> None:
    """Cohort heat map: mean disc-alone residual / sigma per load case x moment, by verdict."""
    plt = _plt()
    verdicts = sorted(diag.verdicts(), key=lambda v: (v != NONE, v))
    sig = diag.sigma_by_moment if diag.sigma_by_moment is not None else diag.sigma_deg
    ncol = min(3, len(verdicts))
    nrow = int(np.ceil(len(verdicts) / ncol))
    width = max(4.2, 0.45 * len(diag.moments) + 2.2)
    fig, axes = plt.subplots(
        nrow, ncol, figsize=(width * ncol, 2.8 * nrow), squeeze=False, constrained_layout=True
    )
    im = None
    for ax, v in zip(axes.flat, verdicts):
        group: list[SpecimenDiagnosis] = [s for s in diag.specimens if s.verdict == v]
        z = np.stack([s.residuals for s in group]) / sig
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a cell nobody measured: NaN
            mean = np.nanmean(z, 0)
        im = ax.imshow(mean, cmap="RdBu_r", vmin=-4, vmax=4, aspect="auto")
        ax.set_title(f"{v} (n = {len(group)})", fontsize=10)
        ax.set_yticks(range(4), [LABELS.get(lc, lc) for lc in LOAD_CASES], fontsize=9)
        step = max(1, int(np.ceil(len(diag.moments) / 10)))
        ticks = list(range(0, len(diag.moments), step))
        ax.set_xticks(ticks, [f"{diag.moments[k]:g}" for k in ticks], fontsize=8, rotation=45)
        ax.set_xlabel("moment (Nm)", fontsize=9)
    for ax in list(axes.flat)[len(verdicts) :]:
        ax.axis("off")
    if im is not None:
        fig.colorbar(im, ax=axes.ravel().tolist(), label="mean residual / σ", shrink=0.9)
    fig.suptitle("disc-alone residual (measured − model) by verdict", fontsize=11)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_inclusion(diag: Diagnosis, path: Path) -> None:
    """Cohort heat map of inclusion probabilities: each effect (something outside the library,
    a disc outside the parameter box) x each specimen, 0 to 1
    (:mod:`femcal.diagnose.probabilities`, :mod:`femcal.diagnose.outside`)."""
    plt = _plt()
    rows = sorted({e for s in diag.specimens for e in s.probabilities.get("inclusion", {})})
    names = [s.specimen for s in diag.specimens]
    p = np.array(
        [[s.probabilities.get("inclusion", {}).get(e, 0.0) for s in diag.specimens] for e in rows]
        + [[s.probabilities.get("outside_library", 0.0) for s in diag.specimens]]
        + [[s.probabilities.get("outside_box", 0.0) for s in diag.specimens]]
    )
    labels = [*rows, "outside the library", "outside the box"]
    fig, ax = plt.subplots(
        figsize=(max(6.0, 0.22 * len(names) + 3.0), 0.5 * len(labels) + 1.8),
        constrained_layout=True,
    )
    im = ax.imshow(p, cmap="viridis", vmin=0.0, vmax=1.0, aspect="auto")
    ax.set_yticks(range(len(labels)), labels, fontsize=9)
    step = max(1, int(np.ceil(len(names) / 60)))
    ax.set_xticks(range(0, len(names), step), names[::step], fontsize=7, rotation=90)
    ax.set_xlabel("specimen", fontsize=9)
    fig.colorbar(im, ax=ax, label="inclusion probability", shrink=0.9)
    ax.set_title("How probable each explanation is, per specimen", fontsize=11)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def outside_box_note(s: SpecimenDiagnosis) -> str | None:
    """The specimen's out-of-box reading in words (side, load cases, parameters at their
    bounds, remedy) where the verdict names the box or the reading is at least
    :data:`~femcal.diagnose.outside.REPORTED` probable; else None."""
    box = s.outside_box
    if box is None or not (box["named"] or box["probability"] >= REPORTED):
        return None
    return ("Outside the box: " if box["named"] else "Or outside the box: ") + box["summary"]


def _missing(s: SpecimenDiagnosis) -> str:
    """What is missing, for summary.md: the discrepancy's summary, the chosen model's flat
    effects (:func:`~femcal.diagnose.balance.flat_note`), and the out-of-box reading where
    there is one to report (first where the verdict names the box)."""
    text = s.discrepancy["summary"] if s.discrepancy else ""
    if (flat := flat_note(s.probabilities or {})) is not None:
        text = f"{text} {flat}".strip()
    box = outside_box_note(s)
    if box is None:
        return text
    return f"{box} {text}".strip() if s.outside_box["named"] else f"{text} {box}".strip()


def _probable(s: SpecimenDiagnosis) -> str:
    """The most probable models (p >= 0.05), the effects' inclusion probabilities and where
    the verdict's effects act (:func:`_where`)."""
    pr = s.probabilities
    if not pr:
        return ""
    top = [f"{k} {v:.2f}" for k, v in pr.get("models", {}).items() if v >= 0.05][:3]
    inc = [f"{k} {v:.2f}" for k, v in pr.get("inclusion", {}).items() if v >= 0.05]
    if pr.get("outside_box", 0.0) >= 0.05:
        inc.append(f"outside the box {pr['outside_box']:.2f}")
    return "; ".join(top) + (f" (inclusion: {', '.join(inc)})" if inc else "") + _where(s)


def _where(s: SpecimenDiagnosis) -> str:
    """Where each effect of the verdict acts, with the probability of each load case where
    it is below 1: ``; facet_contact acts in Extension, LateralBending 0.84, AxialRotation``."""
    where = s.probabilities.get("acts_in", {})
    parts = []
    for e, cases in s.load_cases.items():
        p = where.get(e, {})
        named = [lc if p.get(lc, 1.0) >= 0.995 else f"{lc} {p[lc]:.2f}" for lc in cases]
        doubt = [f"{lc} {q:.2f}" for lc, q in p.items() if lc not in cases and q >= 0.05]
        parts.append(
            f"{e} acts in {', '.join(named)}" + (f" (also {', '.join(doubt)})" if doubt else "")
        )
    return "; " + "; ".join(parts) if parts else ""


#: What the plotting workers read: (diagnosis, measured, figures' paths), set before they fork.
_PLOTTING: tuple[Diagnosis, np.ndarray, list[Path]] | None = None


def figure_paths(specimens: Sequence[str], pdir: Path) -> list[Path]:
    """Where each specimen's figure goes: ``pdir/<name>.png``, the names distinct over the
    cohort's ``specimens`` (:func:`femcal.calibration.report.figure_names`)."""
    return [pdir / f"{name}.png" for name in figure_names(specimens)]


def _plot_one(i: int) -> None:
    diag, measured, paths = _PLOTTING
    plot_specimen(diag, i, measured[i], paths[i])


def draw_group(
    diag: Diagnosis, rows: np.ndarray, measured: np.ndarray, paths: Sequence[Path], n: int | None
) -> None:
    """The figures of a group's specimens among the cohort's first ``n`` (None: all): ``diag``
    the group's diagnosis, ``rows`` (k,) their indices in the cohort, ``measured`` (N, 4, m) the
    cohort's RoM (deg), ``paths`` (N,) the cohort's figure paths (:func:`figure_paths`). The
    figures :func:`write_diagnosis` draws of them, drawn in this process (a diagnosis' worker,
    :func:`femcal.diagnose.workers.each_group`)."""
    _plt()
    for j, i in enumerate(rows):
        if n is None or i < n:
            plot_specimen(diag, j, measured[i], paths[i])


def drawn_figures(diag: Diagnosis, pdir: Path) -> set[int]:
    """The specimens (indices) of the cohort ``diag`` whose figure is in ``pdir``
    (:func:`draw_group`)."""
    paths = figure_paths([s.specimen for s in diag.specimens], pdir)
    return {i for i, path in enumerate(paths) if path.exists()}


def _plot_specimens(
    diag: Diagnosis, measured: np.ndarray, pdir: Path, n: int, drawn: Collection[int]
) -> None:
    """The first ``n`` specimens' plots but those ``drawn`` already, in one worker process per
    free core where the platform forks (the figures are independent; matplotlib takes most of
    a diagnosis' time)."""
    global _PLOTTING
    todo = [i for i in range(n) if i not in drawn]
    if not todo:
        return
    _PLOTTING = (diag, measured, figure_paths([s.specimen for s in diag.specimens], pdir))
    _plt()  # imported once here, not in each worker
    try:
        workers = min(free_cores(), len(todo))
        if workers > 1 and "fork" in multiprocessing.get_all_start_methods():
            ctx = multiprocessing.get_context("fork")
            with ProcessPoolExecutor(workers, mp_context=ctx) as pool:
                chunk = max(1, len(todo) // (4 * workers))
                list(pool.map(_plot_one, todo, chunksize=chunk))
        else:
            for i in todo:
                _plot_one(i)
    finally:
        _PLOTTING = None


def _parameters(s: SpecimenDiagnosis) -> str:
    best = next((r for r in s.ranking if r["effects"] == list(s.model or s.effects)), None)
    if best is None:
        return ""
    return ", ".join(
        f"{k} {v['value']:.3g} ± {v['sd']:.2g} {v['unit']}" for k, v in best["parameters"].items()
    )


def _settles(p: dict) -> bool:
    """Whether a suggested point settles the question in a practical number of measurements."""
    k = p.get("repeats_to_settle")
    return k is not None and k <= PRACTICAL_REPEATS


def _next(s: SpecimenDiagnosis) -> str:
    n = s.next_measurement
    if not n:
        return ""

    def at(p: dict) -> str:
        k = p.get("repeats_to_settle")
        return (
            f"{p['load_case']} at {p['moment_nm']:.2g} Nm "
            f"({p['difference_deg']:+.3f}°, {p['difference_sigma']:.1f}σ"
            + ("" if k is None else f", {k} measurement{'s' if k > 1 else ''}")
        )

    pair = f"{n['between'][0]} vs {n['between'][1]}"
    if not _settles(n):
        return (
            f"{pair}: no practical measurement tells them apart (at most "
            f"{n['difference_sigma']:.1f}σ, {n['load_case']} at {n['moment_nm']:.2g} Nm)"
        )
    text = f"{pair}: {at(n)}"
    if n.get("within_measured_range") is False:
        text += ", beyond the protocol"
    text += ")"
    inner = n.get("within_protocol")
    if inner:
        text += (
            f"; within the protocol: {at(inner)})"
            if _settles(inner)
            else f"; none practical within the protocol (at most {inner['difference_sigma']:.1f}σ)"
        )
    return text


def write_diagnosis(
    diag: Diagnosis,
    measured: np.ndarray,
    out_dir: Path,
    *,
    plots: bool = True,
    max_plots: int | None = None,
    drawn: Collection[int] = (),
) -> dict:
    """Write ``diagnosis.json``, ``residuals.csv``, ``summary.md``, plots; return the summary.

    ``drawn``: the specimens (indices) whose figure is in ``out_dir/plots`` already (drawn by
    the diagnosis' workers, :func:`draw_group`, :func:`drawn_figures`): kept, not drawn
    again."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    data = diag.to_dict()
    (out_dir / "diagnosis.json").write_text(json.dumps(data["specimens"], indent=2) + "\n")
    residuals_frame(diag).to_csv(out_dir / "residuals.csv", index=False)
    summary = {k: v for k, v in data.items() if k != "specimens"}
    summary["n_specimens"] = len(diag.specimens)
    summary["found_effects"] = diag.found_effects()
    # the wall time is the run's, not the diagnosis': the marker and MLflow hold it
    (out_dir / "summary.json").write_text(json.dumps(split_run(summary)[0], indent=2) + "\n")
    sig = diag.sigma_by_moment
    sig_text = f"{diag.sigma_deg:.4f}° inside the trained moments" + (
        f", up to {float(np.max(sig)):.4f}° beyond" if sig is not None and np.ptp(sig) else ""
    )
    lines = [
        "# Diagnosis",
        "",
        f"Noise σ = {sig_text} (measurement {diag.noise_deg:.4f} ± {diag.noise_sd_deg:.4f}°, "
        "surrogate's own error in quadrature). Each explanation's probability weighs its "
        "criterion with the evidence the search asks before naming it; the verdict says "
        "`unexplained` where a smooth discrepancy (on top of the model, or in place of its "
        "effects) is more probable than the model alone (the χ² test's p beside it), and "
        "`outside_box` where a disc outside the sampled parameter box is more probable than "
        "not (its effects act from about 0 Nm "
        "rather than engage; the remedy: widen `fe.bounds` and run the FE campaign on the "
        f"widened box, `dvc repro fe/dvc.yaml`). Verdicts {diag.verdicts()}; effects "
        f"named {diag.effect_counts()}.",
        *_noise_warning(diag),
        "",
        "| specimen | verdict | probabilities | disc-alone MAE (°) | final MAE (°) | χ² p | "
        "effect parameters | what is missing | to settle it, measure |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in diag.specimens:
        missing = _missing(s)
        p = s.adequacy.get("final", {}).get("p_chi2", float("nan")) if s.adequacy else np.nan
        lines.append(
            f"| {s.specimen} | {s.verdict} | {_probable(s)} | {s.baseline_mae_deg:.3f} | "
            f"{s.final_mae_deg:.3f} | "
            f"{p:.2g} | {_parameters(s)} | {missing} | {_next(s)} |"
        )
    (out_dir / "summary.md").write_text("\n".join(lines) + "\n")
    if plots:
        pdir = out_dir / "plots"
        pdir.mkdir(exist_ok=True)
        n = len(diag.specimens) if max_plots is None else min(len(diag.specimens), max_plots)
        _plot_specimens(diag, measured, pdir, n, set(drawn))
        plot_heatmap(diag, out_dir / "heatmap.png")
        plot_inclusion(diag, out_dir / "inclusion.png")
    return summary


def _noise_warning(diag: Diagnosis) -> list[str]:
    """summary.md's lines for :meth:`Diagnosis.noise_check` where it says the noise is too
    small (none otherwise)."""
    check = diag.noise_check()
    if not check or not check["message"]:
        return []
    return ["", f"**Noise:** {check['message'][0].upper()}{check['message'][1:]}."]
