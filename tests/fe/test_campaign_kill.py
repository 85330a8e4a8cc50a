"""Fault tests of the FE campaign on the real solver: ``kill -9`` halfway, restart, compare.

Like ``tests/test_train.py::test_killed_search_resumes`` for the Optuna search: a real
``femcal simulate`` process (CalculiX ``ccx``, coarse mesh, two Dask workers) is killed with
SIGKILL once the store holds half of the jobs, and restarted. The synchronisation is on the
store itself (the test waits until it holds >= k finished records), never on a fixed sleep.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from fe_helpers import COARSE, MOMENTS, requires_ccx

from femcal.fe.campaign import run_campaign
from femcal.fe.store import CampaignStore, job_hash, make_jobs, settings_hash
from femcal.prepare import read_split
from femcal.schema import LOAD_CASES, PARAMETER_NAMES
from femcal.stages.simulate import fe_space

from synth import study_space

BIN = Path(sys.executable).parent
#: A guard against a hung campaign only; no assertion depends on timing.
DEADLINE_S = 900


def _bounds() -> dict[str, list[float]]:
    space = study_space()
    return {n: [lo, hi] for n, lo, hi in zip(PARAMETER_NAMES, space.lower, space.upper)}


def _write_params(tmp_path: Path, n_configs: int) -> Path:
    params = {
        "fe": {
            "solver": "calculix",
            "settings": dict(COARSE),
            "bounds": {k: [float(v) for v in b] for k, b in _bounds().items()},
            "splits": {"large": n_configs},
            "seed": 3,
            "load_cases": list(LOAD_CASES),
            "moments": list(MOMENTS),
            "out_dir": str(tmp_path / "dataset"),
            "store": str(tmp_path / "runs.jsonl"),
            "metrics_file": str(tmp_path / "simulate.json"),
            "scratch_dir": str(tmp_path / "scratch"),
            "scheduler_address": None,
            "n_workers": 2,
        }
    }
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False))  # bounds in the study's order
    return path


def _expected_hashes(params: Path) -> set[str]:
    """The job hashes of the campaign ``params`` describes, from femcal's own job keys."""
    from femcal.fe.design import split_design

    fe = yaml.safe_load(params.read_text())["fe"]
    space = fe_space(fe["bounds"])
    design_df = split_design(space, fe["splits"], fe["seed"])
    digest = settings_hash(fe["solver"], fe["settings"])
    jobs = make_jobs(design_df, space.names, load_cases=LOAD_CASES, moments=MOMENTS)
    return {job_hash(job, digest) for job in jobs}


def _n_records(store: Path) -> int:
    return len(CampaignStore(store).read()) if store.exists() else 0


def _alive(process) -> bool:
    import psutil

    try:
        return process.is_running() and process.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


@pytest.mark.slow
@requires_ccx
def test_kill_9_halfway_restart_recomputes_loses_and_duplicates_nothing(tmp_path):
    import psutil

    n_configs = 2
    n_jobs = 4 * n_configs
    half = n_jobs // 2
    params = _write_params(tmp_path, n_configs)
    store = tmp_path / "runs.jsonl"
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    env["OMP_NUM_THREADS"] = "1"
    cmd = [str(BIN / "femcal"), "--params", str(params), "simulate"]
    log = (tmp_path / "first.log").open("w")
    proc = subprocess.Popen(
        cmd, env=env, cwd=tmp_path, start_new_session=True, stdout=log, stderr=log
    )
    family: list[psutil.Process] = []
    try:
        deadline = time.monotonic() + DEADLINE_S
        # Wait on the store itself: kill once it holds >= half of the jobs.
        while _n_records(store) < half:
            if proc.poll() is not None:
                pytest.fail(f"the campaign ended early:\n{(tmp_path / 'first.log').read_text()}")
            if time.monotonic() > deadline:
                pytest.fail(f"fewer than {half} jobs finished in {DEADLINE_S} s")
            time.sleep(0.01)
        family = psutil.Process(proc.pid).children(recursive=True)
        os.kill(proc.pid, signal.SIGKILL)  # kill -9 the campaign process itself
        proc.wait()
        at_kill = store.read_bytes()
        killed = CampaignStore(store).read()
        in_flight = [p for p in family if _alive(p) and p.name() == "ccx"]

        # The kill left whole records only, all from the killed run, and no dataset.
        assert half <= len(killed) < n_jobs, "the kill came too late to test a restart"
        assert at_kill.endswith(b"\n")
        assert len({r["campaign_run"] for r in killed}) == 1
        assert not (tmp_path / "dataset").exists()

        # Restart (the killed run's workers and solvers may still be winding down).
        t0 = time.monotonic()
        done = subprocess.run(
            cmd, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=DEADLINE_S
        )
        restart_s = time.monotonic() - t0
        assert done.returncode == 0, done.stderr[-3000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for p in family:  # nothing of the test outlives it
            try:
                p.kill()
            except psutil.Error:
                pass
        log.close()

    k = len(killed)
    assert f"{k} already in {store}" in done.stdout
    assert f"{n_jobs - k} run now" in done.stdout
    final = CampaignStore(store).read()
    hashes = [r["job_hash"] for r in final]
    # Nothing lost: every job of the design is in the store ...
    assert set(hashes) == _expected_hashes(params)
    # ... exactly once (nothing duplicated) ...
    assert len(hashes) == len(set(hashes)) == n_jobs
    # ... and nothing finished was recomputed: the killed run's records are the store's first
    # bytes, unchanged, and the restart computed only the jobs they lack.
    assert store.read_bytes().startswith(at_kill)
    assert final[:k] == killed
    restart = final[k:]
    assert len({r["campaign_run"] for r in restart}) == 1
    assert restart[0]["campaign_run"] != killed[0]["campaign_run"]
    assert not {r["job_hash"] for r in restart} & {r["job_hash"] for r in killed}
    table = read_split(tmp_path / "dataset", "large")
    assert len(table) == n_jobs * len(MOMENTS)
    print(
        f"\nkill -9 after {k} of {n_jobs} jobs ({len(in_flight)} ccx in flight); restart: "
        f"{k} skipped, {len(restart)} run, 0 recomputed, 0 lost, 0 duplicated "
        f"({restart_s:.1f} s)"
    )


@requires_ccx
def test_restart_after_a_torn_append_reruns_only_that_job(coarse_campaign, tmp_path, caplog):
    """A kill inside ``write`` leaves part of a record: the restart cuts it and reruns that job.

    Linux may stop a write to a regular file between pages when SIGKILL arrives, so a torn
    last line is possible; this test builds the store such a kill leaves (11 whole records and
    the first half of the 12th) from the shared campaign's real records.
    """
    folder, design_df, first = coarse_campaign
    lines = (folder / "runs.jsonl").read_bytes().splitlines(keepends=True)
    assert len(lines) == 12
    store = tmp_path / "runs.jsonl"
    kept = b"".join(lines[:11])
    store.write_bytes(kept + lines[11][: len(lines[11]) // 2])
    assert len(CampaignStore(store).read()) == 11  # the reader skips the torn tail
    with caplog.at_level(logging.WARNING, logger="femcal.fe.campaign"):
        result = run_campaign(
            "calculix",
            COARSE,
            design_df,
            store=store,
            moments=MOMENTS,
            n_workers=1,
            scratch_dir=tmp_path / "scratch",
            progress=False,
        )
    assert result.n_skipped == 11 and result.n_run == 1 and result.complete
    assert "cutting off a torn last line" in caplog.text
    final = CampaignStore(store).read()
    assert store.read_bytes().startswith(kept)
    assert len(final) == 12 and len({r["job_hash"] for r in final}) == 12
    assert {r["job_hash"] for r in final} == set(first.records["job_hash"])
