"""The campaign on the real solver: design, durable store, resume, kill -9 and resume."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from fe_helpers import COARSE, MOMENTS, requires_ccx

from femcal.errors import ConfigError, InputDataError
from femcal.fe.campaign import run_campaign
from femcal.fe.design import design, split_design
from femcal.fe.store import CampaignStore
from femcal.prepare import read_split
from femcal.schema import LOAD_CASES, PARAMETER_NAMES, STATUS_FAILED, STATUS_OK

from synth import study_space

BIN = Path(sys.executable).parent


def _lines(path: Path) -> list[str]:
    return [x for x in path.read_text().splitlines() if x.strip()]


def test_same_seed_same_design_and_lhs_strata():
    space = study_space()
    a = design(space, 8, np.random.default_rng(5))
    b = design(space, 8, np.random.default_rng(5))
    c = design(space, 8, np.random.default_rng(6))
    pd.testing.assert_frame_equal(a, b)
    assert not np.allclose(a[list(space.names)], c[list(space.names)])
    assert a["config_id"].tolist() == list(range(8))
    u = space.to_unit(a[list(space.names)].to_numpy())
    # Latin hypercube: each of the 8 strata of every parameter holds exactly one point.
    assert all(sorted(np.floor(u[:, j] * 8).astype(int)) == list(range(8)) for j in range(13))
    s1 = split_design(space, {"large": 4, "small": 2, "test": 3}, seed=1)
    s2 = split_design(space, {"large": 6, "small": 2, "test": 3}, seed=1)
    assert s1["split"].tolist() == ["large"] * 4 + ["small"] * 2 + ["test"] * 3
    # Resizing Large leaves the Test configurations unchanged (own random stream per split).
    t1 = s1[s1["split"] == "test"][list(PARAMETER_NAMES)].to_numpy()
    t2 = s2[s2["split"] == "test"][list(PARAMETER_NAMES)].to_numpy()
    np.testing.assert_array_equal(t1, t2)
    with pytest.raises(ConfigError, match="Unknown split"):
        split_design(space, {"train": 3}, seed=0)


@requires_ccx
def test_store_holds_every_job_with_status_version_and_deck_hash(coarse_campaign):
    folder, design_df, result = coarse_campaign
    assert result.n_jobs == 12 and result.n_run == 12 and result.n_skipped == 0
    assert result.complete and result.n_workers == 2
    lines = _lines(folder / "runs.jsonl")
    assert len(lines) == 12
    df = result.records
    assert sorted(zip(df["config_id"], df["load_case"])) == sorted(
        (c, lc) for c in range(3) for lc in LOAD_CASES
    )
    assert set(df["status"]) <= {STATUS_OK, STATUS_FAILED}
    for rec in df.itertuples():  # a failure is data: a reason, NaN (None) beyond the last level
        if rec.status == STATUS_FAILED:
            assert rec.reason and None in rec.rom_deg
        else:
            assert rec.reason == "" and None not in rec.rom_deg
            assert rec.rom_deg[0] > 0 and np.all(np.diff(rec.rom_deg) > 0)
    assert all(v and v[0].isdigit() for v in df["solver_version"])
    assert all(len(h) == 64 for h in df["deck_hash"])
    assert df["deck_hash"].nunique() == 12  # one deck per configuration x load case
    assert (df["cpu_seconds"] > 0).all() and (df["attempts"] >= 1).all()
    assert df["worker"].nunique() == 2  # both workers took jobs
    assert all(len(rom) == len(MOMENTS) for rom in df["rom_deg"])
    # Successful jobs leave no scratch behind; failed ones keep theirs (path in the record).
    kept = sorted(p.name for p in (folder / "scratch").glob("*"))
    assert len(kept) == int((df["status"] == STATUS_FAILED).sum())
    s = result.summary()
    assert s["failure_rate"] == pytest.approx(len(kept) / 12)
    assert s["cpu_seconds_per_config_mean"] > 0


@requires_ccx
def test_rerun_skips_finished_jobs_and_runs_only_new_ones(coarse_campaign, tmp_path):
    folder, design_df, first = coarse_campaign
    store = tmp_path / "runs.jsonl"
    store.write_bytes((folder / "runs.jsonl").read_bytes())
    again = run_campaign(
        "calculix", COARSE, design_df, store=store, moments=MOMENTS, progress=False
    )
    assert again.n_run == 0 and again.n_skipped == 12 and again.n_workers == 0
    assert len(_lines(store)) == 12
    # One more configuration: only its four jobs run; the stored ones are not touched.
    extra = design(study_space(), 1, np.random.default_rng(99)).assign(config_id=3)
    bigger = pd.concat([design_df.drop(columns="split"), extra], ignore_index=True)
    before = {r["job_hash"]: r for r in CampaignStore(store).read()}
    result = run_campaign(
        "calculix", COARSE, bigger, store=store, moments=MOMENTS, n_workers=2, progress=False
    )
    assert result.n_run == 4 and result.n_skipped == 12 and result.complete
    after = CampaignStore(store).read()
    assert len(after) == 16
    for rec in after[:12]:
        assert rec == before[rec["job_hash"]]  # byte-for-byte the same records
    assert {r["config_id"] for r in after[12:]} == {3}


def test_retry_runs_only_the_failures_a_predicate_picks(coarse_campaign, tmp_path):
    """``retry_failed=timed_out``: a job that hit the wall-clock limit runs again; a failure
    of the model (a fibre-routine abort) stays a result."""
    import json

    from femcal.fe.campaign import timed_out

    folder, design_df, _ = coarse_campaign
    records = [json.loads(line) for line in _lines(folder / "runs.jsonl")]
    records[0].update(status="failed", reason="timeout after 30 s (exit code -9; 3 of 5 levels)")
    records[1].update(status="failed", reason="fiber extension is too large (exit code 201)")
    store = tmp_path / "runs.jsonl"
    store.write_text("".join(json.dumps(r) + "\n" for r in records))
    assert timed_out(records[0]) and not timed_out(records[1]) and not timed_out(records[2])
    result = run_campaign(
        "calculix",
        COARSE,
        design_df,
        store=store,
        moments=MOMENTS,
        retry_failed=timed_out,
        progress=False,
    )
    assert result.n_run == 1 and result.n_skipped == 11
    latest = CampaignStore(store).finished()
    assert latest[records[0]["job_hash"]]["status"] == "ok"  # ran again, converged
    assert latest[records[1]["job_hash"]]["status"] == "failed"  # the model's failure stays


@requires_ccx
def test_torn_last_line_is_ignored_and_cut_off(coarse_campaign, tmp_path, caplog):
    folder, _, _ = coarse_campaign
    store = tmp_path / "runs.jsonl"
    good = (folder / "runs.jsonl").read_bytes()
    store.write_bytes(good + b'{"v":1,"job_hash":"abc","status":"o')  # killed mid-append
    with caplog.at_level(logging.WARNING, logger="femcal.fe.campaign"):
        assert len(CampaignStore(store).read()) == 12
    assert "torn last line" in caplog.text
    with CampaignStore(store).writer():
        pass
    assert store.read_bytes() == good  # cut back to the last complete record
    # A broken line in the middle is not a kill: it is reported with its line number.
    lines = good.split(b"\n")
    lines[3] = b"garbage"
    store.write_bytes(b"\n".join(lines))
    with pytest.raises(InputDataError, match=r"runs.jsonl, line 4: not a job record"):
        CampaignStore(store).read()


def test_store_is_locked_while_a_campaign_writes(tmp_path):
    store = CampaignStore(tmp_path / "runs.jsonl")
    with store.writer():
        with pytest.raises(ConfigError, match="in use by another campaign"):
            with CampaignStore(tmp_path / "runs.jsonl").writer():
                pass


def _params(tmp_path: Path, splits: dict) -> Path:
    params = {
        "fe": {
            "solver": "calculix",
            "settings": dict(COARSE),
            "bounds": {
                n: [lo, hi]
                for n, lo, hi in zip(
                    PARAMETER_NAMES, study_space().lower.tolist(), study_space().upper.tolist()
                )
            },
            "splits": splits,
            "seed": 3,
            "load_cases": list(LOAD_CASES),
            "moments": list(MOMENTS),
            "out_dir": str(tmp_path / "dataset"),
            "store": str(tmp_path / "runs.jsonl"),
            "metrics_file": str(tmp_path / "simulate.json"),
            "scheduler_address": None,
            "n_workers": 1,
        }
    }
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    return path


@pytest.mark.slow
@requires_ccx
def test_kill_9_loses_nothing_finished_and_rerun_resumes(tmp_path):
    params = _params(tmp_path, {"large": 1})
    store = tmp_path / "runs.jsonl"
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    cmd = [str(BIN / "femcal"), "--params", str(params), "simulate"]
    proc = subprocess.Popen(
        cmd,
        env=env,
        cwd=tmp_path,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            if store.exists() and len(_lines(store)) >= 1:
                break
            assert proc.poll() is None, "the campaign ended before it could be killed"
            time.sleep(0.05)
        else:
            pytest.fail("no job reached the store within 120 s")
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the client, its Dask workers and ccx
        proc.wait()
    killed = CampaignStore(store).read()
    assert 1 <= len(killed) < 4, "the kill came too late to test a resume"
    assert not (tmp_path / "dataset").exists()

    done = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert f"{len(killed)} already in" in done.stdout
    assert f"{4 - len(killed)} run now" in done.stdout
    final = CampaignStore(store).read()
    assert len(final) == 4
    assert len({r["job_hash"] for r in final}) == 4  # nothing computed twice
    assert final[: len(killed)] == killed  # the finished records survived unchanged
    table = read_split(tmp_path / "dataset", "large")
    assert len(table) == 4 * 5
    ok = table["status"] == STATUS_OK
    assert table.loc[ok, "rom_deg"].gt(0).all() and table.loc[~ok, "rom_deg"].isna().all()


def test_two_local_clusters_at_once_do_not_compete_for_a_dashboard_port():
    """Each local cluster's dashboard takes a free port: a second cluster beside the first (a
    campaign and a validate on one machine) starts without Dask's "Port 8787 is already in
    use" warning."""
    import warnings

    from femcal.fe.campaign import dask_client

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with dask_client(None, 1) as first, dask_client(None, 1) as second:
            assert first.submit(sum, [1, 2]).result() == 3
            assert second.submit(sum, [3, 4]).result() == 7
    assert not [w for w in caught if "already in use" in str(w.message)]
