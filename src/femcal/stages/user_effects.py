"""The user's effect files (``effects.modules``, ``--effects-module``), loaded before a run."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from femcal.config import settings_of


def effect_modules(params: Mapping[str, Any], given: Sequence[str] | None) -> tuple[Path, ...]:
    """The user's effect files: ``effects.modules`` in params.yaml (relative to its folder, the
    project root), then every ``--effects-module`` (relative to the working directory)."""
    where = params.get("_path", "params.yaml")
    effects = settings_of(params).effects
    modules = effects.modules if effects is not None else ()
    root = Path(where).parent
    return tuple([root / m for m in modules] + [Path(m) for m in given or []])


def load_user_effects(paths: Sequence[Path]) -> list[str]:
    """Import the user's effect files before anything uses the effect registry; the names."""
    if not paths:
        return []
    from femcal.effects import load_effect_modules

    return load_effect_modules(list(paths))


def describe_user_effects(names: Sequence[str], paths: Sequence[Path]) -> list[str]:
    """The line that says which user effects were loaded (none: no line)."""
    if not names:
        return []
    return [f"user effects: {', '.join(names)} (from {', '.join(str(p) for p in paths)})"]
