"""Finite-element models on open solvers: adapters (prepare, run, parse) and campaigns."""

from femcal.fe.base import (
    COMPRESSION,
    FEJob,
    FEResult,
    PreparedRun,
    RunOutcome,
    SolverAdapter,
    available_solvers,
    get_solver,
    make_solver,
    register_solver,
    simulate,
    solver_registry,
)

__all__ = [
    "COMPRESSION",
    "FEJob",
    "FEResult",
    "PreparedRun",
    "RunOutcome",
    "SolverAdapter",
    "available_solvers",
    "get_solver",
    "make_solver",
    "register_solver",
    "simulate",
    "solver_registry",
]
