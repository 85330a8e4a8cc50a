"""`mlflow models serve` answers from a model folder as the train stage writes it.

The real scoring server (``--env-manager local``) on 127.0.0.1, a tiny surrogate, one request;
the answer must equal ``mlflow.pyfunc.load_model(folder).predict`` on the same rows.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import mlflow
import numpy as np
import pytest

from femcal.surrogates.nn import NeuralSurrogate
from femcal.tracking import configure_tracking, ensure_experiment, export_model, log_surrogate

from synth import study_space, tidy_table

BIN = Path(sys.executable).parent
#: Seconds the server may take to answer /ping.
READY_TIMEOUT = 120


@pytest.fixture
def served(tmp_path, monkeypatch):
    """A tiny surrogate exported to models/surrogate-large, and rows to predict."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    configure_tracking(store_dir=tmp_path / "mlruns")
    ensure_experiment("serve", store_dir=tmp_path / "mlruns")
    table = tidy_table(8, seed=0)
    model = NeuralSurrogate(
        study_space(), hidden=(8, 8), max_epochs=2, patience=2, batch_size=128, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    with mlflow.start_run():
        info = log_surrogate(model, study_space())
    folder = export_model(info.model_uri, tmp_path / "models" / "surrogate-large")
    mlflow.set_tracking_uri(None)
    rows = table[["load_case", "moment_nm", *study_space().names]].iloc[::7].head(6)
    return folder, rows


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _post(url: str, payload: dict) -> tuple[int, dict]:
    request = urllib.request.Request(
        url, data=json.dumps(payload).encode(), headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(request, timeout=60) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def test_scoring_server_answers_like_load_model(served, tmp_path):
    folder, rows = served
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    log = tmp_path / "serve.log"
    with open(log, "w") as out:
        server = subprocess.Popen(
            [BIN / "mlflow", "models", "serve", "-m", str(folder), "--env-manager", "local"]
            + ["-h", "127.0.0.1", "-p", str(port)],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=tmp_path,
            start_new_session=True,  # its own process group: the workers stop with it
        )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + READY_TIMEOUT
        while True:
            if server.poll() is not None:
                pytest.fail(f"mlflow models serve exited ({server.returncode}):\n{log.read_text()}")
            try:
                with urllib.request.urlopen(f"{base}/ping", timeout=2) as response:
                    if response.status == 200:
                        break
            except (urllib.error.URLError, ConnectionError, TimeoutError):
                pass
            if time.monotonic() > deadline:
                pytest.fail(f"no /ping answer in {READY_TIMEOUT} s:\n{log.read_text()}")
            time.sleep(0.5)
        split = json.loads(rows.to_json(orient="split", index=False))
        status, answer = _post(f"{base}/invocations", {"dataframe_split": split})
        assert status == 200, answer
        expected = mlflow.pyfunc.load_model(str(folder)).predict(rows)
        np.testing.assert_allclose(answer["predictions"], expected, rtol=1e-6)
        # A missing parameter column: a 400 that names it.
        split = json.loads(rows.drop(columns=["Kappa"]).to_json(orient="split", index=False))
        status, answer = _post(f"{base}/invocations", {"dataframe_split": split})
        assert status == 400 and "Kappa" in answer["message"], answer
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()
