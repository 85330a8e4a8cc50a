"""The options of :func:`femcal.calibration.ga.ga`, each declared here once, with the study's
values as defaults.

The fields carry each option's type with its bounds, default and doc; ``calibrate.options.ga``
in params.yaml and the settings reference read them from here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from femcal.settings.values import Float, Int, OptionError, check_options, option

FITNESS = ("r2", "mae")


@dataclass(frozen=True)
class GaOptions:
    """The settings of :func:`~femcal.calibration.ga.ga` (each field's doc says what it sets).

    Raises
    ------
    OptionError
        On a value outside its field's bounds, counts that do not add up to ``population``,
        or crossover with fewer than 2 selected. Counts are stored as ``int``, ``target_r2``
        as ``float``.
    """

    population: Int(1) = option(20, "individuals per specimen and generation (study: 20)")
    n_selected: Int(1) = option(6, "best individuals kept unchanged and used as parents (study: 6)")
    n_crossover: Int(0) = option(
        4,
        "children of uniform crossover of random pairs of distinct selected individuals per "
        "generation (study: 4; needs n_selected >= 2)",
    )
    n_mutation: Int(0) = option(
        4,
        "copies of random selected individuals with one random parameter redrawn uniformly per "
        "generation (study: 4)",
    )
    n_immigrants: Int(0) = option(
        6,
        "uniform random individuals per generation (study: 6); n_selected + n_crossover + "
        "n_mutation + n_immigrants = population",
    )
    restart_every: Int(1) = option(
        10,
        "generations between restarts: the best individual plus population - 1 uniform random "
        "ones (study: 10)",
    )
    max_generations: Int(1) = option(
        120, "generations at most, the initial population the first (study: 120)"
    )
    target_r2: Float(le=1) = option(
        1.0,
        "a specimen stops once its best mean R² over load cases reaches this (the study's 1 is "
        "practically never reached: every specimen runs max_generations)",
    )
    fitness: Literal[FITNESS] = option(
        "r2",
        "ranking of the individuals: the study's mean R² over load cases or the weighted MAE in "
        "degrees (the stopping test is on R² either way)",
    )

    def __post_init__(self) -> None:
        check_options(self, "ga")
        total = self.n_selected + self.n_crossover + self.n_mutation + self.n_immigrants
        if total != self.population:
            raise OptionError(
                "ga",
                "population",
                f"n_selected + n_crossover + n_mutation + n_immigrants = {self.n_selected} + "
                f"{self.n_crossover} + {self.n_mutation} + {self.n_immigrants} = {total} must "
                f"equal population = {self.population}",
            )
        if self.n_crossover and self.n_selected < 2:
            raise OptionError(
                "ga",
                "n_selected",
                "crossover needs n_selected >= 2 (pairs of distinct parents), or n_crossover: 0; "
                f"got {self.n_selected}",
            )
