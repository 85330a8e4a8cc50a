"""A small fitted neural surrogate of the synthetic study, shared by the calibration tests."""

from __future__ import annotations

import numpy as np
import pytest

from femcal.calibration import CurveModel, SurrogateCurveModel
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table

MOMENTS = (1.0, 2.0, 3.0, 4.0, 5.0)


@pytest.fixture(scope="package")
def small_surrogate() -> NeuralSurrogate:
    table = tidy_table(48, seed=3)
    model = NeuralSurrogate(
        study_space(), hidden=(32, 32), max_epochs=40, patience=40, batch_size=16, seed=0
    )
    return model.fit(table, table["rom_deg"].to_numpy())


@pytest.fixture
def curve_model(small_surrogate: NeuralSurrogate) -> CurveModel:
    return SurrogateCurveModel(small_surrogate, MOMENTS)


@pytest.fixture
def truth(curve_model: CurveModel) -> tuple[np.ndarray, np.ndarray]:
    """Six configurations inside the box and their surrogate curves (exactly reachable)."""
    x = curve_model.space.sample_uniform(6, np.random.default_rng(11))
    return x, curve_model.predict(x)
