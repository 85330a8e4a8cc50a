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


def screened_cohort(measurements: Path, **read_options):
    """A cohort's measurements as the project's commands see them: read, then screened by the
    moment policy of ``params.yaml`` for the registered surrogate (``calibrate.model_uri``).

    Returns
    -------
    params : dict
        ``params.yaml``.
    surrogate : NeuralSurrogate
    policy : femcal.moments.MomentPolicy
    measurements : femcal.measurements.Measurements
        The screened measurements (``read_options`` passed to ``read_measurements``).
    """
    import yaml

    from femcal.measurements import read_measurements
    from femcal.moments import MomentPolicy
    from femcal.tracking import load_surrogate, open_model

    params = yaml.safe_load((REPO / "params.yaml").read_text())
    mom = params["moments"]
    meas = read_measurements(measurements, **read_options)
    surrogate = load_surrogate(open_model(str(REPO / params["calibrate"]["model_uri"])))
    policy = MomentPolicy.for_surrogate(
        surrogate,
        growth=tuple(mom["error_growth"].values()),
        max_log_ratio=tuple(mom["max_log_ratio"].values()),
    )
    return params, surrogate, policy, policy.screen(meas).measurements
