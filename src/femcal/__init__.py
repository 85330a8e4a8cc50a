"""femcal: calibrate finite-element models with neural-network surrogates, within bounds."""

from femcal.errors import FemcalError, InputDataError

__all__ = ["FemcalError", "InputDataError", "ParameterSpace", "__version__"]
__version__ = "0.1.0"


def __getattr__(name: str):
    # ParameterSpace needs numpy and pandas: imported on first use, so that `femcal --help`
    # and the checks of a command's settings and output folder answer without them.
    if name == "ParameterSpace":
        from femcal.space import ParameterSpace

        return ParameterSpace
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
