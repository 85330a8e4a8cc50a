"""Calibration of FE parameters through a frozen surrogate: registry, problem, calibrators.

The names below are imported on first use (they need torch): the figures
(:mod:`femcal.calibration.plots`) and the reports import without it.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

#: Each public name and the module that defines it.
_WHERE = {
    "CalibrationProblem": "base",
    "Solution": "base",
    "available_calibrators": "base",
    "calibrator_registry": "base",
    "get_calibrator": "base",
    "register_calibrator": "base",
    "CurveModel": "model",
    "SurrogateCurveModel": "model",
    "PgdOptions": "pgd_options",
    "CalibrationResult": "result",
    "calibrate": "result",
}

__all__ = [
    "CalibrationProblem",
    "CalibrationResult",
    "CurveModel",
    "PgdOptions",
    "Solution",
    "SurrogateCurveModel",
    "available_calibrators",
    "calibrate",
    "calibrator_registry",
    "get_calibrator",
    "register_calibrator",
]

if TYPE_CHECKING:
    from femcal.calibration.base import (
        CalibrationProblem,
        Solution,
        available_calibrators,
        calibrator_registry,
        get_calibrator,
        register_calibrator,
    )
    from femcal.calibration.model import CurveModel, SurrogateCurveModel
    from femcal.calibration.pgd_options import PgdOptions
    from femcal.calibration.result import CalibrationResult, calibrate


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    globals()[name] = value  # the next access is a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
