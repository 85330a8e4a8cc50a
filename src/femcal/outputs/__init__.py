"""All-or-nothing output folders that belong to one run.

A command writes its outputs into a fresh *staging* folder beside the destination (so on the
same file system), ``<out>.partial-<host>-<pid>-<token>``, and moves it into place with one
``rename`` once it is complete. A marker file inside the folder, ``.femcal-run.json``, records
the run: the command and its arguments, start and end time, process id, host, the MLflow run
id when there is one, and every file the run wrote.

What is already at the destination decides what happens (checked before any heavy work by
:func:`check_destination`, and again, under a lock, at the final move):

* nothing, or an empty folder: the outputs move in;
* a folder femcal wrote (its marker lists every file in it): it is moved aside to the sibling
  ``<out>.previous-<end time of that run>``, and the log says so. The newest ``keep_previous``
  (default 1) of these are kept; older ones, femcal's own (recognised by their marker and
  holding nothing else), are removed. ``dvc repro`` removes a stage's outputs before it runs
  the stage, so nothing is moved aside there;
* anything else (a file; a folder without a marker that is not empty; a folder of femcal's to
  which files were added): refused with :class:`~femcal.errors.OutputFolderError`, which names
  the folder, some of the files and the fix. Such a folder is never overwritten, moved or
  deleted.

A run that fails leaves nothing at the destination, and its staging folder is removed. A run
that is killed leaves its staging folder; the next run into the same destination removes it
once its process is gone (same host, process id no longer alive). The final
move-aside-and-rename holds an exclusive ``flock`` on a lock file beside the destination, so
concurrent runs into one destination each stage separately and the destination always holds
exactly one complete run: the last to finish (the earlier one is moved aside). Locks are
POSIX ``flock``; a killed holder releases its lock with its process.

Examples
--------
>>> with staged_output("results", command="calibrate") as stage:  # doctest: +SKIP
...     (stage.path / "parameters.csv").write_text("...")
...     stage.note(mlflow_run_id="abc")
>>> # results/ now holds parameters.csv and .femcal-run.json, or nothing if the block failed
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import socket
import sys
import time
import uuid
from collections.abc import Iterator, Mapping
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from femcal.errors import OutputFolderError
from femcal.outputs.checks import (
    MARKER,
    check_destination,
    check_file_destination,
    inspect_outputs,
    output_files,
    read_marker,
    refusal,
    write_json_atomic,
    write_text_atomic,
)

__all__ = [
    "MARKER",
    "OutputStage",
    "check_destination",
    "check_file_destination",
    "pid_alive",
    "read_marker",
    "remove_stale_partials",
    "staged_output",
    "write_text_atomic",
]

logger = logging.getLogger(__name__)

#: Format version of the marker.
MARKER_VERSION = 1
PARTIAL = ".partial-"
PREVIOUS = ".previous-"
UNPLACED = ".unplaced-"


# --------------------------------------------------------------------------- small helpers
def _now() -> datetime:
    return datetime.now(timezone.utc)


def _stamp(when: str | None) -> str:
    """A sortable file-name stamp (``20260123T104500Z``) of an ISO time, or of now."""
    try:
        t = datetime.fromisoformat(str(when)) if when else _now()
    except ValueError:
        t = _now()
    if t.tzinfo is None:
        t = t.replace(tzinfo=timezone.utc)
    return t.astimezone(timezone.utc).strftime("%Y%m%dT%H%M%SZ")


def _host() -> str:
    return socket.gethostname()


def _safe(text: str) -> str:
    """``text`` usable inside one file name (no separators, no spaces)."""
    return "".join(c if c.isalnum() or c in "._" else "_" for c in text) or "host"


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` of this host is alive (a zombie counts as dead).

    Parameters
    ----------
    pid : int
        A process id.

    Returns
    -------
    bool
        False for a process that does not exist or has exited; True when it runs (also when
        it belongs to another user).
    """
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    try:  # Linux: an exited child that nobody has reaped yet still answers kill(pid, 0)
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    state = stat.rsplit(")", 1)[-1].split()[:1]
    return state not in (["Z"], ["X"])


# --------------------------------------------------------------------------- siblings
def _siblings(dest: Path, infix: str) -> list[Path]:
    prefix = dest.name + infix
    try:
        return sorted(p for p in dest.parent.iterdir() if p.name.startswith(prefix))
    except OSError:
        return []


def remove_stale_partials(dest: str | Path) -> list[Path]:
    """Remove staging folders of ``dest`` left by killed runs of this host.

    A staging folder ``<dest>.partial-<host>-<pid>-<token>`` is stale when its marker (or,
    without one, its name) names this host and a process id that is no longer alive.
    Staging folders of live processes and of other hosts are left alone.

    Returns
    -------
    list of Path
        The folders removed.
    """
    dest = Path(dest)
    removed = []
    for path in _siblings(dest, PARTIAL):
        marker = read_marker(path)
        if marker is not None:
            owner, me = str(marker.get("host")), _host()
            try:
                pid = int(marker.get("pid") or 0)
            except (TypeError, ValueError):
                continue
        else:  # killed before its marker was written: the name tells host and pid
            parts = path.name[len(dest.name + PARTIAL) :].rsplit("-", 2)
            if len(parts) != 3 or not parts[1].isdigit():
                continue
            owner, me, pid = parts[0], _safe(_host()), int(parts[1])
        if owner != me or pid_alive(pid):
            continue
        shutil.rmtree(path, ignore_errors=True)
        if not path.exists():
            removed.append(path)
            logger.info("Removed %s, left by a killed run (process %d).", path, pid)
    return removed


def _move_aside(dest: Path, marker: Mapping[str, Any]) -> Path:
    base = dest.with_name(f"{dest.name}{PREVIOUS}{_stamp(marker.get('finished'))}")
    aside, n = base, 1
    while aside.exists() or aside.is_symlink():
        aside, n = base.with_name(f"{base.name}-{n}"), n + 1
    os.rename(dest, aside)
    return aside


def _prune_previous(dest: Path, keep: int, *, protect: Path | None) -> list[Path]:
    """Remove femcal's own ``<dest>.previous-*`` folders beyond the newest ``keep``."""
    ours = [
        p for p in _siblings(dest, PREVIOUS) if p.is_dir() and inspect_outputs(p).kind == "femcal"
    ]
    ours.sort(key=lambda p: (str((read_marker(p) or {}).get("finished") or ""), p.name))
    removed = []
    for path in ours[: max(0, len(ours) - keep)]:
        if path == protect and keep > 0:
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    return removed


@contextlib.contextmanager
def _locked(dest: Path, timeout: float | None) -> Iterator[None]:
    """An exclusive lock for ``dest``'s final move: ``flock`` on ``.<name>.femcal-lock``.

    The lock file is removed on release; an acquirer checks that the file it locked is still
    the one at the path (else someone released and removed it meanwhile: it tries again).
    """
    import fcntl

    path = dest.with_name(f".{dest.name}.femcal-lock")
    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            if deadline is None:
                fcntl.flock(fd, fcntl.LOCK_EX)
            else:
                while True:
                    try:
                        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                        break
                    except BlockingIOError:
                        if time.monotonic() >= deadline:
                            raise OutputFolderError(
                                f"Another femcal run is moving its outputs into {dest} (it "
                                f"holds {path}); this run did not wait longer than {timeout:g}"
                                " s. Run again when it has finished, or give another folder."
                            ) from None
                        time.sleep(0.05)
            try:
                same = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
        except BaseException:
            os.close(fd)
            raise
        if same:
            break
        os.close(fd)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
        os.close(fd)


# --------------------------------------------------------------------------- the stage
class OutputStage:
    """A staging folder for one run's outputs, moved into place by :meth:`commit`.

    Use it as a context manager, under its name :data:`staged_output`::

        with staged_output(destination, command="calibrate") as stage:
            ...  # write into stage.path

    Entering opens the stage (:meth:`open`). On leaving the block normally the stage is
    committed (unless it was already); on an exception (also ``KeyboardInterrupt``) the
    staging folder is removed and nothing appears at ``destination``.

    Parameters
    ----------
    destination : str or Path
        The output folder the run's files end up in.
    command : str
        What wrote them (e.g. ``"calibrate"``): recorded in the marker.
    keep_previous : int
        How many earlier femcal output folders of this destination to keep beside it as
        ``<destination>.previous-<time>`` (0: the earlier folder is removed once the new one
        is in place).
    lock_timeout : float, optional
        Seconds to wait for another run's final move into the same destination (None: as
        long as it takes; the move itself takes milliseconds).
    label : str
        How the destination is named in messages (e.g. ``"--out"``).
    info : mapping, optional
        Extra entries for the marker (also later through :meth:`note`).

    Attributes
    ----------
    path : Path
        The staging folder: write the outputs here (``None`` before :meth:`open`).
    destination : Path
        Where they go.
    previous : Path or None
        Where the earlier femcal output folder was moved (after :meth:`commit`).

    Raises
    ------
    OutputFolderError
        On entering: ``destination`` is a file or holds files femcal did not write, or cannot
        be created. On leaving: see :meth:`commit`.
    """

    def __init__(
        self,
        destination: str | Path,
        *,
        command: str,
        keep_previous: int = 1,
        lock_timeout: float | None = None,
        label: str = "output folder",
        info: Mapping[str, Any] | None = None,
    ) -> None:
        if int(keep_previous) < 0:
            raise ValueError(f"keep_previous must be >= 0; got {keep_previous!r}.")
        self.destination = Path(destination)
        self.command = str(command)
        self.keep_previous = int(keep_previous)
        self.lock_timeout = lock_timeout
        self.label = label
        self.info: dict[str, Any] = dict(info or {})
        self.path: Path | None = None
        self.previous: Path | None = None
        self.state = "new"
        self._started = _now()
        self._marker: dict[str, Any] | None = None

    # -- life cycle
    def open(self) -> OutputStage:
        """Check the destination, remove stale staging folders, create this run's."""
        self.destination = check_destination(self.destination, label=self.label)
        self.destination.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_partials(self.destination)
        token = uuid.uuid4().hex[:8]
        name = f"{self.destination.name}{PARTIAL}{_safe(_host())}-{os.getpid()}-{token}"
        self.path = self.destination.with_name(name)
        self.path.mkdir()
        self._started = _now()
        self.state = "open"
        write_json_atomic(self.path / MARKER, self._marker_data("running", None))
        return self

    def note(self, **info: Any) -> None:
        """Add entries to the marker (e.g. ``mlflow_run_id``)."""
        self.info.update(info)
        if self._marker is not None:
            self._marker = None  # finalize again at commit

    def finalize(self) -> dict[str, Any]:
        """Write the complete marker (end time, files) into the staging folder; return it.

        Call it before logging the staging folder somewhere (e.g. to MLflow) so that the
        logged marker is the one that moves into place; :meth:`commit` calls it otherwise.
        """
        self._require("open")
        self._marker = self._marker_data("complete", output_files(self.path))
        write_json_atomic(self.path / MARKER, self._marker)
        return dict(self._marker)

    def commit(self) -> Path:
        """Move the staging folder into place (the earlier femcal output moved aside).

        Returns
        -------
        Path
            The destination.

        Raises
        ------
        OutputFolderError
            Files femcal did not write appeared at the destination meanwhile, or another
            run held the lock longer than ``lock_timeout``. This run's complete outputs are
            then kept beside it as ``<destination>.unplaced-<time>`` (named in the message).
        """
        if self.state == "committed":
            return self.destination
        self._require("open")
        if self._marker is None or self._marker.get("files") != output_files(self.path):
            self.finalize()
        dest = self.destination
        try:
            with _locked(dest, self.lock_timeout):
                found = inspect_outputs(dest)
                if found.kind in ("file", "foreign"):
                    raise refusal(dest, found, label=self.label)
                if found.kind == "empty":
                    shutil.rmtree(dest)  # empty but for system files
                elif found.kind == "femcal":
                    self.previous = _move_aside(dest, found.marker or {})
                os.rename(self.path, dest)
                self.state = "committed"
                removed = _prune_previous(dest, self.keep_previous, protect=self.previous)
        except OutputFolderError as exc:
            kept = self._keep_unplaced()
            raise OutputFolderError(f"{exc} This run's outputs are complete in {kept}.") from None
        if self.previous is not None and self.previous in removed:
            self.previous = None
            logger.info("%s: outputs in place; the earlier run's outputs were removed.", dest)
        elif self.previous is not None:
            logger.info(
                "%s: outputs in place; the earlier run's outputs were moved to %s.",
                dest,
                self.previous,
            )
        else:
            logger.info("%s: outputs in place.", dest)
        return dest

    def discard(self) -> None:
        """Remove the staging folder (nothing reaches the destination)."""
        if self.path is not None and self.state == "open":
            shutil.rmtree(self.path, ignore_errors=True)
            self.state = "discarded"

    # -- the context manager
    def __enter__(self) -> OutputStage:
        return self.open()

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        if exc_type is not None:
            self.discard()
            return
        try:
            self.commit()
        except OutputFolderError:
            raise  # the complete outputs were kept beside the destination (named in the message)
        except BaseException:
            self.discard()
            raise

    # -- internals
    def _require(self, state: str) -> None:
        if self.state != state:
            raise RuntimeError(f"The output stage of {self.destination} is {self.state}.")

    def _keep_unplaced(self) -> Path:
        kept = self.destination.with_name(
            f"{self.destination.name}{UNPLACED}{_stamp(None)}-{os.getpid()}"
        )
        os.rename(self.path, kept)
        self.path, self.state = kept, "unplaced"
        return kept

    def _marker_data(self, status: str, files: list[str] | None) -> dict[str, Any]:
        from femcal import __version__

        return {
            "femcal_run": MARKER_VERSION,
            "command": self.command,
            "argv": list(sys.argv[1:]),
            "status": status,
            "started": self._started.isoformat(timespec="milliseconds"),
            "finished": _now().isoformat(timespec="milliseconds") if files is not None else None,
            "pid": os.getpid(),
            "host": _host(),
            "femcal_version": __version__,
            **self.info,
            "files": files if files is not None else [],
        }


#: Stage a run's outputs beside a destination; move them into place on success:
#: ``with staged_output(destination, command=...) as stage`` (see :class:`OutputStage`).
staged_output = OutputStage
