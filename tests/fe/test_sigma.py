"""The surrogate's stated error against held-out curves (femcal.fe.sigma), on a real small
network trained on the synthetic study-like curves of ``synth``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from femcal.errors import InputDataError
from femcal.fe.sigma import main, sigma_coverage
from femcal.moments import MomentPolicy
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table

MOMENTS = (0.5, 1, 2, 3, 4, 5, 6, 8, 10)


@pytest.fixture(scope="module")
def fitted() -> NeuralSurrogate:
    table = tidy_table(40, seed=3, moments=MOMENTS)
    X, y = table.drop(columns=["rom_deg", "idp_mpa", "status"]), table["rom_deg"].to_numpy()
    model = NeuralSurrogate(
        study_space(), hidden=(32, 32), max_epochs=40, patience=40, batch_size=16, seed=0
    )
    return model.fit(X, y)


def test_coverage_follows_the_stated_error(fitted: NeuralSurrogate) -> None:
    heldout = tidy_table(12, seed=11, moments=MOMENTS)
    policy = MomentPolicy.for_surrogate(fitted, growth=1.0, max_log_ratio=0.5)
    out = sigma_coverage(fitted, heldout, policy)
    assert set(out["coverage_2sigma"]) == {"0.5-5", "5.5-10"}
    assert out["n_points"] == {"0.5-5": 12 * 4 * 6, "5.5-10": 12 * 4 * 3}
    assert set(out["by_load_case"]["0.5-5"]) == {
        "Flexion",
        "Extension",
        "LateralBending",
        "AxialRotation",
    }
    # the same errors against an sd 100 times larger are all covered, against ~0 none
    wide = MomentPolicy((0.5, 10.0), 100.0, 1.0, 0.5)
    assert all(v == 1.0 for v in sigma_coverage(fitted, heldout, wide)["coverage_2sigma"].values())
    tight = MomentPolicy((0.5, 10.0), 1e-9, 1.0, 0.5)
    assert all(v < 0.05 for v in sigma_coverage(fitted, heldout, tight)["coverage_2sigma"].values())
    # MAE and RMS of the held-out errors by band
    pred = fitted.predict(heldout)
    low = heldout["moment_nm"].to_numpy() <= 5
    mae = float(np.abs(pred - heldout["rom_deg"].to_numpy())[low].mean())
    assert out["mae_deg"]["0.5-5"] == pytest.approx(mae)
    assert out["rms_deg"]["0.5-5"] >= out["mae_deg"]["0.5-5"]


def test_rows_without_a_curve_are_left_out_and_none_is_refused(fitted: NeuralSurrogate) -> None:
    heldout = tidy_table(2, seed=5, moments=MOMENTS)
    policy = MomentPolicy.for_surrogate(fitted, growth=1.0, max_log_ratio=0.5)
    heldout.loc[heldout["moment_nm"] > 5, "rom_deg"] = np.nan  # failed runs' missing levels
    out = sigma_coverage(fitted, heldout, policy)
    assert set(out["n_points"]) == {"0.5-5"}
    heldout["rom_deg"] = np.nan
    with pytest.raises(InputDataError, match=r"has no finite rom_deg; give FE curves"):
        sigma_coverage(fitted, heldout, policy)


def test_command_writes_the_metrics_file(fitted: NeuralSurrogate, tmp_path, monkeypatch) -> None:
    from femcal.training.loader import write_loader

    fitted.save(tmp_path / "model")
    write_loader(tmp_path / "model", fitted)  # a model folder as calibrate reads one
    tidy_table(4, seed=7, moments=MOMENTS).to_csv(tmp_path / "test.csv", index=False)
    moments = {"error_growth": 2.0, "max_log_ratio": 0.5}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({"moments": moments}))
    monkeypatch.chdir(tmp_path)
    out = main(["--model-uri", "model", "--heldout", "test.csv", "--metrics-file", "s.json"])
    assert json.loads((tmp_path / "s.json").read_text())["coverage"] == min(
        out["coverage_2sigma"].values()
    )  # the DVC metrics: the worst band; every figure beside it
    saved = json.loads((tmp_path / "s.details.json").read_text())
    assert saved["coverage_2sigma"] == out["coverage_2sigma"]
    assert saved["model_uri"] == "model" and saved["target"] == [0.9, 0.98]
