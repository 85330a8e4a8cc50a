"""Two diagnoses of one cohort side by side: which verdicts differ, and by how much the
probabilities moved.

A change meant to make ``femcal diagnose`` faster must leave its verdicts alone. This compares
the ``diagnosis.json`` of two runs on the same measurements, specimen by specimen:

* **verdict fields**: ``verdict``, ``effects``, ``model`` (the forms fitted, split or tied),
  ``load_cases``, the out-of-box reading (``named``, ``verdict``, ``side``, ``load_cases``,
  ``on_bounds``, ``model``) and ``probabilities.unexplained``; each difference is listed;
* **probabilities**: the largest absolute change of any number under ``probabilities`` (each
  model's posterior, each effect's inclusion, ``acts_in``, ``outside_library``) and of the
  out-of-box reading's ``probability``; and the same without the per-model posteriors, which
  move most where two forms of one model are nearly tied.

Run::

    .venv/bin/python -m experiments.diagnosis_diff REF_DIR NEW_DIR [--tolerance 0.02]

(each a folder holding ``diagnosis.json``, or the file itself). Exit status 1 when a verdict
field differs or a probability moved by more than ``--tolerance``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from femcal.errors import InputDataError

#: The fields of a specimen's diagnosis that make its verdict.
VERDICT_FIELDS = ("verdict", "effects", "model", "load_cases")
#: The fields of the out-of-box reading that make its verdict.
BOX_FIELDS = ("named", "verdict", "side", "load_cases", "on_bounds", "model")


def load(path: Path) -> list[dict[str, Any]]:
    """The specimens of a ``diagnosis.json`` (``path``: the file or its folder)."""
    path = Path(path)
    return json.loads((path / "diagnosis.json" if path.is_dir() else path).read_text())


def _numbers(value: Any, prefix: str = "") -> dict[str, float]:
    """Every number under ``value`` by its dotted path (booleans left out)."""
    if isinstance(value, dict):
        out: dict[str, float] = {}
        for key, item in value.items():
            out.update(_numbers(item, f"{prefix}.{key}" if prefix else str(key)))
        return out
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return {prefix: float(value)}
    return {}


def _box(reading: dict | None) -> dict | None:
    return None if not reading else {k: reading.get(k) for k in BOX_FIELDS}


def _probabilities(s: dict[str, Any]) -> dict[str, float]:
    out = _numbers(s.get("probabilities") or {})
    out["outside_box.probability"] = float((s.get("outside_box") or {}).get("probability") or 0)
    return out


def compare(ref: Sequence[dict], new: Sequence[dict]) -> dict[str, Any]:
    """The verdict differences and the largest probability changes of two diagnoses.

    Parameters
    ----------
    ref, new : sequence of dict, length n
        The specimens of two ``diagnosis.json`` of the same cohort, in the same order.

    Returns
    -------
    dict
        ``flips``: one ``{"specimen", "field", "ref", "new"}`` per differing verdict field;
        ``max_change`` and ``max_change_at`` (specimen, path): the largest change of a
        probability; ``max_change_effects`` and ``max_change_effects_at``: the same without
        the per-model posteriors (``probabilities.models``); ``n``: specimens compared.
    """
    names = [s["specimen"] for s in ref]
    if names != [s["specimen"] for s in new]:
        raise InputDataError(
            "diagnosis_diff: the two diagnoses hold different specimens (or another order); "
            f"got {names[:3]}... and {[s['specimen'] for s in new][:3]}...: compare two runs "
            "on the same measurements."
        )
    flips: list[dict[str, Any]] = []
    best = {"all": (0.0, None), "effects": (0.0, None)}
    for a, b in zip(ref, new):
        pairs = {k: (a.get(k), b.get(k)) for k in VERDICT_FIELDS}
        pairs["outside_box"] = (_box(a.get("outside_box")), _box(b.get("outside_box")))
        pairs["unexplained"] = tuple(
            (s.get("probabilities") or {}).get("unexplained") for s in (a, b)
        )
        for field, (x, y) in pairs.items():
            if json.dumps(x, sort_keys=True) != json.dumps(y, sort_keys=True):
                flips.append({"specimen": a["specimen"], "field": field, "ref": x, "new": y})
        pa, pb = _probabilities(a), _probabilities(b)
        for key in sorted(set(pa) | set(pb)):
            change = abs(pa.get(key, 0.0) - pb.get(key, 0.0))
            for kind in ("all", "effects"):
                if kind == "effects" and key.startswith("models."):
                    continue
                if change > best[kind][0]:
                    best[kind] = (change, (a["specimen"], key))
    return {
        "n": len(names),
        "flips": flips,
        "max_change": best["all"][0],
        "max_change_at": best["all"][1],
        "max_change_effects": best["effects"][0],
        "max_change_effects_at": best["effects"][1],
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("ref", type=Path, help="reference diagnosis (folder or diagnosis.json)")
    parser.add_argument("new", type=Path, help="diagnosis to compare (folder or diagnosis.json)")
    parser.add_argument(
        "--tolerance", type=float, default=0.02, help="largest probability change accepted"
    )
    args = parser.parse_args(argv)
    out = compare(load(args.ref), load(args.new))
    print(
        f"{out['n']} specimens: {len(out['flips'])} verdict fields differ; probabilities moved "
        f"by at most {out['max_change']:.4f} (at {out['max_change_at']}), "
        f"{out['max_change_effects']:.4f} without the per-model posteriors "
        f"(at {out['max_change_effects_at']})"
    )
    for flip in out["flips"]:
        ref = json.dumps(flip["ref"], sort_keys=True)
        new = json.dumps(flip["new"], sort_keys=True)
        print(f"  {flip['specimen']} {flip['field']}: {ref[:120]} -> {new[:120]}")
    return int(bool(out["flips"]) or out["max_change"] > args.tolerance)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
