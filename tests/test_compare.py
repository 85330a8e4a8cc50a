"""Before/after tables of two calibrations (the MLflow look-up is tested in the stage tests)."""

from __future__ import annotations

import json

import pytest

from femcal.compare import comparison_frame, write_comparison


def test_comparison_frame_keeps_shared_metrics_in_order_with_change_and_ratio():
    before = {"mae_deg": 0.12, "mae_deg_Extension": 0.2, "r2_mean": 0.9, "other": 1.0}
    after = {"mae_deg_Extension": 0.05, "mae_deg": 0.04, "r2_mean": 0.99}
    frame = comparison_frame(before, after)
    assert frame["metric"].tolist() == ["mae_deg", "mae_deg_Extension", "r2_mean"]
    row = frame.set_index("metric").loc["mae_deg_Extension"]
    assert row["change"] == pytest.approx(-0.15) and row["ratio"] == pytest.approx(0.25)


def test_write_comparison_writes_markdown_and_json(tmp_path):
    frame = comparison_frame({"mae_deg": 0.1}, {"mae_deg": 0.05})
    paths = write_comparison(
        frame, tmp_path, before={"run_id": "a", "effects": "none"}, after={"run_id": "b"}
    )
    assert [p.name for p in paths] == ["comparison.md", "comparison.json"]
    assert "| mae_deg | 0.1000 | 0.0500 | -0.0500 | 0.50 |" in paths[0].read_text()
    assert json.loads(paths[1].read_text())["before"]["effects"] == "none"


def test_a_comparison_without_a_shared_metric_says_so(tmp_path):
    frame = comparison_frame({"sigma_deg": 0.06}, {"mae_deg": 0.05})
    (md, _) = write_comparison(
        frame,
        tmp_path,
        before={"source": "folder d (femcal diagnose)", "chosen": "given by --compare-to"},
        after={"run_id": "b"},
    )
    text = md.read_text()
    assert "Compared with folder d (femcal diagnose), given by --compare-to." in text
    assert "No metric in common: the earlier output holds none of mae_deg" in text
