"""Calibration figures fit for a paper: size, labels, noise band, histograms, workers."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from PIL import Image

from femcal.calibration import SurrogateCurveModel, calibrate
from femcal.calibration.plots import (
    BAND,
    CALIBRATED,
    DPI,
    HELD_OUT,
    MEASURED,
    FigureCurves,
    dense_curves,
    plot_specimen,
    plot_specimens,
    plot_summary,
)
from femcal.calibration.report import holdout_scores, identifiability, write_outputs
from femcal.figures import chunks, free_cores, plot_workers, text_caching_canvas


@pytest.fixture
def result(curve_model, truth):
    return calibrate(
        curve_model,
        truth[1][:3],
        specimens=["S0", "S1", "S2"],
        method="pgd",
        options={"n_bank_uniform": 64},
    )


@pytest.fixture
def noisy(curve_model, truth):
    """A calibration that knows the noise: each point's sd is 0.05 deg."""
    rng = np.random.default_rng(1)
    targets = truth[1][:3] + rng.normal(0.0, 0.05, truth[1][:3].shape)
    return calibrate(
        curve_model, targets, method="pgd", weight_sd=0.05, options={"n_bank_uniform": 64}
    )


def _legend(fig) -> list[str]:
    return [t.get_text() for legend in fig.legends for t in legend.get_texts()]


def test_a_specimen_figure_has_the_diagnosis_width_and_resolution(tmp_path, result):
    write_outputs(result, tmp_path / "out", max_plots=1)
    with Image.open(tmp_path / "out" / "plots" / "S0.png") as image:
        assert image.size == (1500, 420)
        assert image.info["dpi"] == pytest.approx((DPI, DPI), abs=0.01)


def test_the_legend_names_what_each_line_is_not_the_method(tmp_path, result, curve_model):
    held = holdout_scores(result, curve_model)["prediction"]
    fig = plot_specimen(result, 0, tmp_path / "S0.png", FigureCurves.at_measured(result, held))
    labels = _legend(fig)
    assert labels == [MEASURED, CALIBRATED, HELD_OUT]
    assert result.method not in labels
    ax = fig.axes[0]
    assert ax.get_xlabel() == "moment (Nm)" and ax.get_ylabel() == "RoM (deg)"
    # the legend sits above the axes: it covers no data
    fig.canvas.draw()
    legend_box = fig.legends[0].get_window_extent()
    for ax in fig.axes:
        assert legend_box.y0 >= ax.get_window_extent().y1


def test_the_noise_band_is_drawn_when_the_noise_is_known(tmp_path, result, noisy):
    fig = plot_specimen(noisy, 0, tmp_path / "noisy.png")
    assert BAND in _legend(fig)
    for j, ax in enumerate(fig.axes):
        (band,) = ax.collections
        top = band.get_paths()[0].vertices[:, 1].max()
        expected = noisy.prediction[0, j].max() + 2 * noisy.error_scale_deg[0]
        assert top == pytest.approx(expected, abs=1e-6)
    plain = plot_specimen(result, 0, tmp_path / "plain.png")
    assert BAND not in _legend(plain)
    assert all(not ax.collections for ax in plain.axes)


def test_the_curves_are_continuous_with_the_noise_by_moment(tmp_path, result, small_surrogate):
    curves = dense_curves(
        result,
        lambda m: SurrogateCurveModel(small_surrogate, m),
        holdout_at=lambda m: SurrogateCurveModel(small_surrogate, m),
        sigma_at=lambda m: 0.02 * m,
    )
    assert len(curves.moments) > 4 * len(result.moments)
    assert curves.calibrated.shape == (3, 4, len(curves.moments))
    # at the measured moments the continuous curve is the calibrated prediction
    at = np.searchsorted(curves.moments, result.moments)
    np.testing.assert_allclose(curves.calibrated[:, :, at], result.prediction, atol=1e-5)
    fig = plot_specimen(result, 1, tmp_path / "S1.png", curves)
    model = next(line for line in fig.axes[0].lines if line.get_label() == CALIBRATED)
    assert len(model.get_xdata()) == len(curves.moments)
    band = fig.axes[0].collections[0].get_paths()[0].vertices
    width = band[:, 1].max() - band[:, 1].min()
    assert width > curves.calibrated[1, 0].max() - curves.calibrated[1, 0].min()


def test_the_summary_shows_both_histograms_and_labels_every_axis(tmp_path, result, curve_model):
    held = holdout_scores(result, curve_model)
    fig = plot_summary(result, tmp_path / "summary.png", held, identifiability(result))
    mae, r2 = fig.axes[0], fig.axes[1]
    assert r2.get_ylabel() == "specimens" and r2.get_xlabel()
    assert mae.get_ylabel() == "specimens"
    for ax in (mae, r2):
        assert [t.get_text() for t in ax.get_legend().get_texts()] == [CALIBRATED, HELD_OUT]
        fig.canvas.draw()  # the legend above the axes: it covers no bar
        assert ax.get_legend().get_window_extent().y0 >= ax.get_window_extent().y1 - 1
        # no histogram hides another: each is an outline, or filled with transparency
        bars = [p for p in ax.patches if p.get_visible()]
        assert len(bars) >= 2
        for bar in bars:
            face_alpha = bar.get_facecolor()[3] if bar.get_fill() else 0.0
            assert face_alpha < 0.6
            assert bar.get_linewidth() > 0 and bar.get_edgecolor()[3] > 0


def test_figures_drawn_in_worker_processes_are_those_drawn_in_one(tmp_path, result, noisy):
    paths = [tmp_path / f"one{i}.png" for i in range(3)]
    plot_specimens(noisy, paths, workers=1)
    forked = [tmp_path / f"forked{i}.png" for i in range(3)]
    plot_specimens(noisy, forked, workers=2)
    for a, b in zip(paths, forked):
        assert np.array_equal(np.asarray(Image.open(a)), np.asarray(Image.open(b)))
    alone = tmp_path / "alone.png"
    plot_specimen(noisy, 2, alone)
    assert np.array_equal(np.asarray(Image.open(alone)), np.asarray(Image.open(paths[2])))


def test_the_workers_never_outnumber_the_free_cores(monkeypatch):
    assert plot_workers(64, cores=1) == 1
    assert plot_workers(64, cores=2) == 2
    assert plot_workers(64, cores=16) == 8  # at least 8 figures each
    assert plot_workers(4, cores=2) == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # the command's thread count, or the user's
    assert free_cores() == 1 and plot_workers(64) == 1
    assert [list(c) for c in chunks(5, 1)] == [[0, 1], [2, 3], [4]]


def test_a_text_drawn_again_is_copied_with_the_same_pixels(tmp_path, noisy):
    fig = plot_specimen(noisy, 0, tmp_path / "S0.png")
    canvas = text_caching_canvas(fig)
    canvas.draw()
    first = np.asarray(canvas.buffer_rgba()).copy()
    rendered = canvas.get_renderer().texts_rendered
    assert rendered > 10  # tick labels, titles, legend, axis labels
    canvas.draw()
    assert canvas.get_renderer().texts_rendered == rendered  # nothing laid out again
    assert np.array_equal(first, np.asarray(canvas.buffer_rgba()))
    # the figure as plain Agg draws it: every text within half a pixel of the same place
    plain_canvas = FigureCanvasAgg(fig)
    plain_canvas.draw()
    plain = np.asarray(plain_canvas.buffer_rgba())
    differ = np.abs(plain[..., :3].astype(int) - first[..., :3]).max(-1) > 0
    assert differ.mean() < 0.05


def test_the_summary_page_is_drawn_beside_the_specimens(tmp_path, result):
    drawn = []
    paths = [tmp_path / f"S{i}.png" for i in range(3)]
    plot_specimens(result, paths, workers=1, beside=lambda: drawn.append("summary"))
    assert drawn == ["summary"] and all(p.exists() for p in paths)
    plot_specimens(result, [], beside=lambda: drawn.append("alone"))
    assert drawn == ["summary", "alone"]


def test_the_written_figure_is_the_figure_drawn_in_full(tmp_path, result, noisy):
    """Redrawn per specimen (static pixels kept, the y axes drawn without measuring their tick
    labels, the PNG written from the canvas), a figure has the pixels of a full draw."""
    for calibration in (result, noisy):
        for i in range(3):
            path = tmp_path / f"S{i}.png"
            fig = plot_specimen(calibration, i, path)
            canvas = text_caching_canvas(fig)
            canvas.draw()
            full = np.asarray(canvas.buffer_rgba())[..., :3]
            with Image.open(path) as image:
                assert image.mode == "RGB"
                assert np.array_equal(np.asarray(image), full)


def test_the_parameter_names_of_the_ranges_panel_stay_clear_of_the_panel_beside_it(
    tmp_path, result, curve_model
):
    ranges = identifiability(result)
    long = ranges.assign(parameter=[f"{p}_with_a_long_effect_name" for p in ranges["parameter"]])
    for table in (ranges, long):
        fig = plot_summary(result, tmp_path / "summary.png", None, table)
        renderer = fig.canvas.get_renderer()
        scatter, bars = fig.axes[2], fig.axes[3]
        names = [t.get_window_extent(renderer) for t in bars.get_yticklabels() if t.get_text()]
        assert len(names) == len(table)
        # every name inside the figure and right of the scatter panel's frame
        assert min(b.x0 for b in names) > scatter.get_window_extent(renderer).x1
        # neighbouring names do not overlap
        ys = sorted((b.y0, b.y1) for b in names)
        assert all(a[1] <= b[0] + 0.5 for a, b in zip(ys, ys[1:]))
