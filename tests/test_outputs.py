"""All-or-nothing output folders (femcal.outputs): real folders, real processes, no sleeps.

Processes are synchronised through files (a child writes ``ready``, waits for ``go``): the
waits poll for a file with a generous deadline, so no outcome depends on timing.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from femcal.errors import OutputFolderError
from femcal.outputs import (
    MARKER,
    _locked,
    check_destination,
    check_file_destination,
    read_marker,
    remove_stale_partials,
    staged_output,
    write_text_atomic,
)


def _tree(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (the marker excluded) and its text."""
    return {
        p.relative_to(folder).as_posix(): p.read_text()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != MARKER
    }


def _siblings(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.iterdir() if p.name != out.name)


def _write_run(out: Path, files: dict[str, str], **kwargs) -> Path:
    with staged_output(out, command="test", **kwargs) as stage:
        for name, text in files.items():
            (stage.path / name).parent.mkdir(parents=True, exist_ok=True)
            (stage.path / name).write_text(text)
    return stage.destination


def _wait_for(path: Path, proc: subprocess.Popen | None = None, limit: float = 60.0) -> None:
    """Block until ``path`` exists (a handshake, not a timing assumption)."""
    deadline = time.monotonic() + limit
    while not path.exists():
        if proc is not None and proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"the child ended ({proc.returncode}) before {path.name}:\n{err}")
        if time.monotonic() > deadline:
            pytest.fail(f"{path} did not appear within {limit} s")
        time.sleep(0.01)


def _stop(proc: subprocess.Popen) -> None:
    """Kill a child still running (a failed test), and reap it."""
    if proc.poll() is None:
        proc.kill()
        proc.communicate()


# A child process: stages ``n`` files tagged with its name into OUT, says "ready", waits for
# "go", commits, says "done". Without a "go" file it waits until killed.
CHILD = """
import sys, time
from pathlib import Path
from femcal.outputs import staged_output

out, sync, tag, n = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], int(sys.argv[4])
with staged_output(out, command="child-" + tag) as stage:
    (stage.path / "plots").mkdir()
    for i in range(n):
        (stage.path / "plots" / f"{tag}-{i}.txt").write_text(tag)
    (stage.path / "parameters.csv").write_text(tag)
    (sync / f"ready-{tag}").write_text(str(stage.path))
    while not (sync / f"go-{tag}").exists():
        time.sleep(0.01)
(sync / f"done-{tag}").write_text("")
"""


def _child(tmp_path: Path, out: Path, tag: str, n: int = 20) -> subprocess.Popen:
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    sync = tmp_path / "sync"
    sync.mkdir(exist_ok=True)
    return subprocess.Popen(
        [sys.executable, str(script), str(out), str(sync), tag, str(n)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


# --------------------------------------------------------------------------- one process
def test_outputs_move_into_place_complete_with_their_marker(tmp_path):
    out = tmp_path / "results" / "run"
    with staged_output(out, command="calibrate") as stage:
        assert stage.path.parent == out.parent and stage.path.name.startswith("run.partial-")
        assert not out.exists()  # nothing at the destination while the run works
        (stage.path / "plots").mkdir()
        (stage.path / "plots" / "a.png").write_text("png")
        (stage.path / "parameters.csv").write_text("x")
        stage.note(mlflow_run_id="abc123")
    assert _tree(out) == {"parameters.csv": "x", "plots/a.png": "png"}
    marker = read_marker(out)
    assert marker["status"] == "complete" and marker["command"] == "calibrate"
    assert marker["files"] == ["parameters.csv", "plots/a.png"]
    assert marker["pid"] == os.getpid() and marker["host"] and marker["mlflow_run_id"] == "abc123"
    assert marker["started"] <= marker["finished"]
    assert _siblings(out) == []  # no staging folder, no lock file left behind


def test_a_folder_with_files_femcal_did_not_write_is_refused_and_left_alone(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "parameters.csv").write_text("my own")
    (out / "keep_me.txt").write_text("mine")
    with pytest.raises(
        OutputFolderError,
        match=r"mine already holds files femcal did not write: keep_me\.txt, parameters\.csv "
        r"\(no \.femcal-run\.json marker\)\. femcal never overwrites, moves or deletes them\. "
        r"Give a new or empty output folder, or move these files out of",
    ):
        check_destination(out)
    with pytest.raises(OutputFolderError, match="keep_me.txt"):
        _write_run(out, {"parameters.csv": "femcal"})
    assert _tree(out) == {"parameters.csv": "my own", "keep_me.txt": "mine"}
    assert _siblings(out) == []


def test_a_file_or_a_blocked_path_is_refused(tmp_path):
    (tmp_path / "results").write_text("a file")
    with pytest.raises(OutputFolderError, match=r"results is a file, not a folder"):
        check_destination(tmp_path / "results")
    with pytest.raises(OutputFolderError, match=r"cannot be created: .*results is a file"):
        check_destination(tmp_path / "results" / "run")
    with pytest.raises(OutputFolderError, match=r"is a folder; give the path of a file"):
        check_file_destination(tmp_path, label="--metrics-file")
    assert (tmp_path / "results").read_text() == "a file"


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
def test_an_unwritable_parent_is_refused(tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        with pytest.raises(OutputFolderError, match=r"locked is not writable by this user"):
            check_destination(locked / "run")
    finally:
        locked.chmod(0o700)


def test_an_empty_folder_is_used(tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    _write_run(out, {"a.txt": "1"})
    assert _tree(out) == {"a.txt": "1"}


def test_an_earlier_femcal_output_is_moved_aside_and_only_the_newest_kept(tmp_path):
    out = tmp_path / "out"
    _write_run(out, {"a.txt": "run 1", "plots/p.png": "1", "comparison.md": "vs run 0"})
    first = read_marker(out)
    _write_run(out, {"a.txt": "run 2"})
    # Nothing of run 1 stays at --out (no stale plots, no comparison naming another run).
    assert _tree(out) == {"a.txt": "run 2"}
    (aside,) = [p for p in tmp_path.iterdir() if p.name.startswith("out.previous-")]
    assert _tree(aside) == {"a.txt": "run 1", "plots/p.png": "1", "comparison.md": "vs run 0"}
    assert read_marker(aside) == first
    _write_run(out, {"a.txt": "run 3"})
    aside = [p for p in tmp_path.iterdir() if p.name.startswith("out.previous-")]
    assert [_tree(p) for p in aside] == [{"a.txt": "run 2"}]  # keep_previous=1
    _write_run(out, {"a.txt": "run 4"}, keep_previous=0)
    assert _tree(out) == {"a.txt": "run 4"} and _siblings(out) == []


def test_a_femcal_folder_with_a_file_added_by_the_user_is_refused(tmp_path):
    out = tmp_path / "out"
    _write_run(out, {"parameters.csv": "run 1"})
    (out / "keep_me.txt").write_text("mine")
    with pytest.raises(
        OutputFolderError,
        match=r"holds the outputs of an earlier femcal run \(test, finished .*\) and files that "
        r"run did not write: keep_me\.txt\. femcal moves its own earlier outputs aside, but "
        r"never moves or deletes your files",
    ):
        _write_run(out, {"parameters.csv": "run 2"})
    assert _tree(out) == {"parameters.csv": "run 1", "keep_me.txt": "mine"}
    assert _siblings(out) == []


def test_a_failure_inside_leaves_nothing_at_the_destination(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError, match="plotting failed"):
        with staged_output(out, command="test") as stage:
            (stage.path / "parameters.csv").write_text("half a run")
            raise RuntimeError("plotting failed")
    assert not out.exists() and _siblings(out) == []
    # Over an earlier run: that run stays as it was.
    _write_run(out, {"parameters.csv": "complete"})
    with pytest.raises(KeyboardInterrupt):
        with staged_output(out, command="test") as stage:
            (stage.path / "parameters.csv").write_text("half a run")
            raise KeyboardInterrupt
    assert _tree(out) == {"parameters.csv": "complete"} and _siblings(out) == []


def test_a_run_waiting_for_the_lock_is_refused_after_its_timeout_and_keeps_its_outputs(
    tmp_path,
):
    out = tmp_path / "out"
    with _locked(out, None):  # another run is in the middle of its final move
        with pytest.raises(
            OutputFolderError,
            match=r"Another femcal run is moving its outputs into .*out .*This run's outputs "
            r"are complete in .*out\.unplaced-",
        ):
            _write_run(out, {"a.txt": "mine"}, lock_timeout=0)
    assert not out.exists()
    (kept,) = [p for p in tmp_path.iterdir() if p.name.startswith("out.unplaced-")]
    assert _tree(kept) == {"a.txt": "mine"} and read_marker(kept)["status"] == "complete"


def test_write_text_atomic_replaces_whole(tmp_path):
    path = tmp_path / "reports" / "diagnose.json"
    write_text_atomic(path, json.dumps({"n": 1}))
    write_text_atomic(path, json.dumps({"n": 2}))
    assert json.loads(path.read_text()) == {"n": 2}
    assert sorted(p.name for p in path.parent.iterdir()) == ["diagnose.json"]


# --------------------------------------------------------------------------- processes
def test_a_killed_run_leaves_nothing_partial_and_the_next_run_succeeds(tmp_path):
    out = tmp_path / "out"
    proc = _child(tmp_path, out, "killed")
    try:
        _wait_for(tmp_path / "sync" / "ready-killed", proc)
    finally:
        os.kill(proc.pid, signal.SIGKILL)  # killed while writing (it never gets "go")
        proc.communicate()
    assert not out.exists()  # nothing that looks like a finished run
    (partial,) = [p for p in tmp_path.iterdir() if p.name.startswith("out.partial-")]
    assert read_marker(partial)["status"] == "running"
    _write_run(out, {"parameters.csv": "next"})
    assert _tree(out) == {"parameters.csv": "next"}
    assert not partial.exists()  # the stale staging folder of the dead process is gone


def test_a_staging_folder_of_a_live_process_is_left_alone(tmp_path):
    out = tmp_path / "out"
    proc = _child(tmp_path, out, "alive", n=1)
    try:
        _wait_for(tmp_path / "sync" / "ready-alive", proc)
        assert remove_stale_partials(out) == []
        _write_run(out, {"parameters.csv": "other"})  # another run meanwhile: fine
        (tmp_path / "sync" / "go-alive").write_text("")
        _wait_for(tmp_path / "sync" / "done-alive", proc)
        proc.communicate(timeout=60)
    finally:
        _stop(proc)
    assert proc.returncode == 0
    assert _tree(out) == {"parameters.csv": "alive", "plots/alive-0.txt": "alive"}


@pytest.mark.parametrize("order", [("a", "b"), ("b", "a")])
def test_two_runs_into_one_out_never_mix(tmp_path, order):
    out = tmp_path / "out"
    procs = {tag: _child(tmp_path, out, tag, n=30) for tag in ("a", "b")}
    sync = tmp_path / "sync"
    try:
        for tag, proc in procs.items():  # both have staged all their files
            _wait_for(sync / f"ready-{tag}", proc)
        assert not out.exists()
        first, second = order
        (sync / f"go-{first}").write_text("")
        _wait_for(sync / f"done-{first}", procs[first])
        expected = {f"plots/{first}-{i}.txt": first for i in range(30)}
        assert _tree(out) == {"parameters.csv": first, **expected}
        (sync / f"go-{second}").write_text("")
        _wait_for(sync / f"done-{second}", procs[second])
        for proc in procs.values():
            proc.communicate(timeout=60)
    finally:
        for proc in procs.values():
            _stop(proc)
    assert [p.returncode for p in procs.values()] == [0, 0]
    # The destination holds exactly the later run; the earlier one, whole, beside it.
    tree = _tree(out)
    assert set(tree.values()) == {second} and len(tree) == 31
    assert read_marker(out)["command"] == f"child-{second}"
    assert read_marker(out)["pid"] == procs[second].pid
    (aside,) = [p for p in tmp_path.iterdir() if p.name.startswith("out.previous-")]
    assert set(_tree(aside).values()) == {first} and len(_tree(aside)) == 31
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name or "lock" in p.name]


def test_outputs_of_two_runs_hash_alike_for_dvc(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The marker (times, host, process) is in the project's .dvcignore: DVC hashes the same
    outputs written by two runs alike, so a rebuilt stage output matches its lock."""
    from dvc.repo import Repo

    root = tmp_path / "repo"
    root.mkdir()
    project = Path(__file__).resolve().parents[1]
    (root / ".dvcignore").write_text((project / ".dvcignore").read_text())
    Repo.init(str(root), no_scm=True)
    monkeypatch.chdir(root)
    digests = []
    for _ in range(2):
        with staged_output(root / "out", command="test") as stage:
            (stage.path / "table.csv").write_text("x\n1\n")
        assert read_marker(root / "out")["status"] == "complete"
        with Repo(str(root)) as repo:
            repo.add("out", no_commit=True)
        digests.append((root / "out.dvc").read_text())
        (root / "out.dvc").unlink()
    assert digests[0] == digests[1]
