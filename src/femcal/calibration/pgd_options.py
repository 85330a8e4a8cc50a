"""The options of :func:`femcal.calibration.pgd.pgd` and of its solver
:func:`femcal.calibration.pgd.gauss_newton`, each default declared here once."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from femcal.errors import ConfigError

if TYPE_CHECKING:
    import torch

OPTIMIZERS = ("gauss-newton", "adam", "lbfgsb")
LOSSES = ("l2", "l1")
SELECT = ("mae", "r2")


@dataclass(frozen=True)
class PgdOptions:
    """How :func:`~femcal.calibration.pgd.pgd` starts, iterates, selects and bounds.

    Attributes
    ----------
    optimizer : {"gauss-newton", "adam", "lbfgsb"}
        Projected Levenberg-Marquardt (default, chosen by measurement), projected Adam, or
        SciPy's L-BFGS-B.
    n_starts : int
        Starts per specimen from the nearest bank entries.
    n_random_starts : int
        Additional uniform random starts per specimen.
    n_bank_uniform : int
        Uniform draws added to the bank.
    max_iter : int
        Gauss-Newton iterations (also L-BFGS-B's iteration cap).
    keep_after, keep : int
        Successive halving: after ``keep_after`` iterations only the ``keep`` best starts of
        each specimen continue (0 = all starts run to the end).
    jacobian_members, exact_final : int
        Approximate the Jacobian by that many ensemble members (0 = exact throughout) except
        in the last ``exact_final`` iterations.
    tol : float
        Relative decrease of the loss below which a Gauss-Newton row has converged.
    loss : {"l2", "l1"}
        Weighted squared or absolute error (L1 by iteratively reweighted Gauss-Newton).
    select : {"mae", "r2"}
        How the best start of a specimen is chosen: lowest MAE, or the study's highest mean R²
        over load cases.
    steps, lr : int, float
        Adam's steps and learning rate (unit coordinates).
    noise_deg : float
        Error scale of one RoM value in degrees (surrogate error and measurement noise): the
        tolerance for near-optimal starts and the noise of the identifiability ranges. Where
        the problem carries each specimen's own scale
        (:attr:`~femcal.calibration.base.CalibrationProblem.point_sd`, weights given as inverse
        variances), that is used instead.
    fit_tolerance : float
        A start stops (and counts as converged) once its RMS residual is below
        ``fit_tolerance * noise_deg``: fitting further would fit the surrogate's own error.
        0 leaves the floor of 1e-4 deg (then practically only the relative-decrease, step and
        damping tests stop a start).
    range_z : float
        Half-width of the ranges in standard deviations.
    ranges : bool
        Compute the identifiability ranges.
    effect_levels : tuple of float
        Unit-box levels of the start grid over each effect's parameters (effect models only).
    effect_bank_starts : int
        Effect models: also start from the ``effect_bank_starts`` disc-and-effect combinations
        (of ``effect_bank_samples`` drawn from ``start_bank``, :func:`effect_bank`) nearest each
        specimen's curves.
    effect_bank_samples : int
    effect_shape_starts : int
        Effect models: per effect with shape parameters, also this many starts of a Sobol
        design over all of its parameters (:func:`effect_starts`).
    effect_keep : int
        Effect models: after ``keep_after`` iterations only the ``effect_keep`` best starts of
        each specimen go on (0: every start runs to the end). The disc-alone start with every
        effect at its weak end is the best at first wherever no effect is needed, so it stays.
        Too few kept starts cull the start that leads to a single effect's optimum (docs:
        *Benchmarks > Measurements behind the defaults*).
    effect_rounds : int
        Effect models with several effects: rounds of starts. The first starts one effect at a
        time; each further round starts every effect again from the best solution so far, the
        other effects as found (a combination of effects, found one at a time; docs:
        *Benchmarks > Measurements behind the defaults*).
    effect_max_iter : int, optional
        Effect models: Gauss-Newton iterations of the effect rounds (the disc-alone fit that
        comes first keeps ``max_iter``); None: ``max_iter``. The disc's 13 parameters and up to
        11 effect parameters, several of them shapes, need more steps than the disc alone.
    retry_alpha : float
        Where the problem carries each specimen's error scale
        (:attr:`~femcal.calibration.base.CalibrationProblem.point_sd`): a specimen whose fit
        leaves residuals the noise does not explain (chi-square on the points less the fit's
        effective parameters, p < ``retry_alpha``: the test of
        :attr:`~femcal.calibration.result.CalibrationResult.p_value`) is calibrated again from
        four times the starts, four kept after at least four iterations and at least 40
        iterations in all; the better fit (lower chi-square) is kept. The light default
        settings, fast where the fit explains the data, sometimes leave a specimen in a poorer
        basin, and a fit that misses for lack of starts would read as missing physics. 0: no
        retry.

    """

    optimizer: str = "gauss-newton"
    n_starts: int = 8
    n_random_starts: int = 0
    n_bank_uniform: int = 1024
    max_iter: int = 12
    keep_after: int = 2
    keep: int = 1
    jacobian_members: int = 1
    exact_final: int = 2
    tol: float = 1e-4
    loss: str = "l2"
    select: str = "mae"
    steps: int = 300
    lr: float = 0.02
    noise_deg: float = 0.03
    fit_tolerance: float = 0.25
    range_z: float = 2.0
    ranges: bool = True
    effect_levels: tuple[float, ...] = (0.15, 0.5, 0.85)
    effect_bank_starts: int = 4
    effect_bank_samples: int = 1024
    effect_shape_starts: int = 8
    effect_keep: int = 24
    effect_rounds: int = 3
    effect_max_iter: int | None = 24
    retry_alpha: float = 0.01

    def __post_init__(self) -> None:
        for name, value, choices in (
            ("optimizer", self.optimizer, OPTIMIZERS),
            ("loss", self.loss, LOSSES),
            ("select", self.select, SELECT),
        ):
            if value not in choices:
                raise ConfigError(
                    f"pgd: unknown {name} '{value}'; choose one of {', '.join(choices)}."
                )
        if self.n_starts + self.n_random_starts < 1:
            raise ConfigError("pgd needs n_starts + n_random_starts >= 1.")
        if self.noise_deg <= 0:
            raise ConfigError(f"pgd: noise_deg must be > 0; got {self.noise_deg}.")
        if self.effect_max_iter is not None and self.effect_max_iter < 1:
            raise ConfigError(
                f"pgd: effect_max_iter must be >= 1 (or None: max_iter); got "
                f"{self.effect_max_iter}."
            )
        if not 0 <= self.retry_alpha < 1:
            raise ConfigError(
                f"pgd: retry_alpha must be in [0, 1) (a chi-square p-value; 0: no retry); got "
                f"{self.retry_alpha}."
            )


@dataclass(frozen=True)
class GaussNewtonOptions:
    """How :func:`~femcal.calibration.pgd.gauss_newton` iterates and when a row stops.

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
