"""Hidden-effect data: plant a physical effect into real FE curves, with noise.

The disc's curve comes from the FE results themselves (not from the surrogate): the FE RoM at
its moments is interpolated linearly in log-moment / log-RoM, and below the first FE moment
continued as the power law through the origin with the slope of the first interval, above the
last one with the slope of the last interval. A parallel effect then takes its share of the
applied moment (``M = M_d + M_e(phi_FE(M_d))`` solved by bisection), a series effect adds its
rotation, and Gaussian noise of ``noise_deg`` is added at the chosen moments.

:data:`VISIBLE_RANGES` gives the sub-ranges of the effect parameters drawn for a cohort: effects
strong enough to matter on the 1..5 Nm curves of a typical specimen (the full bounds of an
effect also allow it to be negligible).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from femcal.effects.base import get_effect
from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES
from femcal.space import ParameterSpace

#: Parameter ranges drawn per planted effect (physical units; log-uniform for "log" ones).
VISIBLE_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "facet_contact": {"facet_gap_deg": (0.5, 2.5), "facet_stiffness": (0.3, 3.0)},
    "ligament_tension": {"ligament_slack_deg": (1.0, 4.0), "ligament_stiffness": (0.1, 1.0)},
    "neutral_zone": {"nz_range_deg": (0.4, 1.5), "nz_moment_nm": (0.2, 0.8)},
}
NONE = "none"


def fe_rotation(fe_moments: np.ndarray, fe_rom: np.ndarray, moment: np.ndarray) -> np.ndarray:
    """The FE curve interpolated at any moment > 0.

    Parameters
    ----------
    fe_moments : ndarray, shape (k,)
        Increasing FE moments (> 0), at least two.
    fe_rom : ndarray, shape (..., k)
        FE RoM (> 0) at those moments.
    moment : ndarray, shape (..., q)
        Moments to evaluate at (> 0); broadcast against the leading dimensions of ``fe_rom``.

    Returns
    -------
    ndarray, shape (..., q)
    """
    lm = np.log(np.asarray(fe_moments, dtype=float))
    lr = np.log(np.asarray(fe_rom, dtype=float))
    x = np.log(np.asarray(moment, dtype=float))
    idx = np.clip(np.searchsorted(lm, x) - 1, 0, len(lm) - 2)
    x0, x1 = lm[idx], lm[idx + 1]
    y0 = np.take_along_axis(lr, np.broadcast_to(idx, lr.shape[:-1] + idx.shape[-1:]), -1)
    y1 = np.take_along_axis(lr, np.broadcast_to(idx + 1, lr.shape[:-1] + idx.shape[-1:]), -1)
    return np.exp(y0 + (y1 - y0) * (x - x0) / (x1 - x0))


def plant(
    effect: str,
    params: dict[str, float],
    fe_moments: np.ndarray,
    fe_rom: np.ndarray,
    moments: np.ndarray,
) -> np.ndarray:
    """Curves of one specimen with ``effect`` added, shape (4, q), noise-free.

    Parameters
    ----------
    effect : str
        A registered effect name, or "none".
    params : dict
        The effect's parameters (physical units).
    fe_moments : ndarray, shape (k,)
    fe_rom : ndarray, shape (4, k)
        The specimen's FE RoM per load case.
    moments : ndarray, shape (q,)
        Where to measure.
    """
    applied = np.broadcast_to(np.asarray(moments, dtype=float), (4, len(moments)))
    if effect == NONE:
        return fe_rotation(fe_moments, fe_rom, applied)
    eff = get_effect(effect)()
    # Parameters not given (a law family's shape) take their start: the classic member.
    full = {q.name: q.physical(q.start) for q in eff.parameters} | dict(params)
    p = {k: torch.tensor([float(v)], dtype=torch.float64) for k, v in full.items()}
    mask = np.array([lc in eff.load_cases for lc in LOAD_CASES])[:, None]
    if eff.kind == "series":
        extra = eff.rotation(torch.tensor(applied[None]), p)[0].numpy()
        return fe_rotation(fe_moments, fe_rom, applied) + np.where(mask, extra, 0.0)
    lo = np.log(applied * 1e-3)
    hi = np.log(applied).copy()
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        md = np.exp(mid)
        phi = fe_rotation(fe_moments, fe_rom, md)
        carried = eff.moment(torch.tensor(phi[None]), p)[0].numpy()
        g = md + carried - applied
        hi = np.where(g > 0, mid, hi)
        lo = np.where(g > 0, lo, mid)
    md = np.where(mask, np.exp(0.5 * (lo + hi)), applied)
    return fe_rotation(fe_moments, fe_rom, md)


@dataclass
class PlantedCohort:
    """Measurements with known hidden effects.

    Attributes
    ----------
    specimens : list of str
    moments : ndarray, shape (q,)
    rom_deg : ndarray, shape (n, 4, q)
        Noisy measured RoM.
    clean_deg : ndarray, shape (n, 4, q)
        The same without noise.
    truth : DataFrame
        specimen, config_id, effect and the planted effect parameters (NaN where unused).
    noise_deg : float
    """

    specimens: list[str]
    moments: np.ndarray
    rom_deg: np.ndarray
    clean_deg: np.ndarray
    truth: pd.DataFrame
    noise_deg: float

    def to_long(self) -> pd.DataFrame:
        """The measurements in femcal's long CSV layout."""
        n, _, q = self.rom_deg.shape
        s, j, k = np.meshgrid(np.arange(n), np.arange(4), np.arange(q), indexing="ij")
        return pd.DataFrame(
            {
                "specimen": np.asarray(self.specimens, dtype=object)[s.reshape(-1)],
                "load_case": np.asarray(LOAD_CASES, dtype=object)[j.reshape(-1)],
                "moment_nm": self.moments[k.reshape(-1)],
                "rom_deg": self.rom_deg.reshape(-1),
            }
        )


def make_cohort(
    fe_moments: np.ndarray,
    fe_rom: np.ndarray,
    *,
    classes: Sequence[str] = (NONE, "facet_contact", "ligament_tension", "neutral_zone"),
    n_per_class: int = 12,
    moments: Sequence[float] = (1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0),
    noise_deg: float = 0.05,
    rng: np.random.Generator,
) -> PlantedCohort:
    """A cohort of specimens built from FE curves, each with one planted effect (or none).

    Parameters
    ----------
    fe_moments : ndarray, shape (k,)
        FE moments (> 0).
    fe_rom : ndarray, shape (N, 4, k)
        FE RoM of N configurations (e.g. the study's Test set); each specimen uses a
        different configuration, drawn without replacement.
    classes : sequence of str
        Effect names (and "none"); ``n_per_class`` specimens each.
    moments : sequence of float
        Measured moments (Nm).
    noise_deg : float
        Standard deviation of the Gaussian measurement noise.
    rng : numpy.random.Generator

    Returns
    -------
    PlantedCohort
    """
    n = len(classes) * n_per_class
    if n > len(fe_rom):
        raise ConfigError(
            f"A cohort of {n} specimens needs {n} FE configurations; got {len(fe_rom)}. "
            "Lower n_per_class."
        )
    for c in classes:
        if c != NONE and c not in VISIBLE_RANGES:
            get_effect(c)  # raises for unknown names
            raise ConfigError(f"No planting range for effect '{c}'; add it to VISIBLE_RANGES.")
    q = np.asarray(moments, dtype=float)
    configs = rng.permutation(len(fe_rom))[:n]
    rows, clean = [], []
    for i, cfg in enumerate(configs):
        effect = classes[i // n_per_class]
        params: dict[str, float] = {}
        if effect != NONE:
            eff = get_effect(effect)
            for par in eff.parameters:
                if par.name not in VISIBLE_RANGES[effect]:
                    continue  # a shape parameter: the classic member (see plant)
                lo, hi = VISIBLE_RANGES[effect][par.name]
                visible = ParameterSpace([par.name], [lo], [hi], scales=[par.scale])
                params[par.name] = float(visible.from_unit(np.array([rng.random()]))[0])
        clean.append(plant(effect, params, fe_moments, fe_rom[cfg], q))
        rows.append({"specimen": f"P{i:03d}", "config_id": int(cfg), "effect": effect, **params})
    clean_arr = np.stack(clean)
    noisy = clean_arr + rng.normal(0.0, noise_deg, clean_arr.shape)
    return PlantedCohort(
        specimens=[r["specimen"] for r in rows],
        moments=q,
        rom_deg=np.abs(noisy),
        clean_deg=clean_arr,
        truth=pd.DataFrame(rows),
        noise_deg=float(noise_deg),
    )
