"""Calibration of FE parameters through a frozen surrogate: registry, problem, calibrators."""

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
