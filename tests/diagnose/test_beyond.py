"""The side of the box a disc-alone fit's pressed bounds pull towards (femcal.diagnose.beyond)."""

import numpy as np

from femcal.diagnose.beyond import pressed_side
from femcal.diagnose.box_edge import SOFTER, STIFFER

SIGMA = np.full((4, 3), 0.05)


def _jac(slopes):
    """A Jacobian (4, 3, d): every point moves by ``slopes[k]`` deg per unit of parameter k."""
    return np.broadcast_to(np.asarray(slopes, dtype=float), (4, 3, len(slopes))).copy()


def test_a_stiffness_at_its_upper_bound_pulled_outward_reads_stiffer():
    jac = _jac([-1.0, 0.5])  # a stiffness (less rotation as it grows) and a free parameter
    resid = np.full((4, 3), -0.2)  # the specimen rotates less than the fit
    assert pressed_side(jac, resid, SIGMA, np.array([1.0, 0.0])) == STIFFER


def test_a_stiffness_at_its_lower_bound_pulled_outward_reads_softer():
    jac = _jac([-1.0, 0.5])
    resid = np.full((4, 3), 0.2)  # the specimen rotates more than the fit
    assert pressed_side(jac, resid, SIGMA, np.array([-1.0, 0.0])) == SOFTER


def test_bounds_the_data_do_not_pull_outward_say_nothing():
    jac = _jac([-1.0, 0.5])
    resid = np.full((4, 3), 0.2)  # more rotation: the stiffness at its upper bound wants in
    assert pressed_side(jac, resid, SIGMA, np.array([1.0, 0.0])) is None
    assert pressed_side(jac, resid, SIGMA, np.zeros(2)) is None  # nothing on a bound


def test_the_pull_is_read_over_the_measured_points_only():
    jac = _jac([-1.0])
    resid = np.full((4, 3), np.nan)
    resid[0] = -0.2  # one measured load case: less rotation
    assert pressed_side(jac, resid, SIGMA, np.array([1.0])) == STIFFER
    # a pressed stiffness against residuals of mixed sign: the larger misfit decides
    resid = np.array([[-0.3] * 3, [0.1] * 3, [0.1] * 3, [0.05] * 3])
    assert pressed_side(jac, resid, SIGMA, np.array([1.0])) == STIFFER


def test_with_both_sides_possible_each_stand_in_is_the_mean_of_the_two_sides():
    from femcal.diagnose.outside import _weighted

    reading = {"flatness": {"Flexion": 0.7}, "stand_in_load_cases": ["Flexion"]}
    per_side = {
        STIFFER: {"ligament_tension": {**reading, "stand_in": 1.0}},
        SOFTER: {"ligament_tension": {**reading, "stand_in": 0.0}},
    }
    both = _weighted({STIFFER: 0.5, SOFTER: 0.5}, per_side)
    assert both["ligament_tension"]["stand_in"] == 0.5
    assert both["ligament_tension"]["flatness"] == reading["flatness"]
    assert _weighted({STIFFER: 1.0}, {STIFFER: per_side[STIFFER]}) == per_side[STIFFER]
