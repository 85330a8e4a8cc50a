"""Figures drawn in processes started before torch: the same files, the same pixels."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from femcal.calibration import calibrate
from femcal.calibration.plots import FigureCurves, FigureData, figure_workers
from femcal.calibration.report import write_outputs
from femcal.figures import FigureWorkers


@pytest.fixture(scope="module")
def pool():
    with figure_workers(2) as workers:
        yield workers


@pytest.fixture
def noisy(curve_model, truth):
    """Four specimens whose points have an sd of 0.05 deg (the figures draw a band)."""
    rng = np.random.default_rng(1)
    targets = truth[1][:4] + rng.normal(0.0, 0.05, truth[1][:4].shape)
    return calibrate(
        curve_model,
        targets,
        specimens=[f"S{i}" for i in range(4)],
        method="pgd",
        weight_sd=0.05,
        options={"n_bank_uniform": 64},
    )


def _pixels(path):
    with Image.open(path) as image:
        return np.asarray(image)


def test_the_figure_code_imports_neither_torch_nor_matplotlib():
    code = (
        "import sys, femcal.calibration.plots, femcal.figures\n"
        "print(sorted(m for m in ('torch', 'matplotlib') if m in sys.modules))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]", proc.stdout


def test_workers_started_before_torch_draw_without_it():
    code = (
        "from femcal.calibration.plots import figure_workers\n"
        "with figure_workers(1) as pool:\n"
        "    import torch  # the command's own imports, after the workers started\n"
        "    calls = [(eval, \"sorted(m for m in ('torch', 'matplotlib.figure') if m in "
        "__import__('sys').modules)\")]\n"
        "    print([value for _, value in pool.map(calls)])\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[['matplotlib.figure']]", proc.stdout


@pytest.mark.parametrize("plots", ["all", "summary"])
def test_the_outputs_drawn_in_the_workers_are_those_drawn_here(
    tmp_path, noisy, curve_model, pool, plots
):
    here = write_outputs(noisy, tmp_path / "here", holdout=curve_model, plots=plots)
    there = write_outputs(noisy, tmp_path / "there", holdout=curve_model, plots=plots, pool=pool)
    assert here == there
    files = sorted(p.relative_to(tmp_path / "here") for p in (tmp_path / "here").rglob("*"))
    assert files == sorted(
        p.relative_to(tmp_path / "there") for p in (tmp_path / "there").rglob("*")
    )
    pngs = [f for f in files if f.suffix == ".png"]
    assert len(pngs) == (5 if plots == "all" else 1)
    for name in pngs:
        assert np.array_equal(_pixels(tmp_path / "here" / name), _pixels(tmp_path / "there" / name))


def test_the_data_sent_to_a_worker_are_the_rows_of_its_specimens(noisy):
    data, curves = FigureData.of(noisy), FigureCurves.at_measured(noisy, noisy.prediction + 1)
    part, part_curves = data.take(range(1, 3)), curves.take(range(1, 3))
    assert part.specimens == ("S1", "S2") and part.method == noisy.method
    np.testing.assert_array_equal(part.measured, noisy.measured[1:3])
    np.testing.assert_array_equal(part.error_scale_deg, noisy.error_scale_deg[1:3])
    np.testing.assert_array_equal(part_curves.holdout, noisy.prediction[1:3] + 1)
    np.testing.assert_array_equal(part_curves.moments, curves.moments)


def test_a_worker_error_is_raised_in_the_caller():
    with FigureWorkers(1) as workers, pytest.raises(ZeroDivisionError):
        list(workers.map([(divmod, 1, 0)]))


def test_before_figures_is_called_with_the_tables_written_and_no_figure_yet(tmp_path, noisy):
    out, seen = tmp_path / "out", {}

    def hook(figures):
        seen["files"] = sorted(p.name for p in out.rglob("*") if p.is_file())
        seen["figures"] = dict(figures)

    figures = write_outputs(noisy, out, before_figures=hook)
    assert {"parameters.csv", "metrics.csv", "curves.csv", "summary.json"} <= set(seen["files"])
    assert not [name for name in seen["files"] if name.endswith(".png")]
    assert seen["figures"] == figures
    assert (out / "summary.png").exists() and len(list((out / "plots").glob("*.png"))) == 4
