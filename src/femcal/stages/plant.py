"""Stage ``plant``: a cohort with hidden effects built from the FE curves of the Test set."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from femcal.datasets import load_split
from femcal.stages.common import StageSettings, check_outputs, out_label, path_setting, typed


@dataclass(frozen=True)
class PlantSettings(StageSettings):
    """The ``plant`` section of params.yaml (the output folder checked by :meth:`from_params`)."""

    prepared_dir: Path
    out_dir: Path
    n_per_class: int
    moments: Sequence[float]
    noise_deg: float
    seed: int

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> PlantSettings:
        cfg = typed(params, "plant")
        out = check_outputs(
            path_setting(params, "plant", "out_dir"),
            label=out_label(args.get("out"), "plant.out_dir"),
            metrics_file=args.get("metrics_file"),
        )
        return cls(
            prepared_dir=path_setting(params, "data", "prepared_dir"),
            out_dir=out,
            n_per_class=cfg.n_per_class,
            moments=list(cfg.moments),
            noise_deg=cfg.noise_deg,
            seed=cfg.seed,
        )


def run(settings: PlantSettings) -> dict[str, Any]:
    """Plant the cohort; returns ``{"path": measurements.csv}``."""
    path = run_plant(**settings.call_args())
    return {"path": path}


def describe(figures: Mapping[str, Any]) -> list[str]:
    return [f"planted cohort: {figures['path']} (truth beside it)"]


def run_plant(
    *,
    prepared_dir: Path,
    out_dir: Path,
    n_per_class: int,
    moments: Sequence[float],
    noise_deg: float,
    seed: int,
) -> Path:
    """A planted cohort from the FE curves of the Test set: measurements.csv + truth.csv.

    ``out_dir`` is all or nothing (:mod:`femcal.outputs`).
    """
    from femcal.outputs import check_destination, staged_output

    check_destination(out_dir)
    from femcal.effects.planted import make_cohort
    from femcal.tidy import wide_rom

    test, _ = load_split(prepared_dir, "test")
    _, fe_moments, fe_rom = wide_rom(test)
    cohort = make_cohort(
        fe_moments,
        fe_rom,
        n_per_class=n_per_class,
        moments=moments,
        noise_deg=noise_deg,
        rng=np.random.default_rng(seed),
    )
    with staged_output(out_dir, command="plant") as stage:  # all or nothing
        cohort.to_long().to_csv(stage.path / "measurements.csv", index=False)
        cohort.truth.to_csv(stage.path / "truth.csv", index=False)
    return out_dir / "measurements.csv"
