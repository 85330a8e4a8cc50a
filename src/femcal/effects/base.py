"""Physical effects the disc model lacks, composed with the disc surrogate.

An effect is one small class registered by name. It declares its parameters (name, unit,
bounds), the load cases it acts on, and how it composes with the disc:

* a **parallel** element carries part of the applied moment: ``M = M_disc(phi) + M_e(phi)``;
  the disc curve ``phi = f(M_disc)`` is solved for ``phi`` (:meth:`Effect.moment`);
* a **series** element adds rotation: ``phi = f(M) + phi_e(M)`` (:meth:`Effect.rotation`).

Both are written in torch, so the composite model is differentiable in the disc and effect
parameters. A new effect is a new module::

    from femcal.effects import Effect, EffectParameter, register_effect

    @register_effect
    class CapsuleFriction(Effect):
        name = "capsule_friction"
        kind = "series"
        load_cases = ("AxialRotation",)
        parameters = (EffectParameter("friction_deg", "deg", 0.0, 1.0),)

        def rotation(self, moment_nm, p):
            return p["friction_deg"] * torch.tanh(moment_nm)

and listing ``capsule_friction`` under ``effects`` in params.yaml.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from femcal.errors import ConfigError
from femcal.schema import LOAD_CASES

_EFFECTS: dict[str, type[Effect]] = {}


@dataclass(frozen=True)
class EffectParameter:
    """One parameter of an effect: name, unit and bounds (physical units)."""

    name: str
    unit: str
    lower: float
    upper: float
    log: bool = False  # sampled and optimised on a log scale (bounds must be > 0)
    start: float = 0.5  # unit-box value a calibration starts from (0 = the weak end)


class Effect:
    """Base class of a physical effect (see the module docstring).

    Class attributes
    ----------------
    name : str
        Registry name (used in params.yaml and in verdicts).
    kind : {"parallel", "series"}
    load_cases : tuple of str
        The load cases it acts on (others are the disc alone).
    parameters : tuple of EffectParameter
    """

    name: ClassVar[str] = ""
    kind: ClassVar[str] = "parallel"
    load_cases: ClassVar[tuple[str, ...]] = ()
    parameters: ClassVar[tuple[EffectParameter, ...]] = ()

    def moment(self, rotation_deg: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Moment (Nm) a parallel element carries at a rotation (deg); >= 0, non-decreasing.

        ``rotation_deg`` has shape (B, ...) and each ``p[name]`` shape (B,) broadcast over it.
        """
        raise NotImplementedError

    def rotation(self, moment_nm: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Rotation (deg) a series element adds at an applied moment (Nm)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ helpers
    @classmethod
    def lower(cls) -> np.ndarray:
        return np.array([q.lower for q in cls.parameters], dtype=float)

    @classmethod
    def upper(cls) -> np.ndarray:
        return np.array([q.upper for q in cls.parameters], dtype=float)

    @classmethod
    def names(cls) -> list[str]:
        return [q.name for q in cls.parameters]

    @classmethod
    def load_case_mask(cls) -> torch.Tensor:
        """Bool (4,) over :data:`~femcal.schema.LOAD_CASES`."""
        return torch.tensor([lc in cls.load_cases for lc in LOAD_CASES])

    @classmethod
    def from_unit(cls, u: torch.Tensor) -> dict[str, torch.Tensor]:
        """Unit-box values (B, p) -> physical parameters by name, each (B,)."""
        out = {}
        for j, q in enumerate(cls.parameters):
            if q.log:
                value = q.lower * (q.upper / q.lower) ** u[:, j]
            else:
                value = q.lower + u[:, j] * (q.upper - q.lower)
            out[q.name] = value
        return out

    @classmethod
    def to_unit(cls, x: np.ndarray) -> np.ndarray:
        """Physical values (n, p) -> unit box (n, p)."""
        x = np.asarray(x, dtype=float)
        u = np.empty_like(x)
        for j, q in enumerate(cls.parameters):
            if q.log:
                u[:, j] = np.log(x[:, j] / q.lower) / np.log(q.upper / q.lower)
            else:
                u[:, j] = (x[:, j] - q.lower) / (q.upper - q.lower)
        return u


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Class decorator: register an effect under ``cls.name`` (validated)."""
    if not cls.name or cls.kind not in ("parallel", "series"):
        raise ConfigError(
            f"Effect {cls.__name__} needs a name and kind 'parallel' or 'series'; got "
            f"name={cls.name!r}, kind={cls.kind!r}."
        )
    unknown = [lc for lc in cls.load_cases if lc not in LOAD_CASES]
    if unknown or not cls.load_cases:
        raise ConfigError(
            f"Effect '{cls.name}': load_cases must be a non-empty subset of {list(LOAD_CASES)}; "
            f"got {list(cls.load_cases)}."
        )
    for q in cls.parameters:
        if not q.lower < q.upper or (q.log and q.lower <= 0):
            raise ConfigError(
                f"Effect '{cls.name}' parameter '{q.name}': need lower < upper (and lower > 0 "
                f"on a log scale); got [{q.lower}, {q.upper}]."
            )
    if cls.name in _EFFECTS and _EFFECTS[cls.name] is not cls:
        raise ConfigError(f"An effect named '{cls.name}' is already registered.")
    _EFFECTS[cls.name] = cls
    return cls


def available_effects() -> list[str]:
    """Registered effect names, sorted."""
    _load_builtin()
    return sorted(_EFFECTS)


def get_effect(name: str) -> type[Effect]:
    """The effect class registered under ``name`` (ConfigError listing the names otherwise)."""
    _load_builtin()
    try:
        return _EFFECTS[name]
    except KeyError:
        raise ConfigError(
            f"Unknown physical effect '{name}'; choose one of {', '.join(sorted(_EFFECTS))}, or "
            "register your own (see femcal.effects)."
        ) from None


def _load_builtin() -> None:
    """Import every module of the femcal.effects package: a new file registers itself."""
    import importlib
    import pkgutil

    import femcal.effects as package

    for info in pkgutil.iter_modules(package.__path__):
        importlib.import_module(f"femcal.effects.{info.name}")
