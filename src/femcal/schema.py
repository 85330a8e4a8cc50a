"""Names shared across femcal: load cases, the study's parameters, table columns."""

from __future__ import annotations

#: The four pure-moment load cases of the IVD model, in the canonical order used everywhere.
LOAD_CASES: tuple[str, ...] = ("Flexion", "Extension", "LateralBending", "AxialRotation")

#: The 13 material parameters of the study, in the column order of ParameterBounds.csv.
PARAMETER_NAMES: tuple[str, ...] = (
    "C10Nucleus",
    "C01Nucleus",
    "C10Annulus",
    "K1Annulus",
    "K2Annulus",
    "Kappa",
    "K1Circ",
    "K2Circ",
    "K1Rad",
    "K2Rad",
    "FiberAngle",
    "FiberAngleCirc",
    "FiberAngleRad",
)

#: Physical units of the study's parameters (relative variations are dimensionless, "1").
PARAMETER_UNITS: dict[str, str] = {
    "C10Nucleus": "MPa",
    "C01Nucleus": "MPa",
    "C10Annulus": "MPa",
    "K1Annulus": "MPa",
    "K2Annulus": "1",
    "Kappa": "1",
    "K1Circ": "1",
    "K2Circ": "1",
    "K1Rad": "1",
    "K2Rad": "1",
    "FiberAngle": "deg",
    "FiberAngleCirc": "1",
    "FiberAngleRad": "1",
}

#: Status of a simulation row in a tidy table.
STATUS_OK = "ok"
STATUS_FAILED = "failed"

#: Columns of a tidy FE table (one row per configuration x load case x moment), before parameters.
KEY_COLUMNS: tuple[str, ...] = ("config_id", "load_case", "moment_nm")
#: Output columns of a tidy FE table.
OUTPUT_COLUMNS: tuple[str, ...] = ("rom_deg", "idp_mpa", "status")
#: What a surrogate can be trained to predict (an output column) -> the suffix of its error's
#: name: ``rom_deg`` (the RoM, the calibration's target) and ``idp_mpa`` (the intradiscal
#: pressure, the FE campaign's second output: ``val_mae_mpa``).
TARGETS: dict[str, str] = {"rom_deg": "deg", "idp_mpa": "mpa"}

#: Spellings of load-case names accepted from users, mapped to the canonical name.
_LOAD_CASE_ALIASES: dict[str, str] = {}
for _name in LOAD_CASES:
    _LOAD_CASE_ALIASES[_name.lower()] = _name
_LOAD_CASE_ALIASES.update(
    {
        "lateral bending": "LateralBending",
        "lateral_bending": "LateralBending",
        "lateral-bending": "LateralBending",
        "lb": "LateralBending",
        "axial rotation": "AxialRotation",
        "axial_rotation": "AxialRotation",
        "axial-rotation": "AxialRotation",
        "ar": "AxialRotation",
        "flex": "Flexion",
        "ext": "Extension",
    }
)


def canonical_load_case(name: str) -> str | None:
    """Canonical load-case name for a user spelling, or None when it is not recognised.

    Parameters
    ----------
    name : str
        A spelling such as ``"lateral bending"``, ``"AxialRotation"`` or ``"flexion"``.

    Returns
    -------
    str or None
        One of :data:`LOAD_CASES`, or None.
    """
    return _LOAD_CASE_ALIASES.get(" ".join(str(name).strip().lower().split()))
