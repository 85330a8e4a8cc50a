"""experiments.calibrate_outputs_diff: two calibrate folders equal but for their timings."""

from __future__ import annotations

import json

import pytest

from experiments.calibrate_outputs_diff import compare, main


def _folder(path, seconds: float, mae: str = "0.0066", pid: int = 1):
    path.mkdir()
    (path / "metrics.csv").write_text(f"specimen,mae_deg,seconds\nS1,{mae},{seconds}\n")
    (path / "summary.json").write_text(json.dumps({"mae_deg": mae, "seconds": seconds}))
    (path / "summary.md").write_text(f"pgd in {seconds} s\n| seconds | {seconds} |\n")
    record = {"command": "calibrate", "status": "complete", "files": ["metrics.csv"], "pid": pid}
    (path / ".femcal-run.json").write_text(json.dumps(record))
    (path / "summary.png").write_bytes(str(seconds).encode())
    return path


def test_timings_aside_the_folders_are_equal(tmp_path):
    a = _folder(tmp_path / "a", 0.31, pid=1)
    b = _folder(tmp_path / "b", 0.52, pid=2)
    names, differ, pngs = compare(a, b)
    assert len(names) == 4 and differ == [] and pngs == ["summary.png"]
    assert main([str(a), str(b)]) == 0


def test_a_number_that_moved_is_reported(tmp_path, capsys):
    a = _folder(tmp_path / "a", 0.31)
    b = _folder(tmp_path / "b", 0.31, mae="0.0067")
    assert main([str(a), str(b)]) == 1
    assert "metrics.csv" in capsys.readouterr().out


def test_folders_with_other_files_are_refused(tmp_path):
    a = _folder(tmp_path / "a", 0.31)
    b = _folder(tmp_path / "b", 0.31)
    (b / "extra.csv").write_text("x\n")
    with pytest.raises(SystemExit, match="different files"):
        compare(a, b)
