"""A disc the disc alone fits within the noise, at the edge of the parameter box.

A disc just beyond the box is fitted by the disc alone as well as one inside it: the fit lands
on the box's faces, several of its 13 parameters on their bounds, and its curves lie at the
edge of every curve the box produces. Neither is proof: a disc inside the box, fitted through
noise, also presses bounds (4 of 13 is typical) and may lie near the envelope. This module asks
how often it does so, of the box itself (:func:`edge_reading`).

**The statistic** of a specimen: ``k``, the disc-alone parameters on a bound (unit coordinate
within :data:`AT_BOUND` of 0 or 1), and ``margin``, how far its
curves lie inside the disc's envelope (:func:`margins`: per load case the mean over the
measured points of the distance, in sigma, to the envelope's stiffer edge (``stiffer``) or its
softer one; the smallest over the load cases and the two edges; the side is that edge's).

**The box's answer**: discs drawn uniformly in the box (unit coordinates), their surrogate
curves at the specimen's own measured points with Gaussian noise of each point's sd (noise and
surrogate error), each fitted by the same disc-alone fit. The Monte Carlo p-value
``p = (1 + #{K >= k and margin_r <= margin}) / (1 + R)`` (``R`` draws) is how often a disc
inside the box looks at least as much like one at its edge. :data:`EDGE_DRAWS` draws first; as
many again up to :data:`EDGE_MAX_DRAWS` while fewer than :data:`EDGE_STOP` draws exceed (a
sequential test: a clearly inside specimen costs the first draws only). A draw's margin needs
its curves only, not its fit: only the draws whose margin is at most the specimen's can
exceed, and only they are fitted (:func:`_exceeding`; the fit draws the same numbers from the
generator for any number of rows, so the draws are those of fitting them all, and so is the
count up to the fits' float32 rounding: a fit among other rows lands within 1e-3 in unit
coordinates, which moves a draw's count only where a coordinate sits that close to
:data:`AT_BOUND`).

**The probability**: a disc beyond the box presses the faces it lies beyond and sits at the
envelope's edge, so the likelihood ratio of the event is at most ``1 / p`` (its probability
under the alternative at most 1). The prior odds of a disc outside the box are those of any
further explanation the diagnosis names, ``exp(-min_delta / 2)`` (the prior cost of a first
effect and of a discrepancy, :class:`~femcal.diagnose.DiagnoseOptions`). So ::

    P(outside | k, margin) = o / (o + p),   o = exp(-min_delta / 2)

an upper bound under that prior: with ``min_delta = 10`` it exceeds 0.5 only where fewer than
1 in 150 discs of the box look as much at its edge, and reaches 0.1 at 1 in 15. The
benchmark page (docs/benchmarks/edges.md) gives the measured distributions of ``k`` and the
margin, inside the box and beyond it.
"""

from __future__ import annotations

import math
import types
import zlib
from typing import Any

import numpy as np
import torch

#: Draws of the box's discs per specimen at first (and per further round).
EDGE_DRAWS = 32
#: The most draws per specimen: p resolves down to 1 / (1 + this).
EDGE_MAX_DRAWS = 512
#: Exceeding draws at which the sequential test stops (p is then at least this / draws).
EDGE_STOP = 4
#: A unit-box coordinate closer than this to 0 or 1 is on its bound (here, in the out-of-box
#: reading, :mod:`femcal.diagnose.outside`, and in the failures the diagnosis reports).
AT_BOUND = 1e-3
STIFFER, SOFTER = "stiffer", "softer"


def margins(rom: np.ndarray, lower: np.ndarray, upper: np.ndarray, sigma: np.ndarray):
    """How far curves lie inside the disc's envelope, in sigma, and on which side.

    Parameters
    ----------
    rom : ndarray, shape (r, 4, m)
        Curves (deg), NaN where not measured.
    lower, upper : ndarray, shape (4, m)
        The envelope: the least and largest RoM of the box's discs (deg).
    sigma : ndarray, shape (r, 4, m) or (4, m)
        Each point's sd (deg).

    Returns
    -------
    margin : ndarray, shape (r,)
        Per load case the mean distance of the measured points to the envelope's stiffer edge
        (``rom - lower``) or softer edge (``upper - rom``), in sigma, negative beyond it; the
        smallest over load cases and the two edges (inf where nothing is measured).
    side : list of str, length r
        ``stiffer`` where the stiffer edge is the nearer, else ``softer``.
    """
    with np.errstate(invalid="ignore"):
        near = [
            np.nanmean((rom - lower) / sigma, axis=2),
            np.nanmean((upper - rom) / sigma, axis=2),
        ]
    closest = [np.nanmin(np.where(np.isfinite(d), d, np.inf), axis=1) for d in near]
    side = [STIFFER if a <= b else SOFTER for a, b in zip(*closest)]
    return np.minimum(*closest), side


def bounds_pressed(unit: np.ndarray) -> np.ndarray:
    """Parameters on a bound per disc, shape (r,), of unit coordinates ``unit`` (r, dim)."""
    return np.sum((unit < AT_BOUND) | (unit > 1 - AT_BOUND), axis=1)


def _draw(state, i: int, rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` discs drawn uniformly in the box, their curves at specimen ``i``'s points
    with noise of its sd: (count, 4, m), NaN where the specimen is not measured."""
    base = state.base
    unit = rng.uniform(size=(count, base.dim))
    v = base.from_physical(base.space.from_unit(unit))
    with torch.no_grad():
        curves = base.curves(torch.as_tensor(v, dtype=torch.float32)).double().numpy()
    return np.where(state.mask[i], curves + rng.normal(size=curves.shape) * state.sigma[i], np.nan)


def fitted_unit(state, i: int, sim: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The disc-alone fits (unit coordinates, (r, 13)) of the curves ``sim`` (r, 4, m) under
    specimen ``i``'s weights; ``rng`` feeds the fit's starts (the same draws for any r)."""
    from femcal.diagnose.search import disc_fit  # the same fit (search imports this module)

    base = state.base
    weight = np.ascontiguousarray(np.broadcast_to(state.weight[i], sim.shape))
    fit_state = types.SimpleNamespace(
        base=base, measured=sim, rng=rng, start_bank=state.start_bank, options=state.options
    )
    v_fit, _ = disc_fit(fit_state, weight)
    return base.space.to_unit(base.to_physical(v_fit.double().numpy()))


def _pressed(state, i: int, sim: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Bounds pressed (r,) by the disc-alone fits of the curves ``sim`` (:func:`fitted_unit`)."""
    return bounds_pressed(fitted_unit(state, i, sim, rng))


def _box_draws(state, i: int, env, rng: np.random.Generator, count: int):
    """``count`` discs drawn uniformly in the box, their curves at specimen ``i``'s points
    with noise of its sd, fitted by the disc alone: bounds pressed (count,) and margins
    (count,)."""
    sim = _draw(state, i, rng, count)
    margin, _ = margins(sim, env.lower, env.upper, state.sigma[i])
    return _pressed(state, i, sim, rng), margin


def _exceeding(state, i: int, env, rng: np.random.Generator, count: int, k: int, margin: float):
    """How many of ``count`` box draws (:func:`_box_draws`) press at least ``k`` bounds with
    a margin at most ``margin``: the draws and the count of :func:`_box_draws`, the fits of
    only the draws whose margin is at most ``margin`` (at least one draw is fitted, so that
    the generator moves on as :func:`_box_draws` moves it)."""
    sim = _draw(state, i, rng, count)
    mr, _ = margins(sim, env.lower, env.upper, state.sigma[i])
    near = np.flatnonzero(mr <= margin)
    kr = _pressed(state, i, sim[near if near.size else [0]], rng)
    return int(np.sum(kr >= k)) if near.size else 0


def edge_reading(state, i: int, env, unit_disc: np.ndarray) -> dict[str, Any]:
    """How often a disc inside the box looks as much at its edge as specimen ``i`` (see the
    module docstring).

    Parameters
    ----------
    state : DiagnosisState
        The diagnosis' state (surrogate, measured points, sd, fit weights, options).
    i : int
        The specimen.
    env : Envelope
        The disc alone's envelope over the box (:func:`femcal.reachability.build_envelope`).
    unit_disc : ndarray, shape (13,)
        The specimen's disc-alone fit in the box's unit coordinates.

    Returns
    -------
    dict
        ``bounds_pressed`` (k), ``margin_sigma``, ``side``, ``draws`` (R), ``exceeding``,
        ``p_inside`` (the Monte Carlo p-value), ``likelihood_ratio`` (its bound ``1 / p``),
        ``prior_odds`` and ``probability`` (of a disc beyond the box, :func:`edge_probability`).
    """
    k = int(bounds_pressed(unit_disc[None, :])[0])
    margin, side = margins(state.measured[i][None], env.lower, env.upper, state.sigma[i])
    seed = [int(state.options.seed), zlib.crc32(f"box-edge:{state.specimens[i]}".encode())]
    rng = np.random.default_rng(seed)
    draws = exceeding = 0
    while draws < EDGE_MAX_DRAWS and exceeding < EDGE_STOP:
        count = EDGE_DRAWS if not draws else draws
        exceeding += _exceeding(state, i, env, rng, count, k, float(margin[0]))
        draws += count
    p = (1 + exceeding) / (1 + draws)
    odds = math.exp(-state.options.min_delta / 2)
    return {
        "bounds_pressed": k,
        "margin_sigma": round(float(margin[0]), 3),
        "side": side[0],
        "draws": draws,
        "exceeding": exceeding,
        "p_inside": round(p, 5),
        "likelihood_ratio": round(1 / p, 2),
        "prior_odds": round(odds, 5),
        "probability": edge_probability(p, odds),
    }


def edge_probability(p: float, prior_odds: float) -> float:
    """The probability of a disc beyond the box, ``o / (o + p)``: prior odds ``o`` times the
    likelihood ratio's bound ``1 / p`` (``p`` the box's p-value)."""
    return float(prior_odds / (prior_odds + p))


def edge_words(edge: dict[str, Any]) -> str:
    """The edge reading in words, for the out-of-box summary."""
    return (
        f"the disc alone presses {edge['bounds_pressed']} bounds with its curves "
        f"{edge['margin_sigma']:.2g} sigma inside the {edge['side']} edge of the box's curves, "
        f"as {edge['exceeding']} of {edge['draws']} discs drawn in the box do when fitted "
        f"(likelihood ratio at most {edge['likelihood_ratio']:.3g})"
    )
