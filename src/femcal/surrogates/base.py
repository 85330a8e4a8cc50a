"""The surrogate contract and its registry of names.

A surrogate follows scikit-learn's estimator contract: ``__init__`` only stores its
arguments, ``fit(X, y)`` learns and returns ``self``, fitted attributes end in ``_``.
``X`` is a table with the columns ``load_case``, ``moment_nm`` and the parameter names of
the surrogate's :class:`~femcal.space.ParameterSpace`, in physical units; ``y`` is the RoM in
degrees. ``predict(X)`` returns RoM in degrees, shape (n,).

A new surrogate is one file: a class decorated with :func:`register_surrogate`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import numpy as np
import pandas as pd

from femcal.errors import ConfigError, InputDataError
from femcal.schema import LOAD_CASES
from femcal.space import ParameterSpace


@runtime_checkable
class Surrogate(Protocol):
    """What every surrogate offers."""

    def fit(self, X: pd.DataFrame, y: np.ndarray) -> Surrogate: ...

    def predict(self, X: pd.DataFrame) -> np.ndarray: ...


_REGISTRY: dict[str, Callable[..., Surrogate]] = {}


def register_surrogate(name: str) -> Callable[[type], type]:
    """Class decorator: make a surrogate available under ``name``."""

    def deco(cls: type) -> type:
        if name in _REGISTRY and _REGISTRY[name] is not cls:
            raise ConfigError(f"A surrogate named '{name}' is already registered.")
        _REGISTRY[name] = cls
        cls.registry_name = name
        return cls

    return deco


def available_surrogates() -> list[str]:
    """Registered surrogate names, sorted."""
    _import_builtins()
    return sorted(_REGISTRY)


def make_surrogate(name: str, **kwargs: Any) -> Surrogate:
    """Build the surrogate registered as ``name`` with keyword arguments ``kwargs``."""
    _import_builtins()
    try:
        cls = _REGISTRY[name]
    except KeyError:
        raise ConfigError(
            f"Unknown surrogate '{name}'. Registered surrogates: {', '.join(sorted(_REGISTRY))}."
        ) from None
    return cls(**kwargs)


def _import_builtins() -> None:
    # Importing the modules runs their @register_surrogate decorators.
    import femcal.surrogates.baselines  # noqa: F401
    import femcal.surrogates.nn  # noqa: F401


def check_features(X: pd.DataFrame, space: ParameterSpace, *, what: str = "X") -> None:
    """Raise :class:`InputDataError` unless ``X`` has the columns a surrogate needs."""
    if not isinstance(X, pd.DataFrame):
        raise InputDataError(
            f"{what} must be a pandas DataFrame with columns load_case, moment_nm and "
            f"{', '.join(space.names)}; got {type(X).__name__}."
        )
    needed = ["load_case", "moment_nm", *space.names]
    missing = [c for c in needed if c not in X.columns]
    if missing:
        raise InputDataError(
            f"{what} lacks the column(s) {missing}. A surrogate needs load_case, moment_nm and "
            f"the parameters {', '.join(space.names)} in physical units."
        )
    bad = sorted(set(X["load_case"].astype(str)) - set(LOAD_CASES))
    if bad:
        raise InputDataError(
            f"{what}: unknown load_case value(s) {bad}; valid names are {', '.join(LOAD_CASES)}."
        )
    numeric = X[["moment_nm", *space.names]]
    if numeric.isna().any().any():
        cols = numeric.columns[numeric.isna().any()].tolist()
        raise InputDataError(f"{what}: NaN in column(s) {cols}; fill or drop those rows first.")


def encode_features(X: pd.DataFrame, space: ParameterSpace) -> np.ndarray:
    """Design matrix shared by the tabular baselines.

    Parameters
    ----------
    X : DataFrame, n rows
        Columns ``load_case``, ``moment_nm`` and the parameter names (physical units).
    space : ParameterSpace
        Maps the parameters to the unit box.

    Returns
    -------
    ndarray, shape (n, 4 + 1 + d)
        One-hot load case (order of :data:`~femcal.schema.LOAD_CASES`), moment in Nm,
        parameters in the unit box.
    """
    check_features(X, space)
    lc = X["load_case"].astype(str).to_numpy()
    onehot = (lc[:, None] == np.asarray(LOAD_CASES)[None, :]).astype(float)
    moment = X["moment_nm"].to_numpy(dtype=float)[:, None]
    params = space.to_unit(X[list(space.names)].to_numpy(dtype=float))
    return np.hstack([onehot, moment, params])
