"""femcal: calibrate finite-element models with neural-network surrogates, within bounds."""

from femcal.errors import FemcalError, InputDataError
from femcal.space import ParameterSpace

__all__ = ["FemcalError", "InputDataError", "ParameterSpace", "__version__"]
__version__ = "0.1.0"
