"""The settings of a diagnosis (:func:`femcal.diagnose.diagnose`), each declared here once.

Each option's type with its bounds, its default and its doc are the field's; the ``diagnose``
section of params.yaml, ``femcal diagnose``'s command line and the settings reference read
them from here (:func:`femcal.settings.values.option`).
"""

from __future__ import annotations

from dataclasses import dataclass

from femcal.settings.values import Bool, Float, Int, ListOf, OptionError, check_options, option


@dataclass(frozen=True)
class DiagnoseOptions:
    """How :func:`femcal.diagnose.diagnose` searches, decides and describes.

    The criterion is ``chi^2 + k ln n`` (``k`` the effective number of parameters); each
    field's doc says what it sets.
    """

    min_delta: Float(0) = option(
        10.0,
        "BIC gain the first effect needs over the disc alone (10: very strong evidence); also "
        "the prior cost of a first effect and of a discrepancy",
    )
    min_delta_inadequate: Float(0) = option(
        2.0,
        "gain a further effect (or a split form) needs over a model that holds an effect but "
        "does not explain the data",
    )
    min_delta_adequate: Float(0) | None = option(
        2.0,
        "gain a further effect needs over a model that already explains the data (null: the "
        "search stops there)",
    )
    backward_delta: Float(0) = option(
        1.0,
        "what each effect of a combination must still gain given the others to stay, in [0, "
        "min_delta]: an effect enters at min_delta and leaves below this",
    )
    beam_delta: Float(0) | None = option(
        None,
        "models within this criterion of the best of a level are extended too (null: "
        "min_delta; 0: greedy)",
    )
    alpha: Float(gt=0, lt=1) = option(0.01, "level of the adequacy tests (chi-square, runs)")
    max_effects: Int(1) = option(3, "effects forward selection may add per specimen")
    max_iter: Int(1) = option(25, "Gauss-Newton iterations per fit")
    effect_levels: ListOf(Float(0, 1), min_len=1) = option(
        (0.15, 0.5, 0.85), "unit-box levels of the start grid over a new effect's parameters"
    )
    grid_shapes: Bool = option(True, "the start grid also spans the effects' shape parameters")
    shape_starts: Int(0) = option(
        0, "a new effect also starts from this many points of a Sobol design over its parameters"
    )
    bank_starts: Int(0) = option(
        4,
        "a new effect also starts from this many disc-and-effect combinations (of bank_samples "
        "drawn from the start bank) nearest each specimen's curves",
    )
    bank_samples: Int(1) = option(1024, "disc-and-effect combinations drawn for bank_starts")
    combination_rounds: Int(0) = option(
        1,
        "rounds of fresh starts for each effect of a combination that does not explain the "
        "data yet",
    )
    backward: Bool = option(
        True, "each effect of a combination must still pay given the others (stepwise selection)"
    )
    elimination_cap: Float(0) = option(
        2.0,
        "open-world elimination: the discrepancy in a dropped effect's own load cases may be at "
        "most this factor times what the model with it needed there (0: no cap, else >= 1)",
    )
    discrepancy: Bool = option(True, "fit the discrepancy and describe what is missing")
    curve_points: Int(1) = option(
        48, "points of the continuous curves (log-spaced over the measured moments)"
    )
    seed: Int(0) = option(0, "seed of the diagnosis' start banks")
    workers: Int(1) | None = option(
        None,
        "processes the specimens are shared out over (null: one per CPU this process may use); "
        "a verdict where models are nearly tied can depend on it",
    )

    def __post_init__(self) -> None:
        check_options(self, "diagnose")
        cap = self.elimination_cap
        if not (cap == 0 or cap >= 1):
            raise OptionError(
                "diagnose",
                "elimination_cap",
                "elimination_cap must be >= 1 or 0 (no cap), a factor on the discrepancy the "
                f"larger model needed in the dropped effect's load cases; got {cap}",
            )
        if not self.backward_delta <= self.min_delta:
            raise OptionError(
                "diagnose",
                "backward_delta",
                f"backward_delta must be in [0, min_delta={self.min_delta}] (an effect leaves a "
                f"combination below what it needed to enter); got {self.backward_delta}",
            )
