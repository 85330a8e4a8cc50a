"""One moment policy for every command: which applied moments a surrogate may be used at.

A surrogate is trained on moments ``[lo, hi]`` (its ``moment_range_``, 1..5 Nm for the
champion). Outside that range it extrapolates, and its error grows with the log-moment distance
``L = log(M / hi)`` above the range and ``log(lo / M)`` below it (``L = 0`` inside). The policy
models the surrogate's error sd at a moment ``M`` as ``error_deg * exp(growth * L)``, i.e.
``error_deg * (M / hi) ** growth`` above the range: measured on our own surrogate, the ratio
sd(M) / sd(in range) grows faster than linearly in ``L``, and ``exp(growth * L)`` fits it with
one ``growth`` at every distance measured (``1 + growth * L`` does not; see
``reports/extrapolation.md``). The policy accepts moments with ``L <= max_log_ratio`` (warning
beyond the range, with the larger error counted) and refuses the rest. ``growth`` and
``max_log_ratio`` are measured by ``benchmarks/bench_extrapolation.py`` and set in
params.yaml's ``moments`` section; ``femcal calibrate`` and ``femcal diagnose`` both use
:meth:`MomentPolicy.check`, and count the larger error: calibrate weights each point by
``1 / sd(M)^2`` (:meth:`MomentPolicy.point_weights`, the measurement noise counted when
given), diagnose adds ``sd(M)`` to the noise
(:meth:`MomentPolicy.sigma_surrogate`).
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from femcal.errors import ConfigError, InputDataError

if TYPE_CHECKING:  # pragma: no cover
    from femcal.measurements import Measurements

logger = logging.getLogger(__name__)

#: Measured moments all at least this large look like N·mm rather than Nm.
NMM_THRESHOLD = 100.0
_MAX_LISTED = 6
_BENCH = "benchmarks/bench_extrapolation.py (reports/extrapolation.md)"


def _fmt(values: Sequence[float] | np.ndarray) -> str:
    items = [f"{float(x):g}" for x in values]
    more = f" (and {len(items) - _MAX_LISTED} more)" if len(items) > _MAX_LISTED else ""
    return ", ".join(items[:_MAX_LISTED]) + more


def _range(trained_range: Any) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in trained_range)
    except (TypeError, ValueError):
        raise ConfigError(
            f"trained_range must be a pair (lo, hi) of moments in Nm; got {trained_range!r}. "
            "Use the surrogate's moment_range_, e.g. (1.0, 5.0)."
        ) from None
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
        raise ConfigError(
            f"trained_range must be two finite moments in Nm with 0 < lo < hi; got "
            f"{trained_range!r}. Use the surrogate's moment_range_, e.g. (1.0, 5.0)."
        )
    return lo, hi


def log_distance(moments: Any, trained_range: tuple[float, float]) -> np.ndarray:
    """Log-moment distance of moments from a trained range.

    Parameters
    ----------
    moments : array_like, shape (m,)
        Moments in Nm, > 0.
    trained_range : tuple of float
        ``(lo, hi)`` in Nm, ``0 < lo < hi``.

    Returns
    -------
    ndarray, shape (m,)
        ``log(M / hi)`` above the range, ``log(lo / M)`` below, 0 inside.

    Raises
    ------
    ConfigError
        ``trained_range`` is invalid.
    InputDataError
        A moment is not finite and > 0.
    """
    lo, hi = _range(trained_range)
    m = np.atleast_1d(np.asarray(moments, dtype=np.float64))
    if not np.all(np.isfinite(m) & (m > 0)):
        raise InputDataError(
            f"moments must be finite and > 0 Nm; got {m.tolist()}. Drop the 0 Nm (unloaded) "
            "state and give moments in Nm."
        )
    return np.maximum(0.0, np.maximum(np.log(m / hi), np.log(lo / m)))


@dataclass(frozen=True)
class MomentPolicy:
    """The moments a surrogate may be used at, and its error there.

    Parameters
    ----------
    trained_range : tuple of float
        ``(lo, hi)``: the smallest and largest training moment in Nm (the surrogate's
        ``moment_range_``), ``0 < lo < hi``.
    error_deg : float
        The surrogate's own error sd (deg) inside the trained range, >= 0.
    growth : float
        Growth rate of the error sd per unit of log-moment distance ``L`` beyond the range:
        ``sd(M) = error_deg * exp(growth * L)``, >= 0 (measured: params.yaml
        ``moments.error_growth``).
    max_log_ratio : float
        Moments with ``L > max_log_ratio`` are refused, >= 0: the accepted moments are
        ``lo * exp(-max_log_ratio) .. hi * exp(max_log_ratio)`` Nm (measured: params.yaml
        ``moments.max_log_ratio``, the largest ``L`` the growth was measured at).

    Raises
    ------
    ConfigError
        A field is not a finite number in its range.
    """

    trained_range: tuple[float, float]
    error_deg: float
    growth: float
    max_log_ratio: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "trained_range", _range(self.trained_range))
        checks = (
            ("error_deg", "the surrogate's error sd in degrees", "e.g. 0.03"),
            ("growth", "moments.error_growth", f"measured by {_BENCH}"),
            ("max_log_ratio", "moments.max_log_ratio", f"measured by {_BENCH}"),
        )
        for name, what, hint in checks:
            raw = getattr(self, name)
            try:
                value = float(raw)
            except (TypeError, ValueError):
                value = math.nan
            if isinstance(raw, bool) or not (math.isfinite(value) and value >= 0):
                raise ConfigError(
                    f"MomentPolicy: {name} ({what}) must be a finite number >= 0; got {raw!r}. "
                    f"Set it to a non-negative value ({hint})."
                )
            object.__setattr__(self, name, value)

    @classmethod
    def for_surrogate(
        cls,
        surrogate: Any,
        *,
        growth: float,
        max_log_ratio: float,
        error_deg: float | None = None,
    ) -> MomentPolicy:
        """The policy of a fitted surrogate.

        Parameters
        ----------
        surrogate : object
            A fitted surrogate with ``moment_range_`` (models saved without it were trained on
            1..5 Nm) and ``best_val_mae_deg_``.
        growth, max_log_ratio : float
            See :class:`MomentPolicy` (params.yaml ``moments.error_growth`` and
            ``moments.max_log_ratio``).
        error_deg : float, optional
            The in-range error sd; default ``best_val_mae_deg_ * sqrt(pi / 2)`` (Gaussian
            errors), or 0 (with a logged warning) when the surrogate has no validation error.

        Returns
        -------
        MomentPolicy
        """
        trained = tuple(getattr(surrogate, "moment_range_", (1.0, 5.0)))
        if error_deg is None:
            val = float(getattr(surrogate, "best_val_mae_deg_", math.nan))
            if math.isfinite(val):
                error_deg = val * math.sqrt(math.pi / 2)
            else:
                logger.warning(
                    "The surrogate has no validation error (best_val_mae_deg_ is NaN): its own "
                    "error is not counted (error_deg = 0)."
                )
                error_deg = 0.0
        return cls(trained, error_deg, growth, max_log_ratio)

    @property
    def accepted_range(self) -> tuple[float, float]:
        """``(lo * exp(-max_log_ratio), hi * exp(max_log_ratio))``: the accepted moments, Nm."""
        lo, hi = self.trained_range
        return lo * math.exp(-self.max_log_ratio), hi * math.exp(self.max_log_ratio)

    def log_distance(self, moments: Any) -> np.ndarray:
        """``L`` of each moment (shape (m,)); see :func:`log_distance`."""
        return log_distance(moments, self.trained_range)

    def error_factor(self, moments: Any) -> np.ndarray:
        """``sd(M) / error_deg = exp(growth * L)``, shape (m,); 1 inside the range."""
        return np.exp(self.growth * self.log_distance(moments))

    def sigma_surrogate(self, moments: Any) -> np.ndarray:
        """The surrogate's error sd at each moment.

        Parameters
        ----------
        moments : array_like, shape (m,)
            Moments in Nm, > 0.

        Returns
        -------
        ndarray, shape (m,)
            ``error_deg * exp(growth * L)`` in degrees; ``error_deg`` inside the range.
        """
        return self.error_deg * self.error_factor(moments)

    def weights(self, moments: Any) -> np.ndarray:
        """Relative fit weights ``(error_deg / sd(M))^2 = exp(-2 * growth * L)``, shape (m,).

        1 inside the range; multiply them with the measurement's own weights.
        """
        return 1.0 / self.error_factor(moments) ** 2

    def point_weights(
        self, moments: Any, weight: Any, noise_deg: float | None = None
    ) -> np.ndarray:
        """Relative fit weights of measured points: their inverse variances.

        With a measurement noise ``noise_deg``, a point of weight ``w`` (the mean of ``w``
        repeated measurements, or a relative inverse noise variance) has the variance
        ``noise_deg^2 / w + sd(M)^2`` (the surrogate's error is not averaged by repeats, as in
        the diagnosis), and its fit weight is ``(noise_deg^2 + error_deg^2)`` over that: 1 for
        a single measurement inside the trained range. Without it (``None``), only the
        surrogate's error is counted and ``w`` scales the point's whole inverse variance:
        ``w * exp(-2 * growth * L)``.

        Parameters
        ----------
        moments : array_like, shape (m,)
            Moments in Nm, > 0.
        weight : array_like, shape (..., m)
            The measurements' own weights, >= 0 (0: the point does not count).
        noise_deg : float, optional
            Measurement noise sd in degrees, > 0.

        Returns
        -------
        ndarray, shape (..., m)
            Relative weights, 0 where ``weight`` is 0.

        Raises
        ------
        ConfigError
            ``noise_deg`` is not a finite number > 0.
        """
        w = np.asarray(weight, dtype=float)
        factor2 = self.error_factor(moments) ** 2
        if noise_deg is None:
            return w / factor2
        try:
            noise = math.nan if isinstance(noise_deg, bool) else float(noise_deg)
        except (TypeError, ValueError):
            noise = math.nan
        if not (math.isfinite(noise) and noise > 0):
            raise ConfigError(
                f"The measurement noise sd must be a finite number > 0 (degrees); got "
                f"{noise_deg!r}. Give the sd of one measurement, e.g. 0.05, or none to count "
                "only the surrogate's error."
            )
        positive = w > 0
        var = noise**2 / np.where(positive, w, 1.0) + self.error_deg**2 * factor2
        return np.where(positive, (noise**2 + self.error_deg**2) / var, 0.0)

    def unit_sd(self, noise_deg: float) -> float:
        """The error sd (deg) of a point of fit weight 1 under :meth:`point_weights`: one
        measurement inside the trained range, ``hypot(noise_deg, error_deg)``."""
        return float(math.hypot(noise_deg, self.error_deg))

    def average_sd(self, moments: Any, weight: Any, noise_deg: float, mask: Any = None) -> float:
        """The error sd of a point of average fit weight: ``sqrt(1 / mean(1 / var))``.

        ``var = noise_deg^2 / w + sd(M)^2`` as in :meth:`point_weights`, averaged over the
        points with ``w > 0`` (and ``mask``). A calibration normalises each specimen's weights
        to a mean of 1, so this is the error scale that gives the points their own variances
        (exactly where every specimen has the same weights): one measurement per point inside
        the trained range gives ``hypot(noise_deg, error_deg)``; the mean of ``k`` repeats at
        every point ``sqrt(noise_deg^2 / k + error_deg^2)``.

        Parameters
        ----------
        moments : array_like, shape (m,)
        weight : array_like, shape (..., m)
            The measurements' own weights, >= 0.
        noise_deg : float
            Measurement noise sd in degrees, > 0.
        mask : array_like of bool, shape (..., m), optional
            The measured points (default: every point).

        Returns
        -------
        float
            In degrees.
        """
        rel = self.point_weights(moments, weight, noise_deg)
        keep = rel > 0 if mask is None else (rel > 0) & np.asarray(mask, dtype=bool)
        if not keep.any():
            raise ConfigError("average_sd: no point has a positive weight; give a measured point.")
        return self.unit_sd(noise_deg) / math.sqrt(float(rel[keep].mean()))

    def check(self, meas: Measurements) -> None:
        """Check the measured moments (those with at least one measured point).

        Inside the trained range: silent. Beyond it but within ``max_log_ratio``: one
        ``UserWarning`` (also logged) naming the moments, the trained range and the larger
        error counted. Beyond ``max_log_ratio``: refused.

        Parameters
        ----------
        meas : Measurements

        Raises
        ------
        InputDataError
            A measured moment lies beyond ``max_log_ratio``; the message names the file, the
            moments, the accepted interval and the fixes.

        Warns
        -----
        UserWarning
            A measured moment lies outside the trained range but is accepted.
        """
        lo, hi = self.trained_range
        used = np.asarray(meas.moments)[meas.mask().any(axis=(0, 1))]
        L = self.log_distance(used)
        tol = 1e-9
        refused = used[L > self.max_log_ratio + tol]
        a_lo, a_hi = self.accepted_range
        if refused.size:
            hint = (
                f" The moments look like N·mm ({_fmt(used)}): divide them by 1000 (femcal reads "
                "moments in Nm)."
                if used.size and np.all(used >= NMM_THRESHOLD)
                else ""
            )
            raise InputDataError(
                f"{meas.source}: measured moments {_fmt(refused)} Nm are too far outside the "
                f"surrogate's trained moment range [{lo:g}, {hi:g}] Nm: moments in "
                f"[{a_lo:.3g}, {a_hi:.3g}] Nm are accepted (the trained range widened by the "
                f"factor e^{self.max_log_ratio:g} = {math.exp(self.max_log_ratio):.3g} on each "
                "side, moments.max_log_ratio, as far as the surrogate's extrapolation error was "
                f"measured).{hint} Delete the points at those moments from the measurements, or "
                "train the surrogate on a wider moment range."
            )
        outside = L > tol
        if not np.any(outside):
            return
        far = np.sort(used[outside][np.argsort(-L[outside], kind="stable")[:3]])  # the 3 farthest
        at = ", ".join(f"{s:.3g} deg at {m:g} Nm" for m, s in zip(far, self.sigma_surrogate(far)))
        message = (
            f"{meas.source}: measured moments {_fmt(used[outside])} Nm lie outside the "
            f"surrogate's trained moment range [{lo:g}, {hi:g}] Nm (accepted up to "
            f"[{a_lo:.3g}, {a_hi:.3g}] Nm); the surrogate extrapolates there: surrogate error sd "
            f"{self.error_deg:.3g} deg in range, {at}, counted in sigma (those points weigh "
            "less in the fit)."
        )
        logger.warning(message)
        warnings.warn(message, UserWarning, stacklevel=2)
