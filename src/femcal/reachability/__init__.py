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
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from femcal.errors import ConfigError
from femcal.reachability.envelope import (
    PAIRS,
    TINY,
    Distances,
    Envelope,
    build_envelope,
    envelope_distances,
    reference_curves,
)
from femcal.reachability.report import ReachabilityReport, UnreachableMeasurementsError
from femcal.schema import LOAD_CASES

if TYPE_CHECKING:  # pragma: no cover
    from femcal.measurements import Measurements

__all__ = [
    "DEG_PER_RAD",
    "UnreachableMeasurementsError",
    "ReachabilityReport",
    "Envelope",
    "assess_reachability",
    "build_envelope",
    "check_reachability",
    "reference_curves",
]


logger = logging.getLogger(__name__)

#: Measurement noise sd (deg) assumed when none is given: the planted cohort's noise.
DEFAULT_NOISE_DEG = 0.05
#: A point lies outside the envelope when it is beyond it by more than this many sigma.
Z_OUTSIDE = 3.0
#: A specimen is far outside when at least FAR_FRACTION of its points are outside and its worst
#: point is beyond this many sigma; a file is refused when most of its specimens are.
Z_FAR = 10.0
FAR_FRACTION = 0.5
#: Degrees per radian.
DEG_PER_RAD = 180.0 / math.pi


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


def _physics(effects: Sequence[str]) -> str:
    """The cause "physics the model lacks", naming the model (the disc alone or with
    ``effects``) and the command that names the physics."""
    model = f"the disc with {'+'.join(effects)}" if effects else "the disc alone"
    return (
        f"physics {model} lacks (run `femcal diagnose`: it fits the disc with each effect and "
        "names the one missing; --effects adds it)"
    )


def _candidates(
    effects: Sequence[str] = (),
) -> list[tuple[str, Callable[[np.ndarray], np.ndarray], str]]:
    """(name, transform of rom (n, 4, m), hint) of the likely causes, in order of preference.

    A unit change that brings the values within reach is named alone. A load-case order that
    does is named second, after physics the model (the disc alone, or with ``effects``) lacks:
    a missing element shifts the balance between load cases as a swap does, and is the more
    common of the two."""
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
                f"{_physics(effects)}; else a different load case convention: the curves fit "
                f"with {name}; check which direction each column holds (flexion is forward "
                f"bending; femcal reads {', '.join(LOAD_CASES)})",
            )
        )
    return out


def _where(d: Distances, env: Envelope, rom: np.ndarray, i: int) -> str:
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


def _plain_cause(d: Distances, i: int, *, z_outside: float, single: bool) -> tuple[str, str]:
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
        sigma = np.maximum(sigma, TINY)
    d = envelope_distances(rom, envelope, sigma)
    n_points, n_out, worst = _counts(d.z, z_outside)
    far = (n_out >= far_fraction * n_points) & (worst > z_far)
    status = np.where(n_out == 0, "reachable", np.where(far, "far", "outside"))
    bad = np.flatnonzero(n_out > 0)
    cause = [""] * len(rom)
    key = [""] * len(rom)
    if bad.size:
        sub = rom[bad]
        open_ = np.ones(bad.size, dtype=bool)
        for name, transform, hint in _candidates(envelope.effects):
            if not open_.any():
                break
            nz = envelope_distances(transform(sub[open_]), envelope, sigma).z
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
            if key[i] == "balance" or (not envelope.effects and key[i] in ("above", "below")):
                # no unit change explains it: missing physics is the likelier cause
                cause[i] = f"{_physics(envelope.effects)}; else {cause[i]}"
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
