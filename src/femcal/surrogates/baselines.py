"""The study's classical surrogates (LR, PR, SVR, RF, GP, LightGBM) behind one small class.

Every baseline is a :class:`SklearnSurrogate`: the design matrix of
:func:`~femcal.surrogates.base.encode_features` (one-hot load case, moment in Nm, the 13
parameters in the unit box by their bounds) fed to one fitted scikit-learn object that owns all
the scaling::

    TransformedTargetRegressor(                     # RoM min-max scaled to (0, 1), as the study
        Pipeline([
            ("scale", ColumnTransformer(...)),      # moment min-max scaled to (0, 1); rest as is
            ("model", <study estimator>),
        ]),
        transformer=MinMaxScaler(),
    )

Hyperparameters are the study's (appendix "Models hyperparameters"). Differences from the study:

* **Load case one-hot** instead of one number ``c``. With the study's numeric ``c`` this code
  reproduces the study (Large/Small Test MAE: LR 1.06/1.03, SVR 1.10/1.03, PR2 0.83/0.92,
  PR3 0.56/0.82, PR4 0.42/0.82 deg); one-hot mainly helps LR, SVR and PR.
* **Polynomial regression per load case**: one ``PolynomialFeatures(degree) + Ridge(alpha)``
  per load case on (moment, parameters), the study's alphas, solved exactly in its dual form
  (:class:`PolynomialRidge`). A global degree-5 expansion of the 18 features has 33,649
  columns (5.5 GB on Large); per load case the dual needs a 5,120 x 5,120 Gram matrix.
* **Gaussian process per load case**, exact, on all of that load case's rows (5,120 on Large),
  with the study's fitted kernel ``C(1.35e-5) * RBF(0.974)`` (isotropic, on moment and
  parameters), ``normalize_y=True``, held fixed (``optimizer=None``). One GP on all 20,480 rows
  needs a 3.4 GB Gram matrix and an O(n^3) solve per optimiser step. Re-tuning the kernel by
  maximum likelihood (on 640-1000-row subsets, with restarts) collapsed to the degenerate
  length scale 1e-5 (MAE 1.77 deg; likely because, without a noise term, smooth kernels make
  the Cholesky fail), hence the study's values are used as given. The Cholesky factor is
  released after fitting: the model offers the predictive mean only and stays O(n) in size.

Test MAE (deg, all 1280 rows of the 64 Test configurations) / mean R^2 (per load case over
configurations and moments, averaged over load cases), fitted on all of Large (1024 configs) or
Small (128), one core (whole zoo: 84 s, peak 0.9 GB); the study's 4-fold cross-validated
numbers in brackets::

    baseline          Large                  Small                  fit s (Large)
    linear            0.95 [1.05] / 0.63     0.94 [1.03] / 0.63      0.1
    svr               0.87 [1.04] / 0.71     0.83 [1.05] / 0.74      0.6
    poly2             0.46 [0.82] / 0.92     0.63 [0.96] / 0.83     11
    poly3             0.34 [0.61] / 0.95     0.64 [0.94] / 0.83     12
    poly4             0.33 [0.50] / 0.96     0.77 [0.99] / 0.78     13
    poly5             0.37 [0.54] / 0.94     0.83 [1.07] / 0.73     16
    random_forest     0.38 [0.40] / 0.93     0.62 [0.65] / 0.84      8
    gaussian_process  0.30 [0.33] / 0.96     0.55 [0.62] / 0.85     23
    lightgbm          0.23 [0.28] / 0.97     0.56 [0.57] / 0.86      1
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.compose import ColumnTransformer, TransformedTargetRegressor
from sklearn.pipeline import Pipeline
from sklearn.preprocessing import MinMaxScaler

from femcal.errors import (
    ConfigError,
    InputDataError,
    SurrogateNotFittedError,
    UntrustedArtifactError,
)
from femcal.space import ParameterSpace
from femcal.surrogates.base import encode_features, register_baseline, register_surrogate

# Importable from here too: files saved before the estimators had their own module name
# them by this module's path (TRUSTED_TYPES).
from femcal.surrogates.estimators import (  # noqa: F401, E402
    FACTORIES,
    N_CASES,
    MeanOnlyGP,
    PerLoadCaseRegressor,
    PolynomialRidge,
    threadpools,
)

#: The name by which saved files written with the class's underscore name refer to it here.
_MeanOnlyGP = MeanOnlyGP

__all__ = [
    "BASELINE_NAMES",
    "GaussianProcessSurrogate",
    "LightGBMSurrogate",
    "LinearSurrogate",
    "Poly2Surrogate",
    "Poly3Surrogate",
    "Poly4Surrogate",
    "Poly5Surrogate",
    "RandomForestSurrogate",
    "SklearnSurrogate",
    "SurrogateNotFittedError",
    "SVRSurrogate",
    "TRUSTED_TYPES",
    "load_baseline",
]

#: Registered baseline names, in the order of the study's results table.
BASELINE_NAMES: tuple[str, ...] = (
    "linear",
    "svr",
    "poly2",
    "poly3",
    "poly4",
    "poly5",
    "random_forest",
    "gaussian_process",
    "lightgbm",
)


#: A saved baseline is a folder: ``config.json`` (format, class, file hashes, versions),
#: ``model.skops`` (the fitted scikit-learn objects, as data: skops never unpickles) and, for
#: LightGBM, ``lightgbm.txt`` (the booster in LightGBM's own text format).
BASELINE_FORMAT = "femcal-baseline"
BASELINE_FORMAT_VERSION = 1
_CONFIG_FILE = "config.json"
_MODEL_FILE = "model.skops"
_BOOSTER_FILE = "lightgbm.txt"

#: Types a saved baseline may hold beyond skops's own trusted list (numpy, builtins and
#: scikit-learn's estimators): femcal's estimators and parameter space, the fitted trees of
#: the random forest, the GP kernels and the LightGBM wrapper (its booster is the text file).
#: Loading constructs these from their stored attributes; no code from the file runs.
TRUSTED_TYPES: tuple[str, ...] = (
    "collections.OrderedDict",
    "femcal.space.ParameterSpace",
    "femcal.surrogates.estimators.PerLoadCaseRegressor",
    "femcal.surrogates.estimators.PolynomialRidge",
    "femcal.surrogates.estimators.MeanOnlyGP",
    "femcal.surrogates.estimators._MeanOnlyGP",
    # where files saved before the estimators moved to their own module name them
    "femcal.surrogates.baselines.PerLoadCaseRegressor",
    "femcal.surrogates.baselines.PolynomialRidge",
    "femcal.surrogates.baselines.MeanOnlyGP",
    "femcal.surrogates.baselines._MeanOnlyGP",
    "femcal.surrogates.baselines.SklearnSurrogate",
    "femcal.surrogates.baselines.LinearSurrogate",
    "femcal.surrogates.baselines.SVRSurrogate",
    "femcal.surrogates.baselines.Poly2Surrogate",
    "femcal.surrogates.baselines.Poly3Surrogate",
    "femcal.surrogates.baselines.Poly4Surrogate",
    "femcal.surrogates.baselines.Poly5Surrogate",
    "femcal.surrogates.baselines.RandomForestSurrogate",
    "femcal.surrogates.baselines.GaussianProcessSurrogate",
    "femcal.surrogates.baselines.LightGBMSurrogate",
    "lightgbm.sklearn.LGBMRegressor",
    "sklearn.gaussian_process.kernels.ConstantKernel",
    "sklearn.gaussian_process.kernels.Product",
    "sklearn.gaussian_process.kernels.RBF",
    "sklearn.tree._tree.Tree",
)


# ------------------------------------------------------------------------------ the surrogate
class SklearnSurrogate(RegressorMixin, BaseEstimator):
    """A study baseline: encoded features -> scaled scikit-learn/LightGBM model -> RoM (deg).

    Parameters
    ----------
    space : ParameterSpace
        Parameter names and bounds; the parameters are mapped to the unit box by these bounds.
    estimator_name : str, optional
        One of :data:`BASELINE_NAMES`. Defaults to the registered name of the (sub)class, so
        ``make_surrogate("lightgbm", space=space)`` needs no name.
    n_jobs : int
        Threads for the estimator and for BLAS during ``fit``/``predict`` (-1: no limit).
    seed : int
        The only source of randomness (forest bootstrap and features, boosting; the GP and the
        linear models are deterministic).
    hyper : mapping, optional
        Overrides of the study's hyperparameters, passed to the final estimator (e.g.
        ``{"alpha": 0.5}`` for ``poly4``, ``{"n_estimators": 20}`` for ``lightgbm``,
        ``{"alpha": 1e-6}`` for ``gaussian_process``).

    Attributes
    ----------
    model_ : TransformedTargetRegressor
        The fitted pipeline on the design matrix of ``encode_features``, shape (n, 4 + 1 + d).
    fit_seconds_ : float
        Wall time of the last ``fit``.

    Examples
    --------
    >>> from femcal.surrogates import make_surrogate
    >>> model = make_surrogate("lightgbm", space=space).fit(X_train, y_train)  # doctest: +SKIP
    >>> model.predict(X_test).shape  # doctest: +SKIP
    (1280,)
    """

    registry_name: str | None = None

    def __init__(
        self,
        space: ParameterSpace,
        *,
        estimator_name: str | None = None,
        n_jobs: int = 1,
        seed: int = 0,
        hyper: Mapping[str, Any] | None = None,
    ) -> None:
        self.space = space
        self.estimator_name = estimator_name
        self.n_jobs = n_jobs
        self.seed = seed
        self.hyper = hyper

    # ----------------------------------------------------------------------- helpers
    def _name(self) -> str:
        name = self.estimator_name or type(self).registry_name
        if name not in FACTORIES:
            raise ConfigError(
                f"Unknown baseline '{name}'; choose one of {', '.join(BASELINE_NAMES)}."
            )
        return name

    def _threads(self) -> contextlib.AbstractContextManager:
        if self.n_jobs in (None, -1):
            return contextlib.nullcontext()
        return threadpools().limit(limits=self.n_jobs)

    def _build(self) -> TransformedTargetRegressor:
        name = self._name()
        try:
            model = FACTORIES[name](self.seed, self.n_jobs, **dict(self.hyper or {}))
        except TypeError as exc:
            raise ConfigError(f"Invalid hyperparameters for baseline '{name}': {exc}") from None
        d = self.space.dim
        scale = ColumnTransformer(
            [
                ("load_case", "passthrough", list(range(N_CASES))),
                ("moment", MinMaxScaler(), [N_CASES]),
                ("params", "passthrough", list(range(N_CASES + 1, N_CASES + 1 + d))),
            ]
        )
        return TransformedTargetRegressor(
            regressor=Pipeline([("scale", scale), ("model", model)]),
            transformer=MinMaxScaler(),
        )

    # -------------------------------------------------------------------------- API
    def fit(self, X: pd.DataFrame, y: np.ndarray | pd.Series) -> SklearnSurrogate:
        """Fit on physical inputs and RoM targets.

        Parameters
        ----------
        X : DataFrame, n rows
            Columns ``load_case``, ``moment_nm`` and the parameter names, physical units.
        y : array_like, shape (n,)
            RoM in degrees.

        Returns
        -------
        SklearnSurrogate
            ``self``, fitted.
        """
        Z = encode_features(X, self.space)
        y = np.asarray(y, dtype=float).reshape(-1)
        if y.shape[0] != Z.shape[0]:
            raise InputDataError(f"X has {Z.shape[0]} rows but y has {y.shape[0]} values.")
        if not np.all(np.isfinite(y)):
            raise InputDataError("y holds NaN or inf; drop failed simulations before fitting.")
        model = self._build()
        start = time.perf_counter()
        with self._threads():
            model.fit(Z, y)
        self.fit_seconds_ = time.perf_counter() - start
        self.model_ = model
        return self

    def predict(self, X: pd.DataFrame) -> np.ndarray:
        """Predict RoM in degrees.

        Parameters
        ----------
        X : DataFrame, n rows
            Columns ``load_case``, ``moment_nm`` and the parameter names, physical units.

        Returns
        -------
        ndarray, shape (n,)
            Predicted RoM in degrees.
        """
        if not hasattr(self, "model_"):
            raise SurrogateNotFittedError(
                f"This {type(self).__name__} is not fitted yet; call fit(X, y) before predict."
            )
        Z = encode_features(X, self.space)
        with self._threads():
            return np.asarray(self.model_.predict(Z), dtype=float).reshape(-1)

    def __sklearn_is_fitted__(self) -> bool:
        return hasattr(self, "model_")

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> None:
        """Save the fitted baseline into the folder ``path`` as data, not code.

        The scikit-learn objects go to ``model.skops`` (skops: loading never unpickles), a
        LightGBM booster to ``lightgbm.txt`` (LightGBM's text model), and ``config.json``
        records the format, the class, the files' SHA-256 and the library versions.

        Parameters
        ----------
        path : str or Path
            The folder; created if missing, its files of the same names replaced.

        Raises
        ------
        SurrogateNotFittedError
            The baseline is not fitted.
        """
        import skops.io as sio

        if not hasattr(self, "model_"):
            raise SurrogateNotFittedError(
                f"This {type(self).__name__} is not fitted yet; call fit(X, y) before save."
            )
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        files = [_MODEL_FILE]
        lgbm = _lightgbm_of(self.model_)
        booster = None
        if lgbm is not None:
            booster = lgbm._Booster
            booster.save_model(str(path / _BOOSTER_FILE), num_iteration=-1)
            files.append(_BOOSTER_FILE)
            lgbm._Booster = None  # the booster is stored as text, not inside the skops file
        try:
            sio.dump(self, path / _MODEL_FILE)
        finally:
            if lgbm is not None:
                lgbm._Booster = booster
        config = {
            "format": BASELINE_FORMAT,
            "format_version": BASELINE_FORMAT_VERSION,
            "class": f"{type(self).__module__}:{type(self).__qualname__}",
            "estimator_name": self._name(),
            "sha256": {name: _sha256(path / name) for name in files},
            "versions": _library_versions(),
        }
        (path / _CONFIG_FILE).write_text(json.dumps(config, indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> SklearnSurrogate:
        """Load a baseline saved by :meth:`save`, without running code from its files.

        Parameters
        ----------
        path : str or Path
            The folder written by :meth:`save`.

        Returns
        -------
        SklearnSurrogate
            The fitted baseline; its predictions equal the saved one's bit for bit.

        Raises
        ------
        InputDataError
            The folder is not a saved femcal baseline, or a file is missing or unreadable.
        UntrustedArtifactError
            ``model.skops`` holds a type outside :data:`TRUSTED_TYPES` (a file not written by
            femcal, or altered).
        """
        import skops.io as sio

        folder = Path(path)
        config = _read_config(folder)
        model_file = folder / _MODEL_FILE
        for name, digest in dict(config.get("sha256") or {_MODEL_FILE: None}).items():
            file = folder / str(name)
            if not file.is_file():
                raise InputDataError(
                    f"{file}: missing; {folder} is an incomplete saved baseline. Refit it "
                    "(`dvc repro baselines`)."
                )
            if digest is not None and _sha256(file) != digest:
                raise InputDataError(
                    f"{file}: its SHA-256 is not the one recorded in {folder / _CONFIG_FILE} "
                    "when it was saved: the file was changed or corrupted. Refit the baseline "
                    "(`dvc repro baselines`) or restore the folder (`dvc checkout`)."
                )
        try:
            untrusted = sio.get_untrusted_types(file=model_file)
        except Exception as exc:  # noqa: BLE001 - any unreadable file gets the same answer
            raise InputDataError(
                f"{model_file}: not a readable skops file ({type(exc).__name__}: {exc}). Refit "
                "the baseline (`dvc repro baselines`)."
            ) from None
        refused = sorted(set(untrusted) - set(TRUSTED_TYPES))
        if refused:
            raise UntrustedArtifactError(
                f"{model_file} holds type(s) femcal does not trust: {', '.join(refused)}. A "
                "saved femcal baseline holds only scikit-learn, LightGBM and femcal types "
                "(femcal.surrogates.baselines.TRUSTED_TYPES); this file was altered or not "
                "written by femcal, and loading it could run its code. Refit the baseline "
                "(`dvc repro baselines`), or, if you wrote the file and trust it, load it "
                "yourself with skops.io.load(path, trusted=[...])."
            )
        try:
            obj = sio.load(model_file, trusted=list(untrusted))
        except Exception as exc:  # noqa: BLE001
            raise InputDataError(
                f"{model_file}: could not be loaded ({type(exc).__name__}: {exc}). Refit the "
                "baseline (`dvc repro baselines`)."
            ) from None
        if not isinstance(obj, cls) or not hasattr(obj, "model_"):
            raise InputDataError(
                f"{model_file} holds a {type(obj).__name__}, not a fitted {cls.__name__}. "
                "Load it with the class named in its config.json, or refit it."
            )
        lgbm = _lightgbm_of(obj.model_)
        if lgbm is not None:
            from lightgbm import Booster

            booster_file = folder / _BOOSTER_FILE
            if not booster_file.is_file():
                raise InputDataError(
                    f"{booster_file}: missing; a saved LightGBM baseline keeps its booster "
                    "there. Refit the baseline (`dvc repro baselines`)."
                )
            try:
                lgbm._Booster = Booster(model_file=str(booster_file))
            except Exception as exc:  # noqa: BLE001 - LightGBMError and friends
                raise InputDataError(
                    f"{booster_file}: not a LightGBM text model ({type(exc).__name__}: {exc}). "
                    "Refit the baseline (`dvc repro baselines`)."
                ) from None
        return obj


def _lightgbm_of(model: Any) -> Any | None:
    """The fitted LGBMRegressor inside a baseline's model, or None."""
    from lightgbm import LGBMModel

    pipeline = getattr(model, "regressor_", None)
    est = pipeline.steps[-1][1] if isinstance(pipeline, Pipeline) else None
    return est if isinstance(est, LGBMModel) else None


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _library_versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("scikit-learn", "lightgbm", "skops", "numpy"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:  # pragma: no cover - all are dependencies
            out[pkg] = "?"
    return out


def _read_config(folder: Path) -> dict[str, Any]:
    """``config.json`` of a saved baseline, checked for the format."""
    file = folder / _CONFIG_FILE
    if not file.is_file():
        legacy = folder.with_name(folder.name + ".joblib")
        hint = (
            f" {legacy.name} beside it is a pickle of an older femcal, which femcal no longer "
            "loads (a pickle runs code when loaded)."
            if legacy.exists()
            else ""
        )
        raise InputDataError(
            f"{folder}: not a saved femcal baseline (no {_CONFIG_FILE}).{hint} Refit the "
            "baselines (`dvc repro baselines`), or pass the folder SklearnSurrogate.save wrote."
        )
    try:
        config = json.loads(file.read_text())
    except ValueError as exc:
        raise InputDataError(f"{file}: not valid JSON ({exc}); refit the baseline.") from None
    if not isinstance(config, dict) or config.get("format") != BASELINE_FORMAT:
        raise InputDataError(
            f"{file}: format {config.get('format') if isinstance(config, dict) else config!r}, "
            f"expected {BASELINE_FORMAT!r}; this is not a saved femcal baseline."
        )
    if config.get("format_version") != BASELINE_FORMAT_VERSION:
        raise InputDataError(
            f"{file}: format version {config.get('format_version')!r}; this femcal reads "
            f"version {BASELINE_FORMAT_VERSION}. Refit the baseline (`dvc repro baselines`)."
        )
    return config


def load_baseline(path: str | Path) -> SklearnSurrogate:
    """Load a saved baseline folder (any of the registered baselines).

    Parameters
    ----------
    path : str or Path
        A folder written by :meth:`SklearnSurrogate.save`.

    Returns
    -------
    SklearnSurrogate
        The fitted baseline, of the class recorded in its ``config.json``.

    Raises
    ------
    InputDataError, UntrustedArtifactError
        See :meth:`SklearnSurrogate.load`.
    """
    return SklearnSurrogate.load(path)


# --------------------------------------------------------------------- registered baselines
@register_baseline("linear")
@register_surrogate("linear")
class LinearSurrogate(SklearnSurrogate):
    """Linear regression (study: LR, default settings)."""


@register_baseline("svr")
@register_surrogate("svr")
class SVRSurrogate(SklearnSurrogate):
    """Support vector regression, RBF kernel, C=2.479, gamma="auto" (study: SVR)."""


@register_baseline("poly2")
@register_surrogate("poly2")
class Poly2Surrogate(SklearnSurrogate):
    """Degree-2 polynomial + ridge (alpha=1.0), per load case (study: PR degree 2)."""


@register_baseline("poly3")
@register_surrogate("poly3")
class Poly3Surrogate(SklearnSurrogate):
    """Degree-3 polynomial + ridge (alpha=1.0), per load case (study: PR degree 3)."""


@register_baseline("poly4")
@register_surrogate("poly4")
class Poly4Surrogate(SklearnSurrogate):
    """Degree-4 polynomial + ridge (alpha=0.1169), per load case (study: PR degree 4)."""


@register_baseline("poly5")
@register_surrogate("poly5")
class Poly5Surrogate(SklearnSurrogate):
    """Degree-5 polynomial + ridge (alpha=0.7742), per load case (study: PR degree 5)."""


@register_baseline("random_forest")
@register_surrogate("random_forest")
class RandomForestSurrogate(SklearnSurrogate):
    """Random forest, 51 trees, max_depth=31 (study: RF)."""


@register_baseline("gaussian_process")
@register_surrogate("gaussian_process")
class GaussianProcessSurrogate(SklearnSurrogate):
    """Per-load-case GP, C*RBF kernel tuned on a subset (study: GP); see the module notes."""


@register_baseline("lightgbm")
@register_surrogate("lightgbm")
class LightGBMSurrogate(SklearnSurrogate):
    """LightGBM, 71 leaves, max_depth=24, lr=0.0959, 183 trees (study: LightGBM)."""
