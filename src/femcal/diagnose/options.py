"""The settings of a diagnosis (:func:`femcal.diagnose.diagnose`), each default declared here."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from femcal.errors import ConfigError


@dataclass(frozen=True)
class DiagnoseOptions:
    """How :func:`femcal.diagnose.diagnose` searches, decides and describes.

    Attributes
    ----------
    min_delta : float
        Criterion gain (``chi^2 + k ln n``, ``k`` the effective number of parameters) the
        first effect needs over the disc alone: 10 is "very strong" evidence. It is also the
        prior cost of a first effect and of a discrepancy in the probabilities.
    min_delta_inadequate : float
        Gain a further effect (or a split form) needs over a model that holds an effect but
        does not explain the data.
    min_delta_adequate : float or None
        Gain a further effect needs over a model that already explains the data; None: the
        search stops there.
    backward_delta : float
        What each effect of a combination must still gain given the others to stay (in
        [0, ``min_delta``]): an effect enters at ``min_delta`` and leaves below this.
    beam_delta : float or None
        Models within this criterion of the best of a level are extended too (None:
        ``min_delta``; 0: greedy).
    alpha : float
        Level of the chi-square and runs tests in (0, 1).
    max_effects : int
        At most this many effects per specimen.
    max_iter : int
        Gauss-Newton iterations per fit.
    effect_levels : tuple of float
        Unit-box levels of the start grid over a new effect's parameters.
    grid_shapes : bool
        The start grid also spans the effects' shape parameters.
    shape_starts : int
        A new effect also starts from this many points of a Sobol design over its parameters.
    bank_starts : int
        A new effect also starts from this many disc-and-effect combinations (of
        ``bank_samples`` drawn from the start bank) nearest each specimen's curves.
    bank_samples : int
    combination_rounds : int
        Rounds of fresh starts for each effect of a combination that does not explain the
        data yet.
    backward : bool
        Each effect of a combination must still pay given the others (stepwise selection).
    elimination_cap : float
        Open-world elimination: the discrepancy in a dropped effect's own load cases may be at
        most this factor times what the model with it needed there (0: no cap, else >= 1).
    discrepancy : bool
        Fit the discrepancy and describe what is missing.
    curve_points : int
        Points of the continuous curves (log-spaced over the measured moments).
    seed : int
        Seeds the start banks.
    workers : int or None
        Processes the specimens are shared out over (None: one per CPU this process may use;
        :mod:`femcal.diagnose.workers`). A verdict where models are nearly tied can depend on it.
    """

    min_delta: float = 10.0
    min_delta_inadequate: float = 2.0
    min_delta_adequate: float | None = 2.0
    backward_delta: float = 1.0
    beam_delta: float | None = None
    alpha: float = 0.01
    max_effects: int = 3
    max_iter: int = 25
    effect_levels: tuple[float, ...] = (0.15, 0.5, 0.85)
    grid_shapes: bool = True
    shape_starts: int = 0
    bank_starts: int = 4
    bank_samples: int = 1024
    combination_rounds: int = 1
    backward: bool = True
    elimination_cap: float = 2.0
    discrepancy: bool = True
    curve_points: int = 48
    seed: int = 0
    workers: int | None = None

    def __post_init__(self) -> None:
        if not 0 < self.alpha < 1:
            raise ConfigError(f"diagnose: alpha must be in (0, 1); got {self.alpha}.")
        cap = self.elimination_cap
        if not (cap == 0 or cap >= 1) or not np.isfinite(cap):
            raise ConfigError(
                "diagnose: elimination_cap must be >= 1 or 0 (no cap), a factor on the "
                "discrepancy the larger model needed in the dropped effect's load cases; got "
                f"{cap}."
            )
        for name in ("shape_starts", "bank_starts", "combination_rounds"):
            if getattr(self, name) < 0:
                raise ConfigError(f"diagnose: {name} must be >= 0; got {getattr(self, name)}.")
        if self.workers is not None and self.workers < 1:
            raise ConfigError(
                f"diagnose: workers must be >= 1 or None (one per CPU); got {self.workers}."
            )
        if self.max_effects < 1 or self.max_iter < 1:
            raise ConfigError(
                "diagnose: max_effects and max_iter must be >= 1; got "
                f"{self.max_effects} and {self.max_iter}."
            )
        adequate = self.min_delta_adequate
        if adequate is not None and not adequate >= 0:
            raise ConfigError(f"diagnose: min_delta_adequate must be >= 0 or None; got {adequate}.")
        if not self.min_delta_inadequate >= 0:
            raise ConfigError(
                f"diagnose: min_delta_inadequate must be >= 0; got {self.min_delta_inadequate}."
            )
        if not 0 <= self.backward_delta <= self.min_delta:
            raise ConfigError(
                f"diagnose: backward_delta must be in [0, min_delta={self.min_delta}] (an effect "
                f"leaves a combination below what it needed to enter); got {self.backward_delta}."
            )
        if self.beam_delta is not None and not self.beam_delta >= 0:
            raise ConfigError(
                "diagnose: beam_delta must be >= 0 (how close in criterion a model must be to "
                "the best of its level to be extended too; 0 = greedy) or None (min_delta); got "
                f"{self.beam_delta}."
            )
