"""The inverse model's training data: configurations sampled in the unit box and their curves.

The curves come from the surrogate (a :class:`~femcal.calibration.model.CurveModel` on the
moment grid the inverse model will accept); :func:`rom_mae_deg` scores an inverse model by
re-evaluating the curves at its predictions.
"""

from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING

import numpy as np
import torch

from femcal.errors import ConfigError, InputDataError
from femcal.inverse.model import EVAL_BATCH, InverseModel

if TYPE_CHECKING:
    from femcal.calibration.model import CurveModel

#: Sampling schemes of :func:`make_inverse_dataset`.
SAMPLINGS: tuple[str, ...] = ("lhs", "uniform")


def make_inverse_dataset(
    curve_model: CurveModel,
    n_samples: int = 50_000,
    rng: np.random.Generator | int | None = None,
    *,
    sampling: str = "lhs",
    batch_size: int = EVAL_BATCH,
) -> tuple[np.ndarray, np.ndarray]:
    """Configurations sampled in the study's unit box and their curves from the surrogate.

    Parameters
    ----------
    curve_model : CurveModel
        The surrogate on the moment grid of the curves.
    n_samples : int
        Number of configurations N.
    rng : numpy.random.Generator or int
        Source of the samples (an int seeds a new generator; default seed 0).
    sampling : {"lhs", "uniform"}
        Latin hypercube or independent uniform draws.
    batch_size : int
        Configurations per surrogate call.

    Returns
    -------
    rom : ndarray of float64, shape (N, 4, m)
        RoM in degrees.
    unit : ndarray of float64, shape (N, d)
        The configurations in the min-max unit box.
    """
    if sampling not in SAMPLINGS:
        raise ConfigError(f"Unknown sampling '{sampling}'; choose one of {', '.join(SAMPLINGS)}.")
    n = int(n_samples)
    if n < 1 or int(batch_size) < 1:
        raise ConfigError(f"n_samples and batch_size must be >= 1; got {n_samples}, {batch_size}.")
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng or 0)
    d = curve_model.dim
    if sampling == "lhs":
        strata = np.stack([gen.permutation(n) for _ in range(d)], axis=1)
        unit = (strata + gen.random((n, d))) / n
    else:
        unit = gen.random((n, d))
    out = []
    with torch.no_grad():
        for s in range(0, n, int(batch_size)):
            u = torch.as_tensor(unit[s : s + int(batch_size)], dtype=torch.float32)
            out.append(curve_model.curves(curve_model.from_linear_unit(u)).double().numpy())
    rom = np.concatenate(out)
    if not np.all(np.isfinite(rom)) or np.any(rom <= 0):
        raise InputDataError(
            "The surrogate returned non-finite or non-positive RoM for some sampled "
            "configurations; check the surrogate (log_target=True keeps RoM > 0)."
        )
    return rom, unit


def rom_mae_deg(model: InverseModel, curve_model: CurveModel, rom: np.ndarray) -> float:
    """MAE in degrees between curves and the surrogate's curves at the model's predictions.

    Parameters
    ----------
    model : InverseModel
        Fitted inverse model.
    curve_model : CurveModel
        The surrogate on the model's moment grid.
    rom : ndarray, shape (n, 4, m)
        Curves (measured or from the surrogate).
    """
    unit = model.predict(rom)
    with torch.no_grad():
        parts = [
            curve_model.curves(
                curve_model.from_linear_unit(
                    torch.as_tensor(unit[s : s + EVAL_BATCH], dtype=torch.float32)
                )
            )
            for s in range(0, unit.shape[0], EVAL_BATCH)
        ]
    pred = torch.cat(parts).double().numpy()
    return float(np.mean(np.abs(pred - rom)))


def surrogate_fingerprint(curve_model: CurveModel) -> str:
    """Short hash of a curve model's weights and moment grid (names the Optuna study's data)."""
    h = hashlib.sha256()
    for key, value in sorted(curve_model.net.state_dict().items()):
        h.update(key.encode())
        h.update(value.detach().cpu().contiguous().numpy().tobytes())
    h.update(curve_model.moments.numpy().tobytes())
    return h.hexdigest()[:12]
