"""The study's baseline estimators (scikit-learn API): one regressor per load case, polynomial
ridge, the mean-only GP, and the factory of each baseline by name."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
from lightgbm import LGBMRegressor
from scipy.linalg import solve
from sklearn.base import BaseEstimator, RegressorMixin, clone
from sklearn.ensemble import RandomForestRegressor
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel
from sklearn.linear_model import LinearRegression
from sklearn.svm import SVR
from threadpoolctl import ThreadpoolController

from femcal.errors import (
    ConfigError,
    InputDataError,
)
from femcal.schema import LOAD_CASES

N_CASES = len(LOAD_CASES)  # one-hot columns 0..3 of encode_features; column 4 is the moment


@functools.cache
def threadpools() -> ThreadpoolController:
    """The process's one thread-pool controller, built on first use (~20 ms).

    Limiting threads through it then costs ~0.05 ms per fit or predict call.
    """
    return ThreadpoolController()


# --------------------------------------------------------------------------- building blocks
class PerLoadCaseRegressor(RegressorMixin, BaseEstimator):
    """One clone of ``estimator`` per load case, on the moment and parameter columns.

    Parameters
    ----------
    estimator : sklearn regressor
        Template; cloned for every load case present in the training rows.

    Notes
    -----
    Input ``Z`` has shape (n, 4 + 1 + d): the first four columns are the one-hot load case (as
    made by :func:`~femcal.surrogates.base.encode_features`), the rest are passed on.
    """

    def __init__(self, estimator: BaseEstimator) -> None:
        self.estimator = estimator

    @staticmethod
    def _case(Z: np.ndarray) -> np.ndarray:
        return np.argmax(Z[:, :N_CASES], axis=1)

    def fit(self, Z: np.ndarray, y: np.ndarray) -> PerLoadCaseRegressor:
        """Fit one estimator per load case; ``Z`` shape (n, 4 + 1 + d), ``y`` shape (n,)."""
        case = self._case(Z)
        self.estimators_ = {
            int(c): clone(self.estimator).fit(Z[case == c, N_CASES:], y[case == c])
            for c in np.unique(case)
        }
        return self

    def predict(self, Z: np.ndarray) -> np.ndarray:
        """Predict with each row's load-case model; returns shape (n,)."""
        case = self._case(Z)
        out = np.empty(len(Z))
        for c in np.unique(case):
            if int(c) not in self.estimators_:
                raise InputDataError(
                    f"No training rows had load case {LOAD_CASES[c]}; the surrogate cannot "
                    "predict it. Train on data that includes this load case."
                )
            out[case == c] = self.estimators_[int(c)].predict(Z[case == c, N_CASES:])
        return out


class PolynomialRidge(RegressorMixin, BaseEstimator):
    """``make_pipeline(PolynomialFeatures(degree), Ridge(alpha))``, solved in its dual form.

    Same model and same predictions (up to round-off) as the pipeline, at O(n^2) memory
    instead of O(n * C(p + degree, degree)): degree 5 on 14 columns has 11,628 monomials.

    Parameters
    ----------
    degree : int
        Highest total degree of the monomials (bias included).
    alpha : float
        Ridge penalty, > 0; the intercept is not penalised (``fit_intercept=True``).
    block : int
        Rows per block when building kernel matrices (bounds the temporary memory).

    Attributes
    ----------
    X_fit_ : ndarray, shape (n, p)
        Training inputs.
    dual_coef_ : ndarray, shape (n,)
        Dual coefficients of the centred problem.
    intercept_ : float
        Constant added to ``k(x, X_fit_) @ dual_coef_``.

    Notes
    -----
    The monomial feature map ``phi`` of ``PolynomialFeatures`` (each monomial once) has the
    inner product ``phi(x) . phi(z) = sum_{k <= degree} h_k(x * z)``, with ``h_k`` the complete
    homogeneous symmetric polynomials, obtained from the power sums
    ``P_i = (x ** i) . (z ** i)`` by Newton's identities ``k h_k = sum_{i=1..k} P_i h_{k-i}``.
    Ridge with an intercept equals kernel ridge on the doubly centred Gram matrix ``Kc``:
    ``(Kc + alpha I) a = y - mean(y)``; since ``sum(a) = 0``, the prediction is
    ``k(x, X) @ a + mean(y) - mean_rows(K) @ a``.
    """

    def __init__(self, degree: int = 2, alpha: float = 1.0, block: int = 512) -> None:
        self.degree = degree
        self.alpha = alpha
        self.block = block

    def _kernel(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        powers_b = [B**i for i in range(1, self.degree + 1)]
        out = np.empty((len(A), len(B)))
        for lo in range(0, len(A), self.block):
            a = A[lo : lo + self.block]
            p = [(a**i) @ powers_b[i - 1].T for i in range(1, self.degree + 1)]
            h = [np.ones_like(p[0])]
            for k in range(1, self.degree + 1):
                h.append(sum(p[i - 1] * h[k - i] for i in range(1, k + 1)) / k)
            out[lo : lo + self.block] = sum(h)
        return out

    def fit(self, Z: np.ndarray, y: np.ndarray) -> PolynomialRidge:
        """Solve the centred dual ridge problem; ``Z`` shape (n, p), ``y`` shape (n,)."""
        if not self.alpha > 0:
            raise ConfigError(f"PolynomialRidge needs alpha > 0; got {self.alpha}.")
        Z = np.asarray(Z, dtype=float)
        y = np.asarray(y, dtype=float).reshape(-1)
        K = self._kernel(Z, Z)
        row_mean = K.mean(axis=1)
        K -= row_mean[:, None]
        K -= row_mean[None, :]
        K += row_mean.mean()
        K[np.diag_indices_from(K)] += self.alpha
        coef = solve(K, y - y.mean(), assume_a="pos", overwrite_a=True)
        self.X_fit_ = Z
        self.dual_coef_ = coef
        self.intercept_ = float(y.mean() - row_mean @ coef)
        return self

    def predict(self, Z: np.ndarray) -> np.ndarray:
        """Predictions, shape (n,)."""
        return self._kernel(np.asarray(Z, dtype=float), self.X_fit_) @ self.dual_coef_ + (
            self.intercept_
        )


class MeanOnlyGP(GaussianProcessRegressor):
    """A GaussianProcessRegressor that drops its n x n Cholesky factor after fitting.

    Only the predictive mean (``k(x, X) @ alpha_``) is available, and the fitted model stays
    O(n) in size instead of O(n^2) (otherwise 210 MB per load case, 840 MB in all, on Large).
    """

    def fit(self, X: np.ndarray, y: np.ndarray) -> MeanOnlyGP:
        super().fit(X, y)
        del self.L_
        return self

    def predict(self, X: np.ndarray, return_std: bool = False, return_cov: bool = False) -> Any:
        if return_std or return_cov:
            raise ConfigError("This GP surrogate offers the predictive mean only.")
        return super().predict(X)


# ------------------------------------------------------------------------ the study's models
def _linear(seed: int, n_jobs: int, **hyper: Any) -> BaseEstimator:
    return LinearRegression(**hyper)


def _poly(degree: int, alpha: float) -> Callable[..., BaseEstimator]:
    def make(seed: int, n_jobs: int, **hyper: Any) -> BaseEstimator:
        return PerLoadCaseRegressor(PolynomialRidge(**{"degree": degree, "alpha": alpha, **hyper}))

    return make


def _svr(seed: int, n_jobs: int, **hyper: Any) -> BaseEstimator:
    return SVR(**{"kernel": "rbf", "C": 2.479459357922161, "gamma": "auto", **hyper})


def _random_forest(seed: int, n_jobs: int, **hyper: Any) -> BaseEstimator:
    params = {"n_estimators": 51, "max_depth": 31, **hyper}
    return RandomForestRegressor(random_state=seed, n_jobs=n_jobs, **params)


#: The name by which saved files (skops) written with the underscore name refer to the class.
_MeanOnlyGP = MeanOnlyGP


def _gaussian_process(seed: int, n_jobs: int, **hyper: Any) -> BaseEstimator:
    kernel = ConstantKernel(1.3535458162698054e-05) * RBF(length_scale=0.9739157609228299)
    params = {"kernel": kernel, "normalize_y": True, "optimizer": None, **hyper}
    return PerLoadCaseRegressor(MeanOnlyGP(random_state=seed, **params))


def _lightgbm(seed: int, n_jobs: int, **hyper: Any) -> BaseEstimator:
    params = {
        "num_leaves": 71,
        "max_depth": 24,
        "learning_rate": 0.0959080973897064,
        "n_estimators": 183,
        **hyper,
    }
    return LGBMRegressor(random_state=seed, n_jobs=n_jobs, deterministic=True, verbose=-1, **params)


#: name -> factory(seed, n_jobs, **hyper) returning the unfitted study estimator.
FACTORIES: dict[str, Callable[..., BaseEstimator]] = {
    "linear": _linear,
    "svr": _svr,
    "poly2": _poly(2, 1.0),
    "poly3": _poly(3, 1.0),
    "poly4": _poly(4, 0.11694087489403014),
    "poly5": _poly(5, 0.7741762364391351),
    "random_forest": _random_forest,
    "gaussian_process": _gaussian_process,
    "lightgbm": _lightgbm,
}
