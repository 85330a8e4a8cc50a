"""Saved baselines are data, not code: skops + LightGBM text, exact round trip, no tampering."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import skops.io as sio
from sklearn.preprocessing import FunctionTransformer

from femcal.errors import InputDataError, SurrogateNotFittedError, UntrustedArtifactError
from femcal.surrogates import make_surrogate
from femcal.surrogates.baselines import (
    BASELINE_NAMES,
    LightGBMSurrogate,
    SklearnSurrogate,
    load_baseline,
)

from synth import study_space, tidy_table


@pytest.fixture(scope="module")
def tables() -> tuple[pd.DataFrame, pd.DataFrame]:
    return tidy_table(24, seed=0), tidy_table(8, seed=1)


@pytest.fixture(scope="module")
def saved_lightgbm(tmp_path_factory, tables) -> tuple[Path, np.ndarray]:
    train, test = tables
    model = make_surrogate("lightgbm", space=study_space(), seed=0)
    model.fit(train, train["rom_deg"].to_numpy())
    folder = tmp_path_factory.mktemp("saved") / "lightgbm"
    model.save(folder)
    return folder, model.predict(test)


@pytest.mark.parametrize("name", BASELINE_NAMES)
def test_round_trip_is_bit_identical_and_pickle_free(name, tables, tmp_path):
    train, test = tables
    model = make_surrogate(name, space=study_space(), seed=0)
    model.fit(train, train["rom_deg"].to_numpy())
    model.save(tmp_path / name)
    files = sorted(p.name for p in (tmp_path / name).iterdir())
    expected = ["config.json", "model.skops"] + (["lightgbm.txt"] if name == "lightgbm" else [])
    assert files == sorted(expected)
    config = json.loads((tmp_path / name / "config.json").read_text())
    assert config["format"] == "femcal-baseline" and config["estimator_name"] == name
    loaded = load_baseline(tmp_path / name)
    assert type(loaded) is type(model) and loaded.space == model.space
    np.testing.assert_array_equal(loaded.predict(test), model.predict(test))
    # The saved model and the one still in memory are unchanged by saving (booster re-attached).
    np.testing.assert_array_equal(model.predict(test), loaded.predict(test))


def test_lightgbm_booster_is_lightgbm_text(saved_lightgbm, tables):
    folder, expected = saved_lightgbm
    assert (folder / "lightgbm.txt").read_text().startswith("tree\nversion=")
    assert "lightgbm.basic.Booster" not in sio.get_untrusted_types(file=folder / "model.skops")
    loaded = LightGBMSurrogate.load(folder)
    np.testing.assert_array_equal(loaded.predict(tables[1]), expected)


def test_unfitted_baseline_cannot_be_saved(tmp_path):
    with pytest.raises(SurrogateNotFittedError, match="not fitted yet; call fit"):
        make_surrogate("linear", space=study_space()).save(tmp_path / "x")


def _copy(folder: Path, dest: Path) -> Path:
    dest.mkdir()
    for f in folder.iterdir():
        (dest / f.name).write_bytes(f.read_bytes())
    return dest


def test_changed_file_is_refused_by_its_hash(saved_lightgbm, tmp_path):
    folder, _ = saved_lightgbm
    copy = _copy(folder, tmp_path / "lightgbm")
    text = (copy / "lightgbm.txt").read_text()
    (copy / "lightgbm.txt").write_text(text.replace("leaf_value=", "leaf_value=1", 1))
    with pytest.raises(InputDataError, match=r"lightgbm\.txt: its SHA-256 is not the one"):
        load_baseline(copy)
    copy = _copy(folder, tmp_path / "again")
    (copy / "model.skops").write_bytes((copy / "model.skops").read_bytes() + b"\0")
    with pytest.raises(InputDataError, match=r"model\.skops: its SHA-256 is not the one"):
        load_baseline(copy)


def test_file_with_code_is_refused_before_anything_runs(saved_lightgbm, tmp_path):
    """A skops file that would call os.system (config.json hash updated to match) is refused."""
    folder, _ = saved_lightgbm
    copy = _copy(folder, tmp_path / "evil")
    marker = tmp_path / "ran"
    evil = FunctionTransformer(func=os.system, kw_args={"command": f"touch {marker}"})
    sio.dump(evil, copy / "model.skops")
    config = json.loads((copy / "config.json").read_text())
    digest = hashlib.sha256((copy / "model.skops").read_bytes()).hexdigest()
    config["sha256"]["model.skops"] = digest
    (copy / "config.json").write_text(json.dumps(config))
    with pytest.raises(UntrustedArtifactError, match=r"model\.skops holds type\(s\) femcal does"):
        load_baseline(copy)
    assert not marker.exists()


def test_not_a_saved_baseline(tmp_path, saved_lightgbm):
    with pytest.raises(InputDataError, match=r"not a saved femcal baseline \(no config.json\)"):
        load_baseline(tmp_path / "nothing")
    (tmp_path / "old.joblib").write_bytes(b"pickle")
    with pytest.raises(InputDataError, match=r"old\.joblib beside it is a pickle"):
        load_baseline(tmp_path / "old")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "config.json").write_text('{"format": "something-else"}')
    with pytest.raises(InputDataError, match="expected 'femcal-baseline'"):
        load_baseline(bad)
    (bad / "config.json").write_text("{oops")
    with pytest.raises(InputDataError, match="config.json: not valid JSON"):
        load_baseline(bad)
    copy = _copy(saved_lightgbm[0], tmp_path / "newer")
    config = json.loads((copy / "config.json").read_text())
    (copy / "config.json").write_text(json.dumps({**config, "format_version": 99}))
    with pytest.raises(InputDataError, match="format version 99; this femcal reads version 1"):
        load_baseline(copy)
    copy = _copy(saved_lightgbm[0], tmp_path / "partial")
    (copy / "lightgbm.txt").unlink()
    with pytest.raises(InputDataError, match=r"lightgbm\.txt: missing"):
        load_baseline(copy)


def test_load_checks_the_class(saved_lightgbm):
    from femcal.surrogates.baselines import LinearSurrogate

    with pytest.raises(InputDataError, match="holds a LightGBMSurrogate, not a fitted Linear"):
        LinearSurrogate.load(saved_lightgbm[0])
    assert isinstance(SklearnSurrogate.load(saved_lightgbm[0]), LightGBMSurrogate)
