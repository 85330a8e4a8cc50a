"""What every experiment shares: the repository root, the results folder and the command line
that reproduces a run."""

from __future__ import annotations

import os
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

#: The repository root (experiments run from an editable install of femcal).
REPO = Path(__file__).resolve().parents[1]
#: The experiments pipeline's outputs (experiments/dvc.yaml; DVC-tracked, not in git).
RESULTS = REPO / "experiments" / "results"


def reproduce_command(module: str, argv: Sequence[str] | None) -> str:
    """The command line that reproduces an experiment's run, its torch thread count in front.

    Parameters
    ----------
    module : str
        The experiment's module inside the package, e.g. ``"bench_diagnose"``.
    argv : sequence of str or None
        The run's arguments; None: ``sys.argv[1:]``.

    Returns
    -------
    str
        E.g. ``OMP_NUM_THREADS=1 .venv/bin/python -m experiments.bench_diagnose --seeds 0``.
    """
    threads = os.environ.get("OMP_NUM_THREADS")
    args = sys.argv[1:] if argv is None else argv
    return (
        (f"OMP_NUM_THREADS={threads} " if threads else "")
        + f".venv/bin/python -m experiments.{module} "
        + " ".join(shlex.quote(a) for a in args)
    ).strip()
