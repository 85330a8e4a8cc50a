"""What the reachability check found, per specimen: the report, its notes and its error."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from femcal.errors import InputDataError, listed
from femcal.reachability.envelope import (
    Envelope,
)
from femcal.schema import LOAD_CASES

if TYPE_CHECKING:  # pragma: no cover
    pass


logger = logging.getLogger(__name__)

_MAX_LISTED = 5


_UNIT_KEYS = ("radians", "x1000")


class UnreachableMeasurementsError(InputDataError):
    """The measured curves lie outside every curve the model can produce: a wrong file."""


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
                f"{self.n_outside[i]}/{self.n_points[i]} points outside the envelope of "
                f"{self.envelope.model}, "
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
                f"{self.source}: the measurements lie outside every curve {self.envelope.model} "
                f"can produce over {self.envelope.basis()}: {len(bad)} of {n} specimens have "
                "points outside "
                f"({len(self.far)} with most points outside), by up to "
                f"{max(self.worst_sigma):.0f} sigma ({sigma_text}); specimens {names}; load "
                f"cases {self._load_cases(bad)}. E.g. {self._example(bad)}. Likely cause: "
                f"{cause}{fixed}. Fix the file and run again; if the values are right, the model "
                "cannot represent these specimens (widen the parameter box and retrain, or add "
                "effects with --effects; `femcal diagnose` names the missing physics)."
            )
        return (
            f"{self.source}: {len(bad)} of {n} specimens have measured points outside every "
            f"curve {self.envelope.model} can produce over {self.envelope.basis()} (by more "
            f"than {self.z_outside:g} sigma, {sigma_text}): {names}; load cases "
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
                "%s: every measured point lies within the envelope of %s (every curve it can "
                "produce over its parameter box; checked in %.2f s).",
                self.source,
                self.envelope.model,
                self.seconds + self.envelope.seconds,
            )
            return
        if self.refused:
            raise UnreachableMeasurementsError(text)
        logger.warning(text)


def _listing(items: Sequence[str]) -> str:
    return listed(items, most=_MAX_LISTED)
