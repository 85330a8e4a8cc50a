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

and listing ``capsule_friction`` under ``effects`` in params.yaml. ``load_cases`` says where
it acts; ``load_case_prior = {"AxialRotation": 0.9, "LateralBending": 0.3}`` instead says
where it may act, and the diagnosis chooses among those load cases by the data, each set
priced by the prior (:mod:`femcal.effects.terms`). A parameter declared
``EffectParameter(..., per_load_case=True)`` may differ per load case: the effect's split form
``capsule_friction:split`` (:mod:`femcal.effects.split`) has one copy of it per load case, and
the diagnosis tries it wherever the effect is found.

Where an effect module can live (every one registers its effects when imported):

* in this package (``src/femcal/effects/``): imported on first use of the registry;
* in a file of your own: :func:`load_effect_modules` (``femcal calibrate|diagnose
  --effects-module my_effects.py``, or ``effects.modules`` in params.yaml);
* in an installed package: an entry point in the group ``femcal.effects`` naming a module or
  an :class:`Effect` subclass, loaded on first use of the registry::

      [project.entry-points."femcal.effects"]
      capsule_friction = "my_package.effects"
"""

from __future__ import annotations

import hashlib
import importlib.util
import sys
import traceback
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
import torch.autograd.forward_ad as fwad

from femcal.effects.terms import LIKELY, acting_in, parse_term
from femcal.errors import ConfigError
from femcal.registry import Registry
from femcal.schema import LOAD_CASES
from femcal.space import ParameterSpace

#: The entry-point group installed packages declare their effects in.
ENTRY_POINT_GROUP = "femcal.effects"
#: Effect files loaded by path: resolved path -> the classes they registered (idempotence).
_USER_FILES: dict[Path, list[type[Effect]]] = {}
#: Each effect class' parameter space, built once (keyed by the class and its parameters).
_SPACES: dict[tuple, ParameterSpace] = {}


@dataclass(frozen=True)
class EffectParameter:
    """One parameter of an effect: name, unit, bounds (physical units) and scale.

    ``log=True`` puts it on a log scale in the unit box (the bounds must then be > 0); the
    transform is :class:`~femcal.space.ParameterSpace`'s, like every parameter's in femcal.
    """

    name: str
    unit: str
    lower: float
    upper: float
    log: bool = False  # sampled and optimised on a log scale (bounds must be > 0)
    start: float = 0.5  # unit-box value a calibration starts from (0 = the weak end)
    #: Part of the start grids (calibration, diagnosis). Shape parameters of a law family are
    #: not: they start at the family's classic member (``start``) and move from there.
    grid: bool = True
    #: May differ per load case: the effect's split form (``<effect>:split``,
    #: :mod:`femcal.effects.split`) gives each of its load cases its own copy.
    per_load_case: bool = False

    @property
    def scale(self) -> str:
        """``"log"`` or ``"linear"``."""
        return "log" if self.log else "linear"

    def space(self) -> ParameterSpace:
        """This parameter alone as a one-dimensional :class:`~femcal.space.ParameterSpace`."""
        return ParameterSpace([self.name], [self.lower], [self.upper], [self.unit], [self.scale])

    def physical(self, u: float) -> float:
        """The physical value at unit-box coordinate ``u``."""
        return float(self.space().from_unit(np.array([u], dtype=float))[0])


class Effect:
    """Base class of a physical effect (see the module docstring).

    Class attributes
    ----------------
    name : str
        Registry name (used in params.yaml and in verdicts).
    kind : {"parallel", "series"}
    load_case_prior : dict of str to float
        Where it may act: the prior probability that it acts in each load case (a load case
        left out cannot hold it). Declare this or ``load_cases``, not both: declared alone,
        ``load_cases`` gives each of its load cases the prior 1 (the effect acts there and
        nowhere else).
    load_cases : tuple of str
        The load cases it acts on in its registered form (others are the disc alone): those
        of prior >= 0.5 (:data:`femcal.effects.terms.LIKELY`) where ``load_case_prior`` is
        declared. The diagnosis also fits it in the other load cases its prior allows and
        prices each set by the prior (:mod:`femcal.effects.terms`).
    parameters : tuple of EffectParameter
        Those with ``per_load_case=True`` may differ per load case: the effect's split form,
        ``<name>:split`` (:mod:`femcal.effects.split`), has one copy per load case.
    """

    name: ClassVar[str] = ""
    kind: ClassVar[str] = "parallel"
    load_cases: ClassVar[tuple[str, ...]] = ()
    load_case_prior: ClassVar[dict[str, float]] = {}
    parameters: ClassVar[tuple[EffectParameter, ...]] = ()

    def __init_subclass__(cls, **kwargs) -> None:
        """Derive ``load_cases`` from a declared ``load_case_prior``, or the prior 1 in each
        of the declared ``load_cases``."""
        super().__init_subclass__(**kwargs)
        own_prior, own_cases = "load_case_prior" in cls.__dict__, "load_cases" in cls.__dict__
        if own_prior and not own_cases:
            prior = cls.load_case_prior
            cls.load_cases = tuple(lc for lc in LOAD_CASES if prior.get(lc, 0.0) >= LIKELY)
        elif own_cases and not own_prior:
            cls.load_case_prior = {lc: 1.0 for lc in cls.load_cases}

    def moment(self, rotation_deg: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Moment (Nm) a parallel element carries at a rotation (deg); >= 0, non-decreasing.

        ``rotation_deg`` has shape (B, ...) and each ``p[name]`` shape (B,) broadcast over it.
        """
        raise NotImplementedError

    def rotation(self, moment_nm: torch.Tensor, p: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Rotation (deg) a series element adds at an applied moment (Nm)."""
        raise NotImplementedError

    def moment_at(
        self,
        rotation_deg: torch.Tensor,
        p: Mapping[str, torch.Tensor],
        cases: Sequence[int] | None = None,
    ) -> torch.Tensor:
        """:meth:`moment` where axis 1 of ``rotation_deg`` (B, c, m) holds the load cases
        ``cases`` (indices into :data:`~femcal.schema.LOAD_CASES`; all four by default)."""
        return self.moment(rotation_deg, p)

    def rotation_at(
        self,
        moment_nm: torch.Tensor,
        p: Mapping[str, torch.Tensor],
        cases: Sequence[int] | None = None,
    ) -> torch.Tensor:
        """:meth:`rotation` where axis 1 of ``moment_nm`` (B, c, m) holds the load cases
        ``cases`` (all four by default)."""
        return self.rotation(moment_nm, p)

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
    def space(cls) -> ParameterSpace:
        """The effect's parameters as a :class:`~femcal.space.ParameterSpace` (with scales)."""
        key = (cls, cls.parameters)
        space = _SPACES.get(key)
        if space is None:
            space = ParameterSpace(
                [q.name for q in cls.parameters],
                [q.lower for q in cls.parameters],
                [q.upper for q in cls.parameters],
                [q.unit for q in cls.parameters],
                [q.scale for q in cls.parameters],
            )
            _SPACES[key] = space
        return space

    @classmethod
    def from_unit(cls, u: torch.Tensor) -> dict[str, torch.Tensor]:
        """Unit-box values (B, p) -> physical parameters by name, each (B,).

        A forward-mode dual ``u`` (the Jacobian, :meth:`EffectModel.curves_jacobian`) is mapped
        by its primal and the map's diagonal derivative: the same values, without forward-mode
        AD's slow broadcasting of the map's bounds over every dual row.
        """
        space = cls.space()
        primal, tangent = fwad.unpack_dual(u)
        if tangent is None:
            x = space.from_unit(u)
        else:
            x = fwad.make_dual(space.from_unit(primal), space.from_unit_jacobian(primal) * tangent)
        return {q.name: x[:, j] for j, q in enumerate(cls.parameters)}

    @classmethod
    def to_unit(cls, x: np.ndarray) -> np.ndarray:
        """Physical values (n, p) -> unit box (n, p)."""
        return cls.space().to_unit(np.asarray(x, dtype=float))


def _check_effect(name: str, cls: type[Effect]) -> None:
    """Refuse an effect class that is incomplete or registered under another name."""
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise ConfigError(
            f"Only Effect subclasses can be registered as effects; got {cls!r}. Derive your "
            "class from femcal.effects.Effect."
        )
    if not cls.name or cls.kind not in ("parallel", "series"):
        raise ConfigError(
            f"Effect {cls.__name__} needs a name and kind 'parallel' or 'series'; got "
            f"name={cls.name!r}, kind={cls.kind!r}."
        )
    if any(c in cls.name for c in ":+[]@, "):
        raise ConfigError(
            f"Effect {cls.__name__}: its name {cls.name!r} holds one of ':', '+', '[', ']', '@', "
            "',' or a space, which femcal uses in verdicts (a+b), split forms (a:split) and "
            "load-case sets (a@Flexion,Extension); name it with letters, digits and underscores."
        )
    if name != cls.name:
        raise ConfigError(
            f"Effect {cls.__name__} is named {cls.name!r} (its class attribute `name`) but was "
            f"registered as {name!r}; register it under its own name (@register_effect)."
        )
    unknown = [lc for lc in cls.load_cases if lc not in LOAD_CASES]
    if unknown or not cls.load_cases:
        raise ConfigError(
            f"Effect '{cls.name}': load_cases must be a non-empty subset of {list(LOAD_CASES)}; "
            f"got {list(cls.load_cases)}"
            + (
                " (the load cases of load_case_prior >= 0.5); give one load case a prior >= 0.5."
                if "load_case_prior" in cls.__dict__
                else "."
            )
        )
    _check_prior(cls)
    for q in cls.parameters:
        if not q.lower < q.upper or (q.log and q.lower <= 0):
            raise ConfigError(
                f"Effect '{cls.name}' parameter '{q.name}': need lower < upper (and lower > 0 "
                f"on a log scale); got [{q.lower}, {q.upper}]."
            )


def _check_prior(cls: type[Effect]) -> None:
    """Refuse a ``load_case_prior`` over unknown load cases, outside [0, 1], or declared
    beside ``load_cases`` that are not its likely load cases."""
    prior = cls.load_case_prior
    bad = {lc: p for lc, p in prior.items() if lc not in LOAD_CASES or not 0.0 <= p <= 1.0}
    if bad:
        raise ConfigError(
            f"Effect '{cls.name}': load_case_prior maps load cases of {list(LOAD_CASES)} to "
            f"probabilities in [0, 1]; got {bad}."
        )
    likely = tuple(lc for lc in LOAD_CASES if prior.get(lc, 0.0) >= LIKELY)
    if tuple(cls.load_cases) != likely:
        raise ConfigError(
            f"Effect '{cls.name}' declares load_cases {list(cls.load_cases)} and a "
            f"load_case_prior whose likely load cases (prior >= {LIKELY}) are {list(likely)}. "
            "Declare one of them: load_case_prior alone (load_cases follow from it), or "
            "load_cases alone (prior 1 in each)."
        )


#: The effect registry: built-in modules (every module of this package), installed plugins
#: (entry points of :data:`ENTRY_POINT_GROUP`) and the files :func:`load_effect_modules` loads.
effect_registry: Registry[type[Effect]] = Registry(
    "effect",
    what="physical effect",
    group=ENTRY_POINT_GROUP,
    builtins=("femcal.effects.*",),
    fix=(
        "Or register your own: an Effect subclass decorated with @register_effect, in a file "
        "given to --effects-module (or effects.modules in params.yaml), or in a package with "
        f"an entry point in the group {ENTRY_POINT_GROUP} (see femcal.effects)."
    ),
    name_of=lambda cls: getattr(cls, "name", None),
    accepts=lambda obj: isinstance(obj, type) and issubclass(obj, Effect),
    expects="an Effect subclass",
    on_register=_check_effect,
    rename="Give yours another name (its class attribute `name`)",
)


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Class decorator: register an effect under ``cls.name`` (validated).

    ConfigError if the class is incomplete or another class already holds its name; the same
    class again is not a duplicate.
    """
    return effect_registry.register(cls)


def available_effects() -> list[str]:
    """Registered effect names, sorted (built-in, installed plugins, loaded files)."""
    return effect_registry.names()


def get_effect(name: str) -> type[Effect]:
    """The effect class registered under ``name`` (ConfigError listing the names otherwise);
    ``<name>:split`` is its split form (:func:`femcal.effects.split.split_effect`) and
    ``<name>@<load case>,...`` the effect acting in those load cases
    (:func:`femcal.effects.terms.acting_in`)."""
    from femcal.effects.split import split_effect

    term = parse_term(name)
    cls = effect_registry.get(term.effect)
    if term.cases is not None:
        cls = acting_in(cls, term.cases)
    return split_effect(cls) if term.split else cls


def load_effect_modules(paths: Sequence[str | Path]) -> list[str]:
    """Import effect modules from files, by path, and return the effects they registered.

    Parameters
    ----------
    paths : sequence of str or Path
        Each a ``.py`` file, or a folder whose ``*.py`` files are all loaded (in name order;
        names starting with ``_`` are skipped). Relative paths are relative to the working
        directory.

    Returns
    -------
    list of str
        The names of the effects the files registered, in registration order, each once.

    Raises
    ------
    ConfigError
        A path does not exist, is not a ``.py`` file (or a folder holds none), a module raises
        on import, registers no effect, or registers a name another class already holds.
        Nothing of a module that fails stays registered.

    Notes
    -----
    The built-in and installed-plugin effects are registered first, so a clash with them is
    reported here. Each file is imported once per process, as a module named after its
    resolved path (``femcal_user_effects_<stem>_<hash>``): loading the same file again
    returns the same names and changes nothing.

    Examples
    --------
    >>> load_effect_modules(["my_effects.py"])  # doctest: +SKIP
    ['creep']
    """
    effect_registry.load()
    files = [file for path in paths for file in _effect_files(Path(path))]
    names: list[str] = []
    for file in files:
        for cls in _load_effect_file(file):
            if cls.name not in names:
                names.append(cls.name)
    return names


def _effect_files(path: Path) -> list[Path]:
    """The .py files a path names (a file, or a folder's files); ConfigError otherwise."""
    if not path.exists():
        raise ConfigError(
            f"Effect module {path} does not exist (looked for {path.resolve()}); give the path "
            "of a .py file, or of a folder of .py files, that registers effects."
        )
    if path.is_dir():
        files = sorted(f for f in path.glob("*.py") if not f.name.startswith("_"))
        if not files:
            raise ConfigError(
                f"Effect folder {path} holds no .py file (names starting with '_' are skipped); "
                "put your effect modules there, or give the path of a .py file."
            )
        return files
    if path.suffix != ".py":
        raise ConfigError(
            f"Effect module {path} is not a Python file (suffix {path.suffix or 'none'!r}); give "
            "a .py file that defines and registers effects, or a folder of them."
        )
    return [path]


def _load_effect_file(file: Path) -> list[type[Effect]]:
    """Import one file under a unique module name; the effect classes it registered."""
    resolved = file.resolve()
    if resolved in _USER_FILES:
        classes = _USER_FILES[resolved]
        try:
            for cls in classes:  # a no-op, unless the registry was reset in between
                register_effect(cls)
        except ConfigError as exc:
            raise ConfigError(f"Effect module {file}: {exc}") from exc
        return classes
    stem = "".join(c if c.isalnum() else "_" for c in file.stem)
    digest = hashlib.sha1(str(resolved).encode()).hexdigest()[:12]
    module_name = f"femcal_user_effects_{stem}_{digest}"
    spec = importlib.util.spec_from_file_location(module_name, resolved)
    if spec is None or spec.loader is None:  # pragma: no cover - a .py file always has one
        raise ConfigError(f"Effect module {file} cannot be imported; give a .py file.")
    module = importlib.util.module_from_spec(spec)
    state = effect_registry.snapshot()
    sys.modules[module_name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as exc:
        sys.modules.pop(module_name, None)
        effect_registry.restore(state)
        if isinstance(exc, ConfigError):
            raise ConfigError(f"Effect module {file}: {exc}") from exc
        line = _error_line(exc, resolved)
        raise ConfigError(
            f"Effect module {file} raised {type(exc).__name__} on import"
            f"{f' (line {line})' if line else ''}: {exc}. Fix the module; `python {file}` shows "
            "the full traceback."
        ) from exc
    classes = [cls for name, cls in effect_registry.items() if state.entries.get(name) is not cls]
    if not classes:
        sys.modules.pop(module_name, None)
        defined = [
            obj.__name__
            for obj in vars(module).values()
            if isinstance(obj, type) and issubclass(obj, Effect) and obj.__module__ == module_name
        ]
        hint = (
            f"it defines {', '.join(defined)} but registers none: decorate each with "
            "@register_effect"
            if defined
            else "define an Effect subclass with a name, kind, load_cases and parameters, and "
            "decorate it with @register_effect (see femcal.effects)"
        )
        raise ConfigError(f"Effect module {file} registers no effect; {hint}.")
    _USER_FILES[resolved] = classes
    return classes


def _error_line(exc: BaseException, file: Path) -> int | None:
    """The line of ``file`` an import error arose on (the innermost frame in it), if any."""
    if isinstance(exc, SyntaxError) and exc.lineno and Path(exc.filename or "") == file:
        return exc.lineno
    lines = [f.lineno for f in traceback.extract_tb(exc.__traceback__) if Path(f.filename) == file]
    return lines[-1] if lines else None
