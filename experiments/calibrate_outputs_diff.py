"""Two ``femcal calibrate`` output folders compared file by file, timings aside.

Every table and text file (``*.csv``, ``*.json``, ``*.md``, the run record ``.femcal-run.json``)
must be byte-identical but for what a run's clock or process writes: the ``seconds`` column of
``metrics.csv``, ``seconds`` in ``summary.json`` and ``summary.md`` (and its "in X s" line),
the run record's times, pid, argv and MLflow run id (its list of files must match). The PNGs
are compared byte for byte and reported (``summary.png``'s title holds the seconds).

Usage::

    .venv/bin/python -m experiments.calibrate_outputs_diff BEFORE_DIR AFTER_DIR

Exit code 1 when a file differs beyond those fields.
"""

from __future__ import annotations

import csv
import io
import json
import re
import sys
from pathlib import Path

TEXT_SUFFIXES = (".csv", ".json", ".md")


def _files(root: Path, suffixes: tuple[str, ...]) -> list[Path]:
    return sorted(
        p.relative_to(root) for p in root.rglob("*") if p.is_file() and p.suffix in suffixes
    )


def without_timings(name: str, text: str) -> str:
    """``text`` of the file ``name`` without the fields a run's clock or process writes."""
    if name == "metrics.csv":
        rows = list(csv.reader(io.StringIO(text)))
        k = rows[0].index("seconds") if rows and "seconds" in rows[0] else None
        return "\n".join(",".join(r if k is None else r[:k] + r[k + 1 :]) for r in rows)
    if name == "summary.json":
        figures = json.loads(text)
        figures.pop("seconds", None)
        return json.dumps(figures, sort_keys=True)
    if name == ".femcal-run.json":
        record = json.loads(text)
        return json.dumps({k: record.get(k) for k in ("command", "status", "files")})
    if name == "summary.md":
        return re.sub(r"\| seconds \| [0-9.e+-]+ \|", "", re.sub(r" in [0-9.]+ s", "", text))
    return text


def compare(before: Path, after: Path) -> tuple[list[str], list[str], list[str]]:
    """(text files compared, those differing beyond timings, PNGs differing byte for byte)."""
    names = _files(before, TEXT_SUFFIXES)
    if names != _files(after, TEXT_SUFFIXES):
        raise SystemExit(
            f"the folders hold different files: {names} / {_files(after, TEXT_SUFFIXES)}"
        )
    differ = [
        str(rel)
        for rel in names
        if without_timings(rel.name, (before / rel).read_text())
        != without_timings(rel.name, (after / rel).read_text())
    ]
    pngs = _files(before, (".png",))
    png_differ = [str(r) for r in pngs if (before / r).read_bytes() != (after / r).read_bytes()]
    return [str(n) for n in names], differ, png_differ


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        raise SystemExit(__doc__)
    names, differ, png_differ = compare(Path(args[0]), Path(args[1]))
    print(
        f"{len(names)} text files compared ({', '.join(names)}); differ beyond timings: "
        f"{', '.join(differ) or 'none'}"
    )
    print(f"PNGs byte-different: {len(png_differ)} ({', '.join(png_differ) or 'none'})")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
