"""A slice of the shared FE campaign serves the tests: real CalculiX results, no solver run.

``tests/fe/data/campaign_slice.jsonl`` holds the store records of four Large configurations
of the campaign ``fe/params.yaml`` defines (0.5..10 Nm in 0.5 Nm steps, coarse mesh): two
that reach every level under every load case, one with a fibre abort and an exhausted
increment budget, one whose four jobs all stop early (minimum increment, fibre, timeout). It
was cut from ``fe/data/campaign/runs.jsonl`` with::

    python - <<'EOF'
    import json
    ids = {0, 1, 6, 21}
    with open("fe/data/campaign/runs.jsonl") as f:
        keep = {json.loads(l)["job_hash"]: l for l in f if json.loads(l)["config_id"] in ids}
    with open("tests/fe/data/campaign_slice.jsonl", "w") as f:
        f.writelines(keep.values())
    EOF

If ``fe.settings``, the design or the moments change, the first test fails: cut a new slice
from the new campaign.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from femcal.config import load_params, section
from femcal.fe.dataset import write_dataset
from femcal.fe.design import split_design
from femcal.fe.store import CampaignStore, job_hash, make_jobs, settings_hash
from femcal.prepare import read_split
from femcal.schema import LOAD_CASES, PARAMETER_NAMES, STATUS_FAILED, STATUS_OK
from femcal.stages.simulate import fe_space

REPO = Path(__file__).resolve().parents[2]
SLICE = Path(__file__).parent / "data" / "campaign_slice.jsonl"


@pytest.fixture(scope="module")
def campaign():
    """(fe params section, design rows of the slice, the slice's records)."""
    fe = section(load_params(REPO / "fe" / "params.yaml"), "fe")
    records = CampaignStore(SLICE).read()
    ids = sorted({int(r["config_id"]) for r in records})
    design = split_design(fe_space(fe["bounds"]), fe["splits"], int(fe["seed"]))
    return fe, design[design["config_id"].isin(ids)].reset_index(drop=True), records


def test_the_slice_is_the_campaign_fe_params_defines(campaign):
    fe, design, records = campaign
    digest = settings_hash(fe["solver"], fe["settings"])
    assert {r["settings_hash"] for r in records} == {digest}
    jobs = make_jobs(
        design,
        list(PARAMETER_NAMES),
        load_cases=list(fe["load_cases"]),
        moments=[float(m) for m in fe["moments"]],
    )
    assert sorted(job_hash(j, digest) for j in jobs) == sorted(r["job_hash"] for r in records)
    for r in records:
        row = design.loc[design["config_id"] == r["config_id"], list(PARAMETER_NAMES)]
        np.testing.assert_array_equal(
            row.to_numpy()[0], [r["parameters"][n] for n in PARAMETER_NAMES]
        )


def test_curves_grow_with_the_moment_and_stop_where_the_solver_did(campaign):
    fe, _, records = campaign
    m = len(fe["moments"])
    statuses = {r["status"] for r in records}
    assert statuses == {STATUS_OK, STATUS_FAILED}  # the slice holds both
    for r in records:
        rom = np.array([np.nan if v is None else v for v in r["rom_deg"]])
        idp = np.array([np.nan if v is None else v for v in r["idp_mpa"]])
        assert rom.shape == idp.shape == (m,)
        reached = int(np.isfinite(rom).sum())
        assert np.isfinite(rom[:reached]).all() and np.isnan(rom[reached:]).all()  # a prefix
        assert np.isfinite(idp[:reached]).all()
        assert np.all(np.diff(np.abs(rom[:reached])) > 0), (r["config_id"], r["load_case"])
        if r["status"] == STATUS_OK:
            assert reached == m and r["reason"] == ""
        else:
            assert reached < m and r["reason"]  # a failure keeps the levels it reached


def test_the_slice_writes_the_studys_layout(campaign, tmp_path):
    fe, design, records = campaign
    moments = [float(m) for m in fe["moments"]]
    summary = write_dataset(
        design, records, tmp_path / "ds", space=fe_space(fe["bounds"]), moments=moments
    )
    assert summary["n_jobs"] == len(records) == 4 * len(design)
    assert summary["n_failed"] == sum(r["status"] == STATUS_FAILED for r in records)
    table = read_split(tmp_path / "ds", "large")
    assert sorted(table["moment_nm"].unique()) == moments
    by_job = {(r["config_id"], r["load_case"]): r for r in records}
    for k, cid in enumerate(design["config_id"]):
        rows = table.iloc[k * 4 * len(moments) : (k + 1) * 4 * len(moments)]
        for lc in LOAD_CASES:
            got = rows.loc[rows["load_case"] == lc, "rom_deg"].to_numpy()
            stored = np.array([np.nan if v is None else v for v in by_job[(cid, lc)]["rom_deg"]])
            np.testing.assert_array_equal(got, stored)
            failed = rows.loc[rows["load_case"] == lc, "status"] == STATUS_FAILED
            assert failed.tolist() == np.isnan(stored).tolist()
