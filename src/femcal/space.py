"""The parameter space: names, units and bounds; physical values to the unit box and back.

This is one of exactly two places where femcal normalises (the other is the output scaling
stored inside a fitted surrogate).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from femcal.errors import InputDataError
from femcal.schema import PARAMETER_UNITS


@dataclass(frozen=True)
class ParameterSpace:
    """A box of named physical parameters.

    Parameters
    ----------
    names : sequence of str, length d
        Parameter names, in column order.
    lower, upper : array_like, shape (d,)
        Bounds in physical units; ``lower < upper`` element-wise.
    units : sequence of str, length d, optional
        Physical units ("1" for dimensionless). Defaults to the study's units where known.

    Examples
    --------
    >>> space = ParameterSpace(["a", "b"], [0.0, 10.0], [1.0, 20.0])
    >>> space.to_unit([[0.5, 15.0]])
    array([[0.5, 0.5]])
    >>> space.from_unit([[1.0, 0.0]])
    array([[ 1., 10.]])
    """

    names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    units: tuple[str, ...] = field(default=())

    def __init__(
        self,
        names: Sequence[str],
        lower: Sequence[float] | np.ndarray,
        upper: Sequence[float] | np.ndarray,
        units: Sequence[str] | None = None,
    ) -> None:
        names = tuple(str(n) for n in names)
        lower = np.asarray(lower, dtype=float).reshape(-1)
        upper = np.asarray(upper, dtype=float).reshape(-1)
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})
            raise InputDataError(f"Parameter names must be unique; repeated: {dup}.")
        if not (len(names) == lower.size == upper.size):
            raise InputDataError(
                f"ParameterSpace needs one lower and one upper bound per name; got {len(names)} "
                f"names, {lower.size} lower and {upper.size} upper bounds."
            )
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
            raise InputDataError("Parameter bounds must be finite numbers; got NaN or inf.")
        bad = [n for n, lo, hi in zip(names, lower, upper) if not lo < hi]
        if bad:
            detail = ", ".join(
                f"{n}: lower={lo:g}, upper={hi:g}"
                for n, lo, hi in zip(names, lower, upper)
                if n in bad
            )
            raise InputDataError(
                f"Inverted or empty bounds for {detail}. The lower bound must be strictly less "
                "than the upper bound: swap them or fix the bounds file."
            )
        if units is None:
            units = [PARAMETER_UNITS.get(n, "1") for n in names]
        units = tuple(str(u) for u in units)
        if len(units) != len(names):
            raise InputDataError(f"Got {len(units)} units for {len(names)} parameters.")
        lower.setflags(write=False)
        upper.setflags(write=False)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)
        object.__setattr__(self, "units", units)

    # ------------------------------------------------------------------ basics
    @property
    def dim(self) -> int:
        """Number of parameters d."""
        return len(self.names)

    @property
    def width(self) -> np.ndarray:
        """``upper - lower``, shape (d,)."""
        return self.upper - self.lower

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ParameterSpace):
            return NotImplemented
        return (
            self.names == other.names
            and self.units == other.units
            and np.array_equal(self.lower, other.lower)
            and np.array_equal(self.upper, other.upper)
        )

    def __hash__(self) -> int:
        return hash((self.names, self.lower.tobytes(), self.upper.tobytes()))

    # --------------------------------------------------------------- transforms
    def _check_shape(self, x: np.ndarray, what: str) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        if x.shape[-1] != self.dim:
            raise InputDataError(
                f"{what} must have {self.dim} columns ({', '.join(self.names)}); "
                f"got shape {x.shape}."
            )
        return x

    def to_unit(self, x: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
        """Map physical values to the unit box.

        Parameters
        ----------
        x : array_like, shape (..., d)
            Physical values.

        Returns
        -------
        ndarray, shape (..., d)
            ``(x - lower) / (upper - lower)``; inside the box gives values in [0, 1].
        """
        x = self._check_shape(x, "Physical parameters")
        return (x - self.lower) / self.width

    def from_unit(self, u: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
        """Map unit-box values to physical units, shape (..., d) -> (..., d)."""
        u = self._check_shape(u, "Unit-box parameters")
        return self.lower + u * self.width

    def clip(self, x: np.ndarray) -> np.ndarray:
        """Project physical values onto the box, shape (..., d) -> (..., d)."""
        x = self._check_shape(x, "Physical parameters")
        return np.clip(x, self.lower, self.upper)

    def contains(self, x: np.ndarray, *, atol: float = 0.0) -> np.ndarray:
        """Whether each row lies inside the box (with tolerance ``atol`` in physical units).

        Returns
        -------
        ndarray of bool, shape (...)
        """
        x = self._check_shape(x, "Physical parameters")
        return np.all((x >= self.lower - atol) & (x <= self.upper + atol), axis=-1)

    def exceedance(self, x: np.ndarray) -> np.ndarray:
        """The study's exceedance: sum of values beyond the bounds, in normalised units.

        Returns
        -------
        ndarray, shape (...)
            0 for a point inside the box.
        """
        u = self.to_unit(x)
        return np.sum(np.clip(u - 1.0, 0.0, None) + np.clip(-u, 0.0, None), axis=-1)

    def sample_uniform(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Draw ``n`` points uniformly in the box, shape (n, d), physical units."""
        return self.from_unit(rng.random((n, self.dim)))

    def sample_lhs(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Latin-hypercube sample of ``n`` points over the box, shape (n, d), physical units."""
        strata = np.stack([rng.permutation(n) for _ in range(self.dim)], axis=1)
        u = (strata + rng.random((n, self.dim))) / n
        return self.from_unit(u)

    # --------------------------------------------------------------------- I/O
    @classmethod
    def from_bounds_csv(cls, path: str | Path) -> ParameterSpace:
        """Read the study's ParameterBounds.csv (header = names, row 1 = min, row 2 = max)."""
        path = Path(path)
        try:
            table = pd.read_csv(path)
        except FileNotFoundError:
            raise InputDataError(
                f"Bounds file {path} does not exist; run the 'fetch' stage or give the right path."
            ) from None
        table.columns = [str(c).strip() for c in table.columns]
        if len(table) != 2:
            raise InputDataError(
                f"{path}: expected 2 rows (minimum, then maximum) under the header; "
                f"got {len(table)}. Fix the file so row 1 holds the minima and row 2 the maxima."
            )
        for col in table.columns:
            if not pd.api.types.is_numeric_dtype(table[col]) or table[col].isna().any():
                raise InputDataError(
                    f"{path}: column '{col}' must hold two numbers (minimum, maximum); got "
                    f"{table[col].tolist()}. Fill in numeric bounds."
                )
        try:
            return cls(list(table.columns), table.iloc[0].to_numpy(), table.iloc[1].to_numpy())
        except InputDataError as exc:
            raise InputDataError(f"{path}: {exc}") from None

    def to_dict(self) -> dict:
        """JSON-ready description: names, units, lower, upper."""
        return {
            "names": list(self.names),
            "units": list(self.units),
            "lower": self.lower.tolist(),
            "upper": self.upper.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> ParameterSpace:
        """Inverse of :meth:`to_dict`."""
        try:
            return cls(d["names"], d["lower"], d["upper"], d.get("units"))
        except KeyError as exc:
            raise InputDataError(
                f"Parameter-space description lacks the field {exc}; it needs names, lower, upper."
            ) from None

    def to_json(self, path: str | Path) -> None:
        """Write :meth:`to_dict` as JSON."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def from_json(cls, path: str | Path) -> ParameterSpace:
        """Read a space written by :meth:`to_json`."""
        path = Path(path)
        try:
            return cls.from_dict(json.loads(path.read_text()))
        except FileNotFoundError:
            raise InputDataError(
                f"Parameter-space file {path} does not exist; run the 'prepare' stage first."
            ) from None
        except InputDataError as exc:
            raise InputDataError(f"{path}: {exc}") from None
