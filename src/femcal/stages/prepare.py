"""Stage ``prepare``: one tidy table per split and the parameter space (``data.prepared_dir``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from femcal.paths import setting_path
from femcal.stages.common import path_setting, typed


@dataclass(frozen=True)
class PrepareSettings:
    """The raw study files (``data.source_dir``, else ``data.raw_dir``), the output folder and
    ``data.limit_configs`` (a quick run on the first configurations; ``None`` = all)."""

    raw: Path
    out: Path
    limit_configs: int | None = None

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> PrepareSettings:
        data = typed(params, "data")
        return cls(
            raw=setting_path(params, data.source_dir or data.raw_dir),
            out=path_setting(params, "data", "prepared_dir"),
            limit_configs=data.limit_configs,
        )


def run(settings: PrepareSettings) -> dict[str, Any]:
    """Write the tidy tables; returns ``{"written": {name: path}}``."""
    from femcal.prepare import prepare_dataset

    written = prepare_dataset(settings.raw, settings.out, limit_configs=settings.limit_configs)
    return {"written": dict(written)}


def describe(figures: Mapping[str, Any]) -> list[str]:
    return [f"{name}: {path}" for name, path in figures["written"].items()]
