"""What the posterior elements do to the range of motion: RoM with and without them.

``python -m femcal.fe.posterior_check`` runs one configuration (default: the centre of the
study's parameter box, coarse mesh) as a disc alone, with facets, with the five ligaments,
and with both, under the four moments, and prints the RoM at the last moment and its ratio to
the disc alone's, per load case (a Markdown table; docs/fe-posterior-elements.md quotes it).
Each run is one CalculiX job; ``--jobs`` of them run side by side (one thread each).
"""

from __future__ import annotations

import argparse
import tempfile
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from femcal.fe.base import FEJob, simulate
from femcal.fe.calculix import CalculixDisc
from femcal.fe.calculix_settings import LIGAMENTS
from femcal.schema import LOAD_CASES

#: The centre of the study's parameter box (its ParameterBounds.csv), physical units.
BOX_CENTRE: dict[str, float] = {
    "C10Nucleus": 0.12,
    "C01Nucleus": 0.03,
    "C10Annulus": 0.26,
    "K1Annulus": 25.5,
    "K2Annulus": 105.0,
    "Kappa": 0.165,
    "K1Circ": -0.1,
    "K2Circ": -0.1,
    "K1Rad": -0.1,
    "K2Rad": -0.1,
    "FiberAngle": 30.0,
    "FiberAngleCirc": 0.15,
    "FiberAngleRad": 0.1,
}

#: The segment variants compared: name -> ``posterior`` setting of the adapter.
VARIANTS: dict[str, dict | None] = {
    "disc": None,
    "facets": {"facets": {}},
    "ligaments": {"ligaments": list(LIGAMENTS)},
    "both": {"facets": {}, "ligaments": list(LIGAMENTS)},
}


def segment_rom(
    runs: Mapping[str, Sequence[str]],
    workdir: Path,
    *,
    parameters: Mapping[str, float] = BOX_CENTRE,
    levels: Sequence[float] = (5.0, 10.0),
    geometry: str = "coarse",
    jobs: int = 2,
) -> dict[str, dict[str, float]]:
    """RoM at the last moment of each variant under its load cases.

    Parameters
    ----------
    runs : mapping of str to sequence of str
        Variant name (a key of :data:`VARIANTS`) -> load cases to run.
    workdir : Path
        Folder of the runs (one sub-folder per variant and load case).
    parameters : mapping of str to float
        The disc's 13 parameters, physical units.
    levels : sequence of float
        Moments in Nm (increasing); the RoM is read at the last.
    geometry : str
        Mesh preset of the disc.
    jobs : int
        CalculiX runs side by side.

    Returns
    -------
    dict of str to dict of str to float
        Variant -> load case -> RoM in degrees.

    Raises
    ------
    SolverError
        When a run fails (its reason is in the message).
    """
    from femcal.errors import SolverError

    tasks = [(variant, case) for variant, cases in runs.items() for case in cases]

    def run(task: tuple[str, str]) -> float:
        variant, case = task
        adapter = CalculixDisc(geometry=geometry, posterior=VARIANTS[variant])
        job = FEJob(0, dict(parameters), case, tuple(float(v) for v in levels))
        result = simulate(adapter, job, Path(workdir) / variant / case)
        if not result.ok:
            raise SolverError(f"{variant} {case}: {result.reason}")
        return float(result.rom_deg[-1])

    with ThreadPoolExecutor(max_workers=max(1, int(jobs))) as pool:
        values = list(pool.map(run, tasks))
    out: dict[str, dict[str, float]] = {}
    for (variant, case), value in zip(tasks, values):
        out.setdefault(variant, {})[case] = value
    return out


def ratio_table(rom: Mapping[str, Mapping[str, float]], moment: float) -> str:
    """A Markdown table: RoM of each variant and its ratio to the disc alone's, per load case."""
    cases = [c for c in LOAD_CASES if c in rom["disc"]]
    lines = [
        f"| variant | {' | '.join(f'{c} (deg at {moment:g} Nm, ratio)' for c in cases)} |",
        "|---|" + "---|" * len(cases),
    ]
    for variant, values in rom.items():
        cells = [
            f"{values[c]:.3f} ({values[c] / rom['disc'][c]:.3f})" if c in values else "-"
            for c in cases
        ]
        lines.append(f"| {variant} | {' | '.join(cells)} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    """Print the RoM ratio table of every variant (see the module docstring)."""
    parser = argparse.ArgumentParser(prog="python -m femcal.fe.posterior_check")
    parser.add_argument("--levels", type=float, nargs="+", default=[5.0, 10.0])
    parser.add_argument("--geometry", default="coarse")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--workdir", type=Path, default=None)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        rom = segment_rom(
            {variant: LOAD_CASES for variant in VARIANTS},
            args.workdir or Path(tmp),
            levels=args.levels,
            geometry=args.geometry,
            jobs=args.jobs,
        )
    print(ratio_table(rom, args.levels[-1]))


if __name__ == "__main__":
    main()
