"""The reachability check before a fit, on the study's real data.

A small neural surrogate is trained here on the first 512 configurations of the prepared Large
split (about 20 s on one core), so that these tests depend on `dvc repro prepare` (the data) but
not on the MLflow store or the registered champion. The measurements are the study's own: the
64 Test specimens (`data/raw/Test`, FE curves of configurations inside the box, so within reach
by construction), and a planted cohort built from them by the `plant` stage's code.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest

from femcal.calibration import SurrogateCurveModel, calibrate
from femcal.calibration.report import write_outputs
from femcal.effects.composite import EffectModel
from femcal.errors import ConfigError, InputDataError
from femcal.measurements import Measurements, from_arrays, read_measurements
from femcal.moments import MomentPolicy
from femcal.reachability import (
    DEG_PER_RAD,
    UnreachableMeasurementsError,
    assess_reachability,
    build_envelope,
    check_reachability,
    reference_curves,
)
from femcal.schema import LOAD_CASES
from femcal.stages.calibrate import fit_warnings as _fit_warnings

from synth import study_space, tidy_table

ROOT = Path(__file__).resolve().parents[1]


def _study_data() -> tuple[Path, Path]:
    """The prepared study data and its Test folder: the project's, or prepared from the mirror.

    A fresh clone (CI) has no ``data/``; with FEMCAL_DATA_MIRROR set, the study's files are
    prepared once into a folder of the system's temporary directory (written, then renamed).
    """
    import os
    import tempfile

    prepared, raw_test = ROOT / "data" / "prepared", ROOT / "data" / "raw" / "Test"
    if (prepared / "large.csv").is_file() and raw_test.is_dir():
        return prepared, raw_test
    from femcal.fetch import mirror_from_env

    mirror = mirror_from_env(os.environ)
    if mirror is None:
        return prepared, raw_test
    cache = Path(tempfile.gettempdir()) / f"femcal-tests-prepared-{os.getuid()}"
    if not (cache / "large.csv").is_file():
        from femcal.prepare import prepare_dataset

        staging = cache.with_name(f"{cache.name}.partial-{os.getpid()}")
        prepare_dataset(mirror, staging)
        try:
            os.replace(staging, cache)
        except OSError:  # another test process (an xdist worker) placed it first
            import shutil

            shutil.rmtree(staging, ignore_errors=True)
            if not (cache / "large.csv").is_file():
                raise
    return cache, Path(mirror) / "Test"


PREPARED, RAW_TEST = _study_data()
EFFECTS = ("neutral_zone", "facet_contact", "ligament_tension")
#: The moment policy's settings (params.yaml ``moments``).
GROWTH, MAX_LOG_RATIO = 2.99, 0.51

pytestmark = pytest.mark.skipif(
    not (PREPARED / "large.csv").is_file() or not RAW_TEST.is_dir(),
    reason="needs the study's data: run `make repro` (or `dvc repro prepare`) first",
)


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def disc():
    """A small surrogate of the study's FE model (first 512 Large configurations)."""
    from femcal.datasets import load_split
    from femcal.surrogates.nn import NeuralSurrogate

    table, space = load_split(PREPARED, "large")
    keep = np.sort(table["config_id"].unique())[:512]
    rows = table[table["config_id"].isin(keep)]
    model = NeuralSurrogate(
        space, hidden=(64, 64, 64), max_epochs=300, patience=40, batch_size=32, seed=0
    )
    return model.fit(rows, rows["rom_deg"].to_numpy())


@pytest.fixture(scope="module")
def policy(disc) -> MomentPolicy:
    return MomentPolicy.for_surrogate(disc, growth=GROWTH, max_log_ratio=MAX_LOG_RATIO)


@pytest.fixture(scope="module")
def reference():
    return reference_curves(PREPARED / "large.csv")


@pytest.fixture(scope="module")
def test_meas() -> Measurements:
    return read_measurements(RAW_TEST)


def _envelope(disc, policy, reference, moments, effects=()):
    model = SurrogateCurveModel(disc, moments)
    if effects:
        model = EffectModel(model, list(effects))
    return build_envelope(model, sigma_model=policy.sigma_surrogate(moments), reference=reference)


@pytest.fixture(scope="module")
def envelope(disc, policy, reference, test_meas):
    return _envelope(disc, policy, reference, test_meas.moments)


def _like(meas: Measurements, rom: np.ndarray, source: str = "edited.csv") -> Measurements:
    return from_arrays(meas.specimens, meas.moments, rom, source=source)


@pytest.fixture(scope="module")
def planted(tmp_path_factory) -> Measurements:
    """The planted cohort (hidden facet contact, ligament tension, neutral zone; noise 0.05)."""
    from femcal.stages.plant import run_plant

    out = tmp_path_factory.mktemp("planted")
    path = run_plant(
        prepared_dir=PREPARED,
        out_dir=out,
        n_per_class=12,
        moments=[1, 1.5, 2, 2.5, 3, 3.5, 4, 4.5, 5],
        noise_deg=0.05,
        seed=0,
    )
    return read_measurements(path)


# ----------------------------------------------------------------------------- the envelope
def test_the_envelope_holds_the_fe_curves_and_is_seeded(disc, policy, reference, envelope):
    moments, rom = reference
    assert envelope.lower.shape == envelope.upper.shape == (4, len(moments))
    assert np.all(envelope.lower > 0) and np.all(envelope.lower < envelope.upper)
    # The FE training curves are inside by construction (they are joined in).
    assert np.all(rom >= envelope.lower - 1e-9) and np.all(rom <= envelope.upper + 1e-9)
    again = _envelope(disc, policy, reference, moments)
    np.testing.assert_array_equal(again.upper, envelope.upper)
    np.testing.assert_array_equal(again.balance_lower, envelope.balance_lower)


def test_moments_beyond_the_trained_range_are_covered_with_a_larger_sigma(disc, policy, reference):
    moments = np.array([1.25, 2.5, 5.0, 7.5])
    env = _envelope(disc, policy, reference, moments)
    assert np.all(np.isfinite(env.upper)) and np.all(env.lower < env.upper)
    # The surrogate's error sd at 7.5 Nm is exp(2.99 log 1.5) = 3.4 times the one at the
    # range's end (5 Nm).
    assert env.sigma_model[-1] == pytest.approx(3.36 * env.sigma_model[2], rel=0.01)
    assert np.all(env.upper[:, -1] > env.upper[:, -2])  # the curves keep rising beyond 5 Nm


def test_an_envelope_built_on_other_moments_is_a_config_error(envelope, planted):
    with pytest.raises(ConfigError, match=r"built on moments \[1\.0, 2\.0, 3\.0, 4\.0, 5\.0\]"):
        check_reachability(planted, envelope)


# ----------------------------------------------------------------------------- the check
def test_the_study_test_set_is_within_reach_without_a_warning(test_meas, envelope, caplog):
    report = check_reachability(test_meas, envelope)
    assert report.outside == [] and not report.refused
    assert set(report.status) == {"reachable"} and report.notes() == [""] * 64
    with caplog.at_level(logging.INFO, logger="femcal.reachability"):
        report.enforce()
    assert [r.levelno for r in caplog.records] == [logging.INFO]
    assert "every measured point lies within the envelope of the disc alone" in caplog.text


def test_radians_are_refused_with_the_hint(test_meas, envelope):
    radians = _like(test_meas, test_meas.rom_deg / DEG_PER_RAD, "rom_in_radians.csv")
    report = check_reachability(radians, envelope)
    assert report.refused and set(report.cause_key) == {"radians"}
    with pytest.raises(UnreachableMeasurementsError, match="radians") as info:
        report.enforce()
    text = str(info.value)
    assert isinstance(info.value, InputDataError)  # a measurement error: exit code 2 in the CLI
    assert text.startswith("rom_in_radians.csv: the measurements lie outside every curve")
    assert "multiply by 57.3" in text and "64 of the 64 come within reach" in text
    assert "specimens '0', '1'" in text and "Flexion (" in text


def test_values_a_thousand_times_too_large_hint_at_the_unit(test_meas, envelope):
    big = _like(test_meas, test_meas.rom_deg * 1000)
    with pytest.raises(UnreachableMeasurementsError, match=r"1000x too large: N·mm"):
        check_reachability(big, envelope).enforce()


def test_one_specimen_three_times_too_soft_warns_for_that_specimen_only(
    test_meas, envelope, caplog
):
    rom = test_meas.rom_deg.copy()
    # The softest specimen: x3 takes it beyond the softest disc of the box. (Most specimens
    # times 3 are still curves some softer disc produces: 9 of the 64 are flagged.)
    i = int(np.nanargmax(np.nanmax(rom, axis=(1, 2))))
    rom[i] *= 3
    report = check_reachability(_like(test_meas, rom), envelope)
    name = test_meas.specimens[i]
    assert report.outside == [name] and not report.refused
    assert report.cause_key[i] == "above"
    assert [bool(n) for n in report.notes()] == [k == i for k in range(64)]
    with caplog.at_level(logging.WARNING, logger="femcal.reachability"):
        report.enforce()
    assert len(caplog.records) == 1
    assert re.search(rf"edited\.csv: 1 of 64 specimens .*: '{name}'; load cases", caplog.text)


def test_swapped_load_cases_get_the_convention_hint(test_meas, envelope):
    # LateralBending and AxialRotation swapped: the specimens whose swap leaves the envelope
    # are named, each with the swap as its likely cause (the others are curves the disc can
    # produce either way, and a fit reaches them).
    swapped = _like(test_meas, test_meas.rom_deg[:, [0, 1, 3, 2]])
    report = check_reachability(swapped, envelope)
    assert len(report.outside) >= 5 and not report.refused
    keys = {report.cause_key[test_meas.specimens.index(s)] for s in report.outside}
    assert keys == {"load_cases:Flexion,Extension,AxialRotation,LateralBending"}
    assert "the curves fit with LateralBending and AxialRotation swapped" in report.message()


def test_flexion_extension_swapped_get_the_convention_hint_where_the_model_tells_them_apart():
    """On the study's disc, flexion and extension are nearly interchangeable over the box, so
    a Flexion/Extension swap of FE-like curves mostly stays within reach. In a world whose
    model ties extension to 1.5 x flexion (tests/synth.py), the swap is out of reach and named.
    """
    from femcal.surrogates.nn import NeuralSurrogate

    table = tidy_table(48, seed=3)
    surrogate = NeuralSurrogate(
        study_space(), hidden=(32, 32), max_epochs=40, patience=40, batch_size=16, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    moments = np.arange(1.0, 6.0)
    model = SurrogateCurveModel(surrogate, moments)
    rom = model.predict(study_space().sample_uniform(6, np.random.default_rng(1)))
    env = build_envelope(model, sigma_model=0.02)
    names = [f"S{i}" for i in range(6)]
    assert check_reachability(from_arrays(names, moments, rom), env).outside == []
    swapped = from_arrays(names, moments, rom[:, [1, 0, 2, 3]], source="swapped.csv")
    report = check_reachability(swapped, env)
    assert report.outside == names
    assert set(report.cause_key) == {"load_cases:Extension,Flexion,LateralBending,AxialRotation"}
    hint = (
        "physics the disc alone lacks (run `femcal diagnose`: it fits the disc with each effect "
        "and names the one missing; --effects adds it); else a different load case convention: "
        "the curves fit with Flexion and Extension swapped"
    )
    assert hint in report.message()


def test_planted_effects_are_within_reach_with_the_effects_on(disc, policy, reference, planted):
    env = _envelope(disc, policy, reference, planted.moments, EFFECTS)
    assert env.effects == EFFECTS
    report = check_reachability(planted, env)
    assert report.outside == [], report.message()
    # ... while the same cohort in radians is still refused with the effects on.
    radians = _like(planted, planted.rom_deg / DEG_PER_RAD)
    with pytest.raises(UnreachableMeasurementsError, match="radians"):
        check_reachability(radians, env).enforce()


# ----------------------------------------------------------------------------- the outputs
def test_a_fit_worse_than_the_mean_is_flagged_never_a_plain_success(
    tmp_path, disc, policy, test_meas, envelope
):
    # What calibrate did before the check: four specimens in radians, fitted anyway.
    meas = test_meas.subset(["0", "1", "2", "3"])
    rom = meas.rom_deg / DEG_PER_RAD
    report = check_reachability(_like(meas, rom), envelope)
    result = calibrate(
        SurrogateCurveModel(disc, meas.moments),
        rom,
        specimens=meas.specimens,
        method="pgd",
        options={"n_bank_uniform": 64, "n_starts": 2, "max_iter": 4},
    )
    assert np.all(result.r2_mean < 0)
    figures = write_outputs(result, tmp_path, plots=False, reachability=report.notes())
    assert figures["n_r2_negative"] == 4 and figures["n_outside_envelope"] == 4
    metrics = pd.read_csv(tmp_path / "metrics.csv", keep_default_na=False)
    assert metrics["flag"].tolist() == ["R2<0; outside envelope"] * 4
    assert metrics["reachability"].str.contains("values look like radians").all()
    summary = (tmp_path / "summary.md").read_text()
    assert "**Warning: 4 of 4 specimens fit worse than their mean (R² < 0): see metrics.csv" in (
        summary
    )
    assert json.loads((tmp_path / "summary.json").read_text())["n_r2_negative"] == 4
    line = _fit_warnings(figures, "out")
    assert "WARNING: 4 of 4 specimens fit worse than their mean (R² < 0): see out/metrics.csv" in (
        line
    )


def test_a_good_fit_has_no_flag(tmp_path, disc, test_meas):
    meas = test_meas.subset(["0", "1"])
    result = calibrate(
        SurrogateCurveModel(disc, meas.moments),
        meas.rom_deg,
        specimens=meas.specimens,
        method="pgd",
        options={"n_bank_uniform": 64, "n_starts": 2, "max_iter": 4},
    )
    figures = write_outputs(result, tmp_path, plots=False, reachability=["", ""])
    metrics = pd.read_csv(tmp_path / "metrics.csv", keep_default_na=False)
    assert metrics["flag"].tolist() == ["", ""] and figures["n_r2_negative"] == 0
    assert "Warning" not in (tmp_path / "summary.md").read_text()
    assert _fit_warnings(figures, "out") == ""


# ----------------------------------------------------------------------------- the stage
@pytest.fixture(scope="module")
def registry(tmp_path_factory, disc):
    """A private MLflow store with ``disc`` registered as the champion."""
    from femcal.tracking import (
        configure_tracking,
        ensure_experiment,
        log_surrogate,
        register_and_promote,
    )

    root = tmp_path_factory.mktemp("registry")
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("MLFLOW_TRACKING_URI", raising=False)
        configure_tracking(store_dir=root / "mlruns")
        ensure_experiment("test", store_dir=root / "mlruns")
        with mlflow.start_run():
            info = log_surrogate(disc, disc.space)
        register_and_promote(info.model_uri, name="ivd-rom-surrogate", val_metric=0.1)
        yield root
    mlflow.set_tracking_uri(None)


def _write_long(path: Path, meas: Measurements, rom: np.ndarray) -> Path:
    i, k, j = np.nonzero(~np.isnan(rom))
    pd.DataFrame(
        {
            "specimen": [meas.specimens[a] for a in i],
            "load_case": [LOAD_CASES[a] for a in k],
            "moment_nm": meas.moments[j],
            "rom_deg": rom[i, k, j],
        }
    ).to_csv(path, index=False)
    return path


def _run(registry, measurements, out):
    from femcal.jobs.calibrate import CalibrationJob, run_calibration

    return run_calibration(
        CalibrationJob(
            measurements=measurements,
            out_dir=registry / out,
            method="pgd",
            model_uri="models:/ivd-rom-surrogate@champion",
            holdout_uri=None,
            start_bank=PREPARED / "large.csv",
            options={"n_starts": 2, "max_iter": 4},
            seed=0,
            error_growth=GROWTH,
            max_log_ratio=MAX_LOG_RATIO,
            plots=False,
        )
    )


def test_calibrate_refuses_radians_before_the_fit(registry, test_meas):
    meas = test_meas.subset([str(i) for i in range(8)])
    path = _write_long(registry / "radians.csv", meas, meas.rom_deg / DEG_PER_RAD)
    with pytest.raises(UnreachableMeasurementsError, match=r"radians\.csv: .*multiply by 57\.3"):
        _run(registry, path, "radians-out")
    assert not (registry / "radians-out").exists()  # refused before the fit: nothing written


def test_calibrate_marks_the_specimen_out_of_reach(registry, test_meas, caplog):
    meas = test_meas.subset(["53", "0", "1", "2"])  # 53: the softest Test specimen
    rom = meas.rom_deg.copy()
    rom[0] *= 3
    path = _write_long(registry / "soft.csv", meas, rom)
    with caplog.at_level(logging.WARNING, logger="femcal.reachability"):
        _, figures = _run(registry, path, "out")
    assert re.search(r"soft\.csv: 1 of 4 specimens .*: '53'", caplog.text)
    assert figures["n_outside_envelope"] == 1
    metrics = pd.read_csv(registry / "out" / "metrics.csv", keep_default_na=False)
    assert metrics["reachability"].str.match(r"\d+/20 points outside the envelope of the disc")[0]
    assert metrics["reachability"].tolist()[1:] == ["", "", ""]
    assert "outside envelope" in metrics["flag"][0]
    assert "specimens have measured points outside every curve" in (
        (registry / "out" / "summary.md").read_text()
    )


def test_assess_reachability_checks_in_well_under_a_second(disc, policy, test_meas):
    report = assess_reachability(
        test_meas,
        SurrogateCurveModel(disc, test_meas.moments),
        sigma_model=policy.sigma_surrogate(test_meas.moments),
        reference=PREPARED / "large.csv",
    )
    assert report.outside == []
    # Generous bound (a loaded CI machine); typically 0.05-0.2 s for the 64 specimens.
    assert report.envelope.seconds + report.seconds < 5.0
