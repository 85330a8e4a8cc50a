"""experiments.inclusion_scores: inclusion probabilities scored against a cohort's answers."""

from __future__ import annotations

import pytest

from experiments.inclusion_scores import answers, scores


def test_forms_are_summed_and_confident_answers_counted(tmp_path):
    path = tmp_path / "answers.csv"
    path.write_text("specimen,effects\n0,facet_contact ligament_tension\n1,\n")
    truth = answers(path)
    assert truth == {"0": {"facet_contact", "ligament_tension"}, "1": set()}
    diagnosis = [
        {"specimen": 0, "probabilities": {"inclusion": {"facet_contact:split": 1.0}}},
        {"specimen": "1", "probabilities": {"inclusion": {"neutral_zone@Flexion": 0.95}}},
    ]
    got = scores(diagnosis, truth)
    assert got["pairs"] == 6
    assert got["present_confident"] == "1/2" and got["absent_confident"] == "1/4"
    # misses: the ligament at 0 (clipped to 0.001) and the neutral zone at 0.95
    assert got["brier"] == pytest.approx((0.999**2 + 0.95**2 + 4e-6) / 6, abs=1e-4)


def test_answers_without_the_columns_are_refused(tmp_path):
    path = tmp_path / "answers.csv"
    path.write_text("name,truth\n0,none\n")
    with pytest.raises(SystemExit, match="needs the columns specimen and effects"):
        answers(path)
