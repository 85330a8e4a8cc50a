"""scikit-learn's regressor contract without importing scikit-learn.

:class:`RegressorContract` gives a class the methods scikit-learn's ``BaseEstimator`` and
``RegressorMixin`` give (``get_params``, ``set_params``, ``score``, the estimator tags, a
repr of the changed parameters), so that :func:`sklearn.base.clone`, grid searches and
pipelines take it as one of theirs. scikit-learn is imported only where one of its functions
is called (``score``'s R², the tags scikit-learn asks for): loading a fitted surrogate to
predict imports none of it.
"""

from __future__ import annotations

import inspect
from typing import Any

from femcal.errors import ConfigError


class RegressorContract:
    """A regressor in scikit-learn's sense: parameters are the ``__init__`` arguments, stored
    unchanged under their own names (``__init__`` has no ``*args``).

    Subclasses define ``__init__``, ``fit`` and ``predict``; ``score`` is the R² of
    ``predict`` (scikit-learn's ``r2_score``).
    """

    _estimator_type = "regressor"

    @classmethod
    def _get_param_names(cls) -> list[str]:
        """The ``__init__`` arguments' names, sorted (scikit-learn's order)."""
        init = cls.__init__
        if init is object.__init__:
            return []
        names = []
        for p in inspect.signature(init).parameters.values():
            if p.name == "self" or p.kind == p.VAR_KEYWORD:
                continue
            if p.kind == p.VAR_POSITIONAL:
                raise ConfigError(
                    f"{cls.__name__}.__init__ takes *{p.name}; a scikit-learn estimator names "
                    "every parameter in its signature. Give each one a name."
                )
            names.append(p.name)
        return sorted(names)

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The parameters by name; with ``deep``, those of nested estimators as
        ``<name>__<parameter>`` too."""
        out: dict[str, Any] = {}
        for key in self._get_param_names():
            value = getattr(self, key)
            if deep and hasattr(value, "get_params") and not isinstance(value, type):
                out.update((f"{key}__{k}", v) for k, v in value.get_params().items())
            out[key] = value
        return out

    def set_params(self, **params: Any) -> RegressorContract:
        """Set parameters by name (``<name>__<parameter>`` for a nested estimator's); returns
        ``self``.

        Raises
        ------
        ConfigError
            A name that is not a parameter (also a ``ValueError``, as scikit-learn raises).
        """
        if not params:
            return self
        valid = self.get_params(deep=True)
        nested: dict[str, dict[str, Any]] = {}
        for name, value in params.items():
            key, delim, sub_key = name.partition("__")
            if key not in valid:
                raise ConfigError(
                    f"Invalid parameter {key!r} for estimator {type(self).__name__}; got "
                    f"{name}={value!r}. Valid parameters are: {self._get_param_names()!r}."
                )
            if delim:
                nested.setdefault(key, {})[sub_key] = value
            else:
                setattr(self, key, value)
                valid[key] = value
        for key, sub_params in nested.items():
            valid[key].set_params(**sub_params)
        return self

    def score(self, X: Any, y: Any, sample_weight: Any = None) -> float:
        """R² of ``predict(X)`` against ``y`` (scikit-learn's ``r2_score``)."""
        from sklearn.metrics import r2_score

        return float(r2_score(y, self.predict(X), sample_weight=sample_weight))

    def __sklearn_tags__(self) -> Any:
        """scikit-learn's tags of a regressor (``fit`` needs ``y``)."""
        from sklearn.utils import RegressorTags, Tags, TargetTags

        return Tags(
            estimator_type="regressor",
            target_tags=TargetTags(required=True),
            transformer_tags=None,
            regressor_tags=RegressorTags(),
            classifier_tags=None,
        )

    def __repr__(self) -> str:
        """``Class(name=value, ...)`` of the parameters that differ from their defaults."""
        signature = inspect.signature(type(self).__init__).parameters
        changed = []
        for key, value in self.get_params(deep=False).items():
            default = signature[key].default if key in signature else inspect.Parameter.empty
            if default is inspect.Parameter.empty or not _same(value, default):
                changed.append(f"{key}={value!r}")
        return f"{type(self).__name__}({', '.join(changed)})"


def _same(value: Any, default: Any) -> bool:
    """``value`` equals ``default`` (an object whose comparison fails or is not a bool:
    different)."""
    if value is default:
        return True
    try:
        return bool(value == default) and type(value) is type(default)
    except Exception:  # noqa: BLE001 - arrays and odd objects compare as different
        return False
