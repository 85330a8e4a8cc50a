"""`dvc repro fe/dvc.yaml` for real (CalculiX, coarse mesh), in a temporary copy of the repo.

simulate -> prepare -> train@large -> calibrate@fe-test -> validate on 11 configurations;
the root pipeline (./dvc.yaml) is not run.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml
from checkout import copy_working_tree
from fe_helpers import requires_ccx

from femcal.prepare import read_split

BIN = Path(sys.executable).parent
#: The committed campaign stores (hours of CalculiX): the test runs its own from scratch.
STORES = (
    "fe/data/campaign/",
    "fe/data/adapt-campaign/",
    "fe/data/validation-campaign/",
    "fe/data/cohort-campaign/",
    "fe/data/predictive-campaign/",
)


def _run(args, cwd, env):
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise AssertionError(
            f"{' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
        )
    return proc


@pytest.mark.slow
@requires_ccx
def test_fe_pipeline_runs_and_resumes(tmp_path):
    root = tmp_path / "repo"
    # from scratch: without the committed store of the shipped campaign (hours of CalculiX)
    copy_working_tree(root, skip=lambda rel: rel.startswith(STORES))
    params_path = root / "fe" / "params.yaml"
    params = yaml.safe_load(params_path.read_text())
    params["fe"]["splits"] = {"large": 8, "small": 1, "test": 2}
    params["fe"]["batches"] = []  # the shipped campaign's further batches: hours of CalculiX
    params["fe"]["moments"] = [1, 2, 3, 4, 5]  # the shipped 0.5..10 Nm grid costs 2-3x more
    params["validate"]["refine"]["max_fe_runs"] = 2  # one refinement step per specimen
    params["adapt"].update(
        {"rounds": 1, "n_explore": 1, "n_candidates": 8, "finetune": {"max_epochs": 2}}
    )
    params["adapt"]["calibrate_options"] = {"n_starts": 2, "max_iter": 3}
    # A loaded CI machine must not turn slow runs into timeouts (failures are tested elsewhere).
    params["fe"]["settings"]["timeout_s"] = 300
    # adapt needs an ensemble; two trials of the FE training's Optuna study
    params["train"]["large"].update({"final_members": 2, "n_trials": 2})
    params["train"]["large"]["fixed"].update({"width": 16, "depth": 2, "max_epochs": 5})
    params["train"]["idp"].update({"final_members": 1})
    params["train"]["idp"]["fixed"].update({"width": 16, "depth": 2, "max_epochs": 5})
    params["cohort"]["per_class"] = 1  # one specimen of each of the four classes
    params["calibrate"]["max_plots"] = 1
    params["calibrate"]["options"]["pgd"] = {"n_starts": 2, "max_iter": 3}
    params_path.write_text(yaml.safe_dump(params, sort_keys=False))
    # The predict stage on one specimen, noise-free, with a short FE limit: the 5-epoch
    # surrogate calibrates to extreme parameters, whose runs fail slowly.
    dvc_yaml = root / "fe" / "dvc.yaml"
    predict = "python -m femcal.fe.predictive --metrics-file reports/metrics/predictive.json"
    assert predict in dvc_yaml.read_text()
    dvc_yaml.write_text(
        dvc_yaml.read_text().replace(
            predict, f"{predict} --n-specimens 1 --variants clean --timeout-s 60"
        )
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    env["FEMCAL_OPTUNA_STORAGE"] = ""
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    _run(["git", "init", "-q"], root, env)
    _run([*git, "add", "-A"], root, env)
    _run([*git, "commit", "-qm", "copy"], root, env)

    first = _run([BIN / "dvc", "repro", "fe/dvc.yaml"], root, env)
    stages = ("simulate", "prepare", "train@large", "train@idp", "adapt", "calibrate@fe-test")
    for stage in (*stages, "validate", "cohort", "predict", "sigma"):
        assert f"Running stage 'fe/dvc.yaml:{stage}'" in first.stdout
    assert "Running stage 'fetch'" not in first.stdout  # the root pipeline is not run
    fe = root / "fe"
    campaign = json.loads((fe / "data/dataset/campaign.json").read_text())
    assert campaign["n_jobs"] == 44 and campaign["n_configurations"] == 11
    assert len(read_split(fe / "data/dataset", "large")) == 8 * 20
    assert json.loads((fe / "reports/metrics/simulate.json").read_text())["n"] == 11  # DVC metrics
    assert json.loads((fe / "reports/simulate.json").read_text())["n_jobs"] == 44
    calibrated = pd.read_csv(fe / "reports/calibration/fe-test/parameters.csv")
    assert len(calibrated) == 2
    validation = pd.read_csv(fe / "reports/validation/validation.csv")
    assert len(validation) == 2 and validation["fe_mae_deg"].notna().all()
    # A compression run that failed is data (NaN here, counted in validate.json), never zero.
    reached = validation[["idp_mpa_300N", "idp_mpa_2000N"]].notna().all(axis=1)
    assert reached.any()
    idp = validation.loc[reached]
    assert (idp["idp_mpa_2000N"] > idp["idp_mpa_300N"]).all()
    headline = json.loads((fe / "reports/metrics/validate.json").read_text())  # DVC metrics
    assert headline["failed"] >= int((~reached).sum()) and headline["n"] == 2
    metrics = json.loads((fe / "reports/validate.json").read_text())  # every figure
    assert metrics["n_specimens"] == 2
    # The IDP head against FE under the moments; the published in vivo values of params.yaml
    # against the discs' pressure-force curves.
    assert json.loads((fe / "reports/metrics/train-idp.json").read_text())["mae_mpa"] >= 0
    # the training reports hold the held-out error (Test split) and the training size
    large = json.loads((fe / "reports/train-large.json").read_text())
    assert large["heldout_mae_deg_0_5"] > 0 and large["n_train_configurations"] == 8
    assert json.loads((fe / "reports/train-idp.json").read_text())["heldout_mae_mpa_0_5"] > 0
    assert metrics["idp_head"]["n_points"] > 0
    published = pd.read_csv(fe / "reports/validation/idp_published.csv")
    assert "relaxed standing" in set(published["condition"])
    assert {row["condition"] for row in metrics["idp_published"]} == set(published["condition"])
    # 1-5 Nm curves: the calibration sees 1-3 Nm, FE predicts 4-5 Nm (both Test specimens).
    predictive = json.loads((fe / "reports/predictive.json").read_text())
    assert predictive["split_nm"] == 3.0 and predictive["n_specimens"] == 1
    assert "fe_predictive_mae_deg" in predictive and "noisy" not in predictive
    assert json.loads((fe / "reports/metrics/cohort.json").read_text())["n"] == 4
    sigma = json.loads((fe / "reports/sigma.json").read_text())
    assert 0.0 <= sigma["coverage_2sigma"]["0.5-5"] <= 1.0  # 1..5 Nm here: one band
    adapt = json.loads((fe / "reports/adapt.json").read_text())
    assert adapt["n_rounds"] == 1 and adapt["n_new_configurations"] == 3  # 2 targets + 1
    assert (fe / "models/surrogate-champion/MLmodel").is_file()
    # FE runs aimed at a Test specimen: up to 2 in validate, plus the adapt round at the same
    # specimens (adapt.targets are validate.measurements)
    assert 1 <= metrics["fe_runs_per_specimen_max_validate"] <= 2
    assert metrics["fe_runs_per_specimen_adapt"] == 1
    assert metrics["fe_runs_per_specimen_max"] == metrics["fe_runs_per_specimen_max_validate"] + 1
    assert metrics["target_noise_deg"] == 0.0
    # the predict stage's figure, copied (NaN, when no predicted point was reached, as null)
    copied, predicted = metrics["fe_predictive_mae_deg"], predictive["fe_predictive_mae_deg"]
    assert (copied is None and math.isnan(predicted)) or copied == pytest.approx(predicted)
    assert metrics["fe_fit_residual_deg"] <= metrics["fe_fit_residual_deg_before_refine"] + 1e-12

    # Rebuilt from the committed stores (no CalculiX run), the dataset and the cohort hash as
    # the lock says: no time, host or process is part of a DVC output.
    def outs(lock: dict, stage: str) -> list:
        return [(o["path"], o["md5"]) for o in lock["stages"][stage]["outs"]]

    locked = yaml.safe_load((fe / "dvc.lock").read_text())
    for stage in ("simulate", "cohort"):
        rebuilt = _run([BIN / "dvc", "repro", "-f", "-s", f"fe/dvc.yaml:{stage}"], root, env)
        assert "run now" not in rebuilt.stdout or "0 run now" in rebuilt.stdout
        assert outs(yaml.safe_load((fe / "dvc.lock").read_text()), stage) == outs(locked, stage)

    # One more Test configuration: the campaign resumes (44 jobs from the store, 4 new).
    params["fe"]["splits"]["test"] = 3
    params_path.write_text(yaml.safe_dump(params, sort_keys=False))
    second = _run([BIN / "dvc", "repro", "-s", "fe/dvc.yaml:simulate"], root, env)
    assert "44 already in" in second.stdout and "4 run now" in second.stdout
