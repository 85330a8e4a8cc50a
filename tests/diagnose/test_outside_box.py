"""A disc outside the parameter box, told apart from a missing element (femcal.diagnose.outside).

The specimens outside the box are a test fixture only: the synthetic study's own training
curves (its "FE model", ``synth.true_curves``) of the stiffest and the most flexible
configurations, scaled beyond the envelope the surrogate trained on them can produce (RoM times
0.55-0.75 and 1.3-1.6). A scaled curve is not the physics of a disc beyond the box, only a
curve of the disc's shape that no disc in the box reaches; the library's planted-effects
generator cannot make one honestly, as it keeps the disc inside the box. The discs at the edge
of the box are the surrogate's own curves of configurations with three stiffness parameters
near a bound, with a facet that engages after a gap added (a linear spring, not femcal's law).
"""

from __future__ import annotations

import dataclasses
import json
import pickle
from collections.abc import Mapping

import numpy as np
import pytest
import torch

from femcal.calibration import SurrogateCurveModel
from femcal.diagnose import OUTSIDE_BOX, UNEXPLAINED, diagnose, search
from femcal.diagnose.outside import (
    FLAT_DISC,
    FLAT_ELEMENT,
    REMEDY,
    cohort_note,
    discrepancy_stand_in,
    flatness,
    split_probabilities,
)
from femcal.diagnose.report import write_diagnosis
from femcal.effects.planted import fe_rotation
from femcal.schema import LOAD_CASES
from femcal.stages.diagnose import describe
from femcal.surrogates.nn import NeuralSurrogate

from synth import study_space, tidy_table, true_curves

NOISE = 0.02
MOMENTS = np.arange(1.0, 5.01, 0.5)
EXT, AR = LOAD_CASES.index("Extension"), LOAD_CASES.index("AxialRotation")
STIFFER = (0.55, 0.65, 0.7, 0.75)
SOFTER = (1.3, 1.4, 1.5, 1.6)
BUILT_IN = ("facet_contact", "ligament_tension", "neutral_zone")


def _with_facet(rom: np.ndarray) -> np.ndarray:
    """Curves (4, m) with a linear facet spring after a 1.5 deg gap in extension and axial
    rotation: ``M = M_disc(phi) + 1.2 (phi - 1.5)_+`` solved for the disc's share."""
    applied = np.broadcast_to(MOMENTS, (4, len(MOMENTS)))
    lo, hi = np.log(applied * 1e-3), np.log(applied).copy()
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        md = np.exp(mid)
        g = md + 1.2 * np.clip(fe_rotation(MOMENTS, rom, md) - 1.5, 0, None) - applied
        hi, lo = np.where(g > 0, mid, hi), np.where(g > 0, lo, mid)
    out = fe_rotation(MOMENTS, rom, applied).copy()
    out[[EXT, AR]] = fe_rotation(MOMENTS, rom, np.exp(0.5 * (lo + hi)))[[EXT, AR]]
    return out


def _plain(x):
    """``x`` with its arrays as bytes and its objects without data of their own (models,
    surrogates) as their identity: equal pickles mean equal contents."""
    if isinstance(x, torch.Tensor):
        x = x.detach().numpy()
    if isinstance(x, np.ndarray):
        return ("array", x.tobytes(), x.shape, str(x.dtype))
    if isinstance(x, Mapping):
        return ("map", tuple((_plain(k), _plain(v)) for k, v in x.items()))
    if isinstance(x, (list, tuple)):
        return (type(x).__name__, tuple(_plain(v) for v in x))
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        fields = dataclasses.fields(x)
        return (type(x).__name__, tuple((f.name, _plain(getattr(x, f.name))) for f in fields))
    if isinstance(x, (str, int, float, bool, type(None), np.generic)):
        return x
    return ("object", type(x).__qualname__, id(x))


def _snapshot(state, decision) -> tuple[bytes, bytes]:
    """The state's contents (but its surrogate and its cache of built models) and the
    decision's, as bytes."""
    kept = {
        f.name: getattr(state, f.name)
        for f in dataclasses.fields(state)
        if f.name not in ("base", "_models", "rng")
    }
    kept["rng"] = state.rng.bit_generator.state
    return pickle.dumps(_plain(kept)), pickle.dumps(_plain(decision))


def _described_by(real, seen: list):
    """``search.assemble_result`` that first notes the decision and afterwards whether the state
    and the decision are as it found them."""

    def describe_and_check(state, decision, **keywords):
        before = _snapshot(state, decision)
        out = real(state, decision, **keywords)
        after = _snapshot(state, decision)
        seen.append((decision, before[0] == after[0], before[1] == after[1]))
        return out

    return describe_and_check


@pytest.fixture(scope="module")
def box_run():
    table = tidy_table(48, seed=3)
    surrogate = NeuralSurrogate(
        study_space(), hidden=(32, 32), max_epochs=40, patience=40, batch_size=16, seed=0
    ).fit(table, table["rom_deg"].to_numpy())
    base = SurrogateCurveModel(surrogate, MOMENTS)
    x = table.groupby("config_id")[list(study_space().names)].first().to_numpy()
    fe = true_curves(x, moments=MOMENTS)  # the training curves, (48, 4, m)
    order = np.argsort(fe.reshape(len(fe), -1).mean(axis=1))  # stiffest first
    curves = [fe[k] * c for k, c in zip(order[:4], STIFFER)]
    curves += [fe[k] * c for k, c in zip(order[::-1][:4], SOFTER)]
    kinds = [f"stiffer x{c}" for c in STIFFER] + [f"softer x{c}" for c in SOFTER]
    # Discs at the edge of the box: C10Annulus, K1Annulus and FiberAngle near a bound.
    space = study_space()
    unit = np.full((3, space.dim), 0.5)
    unit[:, [2, 3, 10]] = [[0.98, 0.98, 0.98], [0.02, 0.02, 0.02], [0.98, 0.02, 0.98]]
    edge = base.predict(space.from_unit(unit))
    curves += [_with_facet(r) for r in edge]
    kinds += [f"edge {k} + facet" for k in range(3)]
    rng = np.random.default_rng(21)
    rom = np.stack(curves) + rng.normal(0, NOISE, (len(curves), 4, len(MOMENTS)))
    seen: list = []
    with pytest.MonkeyPatch.context() as patch:
        # 11 specimens, fewer than two workers' MIN_ROWS each: described in this process
        patch.setattr(search, "assemble_result", _described_by(search.assemble_result, seen))
        diag = diagnose(base, rom, specimens=kinds, noise_deg=NOISE)
    return rom, kinds, diag, seen


@pytest.fixture(scope="module")
def box_world(box_run):
    return box_run[:3]


def _outside(box_world):
    _, kinds, diag = box_world
    return [s for s, k in zip(diag.specimens, kinds) if not k.startswith("edge")]


def test_a_disc_outside_the_box_is_named_with_its_side_and_remedy(box_world):
    got = _outside(box_world)
    named = [s for s in got if OUTSIDE_BOX in s.verdict.split("+")]
    # 8 of 8 when the thresholds were set; at least 7, as the issue asks 75 %.
    assert len(named) >= 7, [s.verdict for s in got]
    for s in named:
        box = s.outside_box
        assert box["named"] and box["probability"] >= 0.5
        assert box["side"] == s.specimen.split()[0], (s.specimen, box["side"])
        assert box["load_cases"] and set(box["load_cases"]) <= set(LOAD_CASES)
        assert box["on_bounds"] and {b["bound"] for b in box["on_bounds"]} <= {"lower", "upper"}
        assert box["remedy"] == REMEDY and "dvc repro fe/dvc.yaml" in box["summary"]
        assert "fe.bounds" in box["summary"] and box["side"] in box["summary"]
        assert s.to_dict()["outside_box"]["verdict"] == s.verdict


def test_no_built_in_effect_keeps_a_confident_inclusion_outside_the_box(box_world):
    for s in _outside(box_world):
        inclusion = s.probabilities["inclusion"]
        assert all(inclusion.get(e, 0.0) < 0.9 for e in BUILT_IN), (s.verdict, inclusion)
        # the shared-out probabilities still sum to one, the box's among them
        assert sum(s.probabilities["models"].values()) == pytest.approx(1.0, abs=2e-3)
        assert s.probabilities["outside_box"] == pytest.approx(
            sum(p for k, p in s.probabilities["models"].items() if OUTSIDE_BOX in k), abs=2e-3
        )


def test_an_element_that_engages_on_a_disc_at_the_edge_is_still_named(box_world):
    _, kinds, diag = box_world
    edge = [s for s, k in zip(diag.specimens, kinds) if k.startswith("edge")]
    for s in edge:
        assert "facet_contact" in s.effects, (s.specimen, s.verdict)
        assert OUTSIDE_BOX not in s.verdict, (s.specimen, s.verdict)
        assert s.probabilities["inclusion"]["facet_contact"] >= 0.9
        if s.outside_box is not None:  # looked, and the facet engages: no stand-in
            assert s.outside_box["stand_ins"]
            facets = [v for k, v in s.outside_box["stand_ins"].items() if "facet" in k]
            assert all(v["stand_in"] < 0.5 for v in facets), s.outside_box["stand_ins"]


def test_the_outputs_carry_the_verdict_like_unexplained(box_world, tmp_path):
    rom, _, diag = box_world
    # the stiffer four: one keeps an effect and drops a stand-in (only the disc alone drawn)
    summary = write_diagnosis(diag, rom, tmp_path, plots=True, max_plots=4)
    assert len(list((tmp_path / "plots").glob("*.png"))) == 4
    assert summary["effects"].get(OUTSIDE_BOX, 0) >= 7
    assert OUTSIDE_BOX not in summary["found_effects"]
    saved = json.loads((tmp_path / "diagnosis.json").read_text())
    assert any(s["outside_box"] and s["outside_box"]["named"] for s in saved)
    table = (tmp_path / "summary.md").read_text()
    assert "| outside_box |" in table and "Outside the box: a disc stiffer" in table
    figures = {
        "diagnosis": diag,
        "n_specimens": len(diag.specimens),
        "user_effects": [],
        "user_effect_paths": [],
        "out_dir": str(tmp_path),
    }
    (line,) = [x for x in describe(figures) if x.startswith("outside the box:")]
    assert "stiffer" in line and "softer" in line and "dvc repro fe/dvc.yaml" in line


def test_the_description_reads_the_decision_and_changes_neither_it_nor_the_state(box_run):
    _, _, diag, seen = box_run
    ((decision, state_kept, decision_kept),) = seen  # one group: one description
    assert state_kept and decision_kept
    # the verdicts, the box's among them, are the decision's, as decided
    assert [s.verdict for s in diag.specimens] == [d.verdict for d in decision.specimens]
    assert any(OUTSIDE_BOX in d.verdict.split("+") for d in decision.specimens)
    with pytest.raises(dataclasses.FrozenInstanceError):
        decision.specimens[0].verdict = "none"
    with pytest.raises(TypeError):
        decision.finals[decision.specimens[0].chosen] = ()


# ------------------------------------------------------------------ the pieces, no surrogate
def test_a_law_that_engages_is_not_flat_and_one_from_zero_is():
    grid = np.geomspace(0.25, 5.0, 40)
    window = np.ones((2, grid.size), dtype=bool)
    gap = np.clip(grid - 1.5, 0, None) / grid  # a share that is 0 until the gap closes
    scaled = np.full(grid.size, 0.3)  # a stiffer disc: the same share at every moment
    flat = flatness(np.stack([gap, scaled]), window)
    assert flat[0] <= FLAT_ELEMENT < FLAT_DISC <= flat[1]
    nothing = flatness(np.zeros((1, grid.size)), window[:1])
    assert np.isnan(nothing[0])  # an effect that does not act there is not read


def test_a_discrepancy_of_one_sign_and_share_in_every_load_case_is_a_disc():
    curve = np.tile(np.linspace(2.0, 6.0, 9), (4, 1))
    assert discrepancy_stand_in(-0.3 * curve, curve, "stiffer")["stand_in"] == 1.0
    assert discrepancy_stand_in(-0.3 * curve, curve, "softer")["stand_in"] == 0.0
    growing = curve * np.linspace(0.0, 0.5, 9) ** 4  # a softening from a moment on
    assert discrepancy_stand_in(growing, curve, "softer")["stand_in"] == 0.0


def test_the_probability_is_shared_between_a_model_and_the_box():
    probabilities = {
        "models": {"facet_contact+ligament_tension": 0.8, "facet_contact": 0.2},
        "inclusion": {"facet_contact": 1.0, "ligament_tension": 0.8},
        "outside_library": 0.0,
    }
    parts = {
        "facet_contact+ligament_tension": [("facet_contact", 0.0), ("ligament_tension", 1.0)],
        "facet_contact": [("facet_contact", 0.5)],
    }
    p = split_probabilities(probabilities, parts)
    assert p["models"] == {"facet_contact+outside_box": 0.8, "facet_contact": 0.1, OUTSIDE_BOX: 0.1}
    assert p["inclusion"] == {"facet_contact": 0.9, "ligament_tension": 0.0}
    assert p["outside_box"] == pytest.approx(0.9) and p["most_probable"].endswith(OUTSIDE_BOX)


def test_the_printed_line_counts_the_sides_and_names_the_bounds():
    reading = {
        "side": "stiffer",
        "on_bounds": [{"parameter": "C10Annulus", "bound": "upper", "value": 0.455}],
    }
    line = cohort_note([reading, dict(reading, side="softer", on_bounds=[])])
    assert line.startswith("outside the box: 2 specimens (1 stiffer, 1 softer")
    assert "C10Annulus (upper 0.455)" in line and "dvc repro fe/dvc.yaml" in line
    assert cohort_note([]) == ""


def test_a_flat_effect_is_shared_with_something_outside_the_library():
    probabilities = {
        "models": {"facet_contact+ligament_tension": 0.8, "facet_contact": 0.2},
        "inclusion": {"facet_contact": 1.0, "ligament_tension": 0.8},
        "outside_library": 0.0,
    }
    parts = {"facet_contact+ligament_tension": [("facet_contact", 0.0), ("ligament_tension", 0.5)]}
    p = split_probabilities(probabilities, parts, alternative=UNEXPLAINED)
    assert p["models"] == {
        "facet_contact+ligament_tension": 0.4,
        f"facet_contact+{UNEXPLAINED}": 0.4,
        "facet_contact": 0.2,
    }
    assert p["inclusion"] == {"facet_contact": 1.0, "ligament_tension": 0.4}
    assert p["outside_library"] == pytest.approx(0.4) and OUTSIDE_BOX not in p
