"""RoM from the neutral position: a step without load first (``neutral_step``), on the real
solver with a pre-strained ligament (coarse mesh)."""

from __future__ import annotations

import numpy as np
import pytest
from fe_helpers import requires_ccx

from femcal.errors import ConfigError
from femcal.fe import FEJob, simulate
from femcal.fe.calculix import CalculixDisc
from femcal.fe.posterior_check import BOX_CENTRE
from femcal.settings import validate_params

#: The intertransverse ligaments taut at rest (slack strain < 0): they turn the unloaded disc
#: into extension, so that from the mesh's geometry flexion starts below zero.
TAUT = {"ligaments": {"intertransverse": {"slack_strain": -0.15, "stiffness_n_per_mm": 40.0}}}
LEVELS = (0.5, 1.0)  # Nm
JOB = FEJob(0, dict(BOX_CENTRE), "Flexion", LEVELS)


def _deck(**settings) -> str:
    return CalculixDisc(geometry="coarse", **settings).deck(JOB)[0]


def test_the_neutral_step_comes_first_without_load_and_prints_the_zero():
    without, with_ = _deck(posterior=TAUT), _deck(posterior=TAUT, neutral_step=True)
    steps = with_.split("*STEP")
    assert len(steps) == 3 and without.count("*STEP") == 1
    assert "*CLOAD" not in steps[1] and "TIME POINTS=NEUTRAL" in steps[1]
    assert steps[2] == without.split("*STEP")[1]  # the loaded step as without it
    assert "*TIME POINTS, NAME=NEUTRAL\n1.\n" in with_


def test_fe_settings_take_neutral_step():
    fe = {"solver": "calculix", "settings": {"neutral_step": "yes"}}
    with pytest.raises(ConfigError, match=r"fe\.settings\.neutral_step"):
        validate_params({"fe": fe}, path="fe/params.yaml", schema="fe")
    fe["settings"]["neutral_step"] = True
    validate_params({"fe": fe}, path="fe/params.yaml", schema="fe")


@requires_ccx
def test_rotations_are_counted_from_where_the_unloaded_disc_settles(tmp_path):
    """The same loaded path (elastic: the neutral step changes nothing after it), each level
    less the rotation at rest: flexion from the neutral position starts above zero."""
    results = {}
    for neutral in (False, True):
        adapter = CalculixDisc(geometry="coarse", posterior=TAUT, neutral_step=neutral)
        results[neutral] = simulate(adapter, JOB, tmp_path / str(neutral))
    assert all(r.ok for r in results.values()), [r.reason for r in results.values()]
    shift = results[True].rom_deg - results[False].rom_deg
    assert shift[0] > 0.1  # deg: the taut ligaments had turned the disc into extension
    # one rotation at rest less at every level (1e-6 deg: the solver's printed digits)
    np.testing.assert_allclose(shift, shift[0], atol=1e-6)
    assert results[True].rom_deg[0] > 0
    # the pressure as without it (1e-6: the loaded step's increments start from another state,
    # and each ends within the solver's residual tolerance of the same equilibrium)
    np.testing.assert_allclose(results[True].idp_mpa, results[False].idp_mpa, rtol=1e-6)
