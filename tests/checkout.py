"""Copy the repository's working tree (tracked and untracked, not ignored) for pipeline tests."""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def copy_working_tree(dest: Path, *, skip: Callable[[str], bool] = lambda rel: False) -> Path:
    """Copy every file ``git ls-files`` lists (cached and untracked, not ignored) into ``dest``.

    ``skip(relative_path)`` leaves a file out. Returns ``dest``.
    """
    files = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split("\0")
    for rel in filter(None, files):
        src = REPO / rel
        if src.is_file() and not skip(rel):
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)
    return dest
