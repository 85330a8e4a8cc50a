"""Shared test fixtures: a tiny synthetic dataset in the study's exact raw layout.

``write_synthetic_study`` writes one split folder (``Large/``, ``Small/`` or ``Test/``) with
the study's file names, header styles and line endings: Latin-hypercube parameters within the
study's bounds, smooth positive increasing RoM curves and IDP curves (negative at high
extension moments for some configurations, as in the real data). Use it through the
``synthetic_study`` fixture (a factory) or the ``synthetic_raw_root`` fixture (all splits).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

#: The study's parameter bounds (ParameterBounds.csv): name -> (minimum, maximum).
STUDY_BOUNDS: dict[str, tuple[float, float]] = {
    "C10Nucleus": (0.03, 0.21),
    "C01Nucleus": (0.0075, 0.0525),
    "C10Annulus": (0.065, 0.455),
    "K1Annulus": (1.0, 50.0),
    "K2Annulus": (10.0, 200.0),
    "Kappa": (0.0, 0.33),
    "K1Circ": (-0.2, 0.0),
    "K2Circ": (-0.2, 0.0),
    "K1Rad": (-0.2, 0.0),
    "K2Rad": (-0.2, 0.0),
    "FiberAngle": (7.5, 52.5),
    "FiberAngleCirc": (0.0, 0.3),
    "FiberAngleRad": (0.0, 0.2),
}
SYNTHETIC_LOAD_CASES: tuple[str, ...] = ("Flexion", "Extension", "LateralBending", "AxialRotation")
#: split -> (folder, file-name infix, header of the result files, line ending), as published.
SYNTHETIC_SPLITS: dict[str, tuple[str, str, str, str]] = {
    "large": ("Large", "", "0,1,2,3,4,5", "\r\n"),
    "small": ("Small", "Small_128_", "0.0,1.0,2.0,3.0,4.0,5.0", "\r\n"),
    "test": ("Test", "TestData_64_", "0.0,1.0,2.0,3.0,4.0,5.0", "\n"),
}
SYNTHETIC_MOMENTS = np.arange(6, dtype=float)


def synthetic_file_names(split: str) -> dict[str, str]:
    """File names of a split: keys "config", "bounds", "ROM_<LC>", "IDP_<LC>"."""
    _, infix, _, _ = SYNTHETIC_SPLITS[split]
    tag = f"_{infix.rstrip('_')}" if infix else ""
    names = {"config": f"MaterialConfigurations{tag}.csv", "bounds": "ParameterBounds.csv"}
    for quantity in ("ROM", "IDP"):
        for lc in SYNTHETIC_LOAD_CASES:
            names[f"{quantity}_{lc}"] = f"{quantity}_Results_{lc}_{infix}wMoment.csv"
    return names


def _write_lines(path: Path, lines: list[str], newline: str) -> None:
    path.write_bytes("".join(line + newline for line in lines).encode())


def _row(values: np.ndarray) -> str:
    return ",".join(repr(float(v)) for v in values)


def write_synthetic_study(root: Path, split: str, n_configs: int, seed: int) -> Path:
    """Write a tiny dataset split in the study's layout under ``root``.

    Parameters
    ----------
    root : Path
        Raw-data root; the split folder (``Large``, ``Small`` or ``Test``) is created in it.
    split : {"large", "small", "test"}
        Which split's names, header style and line endings to mimic.
    n_configs : int
        Number of configurations (rows).
    seed : int
        Seed of the generator; same seed, same files.

    Returns
    -------
    Path
        The split folder.
    """
    folder_name, _, moment_header, newline = SYNTHETIC_SPLITS[split]
    names = synthetic_file_names(split)
    folder = Path(root) / folder_name
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)

    params = list(STUDY_BOUNDS)
    lower = np.array([STUDY_BOUNDS[p][0] for p in params])
    upper = np.array([STUDY_BOUNDS[p][1] for p in params])
    d = len(params)
    strata = np.stack([rng.permutation(n_configs) for _ in range(d)], axis=1)
    unit = (strata + rng.random((n_configs, d))) / n_configs
    x = lower + unit * (upper - lower)

    _write_lines(
        folder / names["bounds"],
        [",".join(params), ",".join(f"{v:g}" for v in lower), ",".join(f"{v:g}" for v in upper)],
        newline,
    )
    _write_lines(folder / names["config"], [",".join(params)] + [_row(r) for r in x], newline)

    m = SYNTHETIC_MOMENTS
    # The unloaded state: exactly 0 (Large) or round-off noise (Small, Test), as published.
    noise = 0.0 if split == "large" else 1e-17
    for k, lc in enumerate(SYNTHETIC_LOAD_CASES):
        softness = 1.0 - unit[:, (k + 2) % d]
        amplitude = 2.0 + 6.0 * softness + k  # degrees
        scale = 1.0 + 2.0 * unit[:, (k + 5) % d]  # Nm
        slope = 0.05 + 0.25 * unit[:, (k + 7) % d]  # degrees / Nm
        rom = amplitude[:, None] * (1 - np.exp(-m / scale[:, None])) + slope[:, None] * m
        gain = 0.02 + 0.08 * unit[:, (k + 3) % d]  # MPa / Nm
        bend = 0.3 * unit[:, (k + 9) % d] if lc == "Extension" else np.zeros(n_configs)
        idp = gain[:, None] * m * (1.0 - bend[:, None] * m)
        zero = noise * rng.standard_normal((n_configs, 2))
        rom[:, 0], idp[:, 0] = zero[:, 0], zero[:, 1]
        _write_lines(folder / names[f"ROM_{lc}"], [moment_header] + [_row(r) for r in rom], newline)
        _write_lines(folder / names[f"IDP_{lc}"], [moment_header] + [_row(r) for r in idp], newline)
    return folder


@pytest.fixture
def synthetic_study(tmp_path: Path) -> Callable[..., Path]:
    """Factory ``make(split="large", n_configs=8, seed=0, root=None) -> split folder``.

    ``root`` defaults to ``tmp_path / "raw"``.
    """

    def make(
        split: str = "large", n_configs: int = 8, seed: int = 0, root: Path | None = None
    ) -> Path:
        return write_synthetic_study(
            root if root is not None else tmp_path / "raw", split, n_configs, seed
        )

    return make


@pytest.fixture
def synthetic_raw_root(tmp_path: Path) -> Path:
    """A raw root with all three splits (6, 4 and 3 configurations)."""
    root = tmp_path / "raw"
    for seed, (split, n) in enumerate((("large", 6), ("small", 4), ("test", 3))):
        write_synthetic_study(root, split, n, seed)
    return root
