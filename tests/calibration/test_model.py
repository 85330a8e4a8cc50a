"""The CurveModel protocol and its two implementations (the disc alone, the disc with effects)."""

from __future__ import annotations

import numpy as np
import torch

from femcal.calibration import CurveModel, SurrogateCurveModel
from femcal.effects.composite import EffectModel


def test_both_models_are_curve_models(curve_model: SurrogateCurveModel) -> None:
    effects = EffectModel(curve_model, ["facet_contact", "neutral_zone"])
    for model in (curve_model, effects):
        assert isinstance(model, CurveModel)
        assert model.unit_space.dim == model.space.dim == model.dim
        assert model.unit_space.names == model.space.names


def test_coordinates_round_trip_through_the_one_transform(curve_model: SurrogateCurveModel) -> None:
    model = EffectModel(curve_model, ["facet_contact", "ligament_tension"])
    v = np.random.default_rng(4).uniform(0.02, 0.98, (6, model.dim))
    x = model.to_physical(v)
    assert model.space.contains(x).all()
    np.testing.assert_allclose(x, model.unit_space.from_unit(v), rtol=1e-12)
    # float32 coordinates: the disc part through the network's own map
    back = model.from_physical(x).double().numpy()
    np.testing.assert_allclose(back, v, atol=1e-5)
    # the disc part is the network's input space, log-scaled where the bounds are positive
    disc = curve_model.unit_space
    np.testing.assert_array_equal(disc.lower, curve_model.net.space.lower)
    assert disc.scales == curve_model.net.space.scales
    assert disc.scales == tuple("log" if lo > 0 else "linear" for lo in disc.lower)


def test_physical_sd_from_the_space_jacobian(curve_model: SurrogateCurveModel) -> None:
    """dx/du of the joint space turns a unit-box sd into physical units (diagnose reports it)."""
    model = EffectModel(curve_model, ["facet_contact"])
    v = np.full((1, model.dim), 0.3)
    dxdu = model.unit_space.from_unit_jacobian(v)[0]
    h = 1e-6
    for j in range(model.dim):
        step = np.zeros_like(v)
        step[0, j] = h
        fd = (model.unit_space.from_unit(v + step) - model.unit_space.from_unit(v - step))[0, j]
        np.testing.assert_allclose(dxdu[j], fd / (2 * h), rtol=1e-6)
    # torch and numpy give the same joint map
    vt = torch.tensor(v)
    np.testing.assert_allclose(model.unit_space.from_unit(vt).numpy(), model.to_physical(v))
