"""The parameter space: names, units, bounds and scales; physical values to the unit box and back.

Each parameter owns its bounds and its scale, ``"linear"`` or ``"log"`` (lmfit's idea): the
unit coordinate of a linear parameter is ``(x - lower) / (upper - lower)``, that of a log one
``(log x - log lower) / (log upper - log lower)``. :class:`ParameterSpace` is the one transform
of femcal: the data's space (linear, the study's normalised units), the surrogate network's
inputs (:meth:`ParameterSpace.log_where_positive`), each effect's parameters and the joint
space of a disc with effects (:meth:`ParameterSpace.concat`) all map through
:meth:`~ParameterSpace.to_unit`, :meth:`~ParameterSpace.from_unit` and their Jacobians, for
numpy arrays and torch tensors alike. The only other normalisation is the output scaling
stored inside a fitted surrogate.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from femcal.errors import InputDataError
from femcal.schema import PARAMETER_UNITS

#: The scales a parameter can have.
SCALES: tuple[str, ...] = ("linear", "log")


def _is_torch(x: object) -> bool:
    """Whether ``x`` is a torch tensor (without importing torch for numpy callers)."""
    return type(x).__module__.split(".")[0] == "torch"


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
    scales : sequence of {"linear", "log"}, length d, optional
        Each parameter's scale in the unit box; all linear by default. A log parameter needs
        ``lower > 0``.

    Examples
    --------
    >>> space = ParameterSpace(["a", "b"], [0.0, 10.0], [1.0, 20.0])
    >>> space.to_unit([[0.5, 15.0]])
    array([[0.5, 0.5]])
    >>> space.from_unit([[1.0, 0.0]])
    array([[ 1., 10.]])
    >>> logged = ParameterSpace(["k"], [1.0], [100.0], scales=["log"])
    >>> logged.to_unit([[10.0]])
    array([[0.5]])
    """

    names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    units: tuple[str, ...] = field(default=())
    scales: tuple[str, ...] = field(default=())

    def __init__(
        self,
        names: Sequence[str],
        lower: Sequence[float] | np.ndarray,
        upper: Sequence[float] | np.ndarray,
        units: Sequence[str] | None = None,
        scales: Sequence[str] | None = None,
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
        scales = tuple(str(c) for c in (scales if scales is not None else ["linear"] * len(names)))
        if len(scales) != len(names):
            raise InputDataError(
                f"Got {len(scales)} scales for {len(names)} parameters; give one scale "
                f"({' or '.join(SCALES)}) per parameter."
            )
        unknown = [f"{n}: {c!r}" for n, c in zip(names, scales) if c not in SCALES]
        if unknown:
            raise InputDataError(
                f"Unknown parameter scale for {', '.join(unknown)}; use one of {list(SCALES)}."
            )
        nonpositive = [
            f"{n}: lower={lo:g}" for n, lo, c in zip(names, lower, scales) if c == "log" and lo <= 0
        ]
        if nonpositive:
            raise InputDataError(
                f"A log-scaled parameter needs a lower bound > 0; got {', '.join(nonpositive)}. "
                "Raise the lower bound or use scale 'linear'."
            )
        lower.setflags(write=False)
        upper.setflags(write=False)
        is_log = np.array([c == "log" for c in scales], dtype=bool)
        is_log.setflags(write=False)
        # The log-scale end points (1.0 where the scale is linear: finite placeholders).
        log_lower = np.log(np.where(is_log, lower, 1.0))
        log_upper = np.log(np.where(is_log, upper, 1.0))
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)
        object.__setattr__(self, "units", units)
        object.__setattr__(self, "scales", scales)
        object.__setattr__(self, "_is_log", is_log)
        object.__setattr__(self, "_log_bounds", (log_lower, log_upper))
        object.__setattr__(self, "_torch_cache", {})

    # ------------------------------------------------------------------ basics
    @property
    def dim(self) -> int:
        """Number of parameters d."""
        return len(self.names)

    @property
    def width(self) -> np.ndarray:
        """``upper - lower``, shape (d,)."""
        return self.upper - self.lower

    @property
    def is_log(self) -> np.ndarray:
        """Whether each parameter is log-scaled, bool, shape (d,)."""
        return self._is_log

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ParameterSpace):
            return NotImplemented
        return (
            self.names == other.names
            and self.units == other.units
            and self.scales == other.scales
            and np.array_equal(self.lower, other.lower)
            and np.array_equal(self.upper, other.upper)
        )

    def __hash__(self) -> int:
        return hash((self.names, self.scales, self.lower.tobytes(), self.upper.tobytes()))

    def __getstate__(self) -> dict:
        # What defines the space (pickle, skops): the derived arrays and caches are rebuilt.
        return {
            "names": self.names,
            "lower": self.lower,
            "upper": self.upper,
            "units": self.units,
            "scales": self.scales,
        }

    def __setstate__(self, state: dict) -> None:
        # A space saved before scales existed (a baseline's skops file) is all linear.
        ParameterSpace.__init__(
            self,
            state["names"],
            state["lower"],
            state["upper"],
            state.get("units"),
            state.get("scales") or None,
        )

    # ------------------------------------------------------------ derived spaces
    def with_scales(self, scales: Sequence[str]) -> ParameterSpace:
        """The same box with other scales, one per parameter."""
        return ParameterSpace(self.names, self.lower, self.upper, self.units, scales)

    def log_where_positive(self) -> ParameterSpace:
        """The same box, log-scaled wherever the bounds are strictly positive.

        This is the surrogate network's input space: a stiffness spanning decades enters the
        network as its logarithm.
        """
        return self.with_scales(["log" if lo > 0 else "linear" for lo in self.lower])

    def linear(self) -> ParameterSpace:
        """The same box with every parameter on a linear scale (the study's normalised units)."""
        return self.with_scales(["linear"] * self.dim)

    @classmethod
    def concat(cls, *spaces: ParameterSpace) -> ParameterSpace:
        """One space of the parameters of several, in order (names must stay unique)."""
        return cls(
            [n for s in spaces for n in s.names],
            np.concatenate([s.lower for s in spaces]),
            np.concatenate([s.upper for s in spaces]),
            [u for s in spaces for u in s.units],
            [c for s in spaces for c in s.scales],
        )

    # --------------------------------------------------------------- transforms
    def _check_shape(self, x, what: str):
        if not _is_torch(x):
            x = np.asarray(x, dtype=float)
        if x.ndim == 0 or x.shape[-1] != self.dim:
            raise InputDataError(
                f"{what} must have {self.dim} columns ({', '.join(self.names)}); "
                f"got shape {tuple(x.shape)}."
            )
        return x

    def _bounds(self, like):
        """``(lower, upper, log_lower, log_upper, is_log)`` as arrays of ``like``'s kind.

        For a tensor: in its dtype and on its device (cached), the log bounds taken in that
        dtype, so float32 callers compute exactly what a float32 network computes.
        """
        if not _is_torch(like):
            return (self.lower, self.upper, *self._log_bounds, self._is_log)
        import torch

        key = (like.dtype, like.device)
        cached = self._torch_cache.get(key)
        if cached is None:
            lo = torch.tensor(np.array(self.lower), dtype=like.dtype, device=like.device)
            hi = torch.tensor(np.array(self.upper), dtype=like.dtype, device=like.device)
            mask = torch.tensor(np.array(self._is_log), device=like.device)
            one = torch.ones_like(lo)
            log_lo = torch.log(torch.where(mask, lo, one))
            log_hi = torch.log(torch.where(mask, hi, one))
            cached = (lo, hi, log_lo, log_hi, mask)
            self._torch_cache[key] = cached
        return cached

    @staticmethod
    def _ops(like):
        """``(log, exp, where)`` of numpy or torch, following ``like``."""
        if _is_torch(like):
            import torch

            return torch.log, torch.exp, torch.where
        return np.log, np.exp, np.where

    def to_unit(self, x):
        """Map physical values to the unit box, each parameter on its own scale.

        Parameters
        ----------
        x : array_like or Tensor, shape (..., d)
            Physical values (log-scaled ones must be > 0).

        Returns
        -------
        ndarray or Tensor, shape (..., d)
            The same kind as ``x`` (a tensor keeps its dtype and device). Inside the box the
            values lie in [0, 1]; outside they continue the same map.
        """
        x = self._check_shape(x, "Physical parameters")
        lo, hi, log_lo, log_hi, mask = self._bounds(x)
        linear = (x - lo) / (hi - lo)
        if not self._is_log.any():
            return linear
        log, _, where = self._ops(x)
        # A positive placeholder keeps the log (and its gradient) finite where the scale is linear.
        safe = where(mask, x, 1.0 if not _is_torch(x) else x.new_ones(()))
        with np.errstate(divide="ignore", invalid="ignore"):
            logged = (log(safe) - log_lo) / (log_hi - log_lo)
        return where(mask, logged, linear)

    def from_unit(self, u):
        """Map unit-box values to physical units, the inverse of :meth:`to_unit`.

        Parameters
        ----------
        u : array_like or Tensor, shape (..., d)

        Returns
        -------
        ndarray or Tensor, shape (..., d)
            Physical values, the same kind as ``u``.
        """
        u = self._check_shape(u, "Unit-box parameters")
        lo, hi, log_lo, log_hi, mask = self._bounds(u)
        linear = lo + u * (hi - lo)
        if not self._is_log.any():
            return linear
        _, exp, where = self._ops(u)
        return where(mask, exp(log_lo + u * (log_hi - log_lo)), linear)

    def to_unit_jacobian(self, x):
        """Elementwise derivative ``du / dx`` of :meth:`to_unit`, shape (..., d).

        The map acts on each parameter alone, so its Jacobian is diagonal; this is that
        diagonal: ``1 / (upper - lower)`` (linear) or ``1 / (x (log upper - log lower))`` (log).
        """
        x = self._check_shape(x, "Physical parameters")
        lo, hi, log_lo, log_hi, mask = self._bounds(x)
        linear = 1.0 / (hi - lo) + 0.0 * x
        if not self._is_log.any():
            return linear
        _, _, where = self._ops(x)
        with np.errstate(divide="ignore", invalid="ignore"):
            logged = 1.0 / (x * (log_hi - log_lo))
        return where(mask, logged, linear)

    def from_unit_jacobian(self, u):
        """Elementwise derivative ``dx / du`` of :meth:`from_unit`, shape (..., d).

        ``upper - lower`` (linear) or ``x(u) (log upper - log lower)`` (log): the diagonal of
        the Jacobian, which turns a unit-box standard deviation into physical units.
        """
        u = self._check_shape(u, "Unit-box parameters")
        lo, hi, log_lo, log_hi, mask = self._bounds(u)
        linear = (hi - lo) + 0.0 * u
        if not self._is_log.any():
            return linear
        _, _, where = self._ops(u)
        return where(mask, self.from_unit(u) * (log_hi - log_lo), linear)

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

        The study's units are linear whatever this space's scales.

        Returns
        -------
        ndarray, shape (...)
            0 for a point inside the box.
        """
        u = self.linear().to_unit(x)
        return np.sum(np.clip(u - 1.0, 0.0, None) + np.clip(-u, 0.0, None), axis=-1)

    def sample_uniform(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Draw ``n`` points uniformly in the unit box (each parameter on its own scale),
        shape (n, d), physical units."""
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
        import pandas as pd  # here only: the CLI's first checks stay light

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
        """JSON-ready description: names, units, lower, upper (and scales, when any is log)."""
        out = {
            "names": list(self.names),
            "units": list(self.units),
            "lower": self.lower.tolist(),
            "upper": self.upper.tolist(),
        }
        if self._is_log.any():
            out["scales"] = list(self.scales)
        return out

    @classmethod
    def from_dict(cls, d: dict) -> ParameterSpace:
        """Inverse of :meth:`to_dict`."""
        try:
            return cls(d["names"], d["lower"], d["upper"], d.get("units"), d.get("scales"))
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
