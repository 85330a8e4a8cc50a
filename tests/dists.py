"""Installed distributions for the plugin tests: a dist-info folder with an
``entry_points.txt`` and its modules on a ``sys.path`` entry, found by
:func:`importlib.metadata.entry_points` as an installed package would be."""

from __future__ import annotations

import importlib
import textwrap
from pathlib import Path


def write(path: Path, text: str) -> Path:
    """``text`` (dedented) into ``path``, its folders made."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))
    return path


def install(
    site: Path,
    entry_points: str,
    modules: dict[str, str],
    *,
    group: str,
    name: str = "regtest-demo",
) -> None:
    """The distribution ``name`` 0.1 on ``site``: ``entry_points`` (lines ``name = target``)
    in ``group``, and ``modules`` (module name -> source) beside it."""
    info = site / f"{name.replace('-', '_')}-0.1.dist-info"
    write(info / "METADATA", f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    write(info / "entry_points.txt", f"[{group}]\n{textwrap.dedent(entry_points)}")
    for module, text in modules.items():
        write(site / f"{module}.py", text)
    importlib.invalidate_caches()
