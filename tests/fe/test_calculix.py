"""The CalculiX disc model on the real solver (coarse mesh): loads, signs, outputs, failures."""

from __future__ import annotations

import hashlib
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from fe_helpers import requires_ccx

from femcal.errors import InputDataError, SolverError
from femcal.fe import COMPRESSION, FEJob, available_solvers, get_solver, simulate
from femcal.fe.calculix import FIBRE_ABORT, CalculixDisc
from femcal.fe.dat import read_dat
from femcal.fe.materials import region_materials
from femcal.schema import LOAD_CASES

BOUNDS = {
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
#: The centre of the study's parameter box.
CENTRE = {name: 0.5 * (lo + hi) for name, (lo, hi) in BOUNDS.items()}
MOMENTS = (1.0, 2.0, 3.0, 4.0, 5.0)
FORCES = (300.0, 1000.0, 2000.0)


def job(load_case: str, config_id: int = 0, **changes: float) -> FEJob:
    levels = FORCES if load_case == COMPRESSION else MOMENTS
    return FEJob(config_id, {**CENTRE, **changes}, load_case, levels)


def last_attempt(workdir: Path, result) -> Path:
    return workdir / f"attempt-{result.attempts - 1}"


@pytest.fixture(scope="module")
def adapter() -> CalculixDisc:
    return CalculixDisc(geometry="coarse")


@pytest.fixture(scope="module")
def centre_runs(adapter, tmp_path_factory) -> dict:
    """Load case -> (result, workdir) at the centre of the box (5 coarse runs)."""
    if shutil.which("ccx") is None:
        pytest.skip("CalculiX (ccx) is not installed; `make install`")
    root = tmp_path_factory.mktemp("centre")
    out = {}
    for case in (*LOAD_CASES, COMPRESSION):
        workdir = root / case
        out[case] = (simulate(adapter, job(case), workdir), workdir)
    return out


def test_registered():
    assert "calculix" in available_solvers()
    solver = get_solver("calculix", geometry="coarse", kappa="ignore")
    assert isinstance(solver, CalculixDisc) and solver.kappa == "ignore"


@requires_ccx
def test_version(adapter):
    assert re.fullmatch(r"\d+\.\d+(\.\d+)?", adapter.version())


def test_missing_executable_is_a_solver_error(tmp_path):
    adapter = CalculixDisc(geometry="coarse", executable=str(tmp_path / "no-ccx"))
    with pytest.raises(SolverError, match="apt-get install calculix-ccx"):
        adapter.version()
    with pytest.raises(SolverError, match="make install"):
        simulate(adapter, job("Flexion"), tmp_path / "run")


@pytest.mark.parametrize(
    ("changes", "name"),
    [
        ({"K2Annulus": float("nan")}, "K2Annulus"),
        ({"FiberAngle": float("inf")}, "FiberAngle"),
        ({"C10Annulus": -0.1}, "C10Annulus"),
        ({"Kappa": 0.4}, "Kappa"),
    ],
)
def test_bad_parameters(adapter, tmp_path, changes, name):
    with pytest.raises(InputDataError, match=name):
        adapter.prepare(job("Flexion", **changes), tmp_path)


def test_missing_parameter(adapter, tmp_path):
    parameters = {k: v for k, v in CENTRE.items() if k != "Kappa"}
    with pytest.raises(InputDataError, match="'Kappa' is missing"):
        adapter.prepare(FEJob(0, parameters, "Flexion", MOMENTS), tmp_path)


def test_deck_is_deterministic_and_hashed(adapter, tmp_path):
    first = adapter.prepare(job("Flexion"), tmp_path / "a")
    again = CalculixDisc(geometry="coarse").prepare(job("Flexion"), tmp_path / "b")
    assert first.deck_hash == again.deck_hash
    assert first.deck_hash == hashlib.sha256(first.deck.read_bytes()).hexdigest()
    other = adapter.prepare(job("Flexion", C10Annulus=0.3), tmp_path / "c")
    assert other.deck_hash != first.deck_hash
    text = first.deck.read_text()
    n_regions = adapter.geometry.n_rings * adapter.geometry.n_regions
    assert len(re.findall(r"\*MATERIAL, NAME=ELASTIC_FIBER_R\d+C\d+", text)) == n_regions
    assert "*RIGID BODY, NSET=TOP" in text and "*TIME POINTS" in text


def static_first_increment(deck: Path) -> float:
    lines = deck.read_text().splitlines()
    return float(lines[lines.index("*STATIC") + 1].split(",")[0])


def test_retry_attempts_start_smaller(adapter, tmp_path):
    increments = [
        static_first_increment(adapter.prepare(job("Flexion"), tmp_path / str(k), k).deck)
        for k in range(3)
    ]
    assert increments[0] > increments[1] > increments[2] > 0


def test_region_interpretation():
    p = {**CENTRE, "Kappa": 0.1, "K1Circ": -0.2, "K1Rad": -0.1, "FiberAngleRad": 0.2}
    fibres = region_materials(p, n_rings=5, n_regions=5, kappa="scale")
    scale = (1 - 3 * 0.1) ** 2
    k1_outer_anterior, _, angle_outer = fibres[0, 0]
    k1_inner_posterior, _, angle_inner = fibres[4, 4]
    assert k1_outer_anterior == pytest.approx(p["K1Annulus"] * scale)
    assert k1_inner_posterior == pytest.approx(p["K1Annulus"] * scale * 0.8 * 0.9)
    assert angle_outer == pytest.approx(p["FiberAngle"])
    assert angle_inner == pytest.approx(p["FiberAngle"] * (1 + 0.3 / 2) * 1.2)
    ignored = region_materials(p, n_rings=5, n_regions=5, kappa="ignore")
    assert ignored[0, 0][0] == pytest.approx(p["K1Annulus"])


@requires_ccx
@pytest.mark.parametrize("case", LOAD_CASES)
def test_moment_load_cases(centre_runs, case):
    result, _ = centre_runs[case]
    assert result.ok, result.reason
    assert result.attempts == 1 and result.cpu_seconds > 0
    rom = result.rom_deg
    assert np.all(np.isfinite(rom)) and np.all(rom > 0)
    assert np.all(np.diff(rom) > 0)
    assert 0.5 <= rom[-1] <= 20.0
    assert np.all(np.isfinite(result.idp_mpa))
    assert len(result.deck_hash) == 64 and result.solver_version


@requires_ccx
def test_flexion_and_extension_turn_opposite_ways(centre_runs):
    rotations = {}
    for case in ("Flexion", "Extension"):
        result, workdir = centre_runs[case]
        dat = read_dat(last_attempt(workdir, result) / "disc.dat")
        final = dat.rotations[max(dat.rotations)]
        assert abs(final[0]) > 10 * max(abs(final[1]), abs(final[2]))  # about x only
        assert math.degrees(abs(final[0])) == pytest.approx(result.rom_deg[-1])
        rotations[case] = final[0]
    assert rotations["Flexion"] < 0 < rotations["Extension"]


@requires_ccx
def test_compression_idp(centre_runs):
    result, _ = centre_runs[COMPRESSION]
    assert result.ok, result.reason
    assert np.all(np.isnan(result.rom_deg))
    idp = result.idp_mpa
    assert np.all(np.diff(idp) > 0)
    assert 0.1 <= idp[0] and idp[-1] <= 3.0
    # nearly hydrostatic nucleus: IDP roughly proportional to the force (Brinckmann 1991)
    assert idp[-1] / idp[0] == pytest.approx(FORCES[-1] / FORCES[0], rel=0.3)


@requires_ccx
@pytest.mark.parametrize("case", ["Flexion", "AxialRotation"])
def test_stiffer_annulus_rotates_less(adapter, centre_runs, tmp_path, case):
    stiff = simulate(adapter, job(case, C10Annulus=0.455, K1Annulus=50.0), tmp_path)
    assert stiff.ok, stiff.reason
    assert np.all(stiff.rom_deg < centre_runs[case][0].rom_deg)


@requires_ccx
def test_non_convergence_is_a_failed_result_with_nan(tmp_path):
    adapter = CalculixDisc(geometry="coarse", max_increments=1, max_attempts=3)
    result = simulate(adapter, job("LateralBending"), tmp_path)
    assert result.status == "failed" and not result.ok
    assert "increments" in result.reason.lower() and "0 of 5 levels" in result.reason
    assert not result.retryable and result.attempts == 1
    assert np.all(np.isnan(result.rom_deg)) and np.all(np.isnan(result.idp_mpa))


@requires_ccx
def test_partial_results_are_kept(tmp_path):
    # Enough increments for the first level only: levels beyond it are NaN, not zeros.
    adapter = CalculixDisc(geometry="coarse", initial_increment=0.2, max_increments=2)
    result = simulate(adapter, job("AxialRotation"), tmp_path)
    assert result.status == "failed"
    reached = np.isfinite(result.rom_deg)
    assert 0 < reached.sum() < len(MOMENTS)
    assert np.all(reached[: reached.sum()])  # a prefix of the levels
    assert np.all(result.rom_deg[reached] > 0)
    assert np.all(np.isnan(result.idp_mpa[~reached]))


@requires_ccx
def test_timeout_is_a_failed_result(tmp_path):
    adapter = CalculixDisc(geometry="coarse", timeout_s=0.05)
    result = simulate(adapter, job("Flexion"), tmp_path)
    assert result.status == "failed"
    assert result.reason.startswith("timeout after 0.05 s of CPU time")
    assert not result.retryable and np.all(np.isnan(result.rom_deg))


@requires_ccx
def test_fibre_abort_is_retried_with_a_smaller_first_increment(tmp_path):
    # A stiff, aligned fibre configuration with a first increment of half the load aborts in
    # the fibre routine (exit code 201); the retry with a smaller first increment converges.
    adapter = CalculixDisc(geometry="coarse", initial_increment=1.0, max_attempts=3)
    compression = FEJob(7, {**CENTRE, "Kappa": 0.0, "K2Annulus": 200.0}, COMPRESSION, (1e3, 2e3))
    result = simulate(adapter, compression, tmp_path)
    first_log = (tmp_path / "attempt-0" / "disc.log").read_text().lower()
    assert FIBRE_ABORT in first_log
    assert result.attempts >= 2
    assert result.ok, result.reason
    assert np.all(np.diff(result.idp_mpa) > 0)
    increments = [
        static_first_increment(tmp_path / f"attempt-{k}" / "disc.inp")
        for k in range(result.attempts)
    ]
    assert increments == sorted(increments, reverse=True) and len(set(increments)) == len(
        increments
    )
    # the decision itself: parse of the aborted attempt says retryable
    first = adapter.prepare(compression, tmp_path / "again", attempt=0)
    failed = adapter.parse(first, adapter.run(first))
    assert failed.status == "failed" and failed.retryable and FIBRE_ABORT in failed.reason
    assert np.all(np.isnan(failed.idp_mpa))
