"""Outputs that belong to one run, through the command line (real MLflow, temporary store).

A reused ``--out`` keeps nothing of the earlier run and MLflow gets only this run's files; a
folder with the user's files is refused before any heavy import; an ad-hoc ``diagnose`` never
writes the pipeline's ``reports/diagnose.json``; the DVC stages pass their metrics files.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import mlflow
import pandas as pd
import pytest
import yaml
from calibration_helpers import MOMENTS

from femcal.cli import main
from femcal.outputs import read_marker
from femcal.tracking import (
    configure_tracking,
    ensure_experiment,
)

from synth import long_csv

ROOT = Path(__file__).resolve().parents[2]


def _params(tmp: Path, *, plots: bool) -> dict:
    return {
        "mlflow": {
            "store_dir": str(tmp / "mlruns"),
            "experiment": "test",
            "model_name": "ivd-rom-surrogate",
        },
        "moments": MOMENTS,
        "calibrate": {
            "datasets": {},
            "out_dir": "cal",
            "method": "pgd",
            "model_uri": "models:/ivd-rom-surrogate@champion",
            "holdout_uri": None,
            "start_bank": None,
            "seed": 0,
            "plots": plots,
            "max_plots": 1,
            "options": {"pgd": {"n_bank_uniform": 128}},
        },
        "diagnose": {
            "measurements": "meas.csv",
            "out_dir": "reports/diagnosis",
            "metrics_file": "reports/diagnose.json",
            "noise_deg": 0.05,
            "candidates": ["neutral_zone"],
            "min_delta": 10.0,
            "seed": 0,
            "plots": False,
            "max_plots": 1,
        },
    }


@pytest.fixture
def settings(tmp_path, monkeypatch):
    """A project folder with params.yaml (plots) and noplots.yaml; the working directory."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.setenv("MLFLOW_RUN_CONTEXT", "{}")  # the commands tag their runs through it
    monkeypatch.chdir(tmp_path)
    for name, plots in (("params.yaml", True), ("noplots.yaml", False)):
        (tmp_path / name).write_text(yaml.safe_dump(_params(tmp_path, plots=plots)))
    return tmp_path


@pytest.fixture
def project(settings, registry_store, truth):
    """``settings`` with the registered surrogate (a copy of the package's registry) and two
    specimens in meas.csv."""
    shutil.copytree(registry_store, settings / "mlruns")
    configure_tracking(store_dir=settings / "mlruns")
    ensure_experiment("test", store_dir=settings / "mlruns")
    long_csv(settings / "meas.csv", truth[1][:2])
    yield settings
    mlflow.set_tracking_uri(None)


def _calibrate_runs() -> pd.DataFrame:
    return mlflow.search_runs(
        filter_string="tags.`femcal.stage` = 'calibrate'",
        order_by=["attributes.start_time ASC"],
    )


def _artifacts(run_id: str, path: str) -> set[str]:
    client = mlflow.MlflowClient()
    out, todo = set(), [path]
    while todo:
        for a in client.list_artifacts(run_id, todo.pop()):
            (todo.append(a.path) if a.is_dir else out.add(a.path))
    return out


def test_a_reused_out_keeps_nothing_stale_and_logs_only_this_runs_files(project, capsys):
    res = project / "res"
    args = ["calibrate", "--measurements", "meas.csv", "--out", "res"]
    assert main(args) == 0
    assert (res / "plots").is_dir() and (res / "summary.png").is_file()
    # Again into the same folder, without plots and with an effect (a before/after page).
    assert main(["--params", "noplots.yaml", *args, "--effects", "facet_contact"]) == 0
    capsys.readouterr()
    runs = _calibrate_runs()
    first, second = runs["run_id"]
    assert not (res / "plots").exists() and not (res / "summary.png").exists()
    assert read_marker(res)["mlflow_run_id"] == second
    assert json.loads((res / "comparison.json").read_text())["before"]["run_id"] == first
    (aside,) = project.glob("res.previous-*")  # the earlier run, whole, beside it
    assert (aside / "summary.png").is_file() and read_marker(aside)["mlflow_run_id"] == first
    # MLflow holds exactly the files of each run.
    logged = {p.removeprefix("calibration/") for p in _artifacts(second, "calibration")}
    assert logged == set(read_marker(res)["files"]) | {".femcal-run.json"}
    assert not any(p.startswith("plots/") or p == "summary.png" for p in logged)
    # The user drops a file of their own there: refused before any work, nothing touched.
    (res / "keep_me.txt").write_text("mine")
    before = sorted(p.name for p in res.iterdir())
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--out res holds the outputs of an earlier femcal run" in err
    assert "keep_me.txt" in err and "never moves or deletes your files" in err
    assert sorted(p.name for p in res.iterdir()) == before
    assert len(_calibrate_runs()) == 2  # no MLflow run for a refused command


@pytest.mark.parametrize(
    ("option", "pngs"),
    [
        ([], {"summary.png", "plots/spec-0.png"}),
        (["--plots", "all"], None),
        (["--plots", "summary"], {"summary.png"}),
        (["--plots", "none"], set()),
    ],
)
def test_plots_option_chooses_the_figures_and_keeps_every_table(project, capsys, option, pngs):
    """params.yaml says plots: true (max_plots: 1): the default and "all" write every figure."""
    pngs = {"summary.png", "plots/spec-0.png"} if pngs is None else pngs
    out = project / "res"
    assert main(["calibrate", "--measurements", "meas.csv", "--out", "res", *option]) == 0
    assert {p.relative_to(out).as_posix() for p in out.rglob("*.png")} == pngs
    assert (out / "plots").is_dir() == ("plots/spec-0.png" in pngs)
    for table in ("parameters.csv", "metrics.csv", "curves.csv", "summary.md", "summary.json"):
        assert (out / table).is_file(), table
    assert len(pd.read_csv(out / "parameters.csv")) == 2
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_plotted"] == (1 if "plots/spec-0.png" in pngs else 0)
    logged = {
        p.removeprefix("calibration/")
        for p in _artifacts(_calibrate_runs()["run_id"][0], "calibration")
    }
    assert {p for p in logged if p.endswith(".png")} == pngs  # MLflow gets what was written
    assert "calibrated 2 specimens" in capsys.readouterr().out


def test_plots_option_overrides_plots_false_in_params(project):
    args = ["--params", "noplots.yaml", "calibrate", "--measurements", "meas.csv"]
    assert main([*args, "--out", "off"]) == 0
    assert not list((project / "off").rglob("*.png"))
    assert main([*args, "--out", "on", "--plots", "summary"]) == 0
    assert [p.name for p in (project / "on").rglob("*.png")] == ["summary.png"]


def test_an_adhoc_diagnose_leaves_the_pipelines_metrics_alone(project, capsys):
    tracked = project / "reports" / "diagnose.json"
    tracked.parent.mkdir()
    tracked.write_text('{"n_specimens": 54}\n')
    args = ["diagnose", "--measurements", "meas.csv", "--out", "elsewhere"]
    assert main(args) == 0
    assert tracked.read_text() == '{"n_specimens": 54}\n'
    assert read_marker(project / "elsewhere")["command"] == "diagnose"
    assert (project / "elsewhere" / "diagnosis.json").is_file()
    # The DVC stage names its metrics file (dvc.yaml: --metrics-file ${diagnose.metrics_file}).
    assert main([*args[:-1], "elsewhere2", "--metrics-file", "reports/diagnose.json"]) == 0
    assert json.loads(tracked.read_text())["n"] == 2
    # beside it, the run record (wall time: not hashed by DVC, not versioned)
    written = sorted(p.name for p in tracked.parent.iterdir())
    assert written == ["diagnose.json", "diagnose.run.json"]
    assert json.loads((tracked.parent / "diagnose.run.json").read_text())["seconds"] > 0


def test_the_first_error_comes_before_any_heavy_import(settings):
    project = settings
    (project / "meas.csv").write_text("specimen,load_case,moment_nm,rom_deg\nA,Flexion,1,2\n")
    (project / "mine").mkdir()
    (project / "mine" / "parameters.csv").write_text("my own")
    (project / "afile").write_text("x")
    code = (
        "import sys; from femcal.cli import main; rc = main(sys.argv[1:]); "
        "print(sorted(m for m in ('torch', 'lightning', 'pytorch_lightning', 'sklearn', "
        "'mlflow', 'pandas') if m in sys.modules)); sys.exit(rc)"
    )
    for cmd, says in (
        (["calibrate", "--measurements", "meas.csv", "--out", "mine"], "--out mine already"),
        (["diagnose", "--out", "afile"], "--out afile is a file, not a folder"),
        (["calibrate", "--measurements", "nope.csv", "--out", "new"], "nope.csv does not exist"),
        (
            ["calibrate", "--measurements", "meas.csv", "--metrics-file", "afile/m.json"],
            "--metrics-file afile/m.json cannot be created: afile is a file",
        ),
    ):
        proc = subprocess.run(
            [sys.executable, "-c", code, *cmd], cwd=project, capture_output=True, text=True
        )
        assert proc.returncode == 2, proc.stderr
        assert says in proc.stderr
        assert proc.stdout.strip() == "[]"  # nothing heavy was imported
    assert (project / "mine" / "parameters.csv").read_text() == "my own"


@pytest.mark.parametrize("dvc_yaml", ["dvc.yaml", "fe/dvc.yaml"])
def test_every_stage_with_metrics_passes_its_metrics_file(dvc_yaml):
    """Only a DVC stage writes reports/*.json: it names the file in its command."""
    stages = yaml.safe_load((ROOT / dvc_yaml).read_text())["stages"]
    explicit = {"calibrate", "diagnose", "simulate", "validate"}  # commands with an ad-hoc mode
    checked = 0
    for name, stage in stages.items():
        body = stage.get("do", stage)
        cmd = body["cmd"][0] if isinstance(body["cmd"], list) else body["cmd"]  # the first
        words = cmd.split()
        while words and "=" in words[0]:  # an environment setting (OMP_NUM_THREADS=1)
            words = words[1:]
        command = words[1]
        if command not in explicit:
            continue
        (metrics,) = [next(iter(m)) for m in body.get("metrics", [])]
        assert f"--metrics-file {metrics}" in cmd, (name, cmd)
        checked += 1
    assert checked >= 2


def test_comparison_names_its_baseline_and_compare_to_chooses_it(project, capsys, caplog):
    """The default "before" is the disc alone (an effect run is never compared with another
    effect run); ``--compare-to`` takes a folder or a run id; the log names the final folder."""
    base = ["--params", "noplots.yaml", "calibrate", "--measurements", "meas.csv"]
    caplog.set_level("INFO", logger="femcal")
    assert main([*base, "--out", "alone"]) == 0
    assert not (project / "alone" / "comparison.md").exists()  # the disc alone: the baseline
    assert "this run is of the disc alone" in caplog.text
    assert main([*base, "--out", "facets", "--effects", "facet_contact"]) == 0
    assert main([*base, "--out", "nz", "--effects", "neutral_zone"]) == 0
    alone, facets, _ = _calibrate_runs()["run_id"]
    page = (project / "nz" / "comparison.md").read_text()
    assert json.loads((project / "nz" / "comparison.json").read_text())["before"]["run_id"] == alone
    assert f"Compared with run {alone}, the default: the latest earlier finished" in page
    log = caplog.text
    assert f"Compared with run {alone}" in log and "): nz/comparison.md" in log
    assert ".partial-" not in log.split("Compared with")[-1]
    # A folder: its summary.json, and its run (marker) for the effects.
    assert main([*base, "--out", "vs_folder", "--effects", "neutral_zone",
                 "--compare-to", "facets"]) == 0  # fmt: skip
    page = (project / "vs_folder" / "comparison.md").read_text()
    assert (
        f"Compared with folder {project / 'facets'} (femcal calibrate), given by --compare-to"
        in page
    )
    assert f"run `{facets}`, effects: facet_contact" in page
    assert "| mae_deg |" in page
    # A run id.
    assert (
        main([*base, "--out", "vs_run", "--effects", "neutral_zone", "--compare-to", facets]) == 0
    )
    assert (
        f"Compared with run {facets}, given by --compare-to"
        in (project / "vs_run" / "comparison.md").read_text()
    )
    capsys.readouterr()
    # Neither a folder nor a run id: refused before any work, with the fix.
    assert main([*base, "--out", "bad", "--compare-to", "no/such/folder"]) == 2
    err = capsys.readouterr().err
    assert "--compare-to no/such/folder: no such folder, and not an MLflow run id" in err
    assert not (project / "bad").exists()
    # An unknown run id: named with the store.
    assert main([*base, "--out", "bad", "--compare-to", "0" * 32]) == 2
    assert f"--compare-to {'0' * 32}: no MLflow run with this id" in capsys.readouterr().err
