"""The measured RoM of a cohort: the :class:`Measurements` container, its checks, from_arrays."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from femcal.errors import InputDataError, listed
from femcal.schema import LOAD_CASES

logger = logging.getLogger(__name__)

#: How many items an error message lists before ``(and N more)``.
MAX_LISTED = 5


# ------------------------------------------------------------------ the container
@dataclass(frozen=True, eq=False)
class Measurements:
    """Measured RoM of ``n`` specimens on the grid specimen x load case x moment.

    Build it with :func:`read_measurements` or :func:`from_arrays`; the constructor
    validates and copies its inputs (the arrays are read-only).

    Parameters
    ----------
    specimens : tuple of str, shape (n,)
        Specimen names, in first-appearance order.
    moments : ndarray, shape (m,)
        Sorted unique moments in Nm (all > 0) over all specimens.
    rom_deg : ndarray, shape (n, 4, m)
        Measured RoM in degrees (>= 0), NaN where not measured; axis 1 follows
        :data:`~femcal.schema.LOAD_CASES`.
    weight : ndarray, shape (n, 4, m)
        Weights (>= 0) of the points in the fit, relative inverse noise variances (the mean
        of ``k`` repeated measurements weighs ``k``); forced to 0 where not measured.
    idp_mpa : ndarray, shape (n, 4, m), or None
        Measured IDP in MPa (finite where measured, NaN elsewhere), or None.
    source : str, optional
        Where the data came from (a file path), used in messages.
    """

    specimens: tuple[str, ...]
    moments: np.ndarray
    rom_deg: np.ndarray
    weight: np.ndarray
    idp_mpa: np.ndarray | None
    source: str = "<memory>"

    def __post_init__(self) -> None:
        fields = _validated(
            self.specimens, self.moments, self.rom_deg, self.weight, self.idp_mpa, self.source
        )
        for name, value in zip(
            ("specimens", "moments", "rom_deg", "weight", "idp_mpa", "source"), fields
        ):
            object.__setattr__(self, name, value)

    @property
    def n_specimens(self) -> int:
        """Number of specimens ``n``."""
        return len(self.specimens)

    def mask(self) -> np.ndarray:
        """Where a point was measured.

        Returns
        -------
        ndarray of bool, shape (n, 4, m)
            True where ``rom_deg`` is not NaN (points with weight 0 count as measured).
        """
        return ~np.isnan(self.rom_deg)

    def missing_load_cases(self) -> dict[str, list[str]]:
        """Load cases in which a specimen has no measured point.

        Returns
        -------
        dict of str to list of str
            ``{specimen: [load case, ...]}`` in :data:`~femcal.schema.LOAD_CASES` order, only
            for specimens that miss at least one load case.
        """
        measured = self.mask().any(axis=2)  # (n, 4)
        return {
            name: [lc for k, lc in enumerate(LOAD_CASES) if not measured[i, k]]
            for i, name in enumerate(self.specimens)
            if not measured[i].all()
        }

    def to_long(self) -> pd.DataFrame:
        """The measured points as a long table.

        Returns
        -------
        pandas.DataFrame, shape (n_points, 5) or (n_points, 6)
            Columns ``specimen, load_case, moment_nm, rom_deg, weight`` (and ``idp_mpa``
            when present), one row per measured point, ordered by specimen (in
            :attr:`specimens` order), load case (in ``LOAD_CASES`` order) and moment.
        """
        i, k, j = np.nonzero(self.mask())
        columns: dict[str, object] = {
            "specimen": pd.array([self.specimens[a] for a in i], dtype="str"),
            "load_case": pd.array([LOAD_CASES[a] for a in k], dtype="str"),
            "moment_nm": self.moments[j].astype(np.float64),
            "rom_deg": self.rom_deg[i, k, j].astype(np.float64),
            "weight": self.weight[i, k, j].astype(np.float64),
        }
        if self.idp_mpa is not None:
            columns["idp_mpa"] = self.idp_mpa[i, k, j].astype(np.float64)
        return pd.DataFrame(columns)

    def subset(self, specimens: Sequence[str]) -> Measurements:
        """The measurements of some specimens only.

        Parameters
        ----------
        specimens : sequence of str
            Names of the specimens to keep, in the order wanted (each once).

        Returns
        -------
        Measurements
            Same source; moments that none of the kept specimens measured are dropped.

        Raises
        ------
        InputDataError
            A name is unknown or repeated, or no name is given.
        """
        names = [specimens] if isinstance(specimens, str) else [str(s) for s in specimens]
        unknown = [s for s in names if s not in self.specimens]
        repeated = repeated_names(names)
        if not names or unknown or repeated:
            problem = (
                "no specimen was requested"
                if not names
                else f"unknown specimens {unknown}"
                if unknown
                else f"repeated specimens {repeated}"
            )
            raise InputDataError(
                f"{self.source}: cannot select specimens: {problem}. The measurements hold "
                f"{listing([repr(s) for s in self.specimens])}; give each wanted name once "
                "(names are case-sensitive)."
            )
        return self._select([self.specimens.index(s) for s in names])

    def without(self, drop: np.ndarray) -> Measurements:
        """The measurements less some points.

        Parameters
        ----------
        drop : array_like of bool, shape (n, 4, m)
            The points to leave out (unmeasured points may be marked too).

        Returns
        -------
        Measurements
            Same source; the dropped points are not measured; specimens left without a
            measured point and moments that no specimen measured any more are removed.

        Raises
        ------
        InputDataError
            ``drop`` has the wrong shape, or it leaves no measured point; or a specimen keeps
            measured points that all have weight 0 (drop those too).
        """
        mask = np.asarray(drop, dtype=bool)
        if mask.shape != self.rom_deg.shape:
            raise InputDataError(
                f"{self.source}: the points to drop have shape {mask.shape}; expected "
                f"{self.rom_deg.shape} (specimens, load cases, moments). Pass one flag per point."
            )
        left = self.mask() & ~mask
        keep = [i for i in range(self.n_specimens) if left[i].any()]
        if not keep:
            raise InputDataError(
                f"{self.source}: dropping those points leaves no measured point; keep at least "
                "one point, or fix the file."
            )
        return self._select(keep, np.where(mask, np.nan, self.rom_deg))

    def _select(self, idx: Sequence[int], rom_deg: np.ndarray | None = None) -> Measurements:
        """The specimens at positions ``idx`` (in that order) of ``rom_deg`` (default
        :attr:`rom_deg`; NaN: not measured), without the moments none of them measured."""
        names = [self.specimens[i] for i in idx]
        rom = (self.rom_deg if rom_deg is None else rom_deg)[idx]
        keep = ~np.all(np.isnan(rom), axis=(0, 1))
        return Measurements(
            specimens=tuple(names),
            moments=self.moments[keep],
            rom_deg=rom[:, :, keep],
            weight=self.weight[idx][:, :, keep],
            idp_mpa=None if self.idp_mpa is None else self.idp_mpa[idx][:, :, keep],
            source=self.source,
        )


# ------------------------------------------------------------- array validation
def listing(items: Sequence[str], total: int | None = None) -> str:
    """``items`` joined by ``", "``, the first :data:`MAX_LISTED` of them and a count of the
    rest (:func:`femcal.errors.listed`; ``total``: how many there are in all)."""
    return listed(items, total=total, most=MAX_LISTED)


def repeated_names(items: Sequence[str]) -> list[str]:
    """The items that appear more than once, sorted."""
    return sorted({s for s in items if items.count(s) > 1})


def _float_array(value: object, name: str, source: str) -> np.ndarray:
    try:
        return np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputDataError(
            f"{source}: {name} must be an array of numbers; could not convert it ({exc}). "
            "Pass numbers (NaN where not measured)."
        ) from None


def _checked_names(specimens: object, src: str) -> tuple[str, ...]:
    """The specimen names of :class:`Measurements` from ``specimens``, checked: a non-empty
    sequence of non-blank, distinct strings (``src`` names the data in the errors)."""
    if isinstance(specimens, str) or not isinstance(specimens, Iterable):
        raise InputDataError(
            f"{src}: specimens must be a sequence of names; got {type(specimens).__name__}. "
            "Pass a list or tuple of strings."
        )
    names = tuple(specimens)
    if not names:
        raise InputDataError(f"{src}: there are no specimens; give at least one specimen.")
    for pos, name in enumerate(names):
        if not isinstance(name, str):
            raise InputDataError(
                f"{src}: specimen names must be strings; got {name!r} "
                f"({type(name).__name__}) at position {pos}. Convert the names with str()."
            )
        if not name.strip():
            raise InputDataError(
                f"{src}: specimen at position {pos} has an empty name; give every specimen a name."
            )
    repeated = repeated_names(names)
    if repeated:
        raise InputDataError(
            f"{src}: repeated specimen names {repeated}; each specimen must appear once "
            "(merge its data or rename it)."
        )
    return names


def _checked_moments(moments: object, src: str) -> np.ndarray:
    """The moments (m,) in Nm of :class:`Measurements` as a float array, checked: non-empty,
    1-D, finite, positive and strictly increasing (``src`` names the data in the errors)."""
    m_arr = _float_array(moments, "moments", src)
    if m_arr.ndim != 1 or m_arr.size == 0:
        raise InputDataError(
            f"{src}: moments must be a non-empty 1-D array of moments in Nm; got shape "
            f"{m_arr.shape}."
        )
    if not np.all(np.isfinite(m_arr)) or np.any(m_arr <= 0) or np.any(np.diff(m_arr) <= 0):
        raise InputDataError(
            f"{src}: moments must be finite, positive (Nm, the unloaded 0 Nm state is not a "
            f"data point) and strictly increasing; got {m_arr.tolist()}. Sort them, drop 0 "
            "and repeated values and reorder the last axis of the arrays to match."
        )
    return m_arr


def _validated(
    specimens: object,
    moments: object,
    rom_deg: object,
    weight: object,
    idp_mpa: object,
    source: object,
) -> tuple[tuple[str, ...], np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, str]:
    """Check and normalise the fields of :class:`Measurements` (copies, read-only arrays)."""
    src = str(source)
    names = _checked_names(specimens, src)
    n = len(names)

    m_arr = _checked_moments(moments, src)
    m = m_arr.size
    shape = (n, len(LOAD_CASES), m)

    def where(cells: np.ndarray, values: np.ndarray) -> str:
        items = [
            f"specimen {names[i]!r}, {LOAD_CASES[k]}, {m_arr[j]:g} Nm: {float(values[i, k, j])!r}"
            for i, k, j in cells[:MAX_LISTED]
        ]
        return listing(items, len(cells))

    def refuse(bad: np.ndarray, values: np.ndarray, problem: str, advice: str) -> None:
        """Raise when the mask ``bad`` holds a cell: ``problem``, the cells, then ``advice``."""
        cells = np.argwhere(bad)
        if cells.size:
            raise InputDataError(f"{src}: {problem} {where(cells, values)}{advice}")

    def shaped(value: object, name: str) -> np.ndarray:
        arr = _float_array(value, name, src)
        if arr.shape != shape:
            raise InputDataError(
                f"{src}: {name} has shape {arr.shape}; expected (n_specimens, "
                f"{len(LOAD_CASES)} load cases, n_moments) = {shape}, with axis 1 in the order "
                f"{', '.join(LOAD_CASES)}. Reshape the array."
            )
        return arr

    rom = shaped(rom_deg, "rom_deg")
    refuse(
        np.isinf(rom),
        rom,
        "rom_deg has infinite values at",
        "; use finite degrees, or NaN where not measured.",
    )
    refuse(
        rom < 0,
        rom,
        "rom_deg has negative values at",
        ". RoM is a magnitude: give absolute values (the direction is given by the load case).",
    )
    measured = ~np.isnan(rom)

    if weight is None:
        raise InputDataError(
            f"{src}: weight is missing; pass an array of shape {shape} (or use from_arrays, "
            "which defaults to 1.0 where measured)."
        )
    w = shaped(weight, "weight")
    refuse(
        measured & ~np.isfinite(w),
        w,
        "weight is missing or infinite at measured points",
        "; give every measured point a finite weight >= 0.",
    )
    refuse(
        measured & (w < 0),
        w,
        "weight has negative values at",
        "; weights must be >= 0 (0 leaves a point out of the fit).",
    )
    w = np.where(measured, w, 0.0)

    idp: np.ndarray | None = None
    if idp_mpa is not None:
        idp = shaped(idp_mpa, "idp_mpa")
        refuse(
            measured & ~np.isfinite(idp),
            idp,
            "idp_mpa is missing or infinite at measured points",
            "; give the IDP of every measured point, or pass idp_mpa=None.",
        )
        idp = np.where(measured, idp, np.nan)

    empty = [names[i] for i in range(n) if not measured[i].any()]
    if empty:
        raise InputDataError(
            f"{src}: specimens {empty} have no measured point; give them data or leave them out."
        )
    unweighted = [names[i] for i in range(n) if not np.any(w[i][measured[i]] > 0)]
    if unweighted:
        raise InputDataError(
            f"{src}: all weights of specimens {unweighted} are 0, so they would not take part "
            "in the fit; give at least one point of each a positive weight or leave them out."
        )

    arrays = [m_arr, rom, w] + ([] if idp is None else [idp])
    for arr in arrays:
        arr.setflags(write=False)
    return names, m_arr, rom, w, idp, src


def from_arrays(
    specimens: Sequence[str],
    moments: Sequence[float] | np.ndarray,
    rom_deg: np.ndarray,
    *,
    weight: np.ndarray | None = None,
    idp_mpa: np.ndarray | None = None,
    source: str = "<memory>",
) -> Measurements:
    """Measurements from arrays, validated like the file readers.

    Parameters
    ----------
    specimens : sequence of str, shape (n,)
        Unique, non-empty specimen names.
    moments : array_like, shape (m,)
        Strictly increasing moments in Nm, all > 0.
    rom_deg : array_like, shape (n, 4, m)
        RoM in degrees (>= 0), NaN where not measured; axis 1 in ``LOAD_CASES`` order.
    weight : array_like, shape (n, 4, m), optional
        Weights >= 0 (finite where measured; set to 0 where not measured). Default: 1.0
        where measured.
    idp_mpa : array_like, shape (n, 4, m), optional
        IDP in MPa, finite where measured (set to NaN where not measured).
    source : str, optional
        Name used in messages.

    Returns
    -------
    Measurements

    Raises
    ------
    InputDataError
        A shape or value is invalid, or a specimen has no measured point with weight > 0.
    """
    if weight is None:
        rom = _float_array(rom_deg, "rom_deg", str(source))
        weight = np.where(np.isnan(rom), 0.0, 1.0)
    meas = Measurements(
        specimens=tuple(specimens) if not isinstance(specimens, str) else specimens,
        moments=moments,
        rom_deg=rom_deg,
        weight=weight,
        idp_mpa=idp_mpa,
        source=str(source),
    )
    warn_missing(meas)
    return meas


def warn_missing(meas: Measurements) -> None:
    """Log one warning per set of missing load cases, naming the specimens."""
    groups: dict[tuple[str, ...], list[str]] = {}
    for name, lcs in meas.missing_load_cases().items():
        groups.setdefault(tuple(lcs), []).append(name)
    for lcs, names in groups.items():
        logger.warning(
            "%s: specimen%s %s ha%s no measured point in %s; %s calibrated on the other load "
            "cases only.",
            meas.source,
            "s" if len(names) > 1 else "",
            listing([repr(s) for s in names]),
            "ve" if len(names) > 1 else "s",
            ", ".join(lcs),
            "they are" if len(names) > 1 else "it is",
        )
