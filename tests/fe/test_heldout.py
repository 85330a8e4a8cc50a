"""The FE surrogate's held-out error added to its training report (femcal.fe.heldout), on a
real small network trained on the synthetic study-like curves of ``synth``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from femcal.errors import InputDataError
from femcal.fe.heldout import add_to_report, band_key, heldout_errors
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table

MOMENTS = (0.5, 1, 2, 3, 4, 5, 6, 8, 10)


@pytest.fixture(scope="module")
def trained() -> tuple[NeuralSurrogate, object]:
    table = tidy_table(24, seed=3, moments=MOMENTS)
    X, y = table.drop(columns=["rom_deg", "idp_mpa", "status"]), table["rom_deg"].to_numpy()
    model = NeuralSurrogate(
        study_space(), hidden=(16, 16), max_epochs=10, patience=10, batch_size=16, seed=0
    )
    return model.fit(X, y), table


def _heldout(n: int, seed: int):
    table = tidy_table(n, seed=seed, moments=MOMENTS)
    return table.assign(config_id=table["config_id"] + 1000)


def test_mae_by_band_and_load_case(trained) -> None:
    model, train = trained
    heldout = _heldout(6, seed=11)
    out = heldout_errors(model, heldout, train)
    err = np.abs(model.predict(heldout) - heldout["rom_deg"].to_numpy())
    low = heldout["moment_nm"].to_numpy() <= 5
    assert out["heldout_mae_deg_0_5"] == pytest.approx(float(err[low].mean()))
    assert out["heldout_mae_deg_5_10"] == pytest.approx(float(err[~low].mean()))
    assert band_key((0.5, 5.0)) == "heldout_mae_deg_0_5"
    assert out["heldout_n_points"] == {"0.5-5": 6 * 4 * 6, "5.5-10": 6 * 4 * 3}
    assert set(out["heldout_mae_deg_by_load_case"]["5.5-10"]) == {
        "Flexion",
        "Extension",
        "LateralBending",
        "AxialRotation",
    }
    assert out["heldout_n_configurations"] == 6
    assert out["n_train_configurations"] == 24


def test_failed_levels_are_left_out_and_empty_tables_refused(trained) -> None:
    model, train = trained
    heldout = _heldout(2, seed=5)
    heldout.loc[heldout["moment_nm"] > 5, "rom_deg"] = np.nan  # a failed run's missing levels
    out = heldout_errors(model, heldout, train)
    assert "heldout_mae_deg_5_10" not in out and "heldout_mae_deg_0_5" in out
    with pytest.raises(InputDataError, match="no finite rom_deg"):
        heldout_errors(model, heldout.assign(rom_deg=np.nan), train)
    with pytest.raises(InputDataError, match="target must be one of"):
        heldout_errors(model, heldout, train, target="rom")
    idp = heldout_errors(model, _heldout(2, seed=6), train, target="idp_mpa")
    assert "heldout_mae_mpa_0_5" in idp and "heldout_mae_mpa_by_load_case" in idp


def test_the_report_keeps_its_figures(tmp_path) -> None:
    report = tmp_path / "train-large.json"
    with pytest.raises(InputDataError, match="run `femcal train` first"):
        add_to_report(report, {"heldout_mae_deg_0_5": 0.1})
    report.write_text(json.dumps({"val_mae_deg": 0.2, "n_trials": 3}))
    merged = add_to_report(report, {"heldout_mae_deg_0_5": 0.1})
    assert (
        json.loads(report.read_text())
        == merged
        == {
            "val_mae_deg": 0.2,
            "n_trials": 3,
            "heldout_mae_deg_0_5": 0.1,
        }
    )
    report.write_text("[1, 2]")
    with pytest.raises(InputDataError, match="not a JSON object"):
        add_to_report(report, {})
