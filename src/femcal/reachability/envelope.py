"""The envelope of the curves a model can produce (per load case and moment); distances to it."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from femcal.errors import ConfigError, InputDataError
from femcal.schema import LOAD_CASES

if TYPE_CHECKING:  # pragma: no cover
    pass


#: Widening of the envelope in log-RoM: a finite sample's extremes fall short of the box's,
#: so a specimen at the far edge of the box may get a warning. The value is chosen so that none
#: of the study's FE curve sets is flagged (docs: *Benchmarks > Measurements behind the
#: defaults*).
MARGIN = 0.1


#: Load-case pairs of the balance features (indices into LOAD_CASES).
PAIRS: tuple[tuple[int, int], ...] = ((0, 1), (2, 3), (0, 2), (0, 3), (1, 2), (1, 3))


TINY = 1e-6  # floor of RoM (deg) inside logarithms


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

    @property
    def model(self) -> str:
        """Which model's envelope this is, for messages: ``"the disc alone"`` or ``"the disc
        with neutral_zone+facet_contact"``."""
        return f"the disc with {'+'.join(self.effects)}" if self.effects else "the disc alone"

    def basis(self) -> str:
        """What the envelope is sampled from: ``"its whole parameter box (1024 surrogate
        curves and 192 FE training curves)"``."""
        ref = f" and {self.n_reference} FE training curves" if self.n_reference else ""
        return f"its whole parameter box ({self.n_evaluated} surrogate curves{ref})"

    def describe(self) -> str:
        """What the envelope is made of, for messages."""
        return f"{self.model} over {self.basis()}"


def _features(y: Any, xp: Any) -> tuple[Any, Any]:
    """Level (B, 4, m) and balance (B, 6, m) features of curves (torch or numpy via ``xp``)."""
    logy = xp.log(xp.clip(y, TINY, None)) if xp is np else y.clamp_min(TINY).log()
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
    logm, logr = np.log(ref_moments), np.log(np.clip(rom, TINY, None))
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

    from femcal.reachability.sobol import scrambled_sobol

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
    # scipy.stats.qmc.Sobol's points, without importing scipy.stats
    u = scrambled_sobol(int(model.dim), math.ceil(math.log2(int(n_samples))), rng)
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
    from femcal.tidy import to_wide

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
class Distances:
    """Per point: sigma beyond the envelope (n, 4, m), NaN where not measured, and details."""

    z: np.ndarray  # max of level and balance, per point
    level: np.ndarray  # signed level excess in deg (> 0 above, < 0 below), 0 inside
    level_z: np.ndarray
    balance_z: np.ndarray  # (n, 6, m)


def envelope_distances(rom: np.ndarray, env: Envelope, sigma: np.ndarray) -> Distances:
    """Sigma distances of curves (n, 4, m) from the envelope; NaN where not measured."""
    measured = ~np.isnan(rom)
    above = np.clip(rom - env.upper, 0.0, None)
    below = np.clip(env.lower - rom, 0.0, None)
    level = np.where(measured, above - below, np.nan)
    level_z = np.abs(level) / sigma
    safe = np.fmax(rom, sigma)  # log-ratio noise floor where a value is tiny
    logr = np.log(np.clip(rom, TINY, None))
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
    return Distances(z=z, level=level, level_z=level_z, balance_z=balance_z)
