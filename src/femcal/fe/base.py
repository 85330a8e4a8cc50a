"""The solver-adapter contract: one FE job in, one :class:`FEResult` (with a status) out.

A job is one configuration (the study's 13 parameters, physical units) under one load case:
a pure moment (``Flexion``, ``Extension``, ``LateralBending``, ``AxialRotation``) applied at
``levels`` in Nm, or axial ``Compression`` at ``levels`` in N. An adapter has three steps:

``prepare(job, workdir, attempt)``
    write the input deck into ``workdir``; ``attempt`` (0, 1, ...) lets an adapter make the
    retry of an aborted run more careful (smaller first increment, ...).
``run(prepared)``
    run the solver, return its exit code, the tail of its log and its CPU seconds.
``parse(prepared, outcome)``
    read the results: RoM (degrees) and IDP (MPa) per level, NaN beyond the last level reached,
    and a status (``"ok"`` or ``"failed"``) with the reason.

:func:`simulate` is the function in front: prepare, run, parse, retry while the adapter says
the failure is retryable. Failed simulations are data with a status, never zeros.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from femcal.errors import ConfigError
from femcal.registry import Registry
from femcal.schema import LOAD_CASES, STATUS_FAILED, STATUS_OK

logger = logging.getLogger(__name__)

#: Name of the axial-compression load case (levels in N); used for IDP validation.
COMPRESSION = "Compression"


@dataclass(frozen=True)
class FEJob:
    """One simulation: a configuration under one load case.

    Parameters
    ----------
    config_id : int
        Row of the configuration in its design.
    parameters : dict of str to float
        The study's 13 material parameters in physical units.
    load_case : str
        One of ``LOAD_CASES`` or ``COMPRESSION``.
    levels : tuple of float
        Moments in Nm (pure-moment load cases) or forces in N (compression), increasing.
    """

    config_id: int
    parameters: dict[str, float]
    load_case: str
    levels: tuple[float, ...]

    def __post_init__(self) -> None:
        if self.load_case not in (*LOAD_CASES, COMPRESSION):
            raise ConfigError(
                f"Unknown load case {self.load_case!r} for FE job {self.config_id}; expected one "
                f"of {', '.join((*LOAD_CASES, COMPRESSION))}."
            )
        levels = np.asarray(self.levels, dtype=float)
        if (
            levels.ndim != 1
            or levels.size == 0
            or np.any(levels <= 0)
            or np.any(np.diff(levels) <= 0)
        ):
            raise ConfigError(
                f"FE job {self.config_id} ({self.load_case}): levels must be positive and "
                f"increasing, got {list(self.levels)}."
            )

    @property
    def key(self) -> str:
        """Stable identifier ``"<config_id>-<load_case>"`` (file names, result tables)."""
        return f"{self.config_id}-{self.load_case}"


@dataclass
class PreparedRun:
    """An input deck written to disk, ready to run."""

    job: FEJob
    workdir: Path
    deck: Path
    deck_hash: str
    attempt: int = 0
    info: dict = field(default_factory=dict)


@dataclass
class RunOutcome:
    """What the solver process did."""

    returncode: int
    log_tail: str
    cpu_seconds: float
    wall_seconds: float


@dataclass
class FEResult:
    """The result of one job: outputs per level and a status.

    Attributes
    ----------
    job : FEJob
    status : str
        ``"ok"`` when every level was reached, else ``"failed"``.
    reason : str
        Empty when ok; otherwise why (solver message, exit code, missing output).
    rom_deg : ndarray of shape (n_levels,)
        Rotation about the load axis in degrees (NaN for compression, and beyond the last
        level reached).
    idp_mpa : ndarray of shape (n_levels,)
        Intradiscal pressure in MPa (NaN beyond the last level reached).
    solver_version : str
    deck_hash : str
        SHA-256 of the input deck of the final attempt.
    attempts : int
    cpu_seconds, wall_seconds : float
        Summed over attempts.
    """

    job: FEJob
    status: str
    reason: str
    rom_deg: np.ndarray
    idp_mpa: np.ndarray
    solver_version: str = ""
    deck_hash: str = ""
    attempts: int = 1
    cpu_seconds: float = 0.0
    wall_seconds: float = 0.0
    retryable: bool = False

    @property
    def ok(self) -> bool:
        return self.status == STATUS_OK


@runtime_checkable
class SolverAdapter(Protocol):
    """What a solver adapter provides (see the module docstring)."""

    name: str
    max_attempts: int

    def version(self) -> str: ...

    def prepare(self, job: FEJob, workdir: Path, attempt: int = 0) -> PreparedRun: ...

    def run(self, prepared: PreparedRun) -> RunOutcome: ...

    def parse(self, prepared: PreparedRun, outcome: RunOutcome) -> FEResult: ...


#: Entry-point group of installed solver-adapter plugins.
ENTRY_POINT_GROUP = "femcal.solvers"

#: The solver registry: adapter classes (or factories) by name; the built-in ones are the
#: modules of this package, plugins the entry points of :data:`ENTRY_POINT_GROUP`.
solver_registry: Registry[Callable[..., SolverAdapter]] = Registry(
    "FE solver",
    group=ENTRY_POINT_GROUP,
    builtins=("femcal.fe.*",),
    fix=(
        "Set fe.solver in params.yaml to one of them, or register your own: an adapter class "
        'decorated with @register_solver("name") in a module of femcal.fe, or in a package '
        f"with an entry point in the group {ENTRY_POINT_GROUP}."
    ),
    expects="a solver adapter class",
)


def register_solver(
    name: str, *, replace: bool = False
) -> Callable[[Callable[..., SolverAdapter]], Callable[..., SolverAdapter]]:
    """Class decorator: make an adapter available as ``make_solver(name, **settings)``.

    ConfigError if another adapter already holds ``name`` (unless ``replace=True``).
    """
    return solver_registry.register(name, replace=replace)


def available_solvers() -> list[str]:
    """Names of the registered solver adapters."""
    return solver_registry.names()


def make_solver(name: str, **settings: object) -> SolverAdapter:
    """An adapter instance by registry name, built with ``settings`` (keyword arguments)."""
    return solver_registry.create(name, **settings)


def get_solver(name: str, **settings: object) -> SolverAdapter:
    """An adapter instance, as :func:`make_solver` (kept for callers of this older name).

    Unlike the ``get_`` functions of the other registries, which return the registered class,
    this one builds the adapter; ``solver_registry.get(name)`` gives the class.
    """
    return make_solver(name, **settings)


def simulate(adapter: SolverAdapter, job: FEJob, workdir: Path) -> FEResult:
    """Run one job through ``adapter``: prepare, run, parse; retry retryable failures.

    Parameters
    ----------
    adapter : SolverAdapter
    job : FEJob
    workdir : Path
        Folder for this job's files; attempt ``k`` writes into ``workdir / f"attempt-{k}"``.

    Returns
    -------
    FEResult
        Status ``"ok"``, or ``"failed"`` with the reason of the last attempt. CPU and wall
        seconds are summed over attempts.
    """
    workdir = Path(workdir)
    cpu = wall = 0.0
    result: FEResult | None = None
    for attempt in range(max(1, adapter.max_attempts)):
        start = time.perf_counter()
        prepared = adapter.prepare(job, workdir / f"attempt-{attempt}", attempt=attempt)
        outcome = adapter.run(prepared)
        result = adapter.parse(prepared, outcome)
        cpu += outcome.cpu_seconds
        wall += time.perf_counter() - start
        result.attempts = attempt + 1
        result.cpu_seconds, result.wall_seconds = cpu, wall
        if result.ok or not result.retryable:
            break
        logger.info("FE job %s attempt %d failed (%s); retrying", job.key, attempt, result.reason)
    assert result is not None
    if not result.ok:
        result.status = STATUS_FAILED
    return result
