"""Tests of the study's classical baselines (femcal.surrogates.baselines), on synthetic data."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from sklearn.base import clone
from sklearn.exceptions import NotFittedError
from sklearn.linear_model import Ridge
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import PolynomialFeatures

from femcal.errors import ConfigError, FemcalError, InputDataError
from femcal.schema import LOAD_CASES, PARAMETER_NAMES
from femcal.space import ParameterSpace
from femcal.surrogates.baselines import (
    BASELINE_NAMES,
    PolynomialRidge,
    SklearnSurrogate,
    SurrogateNotFittedError,
)

LOWER = [0.03, 0.0075, 0.065, 1, 10, 0, -0.2, -0.2, -0.2, -0.2, 7.5, 0, 0]
UPPER = [0.21, 0.0525, 0.455, 50, 200, 0.33, 0, 0, 0, 0, 52.5, 0.3, 0.2]
SPACE = ParameterSpace(PARAMETER_NAMES, LOWER, UPPER)
#: registered name -> class, without importing the whole registry (femcal.surrogates.nn).
CLASSES = {cls.registry_name: cls for cls in SklearnSurrogate.__subclasses__()}


def make_table(n_configs: int = 30, seed: int = 0, linear: bool = False) -> pd.DataFrame:
    """Rows config x load case x moment (1..5 Nm), physical parameters, ``rom_deg``.

    The RoM is a smooth function of three parameters, the load case and the moment (or an
    exactly linear one when ``linear``).
    """
    rng = np.random.default_rng(seed)
    u = rng.random((n_configs, SPACE.dim))
    x = SPACE.from_unit(u)
    frames = []
    for k, lc in enumerate(LOAD_CASES):
        for m in range(1, 6):
            if linear:
                rom = 1.0 + k + 2.0 * u[:, 0] - 1.5 * u[:, 3] + 0.5 * m
            else:
                stiff = 0.6 + 0.8 * u[:, 2] + 0.5 * u[:, 3] * u[:, 10]
                rom = (2.0 + k) * np.log1p(m / stiff)
            frame = pd.DataFrame(x, columns=list(SPACE.names))
            frame.insert(0, "moment_nm", float(m))
            frame.insert(0, "load_case", lc)
            frame["rom_deg"] = rom
            frames.append(frame)
    return pd.concat(frames, ignore_index=True)


@pytest.fixture(scope="module")
def table() -> pd.DataFrame:
    return make_table()


def test_registered_names_match_the_study_table() -> None:
    assert set(CLASSES) == set(BASELINE_NAMES)
    assert len(BASELINE_NAMES) == 9
    assert BASELINE_NAMES[0] == "linear" and BASELINE_NAMES[-1] == "lightgbm"


@pytest.mark.parametrize("name", BASELINE_NAMES)
def test_every_baseline_fits_and_predicts(name: str, table: pd.DataFrame) -> None:
    model = CLASSES[name](space=SPACE, hyper={"n_estimators": 20} if name == "lightgbm" else None)
    fitted = model.fit(table, table["rom_deg"])
    assert fitted is model
    assert hasattr(model, "model_") and model.fit_seconds_ >= 0
    pred = model.predict(table.iloc[:17])
    assert isinstance(pred, np.ndarray) and pred.shape == (17,)
    assert np.all(np.isfinite(pred))
    # Fits the training data better than a constant does (all baselines are smooth enough).
    err = np.mean(np.abs(model.predict(table) - table["rom_deg"]))
    assert err < np.mean(np.abs(table["rom_deg"] - table["rom_deg"].mean()))


@pytest.mark.parametrize("name", ["random_forest", "lightgbm", "gaussian_process"])
def test_same_seed_same_predictions(name: str, table: pd.DataFrame) -> None:
    preds = [
        CLASSES[name](SPACE, seed=3).fit(table, table["rom_deg"]).predict(table) for _ in range(2)
    ]
    np.testing.assert_array_equal(preds[0], preds[1])


def test_seed_changes_a_random_forest(table: pd.DataFrame) -> None:
    a = CLASSES["random_forest"](SPACE, seed=0).fit(table, table["rom_deg"]).predict(table)
    b = CLASSES["random_forest"](SPACE, seed=1).fit(table, table["rom_deg"]).predict(table)
    assert not np.array_equal(a, b)


def test_linear_beats_a_constant_on_a_linear_function() -> None:
    train, test = make_table(30, seed=1, linear=True), make_table(10, seed=2, linear=True)
    model = CLASSES["linear"](SPACE).fit(train, train["rom_deg"])
    mae = np.mean(np.abs(model.predict(test) - test["rom_deg"]))
    mae_constant = np.mean(np.abs(train["rom_deg"].mean() - test["rom_deg"]))
    assert mae < 1e-8 < mae_constant


def test_generic_class_by_name_and_sklearn_contract(table: pd.DataFrame) -> None:
    model = SklearnSurrogate(SPACE, estimator_name="poly2", n_jobs=1, seed=0)
    assert not hasattr(model, "model_")  # __init__ only stores
    params = model.get_params()
    assert params["estimator_name"] == "poly2" and params["seed"] == 0
    twin = clone(model)
    np.testing.assert_allclose(
        model.fit(table, table["rom_deg"]).predict(table),
        twin.fit(table, table["rom_deg"]).predict(table),
    )


def test_polynomial_ridge_equals_the_sklearn_pipeline() -> None:
    rng = np.random.default_rng(0)
    X, Xt = rng.random((120, 5)), rng.random((30, 5))
    y = np.sin(X.sum(axis=1)) + X[:, 0] ** 3
    for degree, alpha in [(2, 1.0), (4, 0.117)]:
        ref = make_pipeline(PolynomialFeatures(degree), Ridge(alpha=alpha)).fit(X, y)
        ours = PolynomialRidge(degree=degree, alpha=alpha, block=7).fit(X, y)
        np.testing.assert_allclose(ours.predict(Xt), ref.predict(Xt), atol=1e-8)


def test_hyper_overrides_and_bad_hyper(table: pd.DataFrame) -> None:
    model = CLASSES["lightgbm"](SPACE, hyper={"n_estimators": 3})
    model.fit(table, table["rom_deg"])
    assert model.model_.regressor_[-1].n_estimators == 3
    with pytest.raises(ConfigError, match="Invalid hyperparameters for baseline 'poly3'"):
        CLASSES["poly3"](SPACE, hyper={"no_such_option": 1}).fit(table, table["rom_deg"])


def test_predict_before_fit_raises(table: pd.DataFrame) -> None:
    with pytest.raises(SurrogateNotFittedError, match="not fitted yet") as info:
        CLASSES["lightgbm"](SPACE).predict(table)
    assert isinstance(info.value, FemcalError) and isinstance(info.value, NotFittedError)


def test_missing_column_raises(table: pd.DataFrame) -> None:
    with pytest.raises(InputDataError, match=r"lacks the column\(s\) \['Kappa'\]"):
        CLASSES["linear"](SPACE).fit(table.drop(columns="Kappa"), table["rom_deg"])
    model = CLASSES["linear"](SPACE).fit(table, table["rom_deg"])
    with pytest.raises(InputDataError, match="moment_nm"):
        model.predict(table.drop(columns="moment_nm"))


def test_bad_targets_raise(table: pd.DataFrame) -> None:
    with pytest.raises(InputDataError, match="X has 600 rows but y has 5 values"):
        CLASSES["linear"](SPACE).fit(table, table["rom_deg"].iloc[:5])
    y = table["rom_deg"].to_numpy().copy()
    y[3] = np.nan
    with pytest.raises(InputDataError, match="NaN or inf"):
        CLASSES["linear"](SPACE).fit(table, y)


def test_unseen_load_case_raises_for_per_load_case_models(table: pd.DataFrame) -> None:
    train = table[table["load_case"] != "Flexion"]
    model = CLASSES["poly2"](SPACE).fit(train, train["rom_deg"])
    with pytest.raises(InputDataError, match="No training rows had load case Flexion"):
        model.predict(table)


def test_unknown_name_raises() -> None:
    with pytest.raises(ConfigError, match="Unknown baseline 'nope'"):
        SklearnSurrogate(SPACE, estimator_name="nope").fit(make_table(3), np.zeros(60))


def test_registry_builds_baselines_and_rejects_unknown_names() -> None:
    pytest.importorskip("femcal.surrogates.nn", reason="the registry also imports the NN module")
    from femcal.surrogates import available_surrogates, make_surrogate

    assert set(BASELINE_NAMES) <= set(available_surrogates())
    assert isinstance(make_surrogate("random_forest", space=SPACE), CLASSES["random_forest"])
    with pytest.raises(ConfigError, match="Unknown surrogate 'no_such_model'"):
        make_surrogate("no_such_model", space=SPACE)
