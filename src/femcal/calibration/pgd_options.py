"""The options of :func:`femcal.calibration.pgd.pgd` and of its solver
:func:`femcal.calibration.gauss_newton.gauss_newton`, each declared here once.

:class:`PgdOptions`' fields carry each option's type with its bounds, default and doc;
``calibrate.options.pgd`` in params.yaml and the settings reference read them from here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from femcal.settings.values import Bool, Float, Int, ListOf, OptionError, check_options, option

if TYPE_CHECKING:
    import torch

OPTIMIZERS = ("gauss-newton", "adam", "lbfgsb")
LOSSES = ("l2", "l1")
SELECT = ("mae", "r2")
_EFFECTS = "effect models: "


@dataclass(frozen=True)
class PgdOptions:
    """How :func:`~femcal.calibration.pgd.pgd` starts, iterates, selects and bounds.

    Each field's doc says what it sets. Where the problem carries each specimen's own error
    scale (:attr:`~femcal.calibration.base.CalibrationProblem.point_sd`, weights given as
    inverse variances), that is used instead of ``noise_deg``. The effect options' values
    are measured in the docs (*Benchmarks > Measurements behind the defaults*).
    """

    optimizer: Literal[OPTIMIZERS] = option(
        "gauss-newton",
        "the local optimiser: projected Levenberg-Marquardt (chosen by measurement), projected "
        "Adam, or SciPy's L-BFGS-B",
    )
    n_starts: Int(0) = option(8, "starts per specimen from the nearest bank entries")
    n_random_starts: Int(0) = option(0, "additional uniform random starts per specimen")
    n_bank_uniform: Int(0) = option(1024, "uniform draws added to the start bank")
    max_iter: Int(0) = option(
        12, "Gauss-Newton iterations (L-BFGS-B's iteration cap; 0: the best start as is)"
    )
    keep_after: Int(0) = option(
        2, "successive halving: iterations before only the keep best starts go on"
    )
    keep: Int(0) = option(1, "starts per specimen kept after keep_after (0 = all)")
    jacobian_members: Int(0) = option(
        1, "ensemble members of the early iterations' Jacobian (0 = exact throughout)"
    )
    exact_final: Int(0) = option(2, "last iterations with the exact Jacobian")
    tol: Float(gt=0) = option(1e-4, "relative loss decrease below which a row has converged")
    loss: Literal[LOSSES] = option(
        "l2", "weighted squared or absolute error (L1 by iteratively reweighted Gauss-Newton)"
    )
    select: Literal[SELECT] = option(
        "mae",
        "how the best start of a specimen is chosen: lowest MAE, or the study's highest mean "
        "R² over load cases",
    )
    steps: Int(0) = option(300, "Adam's steps")
    lr: Float(gt=0) = option(0.02, "Adam's learning rate (unit coordinates)")
    noise_deg: Float(gt=0) = option(
        0.03,
        "error scale of one RoM value in degrees (surrogate error and measurement noise): the "
        "tolerance for near-optimal starts and the noise of the identifiability ranges",
    )
    fit_tolerance: Float(0) = option(
        0.25,
        "a start stops once its RMS residual is below fit_tolerance * noise_deg (fitting "
        "further fits the surrogate's own error); 0: the floor of 1e-4 deg",
    )
    range_z: Float(gt=0) = option(2.0, "half-width of the identifiability ranges in sd")
    ranges: Bool = option(True, "compute the identifiability ranges")
    effect_levels: ListOf(Float(0, 1), min_len=1) = option(
        (0.15, 0.5, 0.85), _EFFECTS + "unit-box levels of the start grid over each effect"
    )
    effect_bank_starts: Int(0) = option(
        4,
        _EFFECTS + "starts from the disc-and-effect combinations (of effect_bank_samples drawn "
        "from the start bank) nearest each specimen's curves",
    )
    effect_bank_samples: Int(1) = option(
        1024, _EFFECTS + "disc-and-effect combinations drawn for effect_bank_starts"
    )
    effect_shape_starts: Int(0) = option(
        8, _EFFECTS + "Sobol starts over each effect's parameters, shape included"
    )
    effect_keep: Int(0) = option(
        24,
        _EFFECTS + "starts per specimen kept after keep_after iterations (0: all); too few "
        "cull the start that leads to a single effect's optimum",
    )
    effect_rounds: Int(1) = option(
        3,
        _EFFECTS + "rounds of starts: the first starts one effect at a time, each further "
        "round every effect again from the best solution so far",
    )
    effect_max_iter: Int(1) | None = option(
        24,
        _EFFECTS + "Gauss-Newton iterations once effects join (null: max_iter; the disc-alone "
        "fit keeps max_iter)",
    )
    retry_alpha: Float(0, lt=1) = option(
        0.01,
        "with a noise_deg: fit again from 4x the starts every specimen left beyond the noise "
        "(chi-square p below this, on the points less the fit's effective parameters; 0: off); "
        "the better fit is kept",
    )

    def __post_init__(self) -> None:
        check_options(self, "pgd")
        if self.n_starts + self.n_random_starts < 1:
            raise OptionError(
                "pgd", "n_starts", "n_starts + n_random_starts must be >= 1 (starts per specimen)"
            )


@dataclass(frozen=True)
class GaussNewtonOptions:
    """How :func:`~femcal.calibration.gauss_newton.gauss_newton` iterates and when a row stops.

    Attributes
    ----------
    max_iter : int
        Iterations at most.
    loss : {"l2", "l1"}
        Weighted squared or absolute error (L1 by iteratively reweighted Gauss-Newton).
    tol : float
        Relative decrease of the loss by a kept step below which a row has converged.
    atol_deg : float or torch.Tensor
        RMS residual in degrees below which a row has converged: one tolerance, or one per
        specimen (a tensor of shape (n_specimens,)).
    l1_delta : float
        Floor of the absolute residual (degrees) in the L1 reweighting.
    keep_after, keep : int
        Successive halving: after ``keep_after`` iterations only the ``keep`` best starts of
        each specimen go on, the others stop where they are (0 in either: all starts run to
        the end).
    jacobian_members : int
        The Jacobian of the first iterations comes from that many ensemble members only
        (cheaper; steps are still accepted on the exact loss); 0: exact throughout.
    exact_final : int
        With ``jacobian_members > 0``: the last ``exact_final`` iterations use the exact
        Jacobian.
    keep_first : bool
        With successive halving, each specimen's first start goes on too.
    settle_exact : bool
        With ``jacobian_members > 0``: a row goes on with the exact Jacobian once it has
        converged on the cheaper one or a kept step gained less than 1%, until it converges
        again, so that it stops where the exact loss is stationary (the cheaper Jacobian only
        shortens the way there).
    """

    max_iter: int
    loss: str
    tol: float
    atol_deg: float | torch.Tensor = 1e-4
    l1_delta: float = 1e-3
    keep_after: int = 0
    keep: int = 0
    jacobian_members: int = 0
    exact_final: int = 2
    keep_first: bool = False
    settle_exact: bool = False
