"""scikit-learn's estimator contract of the surrogates, without importing scikit-learn."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from test_nn import SPACE, make_data

from femcal.errors import ConfigError
from femcal.surrogates.contract import RegressorContract
from femcal.surrogates.nn import NeuralSurrogate


class Line(RegressorContract):
    """y = slope * x + offset, with an optional nested estimator (a parameter like any)."""

    def __init__(self, slope: float = 1.0, *, offset: float = 0.0, inner=None) -> None:
        self.slope = slope
        self.offset = offset
        self.inner = inner

    def fit(self, X, y):
        self.fitted_ = True
        return self

    def predict(self, X):
        return self.slope * np.asarray(X, dtype=float)[:, 0] + self.offset


def test_get_params_set_params_round_trip_with_nested_estimators() -> None:
    model = Line(2.0, inner=Line(offset=1.0))
    params = model.get_params()
    assert params["slope"] == 2.0 and params["offset"] == 0.0
    assert params["inner__offset"] == 1.0 and params["inner__slope"] == 1.0
    assert set(model.get_params(deep=False)) == {"slope", "offset", "inner"}
    assert model.set_params(slope=3.0, inner__slope=-1.0) is model
    assert model.slope == 3.0 and model.inner.slope == -1.0
    assert Line().set_params().get_params(deep=False) == Line().get_params(deep=False)


def test_set_params_refuses_an_unknown_name() -> None:
    with pytest.raises(ConfigError, match=r"Invalid parameter 'slop' for estimator Line; got "):
        Line().set_params(slop=1.0)
    with pytest.raises(ValueError, match="Valid parameters are: \\['inner', 'offset', 'slope'\\]"):
        Line().set_params(inner__x=1.0, slop=2.0)


def test_varargs_init_is_refused() -> None:
    class Bad(RegressorContract):
        def __init__(self, *values):
            self.values = values

    with pytest.raises(ConfigError, match=r"Bad.__init__ takes \*values; .* Give each one"):
        Bad().get_params()


def test_sklearn_clone_score_tags_and_repr() -> None:
    from sklearn.base import clone, is_regressor

    model = Line(2.0, offset=0.5)
    twin = clone(model)
    assert twin is not model and twin.get_params() == model.get_params()
    assert is_regressor(model)
    X = np.arange(6.0).reshape(-1, 1)
    assert model.score(X, 2.0 * X[:, 0] + 0.5) == pytest.approx(1.0)
    assert repr(model) == "Line(offset=0.5, slope=2.0)"
    assert repr(Line()) == "Line()"


def test_neural_surrogate_clones_with_sklearn() -> None:
    from sklearn.base import clone

    model = NeuralSurrogate(SPACE, hidden=(8,), max_epochs=2)
    twin = clone(model)
    assert twin.get_params(deep=False).keys() == model.get_params(deep=False).keys()
    assert twin.hidden == (8,) and twin.max_epochs == 2 and twin.space.names == SPACE.names
    assert twin.set_params(max_epochs=5).max_epochs == 5 and model.max_epochs == 2


def test_loading_and_predicting_imports_no_sklearn(tmp_path: Path) -> None:
    """A saved network is loaded and predicts in a fresh interpreter without scikit-learn or
    scipy.stats (they take about a second to import)."""
    torch.set_num_threads(1)
    X, y = make_data(12, seed=1)
    NeuralSurrogate(SPACE, hidden=(8,), max_epochs=1, val_fraction=0.0).fit(X, y).save(
        tmp_path / "model"
    )
    X.head(4).to_csv(tmp_path / "rows.csv", index=False)
    code = textwrap.dedent(
        f"""
        import json, sys
        import pandas as pd
        from femcal.surrogates.nn import NeuralSurrogate
        model = NeuralSurrogate.load({str(tmp_path / "model")!r})
        model.get_params(); model.set_params(max_epochs=3)
        pred = model.predict(pd.read_csv({str(tmp_path / "rows.csv")!r}))
        print(json.dumps([len(pred), sorted(m for m in ("sklearn", "scipy.stats")
                                           if m in sys.modules)]))
        """
    )
    env_code = [sys.executable, "-c", code]
    out = subprocess.run(env_code, capture_output=True, text=True, check=True)
    n, imported = json.loads(out.stdout.strip().splitlines()[-1])
    assert n == 4 and imported == []
