"""docs/scripts/tutorial_figures.py writes where ``--out`` says (default docs/figures)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
LOAD_CASES = ("Flexion", "Extension", "LateralBending", "AxialRotation")
CLASSES = ("none", "facet_contact", "ligament_tension", "neutral_zone")


@pytest.fixture
def script(tmp_path, monkeypatch):
    """The script, reading small pipeline outputs of four specimens (one per class)."""
    spec = importlib.util.spec_from_file_location(
        "tutorial_figures", ROOT / "docs" / "scripts" / "tutorial_figures.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    planted, diagnosis, calibration = (tmp_path / n for n in ("planted", "diag", "cal"))
    for folder in (planted, diagnosis / "plots", calibration):
        folder.mkdir(parents=True)
    names = [f"s{i}" for i in range(4)]
    pd.DataFrame(
        [(s, lc, m, 0.5 * m) for s in names for lc in LOAD_CASES for m in (1, 2, 3)],
        columns=["specimen", "load_case", "moment_nm", "rom_deg"],
    ).to_csv(planted / "measurements.csv", index=False)
    pd.DataFrame({"specimen": names, "effect": CLASSES}).to_csv(planted / "truth.csv")
    pd.DataFrame(
        [(s, lc, 1.0) for s in names for lc in LOAD_CASES],
        columns=["specimen", "load_case", "residual_sigma"],
    ).to_csv(diagnosis / "residuals.csv", index=False)
    verdicts = [
        {"specimen": s, "verdict": c, "baseline_mae_deg": 0.1} for s, c in zip(names, CLASSES)
    ]
    (diagnosis / "diagnosis.json").write_text(json.dumps(verdicts))
    pd.DataFrame({"specimen": names, "mae_deg": 0.03}).to_csv(calibration / "metrics.csv")
    monkeypatch.setattr(module, "PLANTED", planted)
    monkeypatch.setattr(module, "DIAGNOSIS", diagnosis)
    monkeypatch.setattr(module, "CALIBRATION", calibration)
    monkeypatch.setattr(
        module,
        "NEEDED",
        {"plant": [planted / "truth.csv"], "diagnose": [diagnosis / "diagnosis.json"]},
    )
    return module


def test_out_chooses_the_folder_and_docs_figures_is_the_default(script, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert script.main(["--out", "figs"]) == 0
    written = {p.name for p in (tmp_path / "figs").iterdir()}
    assert {"tutorial-cohort.png", "tutorial-verdicts.md", "tutorial-before-after.md"} <= written
    assert script.parse_args([]).out == ROOT / "docs" / "figures"


def test_the_calibration_figure_of_the_diagnosed_specimen_is_copied(script, tmp_path):
    """The docs show the recalibration's own figure of the specimen whose diagnosis they show."""
    (script.DIAGNOSIS / "plots" / "s1.png").write_bytes(b"diagnosis of s1")
    (script.CALIBRATION / "plots").mkdir()
    (script.CALIBRATION / "plots" / "s1.png").write_bytes(b"calibration of s1")
    (script.CALIBRATION / "plots" / "s0.png").write_bytes(b"calibration of s0")
    assert script.main(["--out", str(tmp_path / "figs")]) == 0
    assert (tmp_path / "figs" / "tutorial-specimen.png").read_bytes() == b"diagnosis of s1"
    assert (tmp_path / "figs" / "tutorial-calibration.png").read_bytes() == b"calibration of s1"


def test_absent_outputs_exit_0_unless_required(script, tmp_path, monkeypatch, capsys):
    """A fresh clone builds the docs without the figures; CI (after ``make repro``) requires
    them, so a pipeline that stops writing them fails CI."""
    monkeypatch.setattr(script, "NEEDED", {"plant": [ROOT / "data" / "planted" / "absent.csv"]})
    assert script.main(["--out", str(tmp_path / "figs")]) == 0
    assert script.main(["--out", str(tmp_path / "figs"), "--require"]) == 1
    assert "absent.csv" in capsys.readouterr().out
