"""Calibration of FE parameters through a frozen surrogate: registry, problem, calibrators."""

from femcal.calibration.base import (
    CalibrationProblem,
    CalibrationResult,
    Solution,
    available_calibrators,
    calibrate,
    calibrator_registry,
    get_calibrator,
    register_calibrator,
)
from femcal.calibration.model import CurveModel, SurrogateCurveModel

__all__ = [
    "CalibrationProblem",
    "CalibrationResult",
    "CurveModel",
    "Solution",
    "SurrogateCurveModel",
    "available_calibrators",
    "calibrate",
    "calibrator_registry",
    "get_calibrator",
    "register_calibrator",
]
