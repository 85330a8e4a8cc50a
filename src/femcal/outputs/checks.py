"""What is at an output folder before anything is written there (femcal's marker, the user's
files, a file where a folder should be), and atomic writes of single files."""

from __future__ import annotations

import json
import os
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from femcal.errors import OutputFolderError

#: The marker file of a folder femcal wrote (inside the folder).
MARKER = ".femcal-run.json"


#: Files operating systems drop into folders on their own: never counted as the user's.
SYSTEM_FILES = frozenset({".DS_Store", "Thumbs.db", "desktop.ini"})


#: Foreign files named in a message (the rest are counted).
_SHOWN = 5


def output_files(folder: Path) -> list[str]:
    """Every file under ``folder`` (relative POSIX paths, sorted), the marker excluded."""
    out = []
    for root, dirs, names in os.walk(folder):
        rel = Path(root).relative_to(folder)
        # A symbolic link to a folder is listed as a file (os.walk does not follow it).
        names = names + [d for d in dirs if (Path(root) / d).is_symlink()]
        for name in names:
            path = (rel / name).as_posix()
            if path != MARKER:
                out.append(path)
    return sorted(out)


def write_json_atomic(path: Path, data: Mapping[str, Any]) -> None:
    """Write ``data`` as indented JSON to ``path`` (:func:`write_text_atomic`)."""
    write_text_atomic(path, json.dumps(data, indent=2, default=str) + "\n")


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary file beside it and one rename.

    A reader sees the old content or the new one, never a part; concurrent writers leave one
    complete version. The parent folder is created when missing.

    Parameters
    ----------
    path : str or Path
        The file to write (replaced if it exists).
    text : str
        Its new content.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def read_marker(folder: str | Path) -> dict[str, Any] | None:
    """The marker of a folder femcal wrote, or None (no marker, or not a valid one).

    Parameters
    ----------
    folder : str or Path
        A folder (or a path that is not one: None).
    """
    try:
        data = json.loads((Path(folder) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or "femcal_run" not in data:
        return None
    return data


@dataclass
class Found:
    """What is at a destination: kind in {"absent", "file", "empty", "femcal", "foreign"}."""

    kind: str
    marker: dict[str, Any] | None = None
    foreign: list[str] = field(default_factory=list)


def inspect_outputs(path: Path) -> Found:
    """What is at the output folder ``path``: nothing, a file, an empty folder, femcal's
    outputs (with its run marker), or a folder holding files femcal did not write.

    Returns
    -------
    Found
        Its ``kind``, the run marker if any, and the files femcal did not write.
    """
    if not path.exists() and not path.is_symlink():
        return Found("absent")
    if not path.is_dir():
        return Found("file")
    marker = read_marker(path)
    present = [f for f in output_files(path) if Path(f).name not in SYSTEM_FILES]
    if marker is None:
        if (path / MARKER).exists():
            return Found("foreign", None, [MARKER, *present])
        return Found("empty") if not present else Found("foreign", None, present)
    listed = set(marker.get("files") or [])
    foreign = [f for f in present if f not in listed]
    return Found("femcal", marker) if not foreign else Found("foreign", marker, foreign)


def _describe(found: Found) -> str:
    shown = ", ".join(found.foreign[:_SHOWN])
    more = len(found.foreign) - _SHOWN
    return shown + (f" and {more} more" if more > 0 else "")


def refusal(path: Path, found: Found, *, label: str) -> OutputFolderError:
    """The error that refuses to write to ``path``, given what is there (:func:`inspect_outputs`).

    Parameters
    ----------
    path : Path
        The output folder.
    found : Found
        What is there: a file, or a folder holding files femcal did not write.
    label : str
        How the message names the folder, for example ``"output folder"``.

    Returns
    -------
    OutputFolderError
        Says what is in the way and how to make room.
    """
    if found.kind == "file":
        return OutputFolderError(
            f"{label} {path} is a file, not a folder; femcal writes a folder of outputs there "
            "and never overwrites a file. Give a folder path (new, empty, or one of femcal's "
            "earlier output folders)."
        )
    if found.marker is not None:
        run = found.marker
        return OutputFolderError(
            f"{label} {path} holds the outputs of an earlier femcal run ({run.get('command')}, "
            f"finished {run.get('finished') or 'never'}) and files that run did not write: "
            f"{_describe(found)}. femcal moves its own earlier outputs aside, but never moves "
            f"or deletes your files: move them out of {path}, or give another output folder."
        )
    return OutputFolderError(
        f"{label} {path} already holds files femcal did not write: {_describe(found)} (no "
        f"{MARKER} marker). femcal never overwrites, moves or deletes them. Give a new or "
        f"empty output folder, or move these files out of {path} (an output folder of a "
        "femcal older than the marker: delete it or move it away)."
    )


def check_destination(out: str | Path, *, label: str = "output folder") -> Path:
    """Check, without writing anything, that ``out`` can receive a femcal run's outputs.

    Cheap (no heavy import): call it before loading models or data, so that a bad output
    folder is the first error, not the last.

    Parameters
    ----------
    out : str or Path
        The output folder.
    label : str
        How the folder is named in messages (e.g. ``"--out"``).

    Returns
    -------
    Path
        The destination (a symbolic link to a folder is followed).

    Raises
    ------
    OutputFolderError
        ``out`` is a file; a folder holding files femcal did not write; or it cannot be
        created (a parent is a file, or not writable).
    """
    path = Path(out)
    if path.is_symlink() and path.is_dir():
        path = path.resolve()
    found = inspect_outputs(path)
    if found.kind in ("file", "foreign"):
        raise refusal(path, found, label=label)
    parent = path.parent if str(path.parent) else Path(".")
    _check_parent(parent, path, label=label)
    return path


def check_file_destination(path: str | Path, *, label: str = "file") -> Path:
    """Check that the file ``path`` can be written (its folder exists or can be created).

    Parameters
    ----------
    path : str or Path
        A file to be (re)written, e.g. a DVC metrics file.
    label : str
        How it is named in messages (e.g. ``"--metrics-file"``).

    Raises
    ------
    OutputFolderError
        ``path`` is a folder, or its folder cannot be created or written.
    """
    path = Path(path)
    if path.is_dir():
        raise OutputFolderError(
            f"{label} {path} is a folder; give the path of a file, e.g. {path / 'metrics.json'}."
        )
    _check_parent(path.parent if str(path.parent) else Path("."), path, label=label)
    return path


def _check_parent(parent: Path, path: Path, *, label: str) -> None:
    probe = parent
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise OutputFolderError(
            f"{label} {path} cannot be created: {probe} is a file, not a folder. Give a path "
            "whose parent folders are folders."
        )
    if not os.access(probe, os.W_OK | os.X_OK):
        raise OutputFolderError(
            f"{label} {path} cannot be created: the folder {probe} is not writable by this "
            "user. Give a path in a folder you can write to, or change its permissions."
        )
