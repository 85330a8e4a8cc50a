"""One moment policy for every command: which applied moments a surrogate may be used at.

A surrogate is trained on moments ``[lo, hi]`` (its ``moment_range_``). Outside that range it
extrapolates, and its error grows with the log-moment distance ``L = log(M / hi)`` above the
range and ``log(lo / M)`` below it (``L = 0`` inside): the policy's error sd at ``M`` is the
in-range sd times ``exp(growth[side] * L)`` (``side``: ``below`` or ``above``). Each side's
growth and its limit ``max_log_ratio[side]`` (the largest ``L`` measured) come from
``experiments/bench_extrapolation.py`` on held-out FE curves, set in params.yaml's ``moments``.

``femcal calibrate`` and ``femcal diagnose`` both screen a file with :meth:`MomentPolicy.screen`:
points at moments within the limits are used (a warning beyond the trained range, with the
larger error counted); points beyond them are dropped with a warning naming each one (file,
specimen, load case, moment) and listed in the outputs (:data:`DROPPED_FILE`); a file none of
whose points is usable is refused. Both count the larger error: calibrate weights each point by
``1 / sd(M)^2`` (:meth:`MomentPolicy.point_weights`, the measurement noise counted when given),
diagnose adds ``sd(M)`` to the noise (:meth:`MomentPolicy.sigma_surrogate`).
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from femcal.errors import ConfigError, FemcalWarning, InputDataError, listed

if TYPE_CHECKING:  # pragma: no cover
    from femcal.measurements import Measurements

logger = logging.getLogger(__name__)

_MAX_LISTED = 6
_BENCH = "experiments/bench_extrapolation.py (docs/benchmarks/index.md)"
_TOL = 1e-9
#: The sides of the trained moment range, in the order of the per-side pairs.
SIDES = ("below", "above")
#: The file of a stage's outputs listing the points the policy dropped.
DROPPED_FILE = "dropped_points.csv"
#: Its columns: where each dropped point came from, its values and why it was dropped.
DROPPED_COLUMNS = ("source", "specimen", "load_case", "moment_nm", "rom_deg", "weight", "reason")


def _fmt(values: Sequence[float] | np.ndarray) -> str:
    return listed([f"{float(x):g}" for x in values], most=_MAX_LISTED)


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


def _pair(value: Any, name: str) -> tuple[float, float]:
    """A per-side setting as ``(below, above)``: one number for both sides, a mapping
    ``{below, above}`` or a pair; each a finite number >= 0."""
    if isinstance(value, Mapping):
        unknown = sorted(set(map(str, value)) - set(SIDES))
        raw = [value.get(side, math.nan) for side in SIDES] if not unknown else None
    elif isinstance(value, str | bytes) or not isinstance(value, Sequence | np.ndarray):
        raw = [value, value]
    else:
        raw = list(value) if len(value) == 2 else None
    out = []
    for item in raw or []:
        try:
            number = math.nan if isinstance(item, bool) else float(item)
        except (TypeError, ValueError):
            number = math.nan
        out.append(number)
    if len(out) != 2 or not all(math.isfinite(x) and x >= 0 for x in out):
        what = {
            "growth": "moments.error_growth, the growth of the error sd per unit of L",
            "max_log_ratio": "moments.max_log_ratio, the largest L used",
        }[name]
        raise ConfigError(
            f"MomentPolicy: {name} ({what}) must be a number >= 0 or one per side of the "
            f"trained range, {{below: ..., above: ...}}; got {value!r}. Set each side to the "
            f"value measured by {_BENCH}."
        )
    return out[0], out[1]


def _profile(value: Any) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``(moments, sd)`` checked: equal lengths >= 1, moments > 0 ascending, sd finite >= 0."""
    try:
        at, sd = (np.asarray(v, dtype=np.float64).ravel() for v in value)
        ok = len(at) == len(sd) >= 1 and bool(np.all(at > 0) and np.all(np.diff(at) > 0))
        ok = ok and bool(np.all(np.isfinite(sd)) and np.all(sd >= 0))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ConfigError(
            "MomentPolicy: profile must be (moments, sd) of equal length, moments > 0 in Nm "
            f"ascending and sd >= 0 in degrees; got {value!r}. Pass a surrogate's "
            "val_error_profile_ or None."
        )
    return tuple(at.tolist()), tuple(sd.tolist())


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
    growth : float or (float, float) or mapping
        Growth rate of the error sd per unit of log-moment distance ``L`` beyond the range,
        ``(below, above)`` (a mapping ``{below, above}`` or one number for both sides), each
        >= 0: ``sd(M) = error_deg * exp(growth[side] * L)`` (measured: params.yaml
        ``moments.error_growth``). Stored as the pair.
    max_log_ratio : float or (float, float) or mapping
        The largest ``L`` used on each side, ``(below, above)`` as ``growth``, each >= 0: the
        accepted moments are ``lo * exp(-max_log_ratio[0]) .. hi * exp(max_log_ratio[1])`` Nm
        (measured: params.yaml ``moments.max_log_ratio``, the largest ``L`` the growth was
        measured at on that side). Stored as the pair.
    profile : (moments, sd) or None, optional
        The in-range error sd by moment (Nm ascending, deg), interpolated in log-moment
        (constant beyond its ends): a surrogate's validation error by moment
        (``val_error_profile_``). None: ``error_deg`` at every moment.
    relative : sequence of float or None, optional
        The in-range error sd over the RoM at the profile's moments (``relative_rms``), for
        :meth:`sigma_surrogate` at given curves. None: the profile alone.

    Raises
    ------
    ConfigError
        A field is not a finite number in its range.
    """

    trained_range: tuple[float, float]
    error_deg: float
    growth: tuple[float, float]
    max_log_ratio: tuple[float, float]
    profile: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    relative: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "trained_range", _range(self.trained_range))
        raw = self.error_deg
        try:
            value = math.nan if isinstance(raw, bool) else float(raw)
        except (TypeError, ValueError):
            value = math.nan
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(
                f"MomentPolicy: error_deg (the surrogate's error sd in degrees) must be a finite "
                f"number >= 0; got {raw!r}. Set it to a non-negative value, e.g. 0.03."
            )
        object.__setattr__(self, "error_deg", value)
        object.__setattr__(self, "growth", _pair(self.growth, "growth"))
        object.__setattr__(self, "max_log_ratio", _pair(self.max_log_ratio, "max_log_ratio"))
        if self.profile is not None:
            object.__setattr__(self, "profile", _profile(self.profile))
        if self.relative is not None:
            at = self.profile[0] if self.profile is not None else ()
            object.__setattr__(self, "relative", _profile((at, self.relative))[1])

    @classmethod
    def for_surrogate(
        cls,
        surrogate: Any,
        *,
        growth: Any,
        max_log_ratio: Any,
        error_deg: float | None = None,
    ) -> MomentPolicy:
        """The policy of a fitted surrogate.

        Parameters
        ----------
        surrogate : object
            A fitted surrogate with ``moment_range_`` (models saved without it were trained on
            1..5 Nm) and ``best_val_mae_deg_``.
        growth, max_log_ratio : float or (float, float) or mapping
            See :class:`MomentPolicy` (params.yaml ``moments.error_growth`` and
            ``moments.max_log_ratio``, one value per side).
        error_deg : float, optional
            The in-range error sd; default ``best_val_mae_deg_ * sqrt(pi / 2)`` (Gaussian
            errors), or 0 (with a logged warning) when the surrogate has no validation error.

        Returns
        -------
        MomentPolicy
        """
        trained = tuple(getattr(surrogate, "moment_range_", (1.0, 5.0)))
        found = getattr(surrogate, "val_error_profile_", None) if error_deg is None else None
        profile = (found["moments"], found["rms_deg"]) if found else None
        relative = found.get("relative_rms") if found else None
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
        return cls(trained, error_deg, growth, max_log_ratio, profile, relative)

    def as_params(self) -> dict[str, float]:
        """The per-side settings as flat names (``moments.error_growth.below``, ...), to log."""
        out = {}
        for key, pair in (("error_growth", self.growth), ("max_log_ratio", self.max_log_ratio)):
            out.update({f"moments.{key}.{side}": v for side, v in zip(SIDES, pair)})
        return out

    @property
    def accepted_range(self) -> tuple[float, float]:
        """``(lo * exp(-max_log_ratio[0]), hi * exp(max_log_ratio[1]))``: the accepted moments,
        Nm."""
        lo, hi = self.trained_range
        below, above = self.max_log_ratio
        return lo * math.exp(-below), hi * math.exp(above)

    def log_distance(self, moments: Any) -> np.ndarray:
        """``L`` of each moment (shape (m,)); see :func:`log_distance`."""
        return log_distance(moments, self.trained_range)

    def _per_side(self, pair: tuple[float, float], moments: Any) -> np.ndarray:
        """``pair[1]`` above the trained range, ``pair[0]`` elsewhere, shape (m,)."""
        m = np.atleast_1d(np.asarray(moments, dtype=np.float64))
        return np.where(m > self.trained_range[1], pair[1], pair[0])

    def error_factor(self, moments: Any) -> np.ndarray:
        """``sd(M) / error_deg = exp(growth[side] * L)``, shape (m,); 1 inside the range."""
        return np.exp(self._per_side(self.growth, moments) * self.log_distance(moments))

    def accepts(self, moments: Any) -> np.ndarray:
        """Whether each moment is within the limits, ``L <= max_log_ratio[side]``, shape (m,)."""
        limit = self._per_side(self.max_log_ratio, moments)
        return self.log_distance(moments) <= limit + _TOL

    def sigma_surrogate(self, moments: Any, rom_deg: Any = None) -> np.ndarray:
        """The surrogate's error sd at each moment, or at each point of given curves.

        Parameters
        ----------
        moments : array_like, shape (m,)
            Moments in Nm, > 0.
        rom_deg : array_like, shape (..., m), optional
            RoM at those moments, e.g. the measured curves (NaN where not measured).

        Returns
        -------
        ndarray, shape (m,) or (..., m)
            ``sd_in(M) * exp(growth * L)`` in degrees: ``sd_in`` is the profile at ``M`` (its
            end beyond the trained range), else ``error_deg``; ``relative(M) * |RoM|`` at a
            point of ``rom_deg`` when a ``relative`` profile is given.
        """
        m = np.atleast_1d(np.asarray(moments, dtype=np.float64))
        x = np.log(np.clip(m, *self.trained_range))
        if self.profile is None:
            inside = np.full(m.shape, self.error_deg)
        else:
            at, sd = (np.asarray(v, dtype=np.float64) for v in self.profile)
            inside = np.interp(x, np.log(at), sd)
        absolute = inside * self.error_factor(m)
        if rom_deg is None or self.relative is None:
            return absolute
        rel = np.interp(x, np.log(np.asarray(self.profile[0])), np.asarray(self.relative))
        local = rel * self.error_factor(m) * np.abs(np.asarray(rom_deg, dtype=np.float64))
        return np.where(np.isfinite(local), local, absolute)

    def weights(self, moments: Any) -> np.ndarray:
        """Relative fit weights ``(error_deg / sd(M))^2 = exp(-2 * growth * L)``, shape (m,).

        1 inside the range; multiply them with the measurement's own weights.
        """
        return 1.0 / self.error_factor(moments) ** 2

    def point_weights(
        self, moments: Any, weight: Any, noise_deg: float | None = None, rom_deg: Any = None
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
        rom_deg : array_like, shape (..., m), optional
            The measured curves: ``sd(M)`` at each point as :meth:`sigma_surrogate` gives it.

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
        if noise_deg is None:  # curves without noise: the same weight inside the range
            return w / self.error_factor(moments) ** 2
        sd2 = self.sigma_surrogate(moments, rom_deg) ** 2
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
        var = noise**2 / np.where(positive, w, 1.0) + sd2
        return np.where(positive, (noise**2 + self.error_deg**2) / var, 0.0)

    def unit_sd(self, noise_deg: float) -> float:
        """The error sd (deg) of a point of fit weight 1 under :meth:`point_weights`: one
        measurement inside the trained range, ``hypot(noise_deg, error_deg)``."""
        return float(math.hypot(noise_deg, self.error_deg))

    def average_sd(
        self, moments: Any, weight: Any, noise_deg: float, mask: Any = None, rom_deg: Any = None
    ) -> float:
        """The error sd of a point of average fit weight: ``sqrt(1 / mean(1 / var))``.

        ``var = noise_deg^2 / w + sd(M)^2`` as in :meth:`point_weights`, averaged over the
        points with ``w > 0`` (and ``mask``). A calibration normalises each specimen's weights
        to a mean of 1, so this is the error scale that gives the points their own variances
        (exactly where every specimen has the same weights): one measurement per point with
        ``sd(M) = error_deg`` gives ``hypot(noise_deg, error_deg)``.

        Parameters
        ----------
        moments : array_like, shape (m,)
        weight : array_like, shape (..., m)
            The measurements' own weights, >= 0.
        noise_deg : float
            Measurement noise sd in degrees, > 0.
        mask, rom_deg : array_like, shape (..., m), optional
            The measured points (default: every point), the curves (:meth:`point_weights`).

        Returns
        -------
        float
            In degrees.
        """
        rel = self.point_weights(moments, weight, noise_deg, rom_deg)
        keep = rel > 0 if mask is None else (rel > 0) & np.asarray(mask, dtype=bool)
        if not keep.any():
            raise ConfigError("average_sd: no point has a positive weight; give a measured point.")
        return self.unit_sd(noise_deg) / math.sqrt(float(rel[keep].mean()))

    def screen(self, meas: Measurements) -> Screened:
        """The usable part of a file: its points at accepted moments.

        Inside the trained range: silent. Beyond it but within ``max_log_ratio`` of its side:
        one ``UserWarning`` (also logged) naming the moments, the trained range and the larger
        error counted. Beyond ``max_log_ratio``: the points are dropped, with a ``UserWarning``
        (also logged) naming each (file, specimen, load case, moment); a specimen left without
        a point of positive weight is dropped whole. Moments nobody measured are not looked at.

        Parameters
        ----------
        meas : Measurements

        Returns
        -------
        Screened
            ``measurements``: ``meas`` less the dropped points (``meas`` itself when none is
            dropped); ``dropped``: one row per dropped point (:data:`DROPPED_COLUMNS`).

        Raises
        ------
        InputDataError
            No measured point is usable; the message names the file, the field
            (``moment_nm``), the accepted moments and the fixes. Or some curves' moments are
            all at least :data:`femcal.measurements.units.NMM_THRESHOLD` while others' are not
            (N·mm beside Nm): the message names the file, the field, the load cases and
            specimens, and the fix.

        Warns
        -----
        FemcalWarning
            Points are dropped, or a measured moment lies outside the trained range but is
            accepted (a ``UserWarning``, also logged: the command line shows the log line).
        """
        from femcal.measurements.units import refuse_mixed_units

        measured = meas.mask()
        refuse_mixed_units(meas, measured)
        used_cols = measured.any(axis=(0, 1))
        used = np.asarray(meas.moments)[used_cols]
        accepted = self.accepts(meas.moments)
        if not np.any(accepted & used_cols):
            self._refuse_all(meas, used)
        drop = measured & ~accepted[None, None, :]
        lost = ~np.any(measured & ~drop & (np.asarray(meas.weight) > 0), axis=(1, 2))
        if lost.all():
            a_lo, a_hi = self.accepted_range
            raise InputDataError(
                f"{meas.source}: no measured point is usable: the points at moments in "
                f"[{a_lo:.3g}, {a_hi:.3g}] Nm all have weight 0 (field weight) and the others "
                f"lie outside that interval (field moment_nm: {_fmt(used[~accepted[used_cols]])} "
                f"Nm; {self._limits()}). Give the points inside it a positive weight."
            )
        reasons = np.where(drop, "moment", "")
        drop = drop | (measured & lost[:, None, None])
        reasons = np.where(drop & (reasons == ""), "specimen", reasons)
        dropped = self._dropped_table(meas, drop, reasons)
        kept = meas
        if drop.any():
            kept = meas.without(drop)
            _warn(self._dropped_message(meas, dropped, lost, kept))
        self._warn_outside(kept)
        return Screened(kept, dropped)

    def _refuse_all(self, meas: Measurements, used: np.ndarray) -> None:
        from femcal.measurements.units import NMM_THRESHOLD

        lo, hi = self.trained_range
        a_lo, a_hi = self.accepted_range
        hint = (
            f" The moments look like N·mm ({_fmt(used)}): divide them by 1000 (femcal reads "
            "moments in Nm)."
            if used.size and np.all(used >= NMM_THRESHOLD)
            else ""
        )
        raise InputDataError(
            f"{meas.source}: no measured point is usable: every measured moment (field "
            f"moment_nm: {_fmt(used)} Nm) lies outside the moments the surrogate is used at, "
            f"[{a_lo:.3g}, {a_hi:.3g}] Nm (its trained range [{lo:g}, {hi:g}] Nm widened as far "
            f"as its error was measured: {self._limits()}).{hint} Give the moments in Nm within "
            "that interval, or train the surrogate on a wider moment range."
        )

    def _limits(self) -> str:
        below, above = self.max_log_ratio
        return f"moments.max_log_ratio below {below:g}, above {above:g}"

    def _dropped_table(self, meas: Measurements, drop: np.ndarray, reasons: np.ndarray):
        import pandas as pd

        from femcal.schema import LOAD_CASES

        lo, hi = self.trained_range
        a_lo, a_hi = self.accepted_range
        i, k, j = np.nonzero(drop)
        moments = np.asarray(meas.moments)
        why = {
            "moment": lambda m: (
                f"{m:g} Nm {'below' if m < lo else 'above'} the accepted "
                f"{a_lo:.3g}..{a_hi:.3g} Nm ({self._limits()})"
            ),
            "specimen": lambda m: "its specimen has no other point of positive weight",
        }
        return pd.DataFrame(
            {
                "source": [meas.source] * len(i),
                "specimen": [meas.specimens[a] for a in i],
                "load_case": [LOAD_CASES[a] for a in k],
                "moment_nm": moments[j].astype(float),
                "rom_deg": np.asarray(meas.rom_deg)[i, k, j].astype(float),
                "weight": np.asarray(meas.weight)[i, k, j].astype(float),
                "reason": [why[r](moments[b]) for r, b in zip(reasons[i, k, j], j)],
            },
            columns=list(DROPPED_COLUMNS),
        )

    def _dropped_message(self, meas: Measurements, dropped, lost: np.ndarray, kept) -> str:
        a_lo, a_hi = self.accepted_range
        points = [
            f"specimen {s!r} {lc} {m:g} Nm"
            for s, lc, m in zip(dropped["specimen"], dropped["load_case"], dropped["moment_nm"])
        ]
        shown = listed(points, most=_MAX_LISTED, sep="; ")
        gone = [s for s, x in zip(meas.specimens, lost) if x]
        whole = f" Specimens left out whole (no point left): {', '.join(gone)}." if gone else ""
        return (
            f"{meas.source}: dropped {len(points)} measured point(s) at moments "
            f"{_fmt(np.unique(dropped['moment_nm']))} Nm, outside the moments the surrogate is "
            f"used at, [{a_lo:.3g}, {a_hi:.3g}] Nm ({self._limits()}): {shown}.{whole} "
            f"The outputs list them ({DROPPED_FILE}); the other {int(kept.mask().sum())} points "
            "are used. To use them, train the surrogate on a wider moment range."
        )

    def _warn_outside(self, meas: Measurements) -> None:
        lo, hi = self.trained_range
        used = np.asarray(meas.moments)[meas.mask().any(axis=(0, 1))]
        L = self.log_distance(used)
        outside = L > _TOL
        if not np.any(outside):
            return
        far = np.sort(used[outside][np.argsort(-L[outside], kind="stable")[:3]])  # the 3 farthest
        at = ", ".join(f"{s:.3g} deg at {m:g} Nm" for m, s in zip(far, self.sigma_surrogate(far)))
        a_lo, a_hi = self.accepted_range
        _warn(
            f"{meas.source}: measured moments {_fmt(used[outside])} Nm lie outside the "
            f"surrogate's trained moment range [{lo:g}, {hi:g}] Nm (accepted up to "
            f"[{a_lo:.3g}, {a_hi:.3g}] Nm); the surrogate extrapolates there: surrogate error sd "
            f"{self.error_deg:.3g} deg in range, {at}, counted in sigma (those points weigh "
            "less in the fit).",
            stacklevel=4,
        )


def _warn(message: str, stacklevel: int = 3) -> None:
    """Log ``message`` and warn with it at the caller of :meth:`MomentPolicy.screen`
    (a :class:`~femcal.errors.FemcalWarning`, which the command line does not print again)."""
    logger.warning(message)
    warnings.warn(message, FemcalWarning, stacklevel=stacklevel)


@dataclass(frozen=True, eq=False)
class Screened:
    """A file screened by :meth:`MomentPolicy.screen`.

    Parameters
    ----------
    measurements : Measurements
        The usable points.
    dropped : pandas.DataFrame, shape (k, 7)
        One row per dropped point, columns :data:`DROPPED_COLUMNS`.
    """

    measurements: Measurements
    dropped: Any

    def write(self, folder: Any) -> Path:
        """Write ``dropped`` to ``folder/dropped_points.csv`` (a header only when none was
        dropped); returns its path."""
        path = Path(folder) / DROPPED_FILE
        self.dropped.to_csv(path, index=False)
        return path
