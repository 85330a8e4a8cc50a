"""Stage ``fetch``: the study's FE data from its pinned address or a mirror, SHA-256 checked."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from femcal.stages.common import path_setting


@dataclass(frozen=True)
class FetchSettings:
    """Where the files go (``data.raw_dir`` or ``--out``) and whether to show progress."""

    out: Path
    progress: bool = False

    @classmethod
    def from_params(cls, params: Mapping[str, Any], args: Mapping[str, Any]) -> FetchSettings:
        out = Path(args["out"]) if args.get("out") else path_setting(params, "data", "raw_dir")
        return cls(out=out, progress=bool(args.get("progress")))


def run(settings: FetchSettings) -> dict[str, Any]:
    """Fetch (or copy from ``FEMCAL_DATA_MIRROR``) every file; returns what was fetched."""
    from femcal.fetch import fetch_dataset, mirror_from_env

    mirror = mirror_from_env()
    paths = fetch_dataset(settings.out, mirror=mirror, progress=settings.progress)
    return {"n_files": len(paths), "mirror": str(mirror) if mirror else None, "out": settings.out}


def describe(figures: Mapping[str, Any]) -> list[str]:
    src = (
        f"mirror {figures['mirror']}" if figures["mirror"] else "the study's pinned public address"
    )
    return [
        f"fetched {figures['n_files']} files from {src} into {figures['out']} (SHA-256 verified)"
    ]
