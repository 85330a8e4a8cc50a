"""Can the model produce the measured curves at all? The reachability check before a fit.

A calibration always returns *some* parameters. When the measured curves lie outside every
curve the model can produce over its parameter box (rotations in radians instead of degrees,
load cases swapped, a specimen from another joint), the fit ends on the bounds with a
meaningless result, and the only trace is a poor R². This module compares each specimen with
the model's **envelope** before the fit, and says what is wrong.

The envelope (:class:`Envelope`, :func:`build_envelope`) holds, per load case and measured
moment,

* the **level**: the smallest and largest RoM the model produces over the box;
* the **balance**: the smallest and largest log-ratio ``log(RoM_a / RoM_b)`` between two load
  cases at the same moment (the six pairs of :data:`PAIRS`). Swapped load cases can stay within
  every level and still leave the balance the disc allows.

It is computed from the model's own curves on a seeded scrambled-Sobol sample of its unit box
(the network's coordinates, log-scaled where a parameter is positive; with effects, the effect
parameters too, every second sample on a vertex of their box: each effect at full strength or
absent), at the measurement's own moments, so that a 7.5 Nm protocol is covered where the
surrogate extrapolates; joined with the FE training curves when given (interpolated in log-log
onto the measured moments inside their range); and widened by :data:`MARGIN` in log-RoM, as a
finite sample's extremes fall short of the box's. The extremes are not searched for by
optimisation: at the corners of the box, far from any training configuration, the surrogate
is not trusted (on the champion, some corners give non-monotone curves of several hundred
degrees), and an optimiser finds exactly those.

:func:`check_reachability` measures how far each measured point lies outside, in units of
``sigma(M) = sqrt(noise^2 + sd_model(M)^2)`` (the measurement noise and the surrogate's own
error at that moment, :meth:`femcal.moments.MomentPolicy.sigma_surrogate`, larger beyond the
trained moments), and names the likely cause by simple tests: the values times 57.3 (radians),
divided by 1000, or with load cases permuted (Flexion/Extension or LateralBending/AxialRotation
swapped) would lie inside. :meth:`ReachabilityReport.enforce` raises
:class:`UnreachableMeasurementsError` when the file as a whole is wrong (most specimens far
outside, or most outside and one unit change fits them), and otherwise logs one warning naming
the specimens outside. :func:`assess_reachability` does all three for the calibrate and
diagnose commands.

A swap is only seen when it leaves the envelope: on the study's disc, flexion and extension
are nearly interchangeable over the box (their ranges overlap and their ratio spans about 0.3
to 3), so the Test set with Flexion and Extension swapped is still within reach, and a
calibration fits it.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from femcal.errors import ConfigError, InputDataError
from femcal.schema import LOAD_CASES

if TYPE_CHECKING:  # pragma: no cover
    from femcal.measurements import Measurements

logger = logging.getLogger(__name__)

#: Measurement noise sd (deg) assumed when none is given: the planted cohort's noise.
DEFAULT_NOISE_DEG = 0.05
#: A point lies outside the envelope when it is beyond it by more than this many sigma.
Z_OUTSIDE = 3.0
#: A specimen is far outside when at least FAR_FRACTION of its points are outside and its worst
#: point is beyond this many sigma; a file is refused when most of its specimens are.
Z_FAR = 10.0
FAR_FRACTION = 0.5
#: Widening of the envelope in log-RoM: a finite sample's extremes fall short of the box's.
#: Measured on the champion (5 moments, FE curves joined): the extremes of 65,536 samples lie
#: beyond those of 1,024 by a median 0.14 (90%: 0.29; the flexion/extension balance at 1 Nm:
#: 0.49). With 0.1, none of the study's 1,216 FE curve sets (Large without the FE reference,
#: Small, Test) is flagged; a specimen at the far edge of the box may get a warning.
MARGIN = 0.1
#: Load-case pairs of the balance features (indices into LOAD_CASES).
PAIRS: tuple[tuple[int, int], ...] = ((0, 1), (2, 3), (0, 2), (0, 3), (1, 2), (1, 3))
#: Degrees per radian.
DEG_PER_RAD = 180.0 / math.pi
_TINY = 1e-6  # floor of RoM (deg) inside logarithms
_MAX_LISTED = 5
_UNIT_KEYS = ("radians", "x1000")


class UnreachableMeasurementsError(InputDataError):
    """The measured curves lie outside every curve the model can produce: a wrong file."""


# ------------------------------------------------------------------------ the envelope
@dataclass(frozen=True)
class Envelope:
    """The curves a model can produce over its parameter box, per load case and moment.

    Parameters
    ----------
    moments : ndarray, shape (m,)
        The moment grid in Nm.
    lower, upper : ndarray, shape (4, m)
        Smallest and largest RoM (deg) per load case (axis 0 in
        :data:`~femcal.schema.LOAD_CASES` order) and moment.
    balance_lower, balance_upper : ndarray, shape (6, m)
        Smallest and largest ``log(RoM_a / RoM_b)`` per load-case pair of :data:`PAIRS`.
    sigma_model : ndarray, shape (m,)
        The model's own error sd (deg) at each moment (the surrogate's, from the moment policy).
    effects : tuple of str
        The effects included (their parameters sampled with the material parameters).
    n_evaluated : int
        Surrogate curves evaluated to build it (the sample).
    n_reference : int
        FE training curves joined in.
    seconds : float
        Time taken to build it.
    """

    moments: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    balance_lower: np.ndarray
    balance_upper: np.ndarray
    sigma_model: np.ndarray
    effects: tuple[str, ...] = ()
    n_evaluated: int = 0
    n_reference: int = 0
    seconds: float = 0.0

    def sigma(self, noise_deg: float) -> np.ndarray:
        """``sqrt(noise_deg^2 + sigma_model^2)`` (deg), shape (m,)."""
        return np.hypot(float(noise_deg), self.sigma_model)

    def describe(self) -> str:
        """What the envelope is made of, for messages."""
        what = "the disc model" + (f" with {'+'.join(self.effects)}" if self.effects else "")
        ref = f" and {self.n_reference} FE training curves" if self.n_reference else ""
        return f"{what} over its whole parameter box ({self.n_evaluated} surrogate curves{ref})"


def _features(y: Any, xp: Any) -> tuple[Any, Any]:
    """Level (B, 4, m) and balance (B, 6, m) features of curves (torch or numpy via ``xp``)."""
    logy = xp.log(xp.clip(y, _TINY, None)) if xp is np else y.clamp_min(_TINY).log()
    a = [p[0] for p in PAIRS]
    b = [p[1] for p in PAIRS]
    return y, logy[:, a] - logy[:, b]


def _flat(y: Any, xp: Any) -> Any:
    """All features of curves, shape (B, 4, m) -> (B, 10 m)."""
    level, balance = _features(y, xp)
    cat = np.concatenate if xp is np else xp.cat
    return cat([level.reshape(level.shape[0], -1), balance.reshape(balance.shape[0], -1)], 1)


def _interpolate(ref_moments: np.ndarray, rom: np.ndarray, moments: np.ndarray) -> np.ndarray:
    """Curves (N, 4, m_t) on ``moments`` (m,) by log-log interpolation; NaN outside the range."""
    ref_moments = np.asarray(ref_moments, dtype=float)
    out = np.full(rom.shape[:2] + (moments.size,), np.nan)
    logm, logr = np.log(ref_moments), np.log(np.clip(rom, _TINY, None))
    for j, m in enumerate(moments):
        if not ref_moments[0] - 1e-9 <= m <= ref_moments[-1] + 1e-9:
            continue
        hi = int(np.clip(np.searchsorted(ref_moments, m), 1, ref_moments.size - 1))
        lo = hi - 1
        t = (math.log(m) - logm[lo]) / (logm[hi] - logm[lo]) if ref_moments.size > 1 else 0.0
        out[:, :, j] = np.exp((1 - t) * logr[:, :, lo] + t * logr[:, :, hi])
    return out


def _extremes(feats: Any) -> tuple[Any, Any]:
    """Largest and smallest finite value of every feature over the rows, each (F,)."""
    import torch

    ok = torch.isfinite(feats).all(1, keepdim=True)  # rows the model cannot evaluate: none
    return (
        torch.where(ok, feats, -torch.inf).max(0).values,
        torch.where(ok, feats, torch.inf).min(0).values,
    )


def build_envelope(
    model: Any,
    *,
    sigma_model: float | Sequence[float] | np.ndarray = 0.0,
    reference: tuple[np.ndarray, np.ndarray] | None = None,
    n_samples: int | None = None,
    margin: float = MARGIN,
    seed: int = 0,
) -> Envelope:
    """The envelope of the curves a model produces over its box, on its moment grid.

    Parameters
    ----------
    model : CurveModel or EffectModel
        The disc surrogate (with effects, if any) on the measurement's moment grid: ``dim``,
        ``moments`` (Tensor, shape (m,)), ``curves(v)`` (Tensor (B, dim) in the unit box ->
        (B, 4, m) in deg) and, with effects, ``n_disc`` and ``effect_names``.
    sigma_model : float or array_like, shape (m,)
        The surrogate's error sd (deg) at each moment (``MomentPolicy.sigma_surrogate``).
    reference : tuple (moments, rom), optional
        FE curves to join in: moments shape (m_t,) increasing, rom shape (N, 4, m_t) in deg
        (NaN for failed runs). Used at the grid's moments inside ``[moments[0], moments[-1]]``.
    n_samples : int, optional
        Scrambled-Sobol sample size over the model's unit box (rounded up to a power of 2),
        >= 2; default 1024 for the disc alone, 512 with effects (a composite curve costs about
        ten disc curves: its disc moment is solved by bisection). With effects, every second
        sample puts the effect parameters on a vertex of their box (each effect parameter at
        its bound: full strength or absent).
    margin : float
        Widening in log-RoM, >= 0: the level bounds are multiplied by ``exp(-margin)`` and
        ``exp(margin)``, the balance bounds moved by ``margin`` (:data:`MARGIN`: a finite
        sample's extremes fall short of the box's).
    seed : int
        Seed of the sample (numpy Generator); same seed, same envelope.

    Returns
    -------
    Envelope

    Raises
    ------
    ConfigError
        ``n_samples`` or ``margin`` out of range, or ``sigma_model`` of the wrong shape.
    """
    import torch
    from scipy.stats import qmc

    t0 = time.perf_counter()
    n_disc = int(getattr(model, "n_disc", model.dim))
    if n_samples is None:
        n_samples = 1024 if n_disc == model.dim else 512
    if int(n_samples) < 2 or not (math.isfinite(margin) and margin >= 0):
        raise ConfigError(
            f"build_envelope needs n_samples >= 2 and a finite margin >= 0; got {n_samples!r} "
            f"and {margin!r}. Use the defaults (None: 1024 or 512 with effects; {MARGIN})."
        )
    moments = np.asarray(model.moments, dtype=float).reshape(-1)
    m = moments.size
    sd = (
        np.broadcast_to(np.asarray(sigma_model, dtype=float), (m,)).copy()
        if np.ndim(sigma_model) in (0, 1) and np.size(sigma_model) in (1, m)
        else None
    )
    if sd is None or not np.all(np.isfinite(sd) & (sd >= 0)):
        raise ConfigError(
            f"sigma_model must be a finite sd >= 0 (deg) or one per moment ({m}); got "
            f"{sigma_model!r}. Pass MomentPolicy.sigma_surrogate(moments)."
        )
    rng = np.random.default_rng(seed)
    sobol = qmc.Sobol(int(model.dim), scramble=True, seed=rng)
    u = sobol.random_base2(math.ceil(math.log2(int(n_samples))))
    if n_disc < model.dim:
        # Half the sample at the vertices of the effects' parameter box (their extremes: an
        # effect at full strength or absent), the disc parameters space-filling.
        u[1::2, n_disc:] = np.round(u[1::2, n_disc:])
    v = torch.tensor(u, dtype=torch.float32)
    with torch.no_grad():
        feats = _flat(model.curves(v), torch)
    n_eval = int(v.shape[0])
    hi, lo = _extremes(feats)
    hi_np, lo_np = hi.double().numpy(), lo.double().numpy()
    n_ref = 0
    if reference is not None:
        ref_m, ref_rom = reference
        ref_rom = np.asarray(ref_rom, dtype=float)
        rom = _interpolate(np.asarray(ref_m), ref_rom, moments)
        rom = rom[~np.isnan(ref_rom).any(axis=(1, 2))]  # failed runs out
        n_ref = len(rom)
        if n_ref:
            f = _flat(rom, np)  # NaN at moments outside the reference's range
            hi_np = np.maximum(hi_np, np.where(np.isnan(f), -np.inf, f).max(axis=0))
            lo_np = np.minimum(lo_np, np.where(np.isnan(f), np.inf, f).min(axis=0))
    if not (np.all(np.isfinite(hi_np)) and np.all(np.isfinite(lo_np))):
        raise ConfigError(
            f"The model gave no finite curve on the moments {moments.tolist()} Nm over "
            f"{n_eval} samples of its box; check the surrogate and the effects."
        )
    n_level = len(LOAD_CASES) * m
    hi_np[:n_level] *= math.exp(margin)
    lo_np[:n_level] *= math.exp(-margin)
    hi_np[n_level:] += margin
    lo_np[n_level:] -= margin
    effects = tuple(getattr(model, "effect_names", ()))
    return Envelope(
        moments=moments,
        lower=lo_np[:n_level].reshape(len(LOAD_CASES), m),
        upper=hi_np[:n_level].reshape(len(LOAD_CASES), m),
        balance_lower=lo_np[n_level:].reshape(len(PAIRS), m),
        balance_upper=hi_np[n_level:].reshape(len(PAIRS), m),
        sigma_model=sd,
        effects=effects,
        n_evaluated=n_eval,
        n_reference=n_ref,
        seconds=time.perf_counter() - t0,
    )


def reference_curves(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The FE curves of a prepared split (the training data), for :func:`build_envelope`.

    Parameters
    ----------
    path : str or Path
        A prepared ``<split>.csv`` (params.yaml ``calibrate.start_bank``).

    Returns
    -------
    moments : ndarray, shape (m_t,)
    rom : ndarray, shape (N, 4, m_t)
        RoM in degrees of the converged configurations (failed runs dropped).

    Raises
    ------
    InputDataError
        The file cannot be read, lacks a column, or is not a complete grid.
    """
    from femcal.prepare import to_wide

    columns = ["config_id", "load_case", "moment_nm", "rom_deg", "status"]
    try:
        table = pd.read_csv(path, usecols=columns)
    except (OSError, ValueError) as exc:
        raise InputDataError(
            f"{path}: cannot read the FE reference curves ({exc}); give a prepared split (the "
            f"prepare stage's <split>.csv, columns {', '.join(columns)}), e.g. "
            "data/prepared/large.csv."
        ) from None
    table.loc[table["status"] != "ok", "rom_deg"] = np.nan  # failed runs: no curve
    _, moments, rom = to_wide(table)
    return moments, rom[~np.isnan(rom).any(axis=(1, 2))]


# ------------------------------------------------------------------------ the check
@dataclass(frozen=True)
class _Distances:
    """Per point: sigma beyond the envelope (n, 4, m), NaN where not measured, and details."""

    z: np.ndarray  # max of level and balance, per point
    level: np.ndarray  # signed level excess in deg (> 0 above, < 0 below), 0 inside
    level_z: np.ndarray
    balance_z: np.ndarray  # (n, 6, m)


def _distances(rom: np.ndarray, env: Envelope, sigma: np.ndarray) -> _Distances:
    """Sigma distances of curves (n, 4, m) from the envelope; NaN where not measured."""
    measured = ~np.isnan(rom)
    above = np.clip(rom - env.upper, 0.0, None)
    below = np.clip(env.lower - rom, 0.0, None)
    level = np.where(measured, above - below, np.nan)
    level_z = np.abs(level) / sigma
    safe = np.fmax(rom, sigma)  # log-ratio noise floor where a value is tiny
    logr = np.log(np.clip(rom, _TINY, None))
    a = [p[0] for p in PAIRS]
    b = [p[1] for p in PAIRS]
    ratio = logr[:, a] - logr[:, b]
    sd = np.hypot(sigma / safe[:, a], sigma / safe[:, b])
    excess = np.fmax(ratio - env.balance_upper, env.balance_lower - ratio)
    balance_z = np.clip(excess, 0.0, None) / sd  # NaN where either point is missing
    z = level_z.copy()
    for p, (i, j) in enumerate(PAIRS):
        bz = np.nan_to_num(balance_z[:, p], nan=0.0)
        z[:, i] = np.where(measured[:, i], np.fmax(z[:, i], bz), np.nan)
        z[:, j] = np.where(measured[:, j], np.fmax(z[:, j], bz), np.nan)
    return _Distances(z=z, level=level, level_z=level_z, balance_z=balance_z)


def _counts(z: np.ndarray, z_outside: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points measured (n,), points outside (n,), worst sigma (n,)."""
    measured = ~np.isnan(z)
    n_points = measured.sum(axis=(1, 2))
    n_out = np.sum(np.nan_to_num(z, nan=0.0) > z_outside, axis=(1, 2))
    worst = np.nanmax(np.where(measured, z, -np.inf).reshape(len(z), -1), axis=1)
    return n_points, n_out, np.maximum(worst, 0.0)


def _permutation_name(perm: Sequence[int]) -> str:
    moved = [(k, p) for k, p in enumerate(perm) if k != p]
    if len(moved) == 2 and perm[moved[0][0]] == moved[1][0]:
        return f"{LOAD_CASES[moved[0][0]]} and {LOAD_CASES[moved[1][0]]} swapped"
    return (
        "the load cases in another order ("
        + ", ".join(f"the {LOAD_CASES[k]} column holding {LOAD_CASES[p]}" for k, p in moved)
        + ")"
    )


def _candidates() -> list[tuple[str, Callable[[np.ndarray], np.ndarray], str]]:
    """(name, transform of rom (n, 4, m), hint) of the likely causes, in order of preference."""
    out: list[tuple[str, Callable[[np.ndarray], np.ndarray], str]] = [
        (
            "radians",
            lambda r: r * DEG_PER_RAD,
            "values look like radians: multiply by 57.3 (femcal reads RoM in degrees)",
        ),
        (
            "x1000",
            lambda r: r / 1000.0,
            "values look 1000x too large: N·mm (or millidegrees) somewhere? femcal reads RoM in "
            "degrees at moments in Nm: divide the values by 1000, or convert the unit",
        ),
    ]
    perms = [p for p in itertools.permutations(range(len(LOAD_CASES))) if list(p) != [0, 1, 2, 3]]
    perms.sort(
        key=lambda p: (p not in ((1, 0, 2, 3), (0, 1, 3, 2)), sum(k != v for k, v in enumerate(p)))
    )
    for perm in perms:
        name = _permutation_name(perm)
        out.append(
            (
                "load_cases:" + ",".join(LOAD_CASES[k] for k in perm),
                lambda r, perm=perm: r[:, list(perm)],
                f"a different load case convention? the curves fit with {name}: check which "
                "direction each column holds (flexion is forward bending; femcal reads "
                f"{', '.join(LOAD_CASES)}); if the columns are right, physics the model lacks "
                "(`femcal diagnose` names it, --effects adds it)",
            )
        )
    return out


@dataclass(frozen=True)
class ReachabilityReport:
    """Per specimen: how far its measured points lie outside the model's envelope.

    Attributes
    ----------
    source : str
        The measurement file.
    specimens : tuple of str, shape (n,)
    n_points, n_outside : ndarray of int, shape (n,)
        Measured points, and those beyond the envelope by more than ``z_outside`` sigma.
    worst_sigma : ndarray, shape (n,)
        The largest distance beyond the envelope, in sigma (0 inside).
    worst_where : tuple of str, shape (n,)
        Where and how the worst point lies outside ("" when inside).
    status : tuple of str, shape (n,)
        ``"reachable"``, ``"outside"`` (some points outside) or ``"far"`` (at least
        ``far_fraction`` of its points outside and the worst beyond ``z_far`` sigma).
    cause : tuple of str, shape (n,)
        The likely cause ("" when reachable).
    cause_key : tuple of str, shape (n,)
        A short key of the cause: ``radians``, ``x1000``, ``load_cases:<order>``, ``above``,
        ``below``, ``balance``, ``point`` or "".
    z : ndarray, shape (n, 4, m)
        Sigma beyond the envelope of every point (NaN where not measured).
    envelope : Envelope
    noise_deg, z_outside, z_far, far_fraction : float
        The settings of the check.
    seconds : float
        Time of the check (building the envelope not included).
    """

    source: str
    specimens: tuple[str, ...]
    n_points: np.ndarray
    n_outside: np.ndarray
    worst_sigma: np.ndarray
    worst_where: tuple[str, ...]
    status: tuple[str, ...]
    cause: tuple[str, ...]
    cause_key: tuple[str, ...]
    z: np.ndarray
    envelope: Envelope
    noise_deg: float
    z_outside: float
    z_far: float
    far_fraction: float
    seconds: float

    @property
    def outside(self) -> list[str]:
        """Specimens with points outside the envelope (status "outside" or "far")."""
        return [s for s, st in zip(self.specimens, self.status) if st != "reachable"]

    @property
    def far(self) -> list[str]:
        """Specimens far outside."""
        return [s for s, st in zip(self.specimens, self.status) if st == "far"]

    @property
    def refused(self) -> bool:
        """Whether the file as a whole is wrong: an error rather than a warning.

        True when most specimens (``far_fraction`` of them) are far outside, or when most have
        points outside and one unit change (radians, x1000) brings most of them within reach:
        one mistake made throughout the file. (A load-case order that fits is no proof: physics
        the model lacks can shift the balance between load cases too; it refuses a file only
        when most specimens are far outside.)
        """
        n = len(self.specimens)
        most = max(1, math.ceil(self.far_fraction * n))
        if len(self.far) >= most:
            return True
        units = [k for k in self.cause_key if k in _UNIT_KEYS]
        return len(self.outside) >= most and max(map(units.count, units), default=0) >= most

    def notes(self) -> list[str]:
        """One line per specimen for the outputs ("" when reachable), shape (n,)."""
        out = []
        for i in range(len(self.specimens)):
            if self.status[i] == "reachable":
                out.append("")
                continue
            out.append(
                f"{self.n_outside[i]}/{self.n_points[i]} points outside the model's envelope, "
                f"worst {self.worst_sigma[i]:.1f} sigma ({self.worst_where[i]}); likely cause: "
                f"{self.cause[i]}"
            )
        return out

    def frame(self) -> pd.DataFrame:
        """Per specimen: specimen, status, n_points, n_outside, worst_sigma, where, cause, note."""
        return pd.DataFrame(
            {
                "specimen": list(self.specimens),
                "status": list(self.status),
                "n_points": self.n_points,
                "n_outside": self.n_outside,
                "worst_sigma": self.worst_sigma,
                "where": list(self.worst_where),
                "cause": list(self.cause_key),
                "note": self.notes(),
            }
        )

    def _common_cause(self, names: Sequence[str]) -> tuple[str, str]:
        idx = [self.specimens.index(s) for s in names]
        keys = [self.cause_key[i] for i in idx]
        key = max(set(keys), key=keys.count)
        return key, self.cause[idx[keys.index(key)]]

    def _example(self, names: Sequence[str]) -> str:
        i = max((self.specimens.index(s) for s in names), key=lambda k: self.worst_sigma[k])
        return f"specimen {self.specimens[i]!r}: {self.worst_where[i]}"

    def _load_cases(self, names: Sequence[str]) -> str:
        idx = [self.specimens.index(s) for s in names]
        out = np.nan_to_num(self.z[idx], nan=0.0) > self.z_outside  # (k, 4, m)
        counts = out.sum(axis=(0, 2))
        return ", ".join(
            f"{LOAD_CASES[k]} ({int(counts[k])} points)"
            for k in np.argsort(-counts, kind="stable")
            if counts[k]
        )

    def message(self) -> str:
        """The error (refused) or warning text; "" when every specimen is reachable."""
        bad = self.outside
        if not bad:
            return ""
        n = len(self.specimens)
        sig = self.envelope.sigma(self.noise_deg)
        span = f"{sig.min():.3g}" if np.ptp(sig) < 5e-4 else f"{sig.min():.3g}-{sig.max():.3g}"
        sigma_text = (
            f"sigma = {span} deg: measurement noise {self.noise_deg:g} deg and the surrogate's "
            "error at each moment in quadrature"
        )
        key, cause = self._common_cause(bad)
        names = _listing([repr(s) for s in bad])
        if self.refused:
            explained = sum(k == key for k in self.cause_key)
            fixed = (
                f" ({explained} of the {len(bad)} come within reach with that change)"
                if key in _UNIT_KEYS or key.startswith("load_cases:")
                else ""
            )
            return (
                f"{self.source}: the measurements lie outside every curve the model can produce "
                f"({self.envelope.describe()}): {len(bad)} of {n} specimens have points outside "
                f"({len(self.far)} with most points outside), by up to "
                f"{max(self.worst_sigma):.0f} sigma ({sigma_text}); specimens {names}; load "
                f"cases {self._load_cases(bad)}. E.g. {self._example(bad)}. Likely cause: "
                f"{cause}{fixed}. Fix the file and run again; if the values are right, the model "
                "cannot represent these specimens (widen the parameter box and retrain, or add "
                "effects with --effects; `femcal diagnose` names the missing physics)."
            )
        return (
            f"{self.source}: {len(bad)} of {n} specimens have measured points outside every "
            f"curve the model can produce ({self.envelope.describe()}; more than "
            f"{self.z_outside:g} sigma, {sigma_text}): {names}; load cases "
            f"{self._load_cases(bad)}. E.g. {self._example(bad)}; likely cause: {cause}. A fit "
            "cannot reach those points: check these specimens before trusting their results."
        )

    def enforce(self) -> None:
        """Raise when the file as a whole is wrong; log one warning when some specimens are off.

        Raises
        ------
        UnreachableMeasurementsError
            :attr:`refused`; the message names the file, the specimens, the load cases, the
            likely cause and the fix.

        Notes
        -----
        The warning is logged (logger ``femcal.reachability``), once: the CLI shows it, and the
        outputs of calibrate mark the specimens (``reachability`` column of metrics.csv).
        """
        text = self.message()
        if not text:
            logger.info(
                "%s: every measured point lies within the model's envelope (checked in %.2f s).",
                self.source,
                self.seconds + self.envelope.seconds,
            )
            return
        if self.refused:
            raise UnreachableMeasurementsError(text)
        logger.warning(text)


def _listing(items: Sequence[str]) -> str:
    more = f" (and {len(items) - _MAX_LISTED} more)" if len(items) > _MAX_LISTED else ""
    return ", ".join(items[:_MAX_LISTED]) + more


def _where(d: _Distances, env: Envelope, rom: np.ndarray, i: int) -> str:
    """The worst point of specimen ``i`` in words."""
    z = np.nan_to_num(d.z[i], nan=-1.0)
    k, j = np.unravel_index(int(np.argmax(z)), z.shape)
    moment = f"{env.moments[j]:g} Nm"
    if d.level_z[i, k, j] >= z[k, j] - 1e-12 and d.level[i, k, j] != 0:
        side = "above the largest" if d.level[i, k, j] > 0 else "below the smallest"
        bound = env.upper[k, j] if d.level[i, k, j] > 0 else env.lower[k, j]
        return (
            f"{LOAD_CASES[k]} at {moment}: {rom[i, k, j]:.4g} deg, {side} RoM the model "
            f"produces there, {bound:.4g} deg"
        )
    bz = np.nan_to_num(d.balance_z[i, :, j], nan=-1.0)
    p = int(np.argmax(bz))
    a, b = PAIRS[p]
    ratio = rom[i, a, j] / rom[i, b, j]
    lo, hi = np.exp(env.balance_lower[p, j]), np.exp(env.balance_upper[p, j])
    return (
        f"{LOAD_CASES[a]}/{LOAD_CASES[b]} at {moment}: RoM ratio {ratio:.3g}, the model "
        f"produces {lo:.3g}-{hi:.3g}"
    )


def _plain_cause(d: _Distances, i: int, *, z_outside: float, single: bool) -> tuple[str, str]:
    """(key, text) of the cause of specimen ``i`` when no unit or load-case change explains it."""
    level = np.nan_to_num(d.level[i], nan=0.0)
    over = np.nan_to_num(d.level_z[i], nan=0.0) > z_outside
    if single:
        k, j = np.unravel_index(int(np.argmax(np.nan_to_num(d.z[i], nan=-1.0))), level.shape)
        there = (
            "more rotation than any disc in the box there"
            if level[k, j] > 0 and over[k, j]
            else "less rotation than any disc in the box there"
            if level[k, j] < 0 and over[k, j]
            else "a balance between load cases no disc in the box has there"
        )
        return "point", f"a single point outside ({there}): a typing error or a noisy point?"
    if over.any() and np.all(level[over] > 0):
        return "above", (
            "more rotation than any disc in the parameter box (softer than its softest "
            "configuration): a wrong unit or specimen"
        )
    if over.any() and np.all(level[over] < 0):
        return "below", (
            "less rotation than any disc in the parameter box (stiffer than its stiffest "
            "configuration): a wrong unit or specimen"
        )
    if over.any():
        return "level", (
            "some load cases above and others below what any disc in the box produces: check "
            "the load-case columns and the specimen"
        )
    return "balance", (
        "the balance between load cases (e.g. Flexion against Extension) is outside what any "
        "disc in the box produces: check the load-case columns"
    )


def check_reachability(
    meas: Measurements,
    envelope: Envelope,
    *,
    noise_deg: float | None = None,
    z_outside: float = Z_OUTSIDE,
    z_far: float = Z_FAR,
    far_fraction: float = FAR_FRACTION,
) -> ReachabilityReport:
    """Compare every specimen's measured curves with the model's envelope.

    Parameters
    ----------
    meas : Measurements
        ``n`` specimens on the moment grid the envelope was built on.
    envelope : Envelope
        From :func:`build_envelope` on ``meas.moments``.
    noise_deg : float, optional
        Measurement noise sd in degrees (default :data:`DEFAULT_NOISE_DEG`).
    z_outside : float
        A point is outside when beyond the envelope by more than this many sigma.
    z_far : float
        A specimen is far outside when at least ``far_fraction`` of its points are outside and
        its worst point is beyond ``z_far`` sigma.
    far_fraction : float
        See ``z_far``; the file is refused when this fraction of its specimens is far outside.

    Returns
    -------
    ReachabilityReport
        Call :meth:`ReachabilityReport.enforce` to raise or warn.

    Raises
    ------
    ConfigError
        The envelope was built on other moments, or a setting is out of range.
    """
    t0 = time.perf_counter()
    noise = DEFAULT_NOISE_DEG if noise_deg is None else float(noise_deg)
    if not (
        math.isfinite(noise) and noise >= 0 and 0 < z_outside <= z_far and 0 < far_fraction <= 1
    ):
        raise ConfigError(
            f"check_reachability needs noise_deg >= 0, 0 < z_outside <= z_far and 0 < "
            f"far_fraction <= 1; got {noise_deg!r}, {z_outside!r}, {z_far!r}, {far_fraction!r}."
        )
    if envelope.moments.shape != meas.moments.shape or not np.allclose(
        envelope.moments, meas.moments
    ):
        raise ConfigError(
            f"The envelope was built on moments {envelope.moments.tolist()} Nm, the measurements "
            f"({meas.source}) hold {meas.moments.tolist()} Nm; build it on meas.moments."
        )
    rom = np.asarray(meas.rom_deg, dtype=float)
    sigma = envelope.sigma(noise)
    if np.any(sigma <= 0):
        sigma = np.maximum(sigma, _TINY)
    d = _distances(rom, envelope, sigma)
    n_points, n_out, worst = _counts(d.z, z_outside)
    far = (n_out >= far_fraction * n_points) & (worst > z_far)
    status = np.where(n_out == 0, "reachable", np.where(far, "far", "outside"))
    bad = np.flatnonzero(n_out > 0)
    cause = [""] * len(rom)
    key = [""] * len(rom)
    if bad.size:
        sub = rom[bad]
        open_ = np.ones(bad.size, dtype=bool)
        for name, transform, hint in _candidates():
            if not open_.any():
                break
            nz = _distances(transform(sub[open_]), envelope, sigma).z
            t_points, t_out, t_worst = _counts(nz, z_outside)
            fits = (t_out <= 0.1 * t_points) & (t_worst < z_far) & (t_out < n_out[bad][open_])
            # A transform only explains a specimen clearly off (several points, or far).
            clear = (n_out[bad][open_] >= 2) | (worst[bad][open_] > z_far)
            for pos in np.flatnonzero(open_)[fits & clear]:
                cause[bad[pos]], key[bad[pos]] = hint, name
            open_[np.flatnonzero(open_)[fits & clear]] = False
        for pos in np.flatnonzero(open_):
            i = bad[pos]
            key[i], cause[i] = _plain_cause(
                d, i, z_outside=z_outside, single=bool(n_out[i] == 1 and worst[i] <= z_far)
            )
            if not envelope.effects and key[i] in ("above", "below", "balance"):
                cause[i] += (
                    "; or physics the disc lacks: `femcal diagnose` names it, --effects adds it"
                )
    return ReachabilityReport(
        source=meas.source,
        specimens=tuple(meas.specimens),
        n_points=n_points,
        n_outside=n_out,
        worst_sigma=worst,
        worst_where=tuple(_where(d, envelope, rom, i) if n_out[i] else "" for i in range(len(rom))),
        status=tuple(str(s) for s in status),
        cause=tuple(cause),
        cause_key=tuple(key),
        z=d.z,
        envelope=envelope,
        noise_deg=noise,
        z_outside=float(z_outside),
        z_far=float(z_far),
        far_fraction=float(far_fraction),
        seconds=time.perf_counter() - t0,
    )


def assess_reachability(
    meas: Measurements,
    model: Any,
    *,
    sigma_model: float | Sequence[float] | np.ndarray = 0.0,
    reference: str | Path | None = None,
    noise_deg: float | None = None,
    seed: int = 0,
) -> ReachabilityReport:
    """Build the envelope, check the measurements, raise or warn: the pre-fit check.

    Parameters
    ----------
    meas : Measurements
    model : CurveModel or EffectModel
        On ``meas.moments``, with the effects of the fit (if any).
    sigma_model : float or array_like, shape (m,)
        The surrogate's error sd at each moment (``MomentPolicy.sigma_surrogate``).
    reference : str or Path, optional
        A prepared split whose FE curves join the envelope (params.yaml
        ``calibrate.start_bank``); skipped, with a logged note, when the file is missing.
    noise_deg : float, optional
        Measurement noise sd (deg); default :data:`DEFAULT_NOISE_DEG`.
    seed : int
        Seed of the envelope's sample.

    Returns
    -------
    ReachabilityReport

    Raises
    ------
    UnreachableMeasurementsError
        The file as a whole lies outside the envelope (:attr:`ReachabilityReport.refused`).
    """
    ref = None
    if reference is not None:
        if Path(reference).is_file():
            ref = reference_curves(reference)
        else:
            logger.info(
                "Reachability: %s not found; the envelope is the surrogate's only.", reference
            )
    env = build_envelope(model, sigma_model=sigma_model, reference=ref, seed=seed)
    report = check_reachability(meas, env, noise_deg=noise_deg)
    report.enforce()
    return report
