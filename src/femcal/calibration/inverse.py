"""``inverse``: the study's inverse-model baseline as a calibrator, RoM curves -> parameters.

An adapter: the network, its training and its MLflow model live in :mod:`femcal.inverse`; this
module checks that a calibration problem suits a fitted :class:`~femcal.inverse.InverseModel`
(its full moment grid, its parameter box, every point measured) and registers the
``inverse`` calibrator, which predicts the parameters in one forward pass.

``InverseModel`` stays importable from here: inverse models logged before
:mod:`femcal.inverse` existed name it in their MLflow entry point.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from femcal.calibration.base import CalibrationProblem, Solution, register_calibrator
from femcal.errors import ConfigError, InputDataError
from femcal.schema import LOAD_CASES

if TYPE_CHECKING:  # the inverse package (and Lightning) loads only when this method runs
    from femcal.inverse.model import InverseModel

__all__ = ["InverseModel", "check_problem", "inverse"]

logger = logging.getLogger(__name__)


def __getattr__(name: str) -> Any:
    if name == "InverseModel":  # named by inverse models logged before femcal.inverse existed
        from femcal.inverse.model import InverseModel

        return InverseModel
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def check_problem(problem: CalibrationProblem, model: InverseModel) -> None:
    """Raise unless the problem is on the model's grid, in its box, with every point measured.

    Raises
    ------
    InputDataError
        Another moment grid, or missing points.
    ConfigError
        Another parameter box or dimension.
    """
    from femcal.inverse.model import FIX_PGD

    grid = problem.model.moments.double().numpy()
    trained = np.asarray(model.moments_, dtype=float)
    if grid.shape != trained.shape or not np.allclose(grid, trained, rtol=1e-6, atol=1e-9):
        raise InputDataError(
            f"The inverse model was trained on the moment grid {trained.tolist()} Nm; these "
            f"targets are on {grid.tolist()} Nm. It only accepts its full training grid: "
            f"{FIX_PGD}."
        )
    if model.space is not None and model.space != problem.model.space:
        raise ConfigError(
            "The inverse model was trained on another parameter box "
            f"({list(model.space.names)}, lower {model.space.lower.tolist()}, upper "
            f"{model.space.upper.tolist()}) than the calibration's; retrain it "
            "(`dvc repro train-inverse`) or use `--method pgd`."
        )
    if model.net_.n_params != problem.dim:
        raise ConfigError(
            f"The inverse model predicts {model.net_.n_params} parameters; the calibration has "
            f"{problem.dim}."
        )
    mask = problem.mask.numpy()
    if not mask.all():
        lacking = ~mask.all(axis=(1, 2))
        points = [
            f"{LOAD_CASES[k]} at {grid[j]:g} Nm"
            for k in range(mask.shape[1])
            for j in range(mask.shape[2])
            if not mask[:, k, j].all()
        ]
        shown = ", ".join(points[:8]) + (f" and {len(points) - 8} more" if len(points) > 8 else "")
        raise InputDataError(
            f"Missing RoM values: {int(lacking.sum())} of {mask.shape[0]} specimens (positions "
            f"{np.flatnonzero(lacking)[:10].tolist()} of this batch) lack points ({shown}). The "
            f"inverse model needs all {mask.shape[1]} x {mask.shape[2]} points; {FIX_PGD}."
        )


@register_calibrator("inverse")
def inverse(
    problem: CalibrationProblem,
    *,
    rng: np.random.Generator,
    model: InverseModel | None = None,
    model_uri: str | None = None,
) -> Solution:
    """The study's inverse-model baseline: parameters from the targets in one forward pass.

    Parameters
    ----------
    problem : CalibrationProblem
        Targets of n specimens on the inverse model's full moment grid (no missing points).
        Point weights are ignored: the network reads the curves as they are.
    rng : numpy.random.Generator
        Unused (the prediction is deterministic); part of the calibrator interface.
    model : InverseModel, optional
        A fitted inverse model; loaded from ``model_uri`` when omitted (pass it to keep the
        loading out of the timing and to load it once for several chunks).
    model_uri : str, optional
        MLflow model URI or folder of the inverse model (default: the registered champion,
        :data:`femcal.inverse.store.DEFAULT_INVERSE_URI`).

    Returns
    -------
    Solution
        ``x`` (n, d) in physical units inside the box, ``nit = 1``, ``success`` all True.
    """
    from femcal.inverse.store import DEFAULT_INVERSE_URI, load_inverse

    if model is None:
        model_uri = model_uri or DEFAULT_INVERSE_URI
        logger.info("Loading the inverse model %s", model_uri)
        model = load_inverse(model_uri)
    model.check_fitted()
    check_problem(problem, model)
    unit = model.predict(problem.measured)
    space = problem.model.space
    x = space.clip(problem.model.linear_unit_to_physical(unit))
    n = problem.n_specimens
    return Solution(
        x=x,
        nit=1,
        success=np.ones(n, dtype=bool),
        message="Inverse network: parameters predicted from the curves in one forward pass.",
        info={
            "inverse_val_mae_unit": float(model.best_val_mae_),
            "inverse_moments": model.moments_.tolist(),
        },
    )
