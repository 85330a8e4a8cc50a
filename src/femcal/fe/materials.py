"""The disc model's parameters: their checks, and the materials of each region of the mesh."""

from __future__ import annotations

import math
from collections.abc import Mapping

from femcal.errors import InputDataError
from femcal.schema import PARAMETER_NAMES


def validate_parameters(parameters: Mapping[str, float], where: str = "FE job") -> dict[str, float]:
    """Check the study's 13 parameters: present, finite, physically admissible.

    Parameters
    ----------
    parameters : mapping of str to float
    where : str
        Named in the error message (e.g. the job's key).

    Returns
    -------
    dict of str to float
        The 13 parameters as floats (other keys are dropped).

    Raises
    ------
    InputDataError
        Naming the offending parameter and the fix.
    """
    out: dict[str, float] = {}
    for name in PARAMETER_NAMES:
        if name not in parameters:
            raise InputDataError(
                f"{where}: parameter {name!r} is missing; give all 13 parameters "
                f"({', '.join(PARAMETER_NAMES)})."
            )
        try:
            value = float(parameters[name])
        except (TypeError, ValueError):
            raise InputDataError(
                f"{where}: parameter {name!r} = {parameters[name]!r} is not a number; "
                "give a finite float."
            ) from None
        if not math.isfinite(value):
            raise InputDataError(
                f"{where}: parameter {name!r} = {value!r} is not finite; give a finite float "
                "(failed or missing design rows must be dropped before simulation)."
            )
        out[name] = value
    positive = ("C10Nucleus", "C10Annulus", "K1Annulus", "K2Annulus")
    for name in positive:
        if out[name] <= 0:
            raise InputDataError(
                f"{where}: parameter {name!r} = {out[name]} must be > 0 (study bounds: "
                "ParameterBounds.csv)."
            )
    if out["C01Nucleus"] < 0:
        raise InputDataError(f"{where}: parameter 'C01Nucleus' = {out['C01Nucleus']} must be >= 0.")
    if not 0.0 <= out["Kappa"] < 1.0 / 3.0:
        raise InputDataError(
            f"{where}: parameter 'Kappa' = {out['Kappa']} must lie in [0, 1/3) (fibre dispersion)."
        )
    for name in ("K1Circ", "K2Circ", "K1Rad", "K2Rad"):
        if out[name] <= -1.0:
            raise InputDataError(
                f"{where}: parameter {name!r} = {out[name]} must be > -1 (relative variation; "
                "study bounds -0.2..0)."
            )
    return out


def region_materials(
    parameters: Mapping[str, float], n_rings: int, n_regions: int, kappa: str = "scale"
) -> dict[tuple[int, int], tuple[float, float, float]]:
    """Fibre constants ``(k1, k2, alpha_deg)`` per annulus ring and region.

    Parameters
    ----------
    parameters : mapping of str to float
        The study's 13 parameters (validated).
    n_rings, n_regions : int
        Rings (0 = outer) and circumferential regions per side (0 = anterior).
    kappa : {"scale", "ignore"}
        Treatment of the fibre dispersion (module docstring).

    Returns
    -------
    dict of (ring, region) to (k1, k2, alpha_deg)
    """
    p = parameters
    factor = (1.0 - 3.0 * p["Kappa"]) ** 2 if kappa == "scale" else 1.0
    out = {}
    for ring in range(n_rings):
        r = ring / (n_rings - 1) if n_rings > 1 else 0.0
        for region in range(n_regions):
            c = region / (n_regions - 1)
            k1 = p["K1Annulus"] * (1 + p["K1Circ"] * c) * (1 + p["K1Rad"] * r) * factor
            k2 = p["K2Annulus"] * (1 + p["K2Circ"] * c) * (1 + p["K2Rad"] * r) * factor
            alpha = p["FiberAngle"] * (1 + p["FiberAngleCirc"] * c) * (1 + p["FiberAngleRad"] * r)
            out[ring, region] = (k1, k2, alpha)
    return out
