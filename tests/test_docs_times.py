"""The pipeline's wall time the docs give is the one docs/benchmarks/index.md measured."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: How far (minutes) a rounded figure in the docs may be from the measured one.
TOLERANCE_MIN = 2.0
#: A duration in words near the pipeline or `make repro`.
_STATED = re.compile(
    r"(?:pipeline|make repro|dvc repro)[^.]{0,80}?about (half an hour|an hour|\d+(?:\.\d+)? "
    r"minutes?|\d+ min)",
    re.IGNORECASE | re.DOTALL,
)


def _minutes(text: str) -> float:
    words = {"half an hour": 30.0, "an hour": 60.0}
    return words.get(text.lower()) or float(text.split()[0])


def _measured() -> float:
    page = (ROOT / "docs" / "benchmarks" / "index.md").read_text()
    section = page.split("## The whole pipeline's wall time", 1)[1]
    m = re.search(r"(\d+) min (\d+) s in all", section)
    assert m, "docs/benchmarks/index.md gives no whole-pipeline wall time"
    return int(m[1]) + int(m[2]) / 60


def test_every_page_gives_the_measured_pipeline_time():
    measured = _measured()
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    stated = [
        (page.relative_to(ROOT).as_posix(), m[1])
        for page in pages
        if "benchmarks" not in page.parts
        for m in _STATED.finditer(page.read_text())
    ]
    assert stated, "no page states the pipeline's time"
    wrong = [(p, text) for p, text in stated if abs(_minutes(text) - measured) > TOLERANCE_MIN]
    assert not wrong, f"measured {measured:.1f} min (docs/benchmarks); the docs say {wrong}"
