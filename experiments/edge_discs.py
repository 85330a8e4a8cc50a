"""The discs of the edge cohorts (:mod:`experiments.edge_cohorts`): the study's held-out FE
curves, the CalculiX discs outside the box, and a disc's RoM as a monotone function of the
moment. numpy and the standard library only.

Every curve is a monotone cubic Hermite interpolation in ``log M - log phi`` (Fritsch &
Carlson 1980, SIAM J Numer Anal 17(2):238-246), a power law with the end secant's slope
beyond the FE moments.
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np

LOAD_CASES: tuple[str, ...] = ("Flexion", "Extension", "LateralBending", "AxialRotation")
#: The committed CalculiX store of discs stiffer than the box.
STORE = Path(__file__).resolve().parent / "fe_outside_box.jsonl.gz"
TEST_FILE = "Test/ROM_Results_{}_TestData_64_wMoment.csv"


def read_test_curves(raw_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """The study's held-out FE curves.

    Returns
    -------
    moments : ndarray, shape (k,)
        Loaded moments (Nm, > 0).
    rom : ndarray, shape (N, 4, k)
        RoM (deg) of the configurations whose curves are all positive and finite.
    """
    curves, moments = [], None
    for lc in LOAD_CASES:
        path = Path(raw_dir) / TEST_FILE.format(lc)
        if not path.is_file():
            raise FileNotFoundError(
                f"No held-out FE curves at {path}: pass --raw-dir, the folder holding the "
                "study's Test/ (or set FEMCAL_DATA_MIRROR)."
            )
        with path.open() as fh:
            m = np.array([float(x) for x in fh.readline().strip().split(",")])
        if moments is not None and not np.array_equal(m, moments):
            raise ValueError(f"{path}: moments {m.tolist()} differ from {moments.tolist()}.")
        moments = m
        curves.append(np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2))
    rom = np.stack(curves, axis=1)[..., moments > 0]
    ok = np.isfinite(rom).all(axis=(1, 2)) & (rom > 0).all(axis=(1, 2))
    return moments[moments > 0], rom[ok]


def read_outside_store(store: Path = STORE) -> list[dict]:
    """The CalculiX discs of ``store`` whose four load cases all finished.

    Returns
    -------
    list of dict
        Per disc (store order): ``config_id``, ``parameters`` (13 values), ``moments`` (k,) and
        ``rom`` (4, k) in deg, the latest finished job of each load case.
    """
    jobs: dict[tuple, dict[str, dict]] = {}
    with gzip.open(store, "rt") as fh:
        for line in fh:
            rec = json.loads(line)
            if rec.get("status") != "ok":
                continue
            key = (rec["config_id"], tuple(sorted(rec["parameters"].items())))
            old = jobs.setdefault(key, {}).get(rec["load_case"])
            if old is None or rec["finished_at"] >= old["finished_at"]:
                jobs[key][rec["load_case"]] = rec
    discs = []
    for (cfg, params), per_lc in jobs.items():
        if set(per_lc) != set(LOAD_CASES):
            continue
        levels = np.asarray(per_lc[LOAD_CASES[0]]["levels"], dtype=float)
        rom = np.array(
            [[np.nan if v is None else v for v in per_lc[lc]["rom_deg"]] for lc in LOAD_CASES]
        )
        if not (np.isfinite(rom).all() and (rom > 0).all()):
            continue
        discs.append(
            {"config_id": int(cfg), "parameters": dict(params), "moments": levels, "rom": rom}
        )
    return discs


def _hermite_slopes(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Fritsch-Carlson slopes of a monotone cubic through (x, y), shape of x."""
    h, delta = np.diff(x), np.diff(y) / np.diff(x)
    d = np.empty_like(x)
    d[0], d[-1] = delta[0], delta[-1]
    w1, w2 = 2 * h[1:] + h[:-1], h[1:] + 2 * h[:-1]
    same = delta[:-1] * delta[1:] > 0
    safe = np.where(same, 1.0, 0.0)
    harm = (w1 + w2) / (w1 / np.where(same, delta[:-1], 1.0) + w2 / np.where(same, delta[1:], 1.0))
    d[1:-1] = harm * safe
    return d


class Disc:
    """A disc's RoM as a monotone function of the applied moment, per load case.

    Parameters
    ----------
    moments : ndarray, shape (k,)
        FE moments (Nm, > 0, increasing).
    rom : ndarray, shape (4, k)
        FE RoM (deg, > 0).
    """

    def __init__(self, moments: np.ndarray, rom: np.ndarray) -> None:
        self.x = np.log(np.asarray(moments, dtype=float))
        self.y = np.log(np.maximum.accumulate(np.asarray(rom, dtype=float), axis=1))
        self.d = np.stack([_hermite_slopes(self.x, row) for row in self.y])

    def rotation(self, moment: np.ndarray) -> np.ndarray:
        """Disc rotation (deg) at ``moment`` (Nm, > 0), shape (4, q)."""
        t = np.log(np.broadcast_to(np.asarray(moment, dtype=float), (4, np.shape(moment)[-1])))
        out = np.empty_like(t)
        x = self.x
        for j in range(4):
            y, d = self.y[j], self.d[j]
            i = np.clip(np.searchsorted(x, t[j]) - 1, 0, len(x) - 2)
            h = x[i + 1] - x[i]
            s = np.clip((t[j] - x[i]) / h, 0.0, 1.0)
            h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
            h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
            inside = h00 * y[i] + h10 * h * d[i] + h01 * y[i + 1] + h11 * h * d[i + 1]
            lo = y[0] + (y[1] - y[0]) / (x[1] - x[0]) * (t[j] - x[0])
            hi = y[-1] + (y[-1] - y[-2]) / (x[-1] - x[-2]) * (t[j] - x[-1])
            out[j] = np.where(t[j] < x[0], lo, np.where(t[j] > x[-1], hi, inside))
        return np.exp(out)
