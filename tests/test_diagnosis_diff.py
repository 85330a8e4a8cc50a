"""experiments/diagnosis_diff.py: verdict differences and probability changes of two
diagnoses, on hand-made diagnosis.json records (no model, no study data)."""

from __future__ import annotations

import copy
import json

import pytest

from experiments import diagnosis_diff as dd
from femcal.errors import InputDataError


def _specimen(name: str, effects: list[str], p: float) -> dict:
    return {
        "specimen": name,
        "verdict": "+".join(effects) or "none",
        "effects": effects,
        "model": effects,
        "load_cases": {e: ["Extension"] for e in effects},
        "outside_box": None,
        "probabilities": {
            "unexplained": False,
            "models": {"+".join(effects) or "none": p, "none": 1 - p},
            "inclusion": {e: p for e in effects},
        },
    }


def test_identical_diagnoses_differ_nowhere(tmp_path):
    ref = [_specimen("A", ["facet_contact"], 0.9), _specimen("B", [], 0.8)]
    (tmp_path / "diagnosis.json").write_text(json.dumps(ref))
    assert dd.main([str(tmp_path), str(tmp_path / "diagnosis.json")]) == 0
    out = dd.compare(ref, copy.deepcopy(ref))
    assert out["flips"] == [] and out["max_change"] == 0.0 and out["n"] == 2


def test_a_changed_model_form_and_moved_probabilities_are_reported(tmp_path, capsys):
    ref = [_specimen("A", ["facet_contact"], 0.9), _specimen("B", [], 0.8)]
    new = copy.deepcopy(ref)
    new[0]["model"] = ["facet_contact:split"]
    new[0]["probabilities"]["models"]["none"] = 0.4  # 0.1 -> 0.4
    new[1]["outside_box"] = {"named": True, "side": "stiffer", "probability": 0.7}
    out = dd.compare(ref, new)
    assert [(f["specimen"], f["field"]) for f in out["flips"]] == [
        ("A", "model"),
        ("B", "outside_box"),
    ]
    assert out["max_change"] == pytest.approx(0.7)
    assert out["max_change_at"] == ("B", "outside_box.probability")
    # without the per-model posteriors the 0.3 of A's "none" does not count
    assert out["max_change_effects"] == pytest.approx(0.7)
    for folder, records in (("ref", ref), ("new", new)):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "diagnosis.json").write_text(json.dumps(records))
    assert dd.main([str(tmp_path / "ref"), str(tmp_path / "new"), "--tolerance", "1"]) == 1
    assert "A model" in capsys.readouterr().out


def test_small_probability_changes_pass_within_the_tolerance():
    ref = [_specimen("A", ["neutral_zone"], 0.9)]
    new = copy.deepcopy(ref)
    new[0]["probabilities"]["inclusion"]["neutral_zone"] = 0.91
    out = dd.compare(ref, new)
    assert out["flips"] == []
    assert out["max_change_effects"] == pytest.approx(0.01)
    assert out["max_change_effects_at"] == ("A", "inclusion.neutral_zone")


def test_other_specimens_are_refused():
    ref = [_specimen("A", [], 0.9)]
    with pytest.raises(InputDataError, match="different specimens.*same measurements"):
        dd.compare(ref, [_specimen("Z", [], 0.9)])
