"""The FE pipeline's outputs rebuilt from the committed stores hash as ``fe/dvc.lock`` says.

A fresh copy of the working tree runs ``dvc repro`` of the stages that read the committed
campaign stores without CalculiX (``simulate``: the dataset; ``cohort``: the FE-made cohort;
``prepare``: the prepared splits), and each output folder's hash must equal the lock's. The
marker ``.femcal-run.json`` (when and where a run wrote the folder) is left out of the hashes
by ``.dvcignore``. The stages after them (training under an Optuna study, CalculiX runs at the
trained surrogate's calibrations) are not rebuilt here.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from checkout import REPO, copy_working_tree

BIN = Path(sys.executable).parent
#: The stages rebuilt from the committed stores alone, and their output folders.
FROM_STORES = {
    "simulate": "data/dataset",
    "cohort": "data/cohort",
    "prepare": "data/prepared",
}


def _outs(lock: Path) -> dict[tuple[str, str], str]:
    """(stage, output path) -> md5 of every output the lock records for ``FROM_STORES``."""
    stages = yaml.safe_load(lock.read_text())["stages"]
    return {
        (name, out["path"]): out["md5"]
        for name, path in FROM_STORES.items()
        for out in stages[name]["outs"]
        if out["path"] == path
    }


@pytest.mark.slow
def test_the_outputs_rebuilt_from_the_committed_stores_hash_as_the_lock_says(tmp_path):
    root = copy_working_tree(tmp_path / "repo", skip=lambda rel: not rel.startswith(("fe/", ".")))
    (root / "src").symlink_to(REPO / "src")  # the stages' code, read through ../src
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}
    env.update(PATH=f"{BIN}{os.pathsep}{env.get('PATH', '')}", OMP_NUM_THREADS="1")
    env["PYTHONPATH"] = str(REPO / "src")
    subprocess.run([BIN / "dvc", "init", "--no-scm", "-q", "-f"], cwd=root, env=env, check=True)
    (root / ".dvcignore").write_text((REPO / ".dvcignore").read_text())
    expected = _outs(root / "fe" / "dvc.lock")
    stages = [f"fe/dvc.yaml:{name}" for name in FROM_STORES]
    proc = subprocess.run(
        [BIN / "dvc", "repro", "-s", *stages], cwd=root, env=env, capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "running the other 0" in proc.stderr  # every job read from the stores
    assert _outs(root / "fe" / "dvc.lock") == expected
