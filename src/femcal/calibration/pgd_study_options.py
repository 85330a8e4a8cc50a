"""The options of :func:`femcal.calibration.pgd_study.pgd_study`, each declared here once.

:class:`PgdStudyOptions`' fields carry each option's type with its bounds, default (the study's
published setting) and doc; ``calibrate.options.pgd-study`` in params.yaml reads them from here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from femcal.settings.values import Float, Int, check_options, option

PROJECTIONS = ("clip", "average")
LOSSES = ("l1", "l2")
OPTIMIZERS = ("adam", "lbfgs")
SELECT = ("r2", "mae")


@dataclass(frozen=True)
class PgdStudyOptions:
    """The study's projected Adam (Atad et al., Algorithm 1) and its ablations."""

    n_starts: Int(1) = option(500, "uniform random starts per specimen (the study's M = 500)")
    steps: Int(0) = option(2250, "optimisation steps (the study's T = 2250)")
    lr: Float(gt=0) = option(0.0971, "learning rate in the unit box (the study's 0.0971)")
    loss: Literal[LOSSES] = option("l1", "row loss (the study: l1)")
    projection: Literal[PROJECTIONS] = option(
        "clip",
        "the study's projection (average the rows, clip to the bounds), or averaging only (the "
        "'no projection' ablation)",
    )
    bounds_penalty: Float(0) = option(
        0.0, "weight of the bounds penalty (the 'L1+bounds loss' ablation; 0 = off)"
    )
    optimizer: Literal[OPTIMIZERS] = option("adam", "the study's Adam, or torch's L-BFGS")
    select: Literal[SELECT] = option("r2", "best start by the study's mean R² or by MAE")

    def __post_init__(self) -> None:
        check_options(self, "pgd-study")
