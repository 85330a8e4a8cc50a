"""Calibration figures: one per specimen (``plots/<specimen>.png``) and a summary page.

A specimen's figure shows, per load case, the measured points, the calibrated model as a
continuous curve (:class:`FigureCurves`, else through the measured moments), the ± 2σ band of
one measurement around it when the noise is known, and the held-out surrogate's curve at the
same parameters; the legend sits above the axes, never on the data. It has the diagnosis'
width and resolution (:mod:`femcal.diagnose.report`).

The per-specimen figures are drawn by one figure per process, redrawn for each specimen
(building four axes costs more than drawing them), in worker processes on the free cores
(:func:`femcal.figures.plot_workers`).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from femcal.calibration.result import CalibrationResult
from femcal.figures import (
    LOAD_CASE_LABELS,
    chunks,
    dense_grid,
    fork_map,
    noise_band,
    plot_workers,
    progress_over,
    text_caching_canvas,
)
from femcal.schema import LOAD_CASES

#: The per-specimen figure: width and height (inches) and resolution, as the diagnosis'.
WIDTH_IN, HEIGHT_IN, DPI = 15.0, 4.2, 100

#: Labels of what the figures draw.
MEASURED, CALIBRATED, HELD_OUT = "measured", "calibrated model", "held-out surrogate"
BAND = "± 2σ of one measurement (noise and surrogate error)"


@dataclass(frozen=True)
class FigureCurves:
    """The curves a specimen's figure draws, continuous where a model gave them densely.

    Attributes
    ----------
    moments : ndarray, shape (q,)
        Moments in Nm.
    calibrated : ndarray, shape (n, 4, q)
        The calibrated model's RoM at ``moments`` (the first n specimens).
    holdout : ndarray, shape (n, 4, q), optional
        The held-out surrogate's RoM at the same parameters.
    sigma : ndarray, shape (q,), optional
        The sd (deg) of one measurement at ``moments``: the noise and the surrogate's error in
        quadrature. None: the result's own error scale, if any (a band of constant width).
    """

    moments: np.ndarray
    calibrated: np.ndarray
    holdout: np.ndarray | None = None
    sigma: np.ndarray | None = None

    @classmethod
    def at_measured(
        cls, result: CalibrationResult, holdout: np.ndarray | None = None
    ) -> FigureCurves:
        """The result's own curves, at the measured moments (no model at hand)."""
        return cls(np.asarray(result.moments, dtype=float), result.prediction, holdout)


def dense_curves(
    result: CalibrationResult,
    model_at: Callable[[np.ndarray], Any],
    *,
    holdout_at: Callable[[np.ndarray], Any] | None = None,
    sigma_at: Callable[[np.ndarray], np.ndarray] | None = None,
    n: int | None = None,
) -> FigureCurves:
    """Continuous curves of the first ``n`` specimens at their calibrated parameters.

    Parameters
    ----------
    result : CalibrationResult
    model_at, holdout_at : callable
        A moment grid (q,) -> the calibrated model (a :class:`~femcal.curves.CurveModel`), and
        the held-out one, on that grid.
    sigma_at : callable, optional
        A moment grid (q,) -> the sd (deg) of one measurement there (q,).
    n : int, optional
        The specimens to draw (default: all).
    """
    moments = dense_grid(result.moments)
    x = result.x[: len(result.x) if n is None else n]
    return FigureCurves(
        moments,
        model_at(moments).predict(x, clip=False),
        None if holdout_at is None else holdout_at(moments).predict(x, clip=False),
        None if sigma_at is None else np.asarray(sigma_at(moments), dtype=float),
    )


def _agg_figure(**kwargs: Any) -> Any:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure  # no pyplot: nothing to close, no backend state

    return Figure(**kwargs)


class _SpecimenFigure:
    """The per-specimen figure of one process, redrawn for every specimen: its lines, band,
    titles and limits change; its axes, layout (fixed margins, no layout engine, no tight
    box) and legend stay."""

    def __init__(self, result: CalibrationResult, curves: FigureCurves) -> None:
        from matplotlib.patches import Patch
        from matplotlib.ticker import MaxNLocator

        self.result, self.curves = result, curves
        self.fig = _agg_figure(figsize=(WIDTH_IN, HEIGHT_IN), dpi=DPI)
        self.axes = self.fig.subplots(1, len(LOAD_CASES))
        self.fig.subplots_adjust(left=0.045, right=0.99, bottom=0.13, top=0.76, wspace=0.2)
        self.banded = curves.sigma is not None or result.error_scale_deg is not None
        self.bands: list[Any] = [None] * len(LOAD_CASES)
        self.lines = []
        x_max = float(np.max(curves.moments)) * 1.05
        for ax in self.axes:
            held = None
            if curves.holdout is not None:
                held = ax.plot([], [], "--", color="C3", lw=1.4, label=HELD_OUT)[0]
            model = ax.plot([], [], "-", color="C0", lw=1.8, label=CALIBRATED)[0]
            measured = ax.plot([], [], "o", color="black", ms=4.5, zorder=3, label=MEASURED)[0]
            note = ax.text(0.5, 0.5, "not measured", ha="center", transform=ax.transAxes)
            self.lines.append((measured, model, held, note))
            ax.set_xlim(0, x_max)
            ax.set_xlabel("moment (Nm)", fontsize=10)
            ax.yaxis.set_major_locator(MaxNLocator(5))
        self.axes[0].set_ylabel("RoM (deg)", fontsize=10)
        handles = [line for line in self.lines[0][:3] if line is not None]
        if self.banded:
            handles.append(Patch(color="C0", alpha=0.2, lw=0, label=BAND))
        self.fig.legend(
            handles=handles,
            loc="upper right",
            bbox_to_anchor=(0.99, 1.0),
            ncol=len(handles),
            frameon=False,
            fontsize=9,
        )
        self.title = self.fig.text(0.01, 0.975, "", ha="left", va="top", fontsize=11)
        for ax in self.axes:
            # Placed by hand: no search of the tick labels' boxes at every draw.
            ax.xaxis.set_label_coords(0.5, -0.1)
            ax.yaxis.set_label_coords(-0.13, 0.5)
        self.background = self._static_background()

    def _changing(self) -> list[Any]:
        """What changes per specimen: each axes' y axis, title, curves and note, the title."""
        out = [self.title]
        for ax, lines in zip(self.axes, self.lines):
            out += [ax.yaxis, ax.title, *(line for line in lines if line is not None)]
        return out

    def _static_background(self) -> Any:
        """Draw what never changes (axes, x axes, labels, legend) once; keep its pixels."""
        canvas = text_caching_canvas(self.fig)
        for artist in self._changing():
            artist.set_animated(True)
        canvas.draw()
        return canvas.copy_from_bbox(self.fig.bbox)

    def _sigma(self, i: int) -> Any:
        if self.curves.sigma is not None:
            return self.curves.sigma
        scale = self.result.error_scale_deg
        return None if scale is None else float(scale[i])

    def draw(self, i: int, path: Path) -> None:
        """Write specimen ``i``'s figure: the static pixels, then what changes drawn on them."""
        result, curves, canvas = self.result, self.curves, self.fig.canvas
        canvas.restore_region(self.background)
        sigma = self._sigma(i)
        for j, (ax, lc) in enumerate(zip(self.axes, LOAD_CASES)):
            measured, model, held, note = self.lines[j]
            y = result.measured[i, j]
            ok = np.isfinite(y)
            measured.set_data(result.moments[ok], y[ok])
            note.set_visible(not ok.any())
            fit = curves.calibrated[i, j]
            model.set_data(curves.moments, fit)
            shown = [y[ok], fit]
            if held is not None:
                held.set_data(curves.moments, curves.holdout[i, j])
                shown.append(curves.holdout[i, j])
            if self.bands[j] is not None:
                self.bands[j].remove()
                self.bands[j] = None
            if sigma is not None:
                band = noise_band(ax, curves.moments, fit, sigma, color="C0", alpha=0.2)
                band.set_animated(True)
                self.bands[j] = band
                shown += [fit + 2 * np.asarray(sigma), fit - 2 * np.asarray(sigma)]
            _limits(ax, np.concatenate([np.ravel(v) for v in shown]))
            mae, r2 = result.mae_per_load_case[i, j], result.r2_per_load_case[i, j]
            label = LOAD_CASE_LABELS.get(lc, lc)
            # y given: a title placed by hand skips the search for overlapping tick labels
            ax.set_title(
                f"{label}\nMAE {mae:.3f}°, R² {r2:.3f}" if np.isfinite(mae) else label,
                fontsize=10,
                y=1.02,
            )
            for artist in (self.bands[j], held, model, measured, note, ax.yaxis, ax.title):
                if artist is ax.yaxis:
                    _draw_axis(artist, canvas.get_renderer())
                elif artist is not None and artist.get_visible():
                    ax.draw_artist(artist)
        self.title.set_text(
            f"specimen {result.specimens[i]}: MAE {result.mae_deg[i]:.3f}°, "
            f"mean R² {result.r2_mean[i]:.4f}"
        )
        self.fig.draw_artist(self.title)
        _write_png(canvas, path)


def _draw_axis(axis: Any, renderer: Any) -> None:
    """Draw ``axis`` (its ticks, tick labels, label and offset text) as ``axis.draw`` does,
    without the bounding boxes of its tick labels: ``axis.draw`` measures them to place the
    label and the offset text, which :class:`_SpecimenFigure` places by hand (the same
    pixels, a tenth less drawing time)."""
    if not axis.get_visible():
        return
    renderer.open_group(type(axis).__name__, gid=axis.get_gid())
    for tick in axis._update_ticks():
        tick.draw(renderer)
    axis._update_label_position(renderer)  # nothing to do: the label's position is set
    axis.label.draw(renderer)
    axis.offsetText.set_text(axis.major.formatter.get_offset())
    axis.offsetText.draw(renderer)
    renderer.close_group(type(axis).__name__)


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _write_png(canvas: Any, path: Path) -> None:
    """The canvas' pixels as an 8-bit RGB PNG of :data:`DPI` (the figure is opaque: its alpha is
    255 everywhere, so the colours are those ``savefig`` writes, without drawing). Rows
    unfiltered, deflated at level 3: the figures' flat colours compress as well as with PNG's
    adaptive filters, in a third of the time."""
    rgba = np.asarray(canvas.buffer_rgba())  # (height, width, 4), uint8
    height, width = rgba.shape[:2]
    rows = np.empty((height, 1 + 3 * width), dtype=np.uint8)
    rows[:, 0] = 0  # filter type None
    np.copyto(rows[:, 1:].reshape(height, width, 3), rgba[:, :, :3])
    per_metre = round(DPI / 0.0254)
    Path(path).write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
        + _png_chunk(b"pHYs", struct.pack(">IIB", per_metre, per_metre, 1))
        + _png_chunk(b"IDAT", zlib.compress(rows, 3))
        + _png_chunk(b"IEND", b"")
    )


def _limits(ax: Any, values: np.ndarray) -> None:
    """y from 0 (or below, for negative values) to a little above the largest value."""
    values = values[np.isfinite(values)]
    top = float(values.max()) if values.size else 1.0
    low = min(0.0, float(values.min())) if values.size else 0.0
    top = top if top > low else low + 1.0
    ax.set_ylim(low - 0.02 * (top - low) if low < 0 else 0.0, top + 0.06 * (top - low))


def plot_specimen(
    result: CalibrationResult, i: int, path: Path, curves: FigureCurves | None = None
) -> Any:
    """The figure of specimen ``i`` (one PNG): measured vs calibrated RoM per load case.

    Returns
    -------
    matplotlib.figure.Figure
        The figure written (to restyle it and save it again, e.g. as PDF for a paper).
    """
    figure = _SpecimenFigure(result, curves or FigureCurves.at_measured(result))
    figure.draw(i, path)
    for artist in figure.fig.findobj(lambda a: a.get_animated()):
        artist.set_animated(False)  # drawn by savefig too, as any figure
    return figure.fig


#: What the drawing workers read: (result, curves, paths, the other figure), set before they
#: fork; and the figure of this process.
_DRAWING: tuple[CalibrationResult, FigureCurves, Sequence[Path], Callable[[], Any] | None] | None
_DRAWING = None
_FIGURE: tuple[int, _SpecimenFigure] | None = None


def _draw(piece: range | None) -> None:
    global _FIGURE
    result, curves, paths, other = _DRAWING
    if piece is None:
        other()
        return
    if _FIGURE is None or _FIGURE[0] != id(_DRAWING):
        _FIGURE = id(_DRAWING), _SpecimenFigure(result, curves)
    for i in piece:
        _FIGURE[1].draw(i, paths[i])


def plot_specimens(
    result: CalibrationResult,
    paths: Sequence[Path],
    curves: FigureCurves | None = None,
    *,
    progress: bool = False,
    workers: int | None = None,
    beside: Callable[[], Any] | None = None,
) -> None:
    """The figures of specimens ``0 .. len(paths) - 1`` into ``paths``.

    ``curves``: what to draw (default: the result's curves at the measured moments);
    ``progress`` shows a bar (stderr) over the specimens; ``workers``: the processes to draw
    in (default: :func:`femcal.figures.plot_workers`, the free cores); ``beside``: one more
    figure to draw (a function that writes it, e.g. the summary page), first, in a worker of
    its own while the others draw the specimens.
    """
    global _DRAWING, _FIGURE
    if not len(paths):
        if beside is not None:
            beside()
        return
    curves = curves or FigureCurves.at_measured(result)
    workers = plot_workers(len(paths)) if workers is None else max(1, int(workers))
    _agg_figure()  # matplotlib imported once here, not in each worker
    _DRAWING, _FIGURE = (result, curves, list(paths), beside), None
    try:
        pieces = ([None] if beside is not None else []) + chunks(len(paths), workers)
        for _ in progress_over(fork_map(_draw, pieces, workers), len(paths), "plots", progress):
            pass
    finally:
        _DRAWING = _FIGURE = None


def _histograms(ax: Any, samples: Sequence[tuple[str, np.ndarray, str]], xlabel: str) -> None:
    """Outlined (step) histograms on shared bins, each seen through the others (the second
    dashed: equal counts still show both); the legend above the axes, off the data."""
    data = [(label, v[np.isfinite(v)], colour) for label, v, colour in samples]
    pooled = np.concatenate([v for _, v, _ in data]) if data else np.zeros(0)
    bins = np.histogram_bin_edges(pooled, bins=min(30, max(5, pooled.size // 3 or 5)))
    for k, (label, values, colour) in enumerate(data):
        style = "-" if k == 0 else "--"
        ax.hist(values, bins=bins, histtype="step", lw=1.8, ls=style, color=colour, label=label)
    ax.set_xlabel(xlabel, fontsize=10)
    ax.set_ylabel("specimens", fontsize=10)
    if len(data) > 1:
        ax.legend(
            fontsize=9, loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=len(data), frameon=False
        )


def _room_for_names(ax: Any, left_of: Any, names: Sequence[str]) -> None:
    """Move ``ax``'s left edge right of ``left_of`` by the width of its longest tick label.

    The width is estimated without drawing (0.6 em per character: DejaVu Sans' widest lower-case
    average), and the labels' size falls from 9 to 7 pt as the names grow from 16 to 32.
    """
    fig = ax.get_figure()
    size = 9.0 if len(names) <= 16 else max(7.0, 9.0 - (len(names) - 16) / 8)
    longest = max((len(str(n)) for n in names), default=0)
    label = 0.6 * size / 72 * longest / fig.get_figwidth()
    box = ax.get_position()
    left = left_of.get_position().x1 + 0.04 + label + 0.01
    ax.set_position([left, box.y0, box.x1 - left, box.height])
    ax.tick_params(axis="y", labelsize=size)


def plot_summary(
    result: CalibrationResult,
    path: Path,
    holdout: dict[str, np.ndarray] | None = None,
    ranges: Any = None,
    determined_width: float = 0.5,
) -> Any:
    """One page: MAE and R² histograms, measured vs calibrated, per-parameter ranges.

    ``holdout``: the held-out surrogate's scores (``mae``, ``r2_mean``), drawn beside the
    calibrated model's; ``ranges``: the identifiability table (``parameter``,
    ``mean_width``), the parameters determined below ``determined_width``.

    Returns
    -------
    matplotlib.figure.Figure
        The figure written.
    """
    # Margins set by hand (no layout engine): room for the parameter names on the left of the
    # ranges panel and for the histograms' legends above their axes.
    fig = _agg_figure(figsize=(12, 8.4), dpi=DPI)
    room = dict(left=0.06, right=0.985, bottom=0.07, top=0.89, hspace=0.32)
    axes = fig.subplots(2, 2, gridspec_kw=dict(room, wspace=0.22 if ranges is None else 0.3))
    held = holdout is not None
    _histograms(
        axes[0, 0],
        [(CALIBRATED, result.mae_deg, "C0")] + ([(HELD_OUT, holdout["mae"], "C3")] if held else []),
        "MAE per specimen (deg)",
    )
    _histograms(
        axes[0, 1],
        [(CALIBRATED, result.r2_mean, "C0")]
        + ([(HELD_OUT, holdout["r2_mean"], "C3")] if held else []),
        "mean R² over load cases",
    )
    ax = axes[1, 0]
    for j, lc in enumerate(LOAD_CASES):
        y = result.measured[:, j].reshape(-1)
        ok = np.isfinite(y)
        fit = result.prediction[:, j].reshape(-1)[ok]
        ax.plot(y[ok], fit, ".", ms=4, label=LOAD_CASE_LABELS.get(lc, lc))
    lim = float(np.nanmax(result.measured)) * 1.05
    ax.plot([0, lim], [0, lim], "k-", lw=0.6, label="measured = calibrated")
    ax.set_xlabel("measured RoM (deg)", fontsize=10)
    ax.set_ylabel("calibrated RoM (deg)", fontsize=10)
    ax.legend(fontsize=9, loc="upper left", frameon=False)
    ax = axes[1, 1]
    if ranges is not None:
        _room_for_names(ax, axes[1, 0], list(ranges["parameter"]))
        ax.barh(ranges["parameter"], ranges["mean_width"], color="C2")
        ax.axvline(determined_width, color="k", lw=0.6)
        ax.set_xlabel("mean identifiability range (fraction of the bounds)", fontsize=10)
        ax.set_xlim(0, 1)
    else:
        ax.text(0.5, 0.5, f"{result.method} gives no ranges", ha="center", va="center")
        ax.set_axis_off()
    fig.suptitle(
        f"{result.method}: {len(result.specimens)} specimens, "
        f"MAE {np.nanmean(result.mae_deg):.4f}°, mean R² {np.nanmean(result.r2_mean):.4f}, "
        f"max exceedance {np.max(result.exceedance):g}",
        fontsize=11,
    )
    canvas = text_caching_canvas(fig)
    canvas.draw()
    _write_png(canvas, path)
    return fig
