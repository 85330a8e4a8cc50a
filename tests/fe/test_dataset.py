"""A campaign as a dataset in the study's layout, read by prepare unchanged."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from fe_helpers import MOMENTS, requires_ccx

from femcal.errors import InputDataError
from femcal.fe.campaign import run_campaign
from femcal.fe.dataset import write_dataset
from femcal.fe.design import split_design
from femcal.prepare import SPLITS, prepare_dataset, read_split
from femcal.schema import LOAD_CASES, PARAMETER_NAMES, STATUS_FAILED, STATUS_OK

from synth import study_space


@requires_ccx
def test_dataset_reads_with_prepare_and_keeps_every_value(coarse_campaign, tmp_path):
    _, design_df, result = coarse_campaign
    records = result.records.to_dict(orient="records")
    summary = write_dataset(
        design_df, records, tmp_path / "ds", space=study_space(), moments=MOMENTS
    )
    written = prepare_dataset(tmp_path / "ds", tmp_path / "prepared")  # all three splits
    assert set(written) == {"large", "small", "test", "parameter_space"}
    by_job = {(r["config_id"], r["load_case"]): r for r in records}
    for split in ("large", "small", "test"):
        table = read_split(tmp_path / "ds", split)
        cid = int(design_df.loc[design_df["split"] == split, "config_id"].iloc[0])
        x = design_df.loc[design_df["config_id"] == cid, list(PARAMETER_NAMES)].to_numpy()
        np.testing.assert_array_equal(table[list(PARAMETER_NAMES)].to_numpy()[0], x[0])
        for lc in LOAD_CASES:
            rows = table[table["load_case"] == lc]
            stored = np.array([np.nan if v is None else v for v in by_job[(cid, lc)]["rom_deg"]])
            np.testing.assert_array_equal(rows["rom_deg"].to_numpy(), stored)  # exact
            failed = rows["status"] == STATUS_FAILED
            assert failed.to_numpy().tolist() == np.isnan(stored).tolist()
    runs = pd.read_csv(tmp_path / "ds" / "runs.csv")
    assert len(runs) == 12
    assert runs["solver_version"].notna().all() and runs["deck_hash"].str.len().eq(64).all()
    assert (runs["cpu_seconds"] > 0).all()
    saved = json.loads((tmp_path / "ds" / "campaign.json").read_text())
    assert saved == json.loads(json.dumps(summary))
    assert saved["n_configurations_per_split"] == {"large": 1, "small": 1, "test": 1}
    assert saved["n_jobs"] == 12 and saved["n_ok"] + saved["n_failed"] == 12
    assert saved["failure_rate"] == pytest.approx(saved["n_failed"] / 12)
    assert len(saved["failures"]) == saved["n_failed"]
    assert saved["cpu_seconds_per_configuration"]["mean"] > 0
    assert saved["moments"] == [float(m) for m in MOMENTS]
    # The campaign's wall time: one run of 12 jobs, from its first start to its last end.
    (run,) = saved["campaign_runs"]
    assert run["jobs"] == 12 and run["workers"] >= 1
    starts, ends = runs["started_at"], runs["finished_at"]
    assert run["wall_seconds"] == pytest.approx(ends.max() - starts.min())
    assert saved["campaign_wall_seconds"] == pytest.approx(run["wall_seconds"])
    # A job missing from the store is an error naming it (unless asked to write it empty).
    with pytest.raises(InputDataError, match=r"load case Flexion: no result in the campaign"):
        write_dataset(
            design_df,
            [r for r in records if not (r["config_id"] == 0 and r["load_case"] == "Flexion")],
            tmp_path / "ds2",
            space=study_space(),
            moments=MOMENTS,
        )
    assert not (tmp_path / "ds2").exists()


@requires_ccx
def test_failed_job_is_data_with_its_reason_and_survives_into_the_dataset(tmp_path):
    # Two increments of at most 0.2 cannot reach the 5 moments: a real solver abort. (Seed 1:
    # a configuration that reaches a level before the increments run out; the qmc design of
    # seed 4 aborts on "fiber extension is too large" at 0 levels instead.)
    settings = {"geometry": "coarse", "initial_increment": 0.2, "max_increments": 2}
    settings["max_attempts"] = 1
    design_df = split_design(study_space(), {"large": 1}, seed=1)
    result = run_campaign(
        "calculix",
        settings,
        design_df,
        store=tmp_path / "runs.jsonl",
        moments=MOMENTS,
        n_workers=2,
        keep_failed=False,
        progress=False,
    )
    assert (result.records["status"] == STATUS_FAILED).all()
    assert result.failure_rate == 1.0
    assert result.failures()["reason"].str.contains("increments").all()
    summary = write_dataset(
        design_df,
        result.records.to_dict(orient="records"),
        tmp_path / "ds",
        space=study_space(),
        moments=MOMENTS,
    )
    assert summary["failure_rate"] == 1.0 and summary["n_failed"] == 4
    assert all("increments" in f["reason"] for f in summary["failures"])
    # Counted by cause: one key per solver message, whatever level each job stopped at.
    assert sum(summary["failure_reasons"].values()) == 4
    assert all("increments" in k and "(exit code" not in k for k in summary["failure_reasons"])
    assert summary["failed_levels_reached"]["n_of"] == 5
    reached = {f["load_case"]: f["levels_reached"] for f in summary["failures"]}
    assert all(0 <= k <= 2 for k in reached.values()) and max(reached.values()) > 0
    layout = SPLITS["large"]
    table = read_split(tmp_path / "ds", "large")
    for lc, k in reached.items():
        text = (tmp_path / "ds" / layout.folder / layout.results("ROM", lc)).read_text()
        row = text.splitlines()[1].split(",")
        assert row[0] == "0.0" and all(float(v) > 0 for v in row[1 : 1 + k])
        assert row[1 + k :] == [""] * (5 - k)  # not reached: empty, never zero
        rows = table[table["load_case"] == lc]
        assert (rows["status"] == STATUS_OK).tolist() == [j < k for j in range(5)]
    ok = table["status"] == STATUS_OK
    assert table.loc[ok, "rom_deg"].gt(0).all()
    assert table.loc[~ok, ["rom_deg", "idp_mpa"]].isna().all().all()
    runs = pd.read_csv(tmp_path / "ds" / "runs.csv")
    assert (runs["status"] == STATUS_FAILED).all() and runs["reason"].str.len().gt(0).all()
