"""The story of a user-written effect (docs/how-to/effect-plugin.md), end to end through `femcal`.

`femcal diagnose` says `unexplained` and describes what is missing -> the user writes that
effect as a class in a file of their own -> `femcal diagnose --effects-module FILE` names it ->
`femcal calibrate --effects NAME --effects-module FILE` -> the error falls to the noise.

The registry is a temporary MLflow store with a small fitted surrogate as champion; the hidden
physics (a softening in flexion and lateral bending) is added to that surrogate's own curves in
numpy, so the data are not built from the user's class.
"""

from __future__ import annotations

import json
import textwrap

import mlflow
import numpy as np
import pandas as pd
import pytest
import yaml

from femcal.calibration import SurrogateCurveModel
from femcal.cli import main
from femcal.schema import LOAD_CASES
from femcal.surrogates.nn import NeuralSurrogate
from femcal.tracking import (
    configure_tracking,
    ensure_experiment,
    log_surrogate,
    register_and_promote,
)

from synth import study_space, tidy_table

NOISE = 0.02
MOMENTS = np.arange(1.0, 5.01, 0.5)
USER_EFFECT = '''
import torch

from femcal.effects import Effect, EffectParameter, register_effect


@register_effect
class DiscSoftening(Effect):
    """Extra rotation that accelerates at high moments (flexion, lateral bending)."""

    name = "disc_softening"
    kind = "series"
    load_cases = ("Flexion", "LateralBending")
    parameters = (
        EffectParameter("softening_deg", "deg", 0.0, 2.0, start=0.0),
        EffectParameter("softening_power", "1", 1.0, 6.0),
    )

    def rotation(self, moment_nm, p):
        a = p["softening_deg"].reshape(-1, 1, 1)
        power = p["softening_power"].reshape(-1, 1, 1)
        return a * (moment_nm / 5.0) ** power
'''


@pytest.fixture
def project(tmp_path, monkeypatch, clean_registry):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    table = tidy_table(48, seed=3)
    surrogate = NeuralSurrogate(
        study_space(), hidden=(32, 32), max_epochs=40, patience=40, batch_size=16, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    # In this world the surrogate's curves ARE the truth: its own error is zero, not its
    # validation error against the synthetic table (which the moment policy would count).
    surrogate.best_val_mae_deg_ = 1e-3
    surrogate.val_error_profile_ = None
    configure_tracking(store_dir=tmp_path / "mlruns")
    ensure_experiment("story", store_dir=tmp_path / "mlruns")
    with mlflow.start_run():
        info = log_surrogate(surrogate, surrogate.space)
    register_and_promote(info.model_uri, name="ivd-rom-surrogate", val_metric=0.1)
    # Measurements: 6 specimens with the softening (0.5..0.9 deg at 5 Nm, power 3..5), 3 without.
    rng = np.random.default_rng(4)
    clean = SurrogateCurveModel(surrogate, MOMENTS).predict(study_space().sample_uniform(9, rng))
    planted = np.arange(9) < 6
    for i in np.flatnonzero(planted):
        extra = rng.uniform(0.5, 0.9) * (MOMENTS / 5.0) ** rng.uniform(3.0, 5.0)
        clean[i, [0, 2]] += extra
    rom = clean + rng.normal(0, NOISE, clean.shape)
    rows = [
        (f"S{i}", lc, m, rom[i, j, k])
        for i in range(9)
        for j, lc in enumerate(LOAD_CASES)
        for k, m in enumerate(MOMENTS)
    ]
    pd.DataFrame(rows, columns=["specimen", "load_case", "moment_nm", "rom_deg"]).to_csv(
        "meas.csv", index=False
    )
    params = {
        "mlflow": {"store_dir": "mlruns", "experiment": "story", "model_name": "ivd-rom-surrogate"},
        "moments": {"error_growth": 2.99, "max_log_ratio": 0.51},
        "effects": {"modules": []},
        "calibrate": {
            "datasets": {},
            "out_dir": "cal",
            "method": "pgd",
            "model_uri": "models:/ivd-rom-surrogate@champion",
            "holdout_uri": None,
            "start_bank": None,
            "seed": 0,
            "plots": False,
            "options": {"pgd": {"n_bank_uniform": 1024, "noise_deg": NOISE}},
        },
        "diagnose": {
            "measurements": "meas.csv",
            "out_dir": "diag",
            "metrics_file": None,
            "noise_deg": NOISE,
            "candidates": None,
            "min_delta": 10.0,
            "seed": 0,
            "plots": True,
            "max_plots": 2,
        },
    }
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    yield tmp_path, planted
    mlflow.set_tracking_uri(None)


def _verdicts(folder) -> dict[str, dict]:
    return {d["specimen"]: d for d in json.loads((folder / "diagnosis.json").read_text())}


def test_unexplained_then_a_user_effect_then_the_error_falls(project, capsys):
    tmp, planted = project
    # 1. The diagnosis: the softened specimens are unexplained, and it says what is missing.
    assert main(["diagnose", "--out", "d1"]) == 0
    printed = capsys.readouterr().out
    assert "unexplained:" in printed and "--effects-module" in printed
    first = _verdicts(tmp / "d1")
    for i, is_planted in enumerate(planted):
        d = first[f"S{i}"]
        if not is_planted:
            assert d["verdict"] == "none", d["verdict"]
            continue
        assert d["verdict"] == "unexplained", d["verdict"]
        text = " ".join(d["discrepancy"]["description"])
        assert "Flexion: more rotation than the model" in text
        assert "growing with the moment" in text
    assert (tmp / "d1" / "plots" / "S0.png").exists() and (tmp / "d1" / "heatmap.png").exists()

    # 2. The user writes the missing effect as a class in a file of their own ...
    (tmp / "my_effects.py").write_text(textwrap.dedent(USER_EFFECT))
    # 3. ... and the diagnosis names it.
    assert main(["diagnose", "--out", "d2", "--effects-module", "my_effects.py"]) == 0
    printed = capsys.readouterr().out
    assert "effects found: disc_softening (6)" in printed
    assert f"--effects disc_softening --noise-deg {NOISE:.3g})" in printed
    second = _verdicts(tmp / "d2")
    for i, is_planted in enumerate(planted):
        assert second[f"S{i}"]["verdict"] == ("disc_softening" if is_planted else "none")

    # 4. Recalibrate with it: the error falls to the noise.
    assert main(["calibrate", "--measurements", "meas.csv", "--out", "before"]) == 0
    args = ["--measurements", "meas.csv", "--out", "after", "--effects", "disc_softening"]
    assert main(["calibrate", *args, "--effects-module", "my_effects.py"]) == 0
    before = pd.read_csv(tmp / "before" / "metrics.csv")["mae_deg"].to_numpy()
    after = pd.read_csv(tmp / "after" / "metrics.csv")["mae_deg"].to_numpy()
    assert after[planted].mean() < before[planted].mean() / 3
    assert after[planted].mean() <= 1.5 * max(after[~planted].mean(), NOISE / 2)
    assert "softening_deg" in (tmp / "after" / "parameters.csv").read_text().splitlines()[0]


def test_repeated_measurements_in_the_file_count_as_one_point_of_their_weight(project, caplog):
    """What to measure next asks for repeated measurements at one point: `femcal diagnose`
    reads such rows (no error), says so, and scores their mean with the noise over root k
    (the surrogate's own error, 1e-3 deg here, does not average out)."""
    tmp, _ = project
    meas = pd.read_csv("meas.csv")
    meas = meas[meas["specimen"] == "S8"]  # one specimen: the reading is what is tested
    s8 = meas[meas["load_case"] == "Flexion"]
    last = s8[s8["moment_nm"] == 5.0].iloc[0]
    repeats = pd.DataFrame([last] * 3).assign(
        rom_deg=last["rom_deg"] + np.array([0.0, 0.01, -0.01])
    )
    pd.concat([meas, repeats]).to_csv("meas_repeats.csv", index=False)
    with caplog.at_level("INFO", logger="femcal.measurements"):
        assert main(["diagnose", "--measurements", "meas_repeats.csv", "--out", "d"]) == 0
    assert "1 point measured more than once" in caplog.text
    assert "'S8' Flexion 5 Nm (4 rows" in caplog.text
    res = pd.read_csv(tmp / "d" / "residuals.csv")
    point = res[(res["specimen"] == "S8") & (res["load_case"] == "Flexion")]
    assert len(point) == len(MOMENTS)  # the four rows are one point
    at5 = point[point["moment_nm"] == 5.0].iloc[0]
    other = point[point["moment_nm"] == 4.5].iloc[0]
    sigma5 = at5["residual_deg"] / at5["residual_sigma"]
    sigma45 = other["residual_deg"] / other["residual_sigma"]
    assert sigma5 == pytest.approx(np.hypot(NOISE / 2, 1e-3 * np.sqrt(np.pi / 2)), rel=1e-3)
    assert sigma45 == pytest.approx(np.hypot(NOISE, 1e-3 * np.sqrt(np.pi / 2)), rel=1e-3)
