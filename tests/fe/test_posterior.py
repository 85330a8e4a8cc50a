"""Posterior elements of the CalculiX model: settings, deck, and their effect on the real solver.

The CalculiX test runs one configuration (the centre of the study's box, coarse mesh, moments
5 and 10 Nm) as a disc alone, with facets, and with the five ligaments, and checks the
direction of each element's effect on the range of motion (docs/fe-posterior-elements.md).
"""

from __future__ import annotations

import copy
import gzip
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from fe_helpers import requires_ccx

from femcal.errors import ConfigError, FemcalError
from femcal.fe import FEJob
from femcal.fe.calculix import CalculixDisc
from femcal.fe.calculix_settings import (
    LIGAMENT_DEFAULTS,
    LIGAMENTS,
    FacetSettings,
    LigamentSettings,
    PosteriorSettings,
    posterior_settings,
)
from femcal.fe.posterior import facet_normal, ligament_curve, posterior_deck
from femcal.fe.posterior_check import BOX_CENTRE, ratio_table, segment_rom
from femcal.fe.store import settings_hash
from femcal.settings import validate_params

ROOT = Path(__file__).resolve().parents[2]
BOUNDS = {
    "C10Nucleus": (0.03, 0.21),
    "C01Nucleus": (0.0075, 0.0525),
    "C10Annulus": (0.065, 0.455),
    "K1Annulus": (1.0, 50.0),
    "K2Annulus": (10.0, 200.0),
    "Kappa": (0.0, 0.33),
    "K1Circ": (-0.2, 0.0),
    "K2Circ": (-0.2, 0.0),
    "K1Rad": (-0.2, 0.0),
    "K2Rad": (-0.2, 0.0),
    "FiberAngle": (7.5, 52.5),
    "FiberAngleCirc": (0.0, 0.3),
    "FiberAngleRad": (0.0, 0.2),
}
CENTRE = {name: 0.5 * (lo + hi) for name, (lo, hi) in BOUNDS.items()}
#: Two moment levels keep the solver test short; the ratios are read at the last (10 Nm).
LEVELS = (5.0, 10.0)
BOTH = {"facets": {}, "ligaments": list(LIGAMENTS)}


def deck(posterior=None, load_case: str = "Flexion") -> str:
    adapter = CalculixDisc(geometry="coarse", posterior=posterior)
    return adapter.deck(FEJob(0, CENTRE, load_case, LEVELS))[0]


# ----------------------------------------------------------------------------- deck
@pytest.mark.parametrize("off", [None, {}, {"ligaments": []}, {"facets": None}])
def test_deck_of_the_disc_alone_is_unchanged(off):
    assert deck(off) == deck()
    assert "GAPUNI" not in deck(off) and "*RIGID BODY, NSET=TOP," in deck(off)


def test_committed_campaign_decks_and_keys_are_reproduced():
    """The first job of fe/'s committed store: same settings hash and deck hash today."""
    store = ROOT / "fe" / "data" / "campaign" / "runs.jsonl.gz"
    if not store.is_file():
        pytest.skip("fe/data/campaign/runs.jsonl.gz is not in this checkout")
    with gzip.open(store, "rt") as fh:
        record = json.loads(fh.readline())
    params = yaml.safe_load((ROOT / "fe" / "params.yaml").read_text())
    validate_params(params, path="fe/params.yaml", schema="fe")
    settings = params["fe"]["settings"]  # as femcal.config.load_params gives them to the stage
    assert settings_hash("calculix", settings) == record["settings_hash"]
    job = FEJob(
        record["config_id"], record["parameters"], record["load_case"], tuple(record["levels"])
    )
    text, _ = CalculixDisc(**settings).deck(job, record["attempts"] - 1)
    assert hashlib.sha256(text.encode()).hexdigest() == record["deck_hash"]


def test_deck_with_every_element():
    text = deck(BOTH)
    assert text.count("*ELEMENT, TYPE=GAPUNI") == 2  # FACET_R, FACET_L
    assert text.count("*ELEMENT, TYPE=SPRINGA") == len(LIGAMENTS)
    assert text.count(", NONLINEAR") == len(LIGAMENTS)
    assert "*RIGID BODY, NSET=TOP_POSTERIOR," in text and "POSTERIOR_LOWER, 1, 3" in text
    assert "** posterior elements:" in text
    # Every number of a spring table has a decimal point (CalculiX reads integers as DOFs).
    block = text.split("*SPRING, ELSET=LIG_FLAVUM, NONLINEAR\n\n")[1].split("*")[0]
    rows = [line.split(", ") for line in block.strip().splitlines()]
    assert rows and all("." in v for row in rows for v in row)


def test_elements_join_the_two_bodies():
    posterior = posterior_settings(BOTH)
    mesh = CalculixDisc(geometry="coarse").mesh
    out = posterior_deck(posterior, mesh.node_sets["TOP"], 1000, 500)
    # 2 facets + 3 midline ligaments + 2 x 2 bilateral ones (capsular, intertransverse)
    assert len(out.names) == 2 + 3 + 4
    lengths = np.linalg.norm(out.upper - out.lower, axis=1)
    for name, length in zip(out.names, lengths):
        if name.startswith("FACET"):
            assert length == 0.0
        else:
            expected = LIGAMENT_DEFAULTS[name[len("LIG_") :].lower()]["length_mm"]
            assert length == pytest.approx(expected)
    assert np.all(out.upper[:, 1] < -mesh.geometry.depth_mm / 2)  # behind the disc


def test_facet_normals_close_in_extension_and_rotation_not_flexion():
    facets = FacetSettings()
    right, left = facet_normal(facets, 1.0), facet_normal(facets, -1.0)
    assert np.linalg.norm(right) == pytest.approx(1.0)
    point = np.array([facets.lateral_mm, -facets.posterior_mm, 0.0])
    down = np.array([0.0, 0.0, -1.0])  # extension moves the posterior upper body down
    assert right @ down > 0 and left @ down > 0
    assert right @ -down < 0  # flexion lifts it: the gap opens
    ccw = np.cross([0.0, 0.0, 1.0], point)  # right facet's motion in +z axial rotation
    assert right @ ccw > 0 and left @ np.cross([0.0, 0.0, 1.0], point * [-1, 1, 1]) < 0


@pytest.mark.parametrize("name", LIGAMENTS)
def test_ligament_curve_is_tension_only_toe_then_linear(name):
    ligament = posterior_settings({"ligaments": {name: {"slack_strain": 0.05}}}).ligaments[name]
    curve = ligament_curve(ligament)
    force, elongation = curve[:, 0], curve[:, 1]
    assert force[0] == 0.0 and elongation[0] == pytest.approx(0.05 * ligament.length_mm)
    assert np.all(np.diff(elongation) > 0) and np.all(np.diff(force) > 0)
    slopes = np.diff(force) / np.diff(elongation)
    assert np.all(np.diff(slopes) >= -1e-9)  # convex: toe stiffening to the linear region
    assert slopes[-1] == pytest.approx(ligament.stiffness_n_per_mm)
    assert elongation[-1] > 10 * ligament.length_mm


def test_defaults_are_declared_once():
    assert set(LIGAMENT_DEFAULTS) == set(LIGAMENTS)
    for values in LIGAMENT_DEFAULTS.values():
        assert isinstance(LigamentSettings(**values), LigamentSettings)
    assert posterior_settings({"facets": {}}).facets == FacetSettings()
    assert not posterior_settings(None).active and posterior_settings({"facets": {}}).active


# ---------------------------------------------------------------------------- errors
@pytest.mark.parametrize(
    ("value", "match"),
    [
        (
            {"ligaments": ["flavm"]},
            r"ligaments\.flavm: unknown ligament; did you mean .*\.flavum\?",
        ),
        (
            {"facets": {"gap_mm": -1}},
            r"facets\.gap_mm: Input should be greater than or equal to 0, got -1",
        ),
        ({"facets": {"stiffnes": 5}}, r"facets\.stiffnes.*stiffness_n_per_mm"),
        ({"ligaments": {"capsular": {"toe_strain": 2}}}, r"capsular\.toe_strain.*got 2"),
        ({"ligaments": 3}, r"expected a list of ligament names or a mapping.*got 3"),
        ({"ligaments": {"flavum": 7}}, r"flavum: expected a mapping of ligament settings"),
        ({"spinous": {}}, r"posterior\.spinous.*unknown"),
        ("facets", r"expected a mapping \(facets, ligaments\) or null"),
    ],
)
def test_bad_posterior_settings(value, match):
    with pytest.raises(ConfigError, match=match) as info:
        posterior_settings(value, where="fe/params.yaml")
    assert isinstance(info.value, FemcalError)
    assert "fe/params.yaml" in str(info.value) and "docs/fe-posterior-elements.md" in str(
        info.value
    )
    with pytest.raises(ConfigError, match=match):
        CalculixDisc(geometry="coarse", posterior=value)


def test_params_file_takes_posterior_and_keeps_it_plain():
    params = yaml.safe_load((ROOT / "fe" / "params.yaml").read_text())
    good = copy.deepcopy(params)
    good["fe"]["settings"]["posterior"] = {"facets": {"gap_mm": 1.0}, "ligaments": ["flavum"]}
    settings = validate_params(good, path="fe/params.yaml", schema="fe").fe.settings
    assert settings["posterior"] == {"facets": {"gap_mm": 1.0}, "ligaments": ["flavum"]}
    assert settings_hash("calculix", settings)  # plain data: hashable into job keys
    assert CalculixDisc(**settings).posterior.facets.gap_mm == 1.0
    bad = copy.deepcopy(params)
    bad["fe"]["settings"]["posterior"] = {"facets": {"inclination_deg": 95}}
    with pytest.raises(
        ConfigError, match=r"fe/params\.yaml.*inclination_deg.*less than or equal to 80, got 95"
    ):
        validate_params(bad, path="fe/params.yaml", schema="fe")


def test_posterior_instance_is_accepted():
    instance = PosteriorSettings(facets=FacetSettings(gap_mm=0.2))
    assert CalculixDisc(geometry="coarse", posterior=instance).posterior is instance


# ----------------------------------------------------------------------- the solver
def test_box_centre_is_the_centre_of_the_bounds():
    assert BOX_CENTRE == pytest.approx(CENTRE)


@pytest.fixture(scope="module")
def segment_runs(tmp_path_factory) -> dict[str, dict[str, float]]:
    """RoM at 10 Nm: disc alone (4 load cases), facets (3), ligaments (2); 9 coarse runs."""
    if shutil.which("ccx") is None:
        pytest.skip("CalculiX (ccx) is not installed; `make install`")
    runs = {
        "disc": ("Flexion", "Extension", "LateralBending", "AxialRotation"),
        "facets": ("Flexion", "Extension", "AxialRotation"),
        "ligaments": ("Flexion", "LateralBending"),
    }
    return segment_rom(runs, tmp_path_factory.mktemp("posterior"), levels=LEVELS, jobs=2)


@pytest.mark.slow  # real CalculiX runs (minutes): CI runs it in its slow step
@requires_ccx
def test_facets_stiffen_extension_and_axial_rotation_not_flexion(segment_runs):
    disc, facets = segment_runs["disc"], segment_runs["facets"]
    ratio = {case: facets[case] / disc[case] for case in facets}
    assert ratio["Extension"] < 0.8
    assert ratio["AxialRotation"] < 0.95
    assert ratio["Flexion"] == pytest.approx(1.0, abs=0.01)


@pytest.mark.slow  # real CalculiX runs (minutes): CI runs it in its slow step
@requires_ccx
def test_ligaments_stiffen_flexion_most_then_lateral_bending(segment_runs):
    """Published direction: removing the posterior ligaments frees flexion most."""
    disc, ligaments = segment_runs["disc"], segment_runs["ligaments"]
    ratio = {case: ligaments[case] / disc[case] for case in ligaments}
    assert ratio["Flexion"] < 0.8
    assert ratio["Flexion"] < ratio["LateralBending"] < 0.98
    assert "| ligaments |" in ratio_table(segment_runs, LEVELS[-1])
