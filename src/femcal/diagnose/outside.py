"""A disc outside the parameter box, told apart from a missing element.

The surrogate knows the discs of its parameter box (``fe.bounds``) and no others. A specimen
whose disc is stiffer (or softer) than every disc in the box is still "explained" by the
search: the disc alone is pressed against the box, and flexible effects make up the rest. Such
effects do not *engage*; they stand in for a stiffer disc. This module tells the two apart with
evidence the diagnosis already holds, and shares the probability between them where they
cannot be told apart (:func:`assess`).

**When it looks** (:func:`femcal.diagnose.beyond.box_evidence`): the specimen lies beyond the
disc's reachable envelope (at least ``REACH_POINTS`` points beyond the level of every curve
the disc alone produces over its box, :func:`femcal.reachability.build_envelope`), or the
disc-alone fit presses against the box (at least ``BOUNDS_PRESSED`` of its parameters on a
bound).
Where the disc alone is probable, the box itself says how often its discs look as much at
its edge (:func:`femcal.diagnose.box_edge.edge_reading`); the disc alone's model then stands
in for a disc beyond the box with that probability, and the diagnosis looks where it is at
least :data:`REPORTED`. Otherwise nothing here changes a diagnosis. Looking is not deciding:
a disc inside the box with strong posterior elements also leaves the disc alone's reach, and
the shapes decide.

**The side**: ``stiffer`` where the points beyond the envelope lie below it (``softer``
above), else from the sign of the disc alone's residuals; where the bounds the disc-alone fit
presses pull it the other way (:func:`femcal.diagnose.beyond.pressed_side`), both sides at
0.5 each: every stand-in probability below is then the mean of the two sides', and the side
reported is the one whose stand-ins carry more. Only an effect that moves the curves
that way can stand in for the disc: a parallel element stiffens, a series element adds
rotation. A laxity saturates by its nature, so its share of the rotation falls over the
moments as a softer disc's stand-in's does: a series effect stands in for a softer disc only in
a model that leaves something unexplained beside it (a softer disc beyond the box leaves more
than any laxity takes up; a laxity inside the box is explained by it).

**What separates them** (:class:`ShapeReader`): an element engages, a stiffer or softer disc
does not. Each fitted effect's share of the load is followed over the moments, from
:data:`LOW_FRACTION` of a load case's largest measured moment to it, in every load case it acts
in (where its share reaches :data:`ACTIVE_SHARE`): the share of the applied moment a parallel
element carries, the share of the rotation a series element adds. An element with a gap, a
slack or a knee carries next to nothing at low moments and a clear share beyond its onset: its
share varies by a large factor. A disc stand-in, acting from about 0 Nm with a law near the
disc's own, keeps about the same share at every moment. The *flatness* of a load case, its
smallest share over its largest (0 where the share changes sign), is read on a ramp: at most
:data:`FLAT_ELEMENT` an element (stand-in probability 0), at least :data:`FLAT_DISC` a disc (1),
linear between. An effect's stand-in probability is the mean over the load cases it acts in:
one acting from about 0 Nm in every load case is the disc, one engaging in every load case an
element, and one that does each in half of them is either (probability 0.5).

A discrepancy (``unexplained``) is read the same way (:func:`discrepancy_stand_in`): a disc
beyond the box leaves a miss of one sign (the side's) and about the same share of the curves at
every moment, in every load case but one at most. It is read on the chosen model's
discrepancy, or on the disc alone's residuals where every effect of the chosen model stands in
(the stand-ins took part of the disc's miss).

**The probabilities** (:func:`split_probabilities`): each fitted model of probability ``p``
whose parts (effects, discrepancy) stand in with probabilities ``s`` keeps ``p prod(1 - s)``;
the rest goes to its out-of-box alternatives, the parts kept as real with ``outside_box``
(``facet_contact+outside_box``, ``outside_box``). Inclusion probabilities are summed anew, so
an effect that only stands in for the disc loses the probability it had. The verdict names the
box where such an alternative is the most probable explanation; the reading says the side, the
load cases, the disc parameters at their bounds and the remedy (:data:`REMEDY`): widen
``fe.bounds``, run the FE campaign on the widened box (``dvc repro fe/dvc.yaml``) and train
the surrogate on it.

The thresholds were set on the specimens of ``tests/diagnose/test_outside_box.py`` and the
synthetic world of ``tests/test_diagnose.py`` (docs: *Explanation > Diagnosis*).
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import torch

from femcal.calibration.model import SurrogateCurveModel
from femcal.diagnose.beyond import box_evidence
from femcal.diagnose.box_edge import SOFTER, STIFFER, edge_reading, edge_words
from femcal.diagnose.result import OUTSIDE_BOX, UNEXPLAINED, model_label
from femcal.effects.composite import EffectModel
from femcal.effects.split import base_name
from femcal.reachability import build_envelope
from femcal.schema import LOAD_CASES

Model = tuple[str, ...]

#: The shapes are read from this fraction of a load case's largest measured moment up to it:
#: "from about 0 Nm", where a gap or a slack has not closed yet.
LOW_FRACTION = 0.05
#: Log-spaced moments of the shapes' grid.
SHAPE_POINTS = 40
#: An effect acts in a load case where its largest share of the load reaches this.
ACTIVE_SHARE = 0.02
#: Flatness (smallest share over the largest) at most this: an element that engages. Real gaps
#: and slacks give 0.00-0.01 in every load case on the tests' specimens (the share is 0 until
#: the gap closes); the stand-ins of a stiffer disc 0.25-0.85 in at least one load case.
FLAT_ELEMENT = 0.1
#: Flatness at least this: a disc stand-in (stand-in probability 1); linear between.
FLAT_DISC = 0.3
#: The probability a model needs to be read for its shape (below, too little to move).
MODEL_FLOOR = 1e-3
#: The verdict names the box where a disc outside it is more probable than this (more probable
#: than not), with the effects whose inclusion probability, shared out, still exceeds it.
NAMED = 0.5
#: An out-of-box reading at least this probable is reported beside a verdict that does not
#: name the box (summary.md, the printed summary): the two could not be told apart.
REPORTED = 0.1
#: The side of the box each kind of effect can stand in for: a parallel element stiffens, a
#: series element adds rotation.
_SIDE_OF_KIND = {"parallel": STIFFER, "series": SOFTER}
#: The remedy, named in every out-of-box verdict.
REMEDY = (
    "widen fe.bounds beyond these parameters' bounds, run the FE campaign on the widened box "
    "(`dvc repro fe/dvc.yaml`) and train the surrogate on it (`dvc repro`)"
)


def stand_in_ramp(flat: np.ndarray) -> np.ndarray:
    """Stand-in probability of flatness values: 0 up to :data:`FLAT_ELEMENT`, 1 from
    :data:`FLAT_DISC`, linear between (NaN, where nothing acts, counts 0)."""
    ramp = (np.asarray(flat, dtype=float) - FLAT_ELEMENT) / (FLAT_DISC - FLAT_ELEMENT)
    return np.nan_to_num(np.clip(ramp, 0.0, 1.0), nan=0.0)


def flatness(share: np.ndarray, window: np.ndarray) -> np.ndarray:
    """Per load case, the smallest share over the largest inside the window.

    Parameters
    ----------
    share : ndarray, shape (4, q)
        The share of the load at each moment of the grid (a sign change reads as 0).
    window : ndarray of bool, shape (4, q)
        The moments each load case is read at.

    Returns
    -------
    ndarray, shape (4,)
        Flatness in [0, 1]; NaN where the largest share stays below :data:`ACTIVE_SHARE`
        (nothing acts there) or the window is empty.
    """
    out = np.full(share.shape[0], np.nan)
    for j in range(share.shape[0]):
        s = share[j][window[j] & np.isfinite(share[j])]
        if not s.size:
            continue
        big = np.max(np.abs(s))
        if big < ACTIVE_SHARE:
            continue
        one_sign = np.all(s > 0) or np.all(s < 0)
        out[j] = float(np.min(np.abs(s)) / big) if one_sign else 0.0
    return out


class ShapeReader:
    """Reads the shapes of fitted effects of a cohort on one moment grid.

    Parameters
    ----------
    base : SurrogateCurveModel
        The disc surrogate on the measurement grid.
    mask : ndarray of bool, shape (n, 4, m)
        The measured points.
    """

    def __init__(self, base, mask: np.ndarray) -> None:
        moments = base.moments.double().numpy()
        largest = np.where(mask, moments[None, None, :], 0.0).max(axis=2)  # (n, 4)
        top = float(np.max(largest)) if np.any(largest > 0) else float(moments.max())
        self.grid = np.geomspace(LOW_FRACTION * top, top, SHAPE_POINTS)
        self.dense = SurrogateCurveModel(base.surrogate, self.grid, space=base.space)
        g = self.grid[None, None, :]
        lo = LOW_FRACTION * largest[..., None] * (1 - 1e-9)
        #: (n, 4, q): per specimen and load case, the grid up to its largest measured moment.
        self.window = (g <= largest[..., None] * (1 + 1e-9)) & (g >= lo)
        self._models: dict[Model, EffectModel] = {}

    def shares(self, effects: Model, v: np.ndarray) -> list[tuple[str, np.ndarray]]:
        """Each effect's side and share of the load (r, 4, q) at unit coordinates ``v``
        (r, dim): the share of the applied moment a parallel element carries, the share of
        the rotation a series element adds."""
        if effects not in self._models:
            self._models[effects] = EffectModel(self.dense, list(effects))
        model = self._models[effects]
        vt = torch.as_tensor(np.asarray(v, dtype=np.float32))
        out = []
        with torch.no_grad():
            phi = model.curves(vt).double()
            applied = model.moments.double().expand_as(phi)
            for e, sl, lc in zip(model.effects, model._slices, model._lc_masks):
                p = {k: t.double() for k, t in e.from_unit(vt[:, sl]).items()}
                mask = lc[None, :, None].double()
                if e.kind == "parallel":
                    share = e.moment_at(phi, p) * mask / applied
                else:
                    share = e.rotation_at(applied, p) * mask / phi.clamp_min(1e-9)
                out.append((_SIDE_OF_KIND[e.kind], share.numpy()))
        return out

    def effect_stand_ins(
        self, effects: Model, v: np.ndarray, i: int, side: str, missing: bool
    ) -> dict:
        """Per effect of model ``effects`` fitted to specimen ``i`` (unit coordinates ``v``,
        shape (dim,)): its flatness in each load case it acts in and its stand-in
        probability, the mean of its load cases' (a law acting from about 0 Nm in a load case
        is the disc's there; one engaging in every load case is an element); 0 for an effect
        that cannot stand in for a disc on ``side``, and for a series effect where nothing
        is ``missing`` beside the model (a laxity's share falls as it saturates, as a softer
        disc's stand-in's does: a softer disc beyond the box leaves more than any laxity
        takes up)."""
        out = {}
        for name, (kind_side, share) in zip(effects, self.shares(effects, v[None, :])):
            flat = flatness(share[0], self.window[i])
            acts = np.flatnonzero(np.isfinite(flat))
            ramp = stand_in_ramp(flat[acts])
            can = kind_side == side and (missing or kind_side == STIFFER)
            out[name] = {
                "flatness": {LOAD_CASES[j]: round(float(flat[j]), 3) for j in acts},
                "stand_in_load_cases": [LOAD_CASES[j] for j, r in zip(acts, ramp) if r >= 0.5],
                "stand_in": float(ramp.mean()) if ramp.size and can else 0.0,
            }
        return out


def discrepancy_stand_in(delta: np.ndarray, pred: np.ndarray, side: str) -> dict[str, Any]:
    """Whether a discrepancy looks like a disc beyond the box: a share of the model's curves of
    one sign (the side's) and about the same size at every moment, in (nearly) every load case.

    Parameters
    ----------
    delta : ndarray, shape (4, m)
        The discrepancy's mean at the measured points (NaN elsewhere).
    pred : ndarray, shape (4, m)
        The model's curves it sits on.
    side : {"stiffer", "softer"}

    Returns
    -------
    dict
        ``flatness`` per load case and ``stand_in``: the second smallest of the load cases'
        stand-in probabilities (every load case but one; a load case with no discrepancy
        counts 0).
    """
    sign = -1.0 if side == STIFFER else 1.0
    share = sign * np.asarray(delta, dtype=float) / np.maximum(np.abs(pred), 1e-9)
    everywhere = np.isfinite(share)
    flat = flatness(share, everywhere)
    for j in range(len(flat)):  # the wrong sign is no stand-in for this side
        ok = everywhere[j]
        if np.isfinite(flat[j]) and np.mean(share[j][ok]) <= 0:
            flat[j] = 0.0
    ramp = np.sort(stand_in_ramp(flat))
    return {
        "flatness": {LOAD_CASES[j]: round(float(f), 3) for j, f in enumerate(flat)},
        "stand_in": float(ramp[1]) if ramp.size >= 2 else 0.0,
    }


def split_probabilities(
    probabilities: dict[str, Any],
    components: dict[str, list[tuple[str, float]]],
    alternative: str = OUTSIDE_BOX,
) -> dict[str, Any]:
    """Share each model's probability between it and its out-of-box alternatives.

    Parameters
    ----------
    probabilities : dict
        A specimen's probabilities (:func:`femcal.diagnose.probabilities.specimen_probabilities`).
    components : dict
        Model label -> its parts (effects as fitted, and ``unexplained`` for a discrepancy),
        each with the probability that it stands in for a disc outside the box.
    alternative : {"outside_box", "unexplained"}
        What the parts that stand in are replaced with: a disc outside the box, or something
        outside the library (:mod:`femcal.diagnose.balance`).

    Returns
    -------
    dict
        A copy with ``models`` shared out: a model of probability ``p`` whose parts stand in
        with probabilities ``s`` keeps ``p prod(1 - s)``; each subset ``R`` of its parts kept as
        real gives ``p prod_R (1 - s) prod_(not R) s`` to the label of ``R`` with
        ``alternative`` (the parts by registered name); ``inclusion``, ``outside_library`` and
        ``most_probable`` summed anew; ``outside_box`` the probability of every label naming
        the box (where ``alternative`` is the box).
    """
    shared: dict[str, float] = {}
    for label, p in probabilities["models"].items():
        parts = components.get(label, [])
        for keep in itertools.product((True, False), repeat=len(parts)):
            w = float(p)
            for (_, s), real in zip(parts, keep):
                w *= (1.0 - s) if real else s
            if w <= 0.0:
                continue
            if all(keep):
                key = label
            else:
                kept = [base_name(n) for (n, _), real in zip(parts, keep) if real]
                effects = [n for n in dict.fromkeys(kept) if n != UNEXPLAINED]
                box = [OUTSIDE_BOX] if alternative == OUTSIDE_BOX else []
                tail = [UNEXPLAINED] if UNEXPLAINED in kept or not box else []
                key = "+".join([*effects, *box, *tail])
            shared[key] = shared.get(key, 0.0) + w
    total = sum(shared.values()) or 1.0
    models = {k: v / total for k, v in sorted(shared.items(), key=lambda kv: -kv[1])}
    inclusion: dict[str, float] = {}
    for label, p in models.items():
        for e in {base_name(x) for x in label.split("+")} - {UNEXPLAINED, OUTSIDE_BOX, "none"}:
            inclusion[e] = inclusion.get(e, 0.0) + p
    out = dict(probabilities)
    out["models"] = {k: round(v, 4) for k, v in models.items() if v >= 1e-4}
    out["inclusion"] = {
        k: round(inclusion.get(k, 0.0), 4)
        for k in sorted(set(inclusion) | set(probabilities["inclusion"]))
    }
    out["outside_library"] = round(sum(v for k, v in models.items() if UNEXPLAINED in k), 4)
    if alternative == OUTSIDE_BOX:
        out["outside_box"] = round(sum(v for k, v in models.items() if OUTSIDE_BOX in k), 4)
    out["most_probable"] = next(iter(models))
    return out


def assess(state, disc, probabilities: list[dict], delta: np.ndarray, final_pred: np.ndarray):
    """The out-of-box reading of every specimen (see the module docstring).

    Parameters
    ----------
    state : DiagnosisState
        The search's state: every fitted model, the chosen ones.
    disc : Fit
        The disc alone's fit of every specimen.
    probabilities : list of dict, length n
        Each specimen's probabilities
        (:func:`~femcal.diagnose.probabilities.specimen_probabilities`).
    delta : ndarray, shape (n, 4, m)
        The discrepancy on top of each specimen's chosen model at the measured points.
    final_pred : ndarray, shape (n, 4, m)
        The chosen model's curves.

    Returns
    -------
    probabilities : list of dict
        Shared out (:func:`split_probabilities`) where the specimen looks beyond the box,
        else as given.
    outside : list of dict or None
        Per specimen that looks beyond the box: ``named`` (the verdict names the box),
        ``verdict``, ``probability``, ``side``, ``load_cases``, ``on_bounds``,
        ``outside_points``, ``stand_ins`` (the chosen model's effects), ``discrepancy``,
        ``remedy`` and ``summary``; None elsewhere.
    """
    base, n = state.base, state.n
    outside: list[dict[str, Any] | None] = [None] * n
    if getattr(base, "surrogate", None) is None:  # no network to read the shapes with
        return probabilities, outside
    pred0 = disc.pred.double().numpy()
    unit = base.space.to_unit(base.to_physical(disc.v.double().numpy()))
    env = build_envelope(base, sigma_model=np.zeros(len(state.sigma_m)))
    with torch.no_grad():
        jac0 = base.curves_jacobian(disc.v)[1].double().numpy()
    evidence = box_evidence(
        base, state.measured, state.sigma, pred0, unit, state.sigma_m, env, jac0
    )
    for i, ev in enumerate(evidence):  # the disc alone probable: how often the box looks so
        if probabilities[i].get("models", {}).get("none", 0.0) >= MODEL_FLOOR:
            ev["edge"] = edge_reading(state, i, env, unit[i])
            if ev["edge"]["probability"] >= REPORTED and not ev["outside_points"]:
                ev["looks"], ev["side"] = True, ev["edge"]["side"]
                ev["sides"] = {ev["side"]: 1.0}
    if not any(e["looks"] for e in evidence):
        return probabilities, outside
    reader = ShapeReader(base, state.mask)
    out = list(probabilities)
    for i in range(n):
        ev = evidence[i]
        if not ev["looks"] or not probabilities[i].get("models"):
            continue
        labels = {model_label(m): m for m in state.per_spec[i]}
        chosen = state.chosen[i]
        sides = ev.get("sides") or {ev["side"]: 1.0}
        parts: dict[str, list[tuple[str, float]]] = {}
        shapes: dict[str, dict] = {}
        gap = None
        pull = dict.fromkeys(sides, 0.0)  # per side, the stand-in probability it gives
        for label, p in probabilities[i]["models"].items():
            discrepancy = label.endswith(UNEXPLAINED)
            m = chosen if discrepancy else labels.get(label)
            if p < MODEL_FLOOR or m is None:
                continue
            per_side = {s: {} for s in sides}
            if m:
                fit, pos = state.per_spec[i][m]
                v = fit.v[pos].double().numpy()
                per_side = {s: reader.effect_stand_ins(m, v, i, s, discrepancy) for s in sides}
            st = _weighted(sides, per_side)
            parts[label] = [(e, st[e]["stand_in"]) for e in m]
            if not m and not discrepancy and "edge" in ev:  # the disc alone, at the box's edge
                parts[label] = [("none", ev["edge"]["probability"])]
            if m == chosen and (discrepancy or not shapes):
                shapes = st
            if discrepancy:
                gaps = {
                    s: _gap_stand_in(i, per_side[s], delta[i], final_pred[i], pred0[i], state, s)
                    for s in sides
                }
                gap = max(gaps.values(), key=lambda g: g["stand_in"])
                gap = {**gap, "stand_in": sum(w * gaps[s]["stand_in"] for s, w in sides.items())}
                parts[label].append((UNEXPLAINED, gap["stand_in"]))
            for s in sides:
                pull[s] += p * sum(r["stand_in"] for r in per_side[s].values())
        if len(sides) > 1:  # the side reported: the one whose stand-ins carry more
            ev = {**ev, "side": max(sides, key=lambda s: (pull[s], s == ev["side"]))}
        out[i] = split_probabilities(probabilities[i], parts)
        fitted = [chosen, *(labels[k] for k in probabilities[i]["models"] if k in labels)]
        outside[i] = _reading(state, ev, out[i], (shapes, gap), fitted)
    return out, outside


def _weighted(sides: dict[str, float], per_side: dict[str, dict]) -> dict[str, dict]:
    """Each effect's stand-in reading under the likelier side, its ``stand_in`` probability
    the mean over the ``sides`` (side -> weight) of each side's."""
    first = per_side[max(sides, key=lambda s: sides[s])]
    return {
        name: {**r, "stand_in": sum(w * per_side[s][name]["stand_in"] for s, w in sides.items())}
        for name, r in first.items()
    }


def _gap_stand_in(i, shapes, delta, pred, pred0, state, side: str) -> dict[str, Any]:
    """The stand-in reading of specimen ``i``'s discrepancy (``delta`` on top of the chosen
    model's curves ``pred``, each (4, m)): where every effect of the chosen model stands in
    for the disc (or it holds none), what is missing is read on the disc alone's residuals
    (``pred0``), as the stand-ins took part of the disc's miss."""
    if all(s["stand_in"] >= 0.5 for s in shapes.values()):
        return discrepancy_stand_in(state.measured[i] - pred0, pred0, side)
    return discrepancy_stand_in(delta, pred, side)


def _reading(state, ev: dict, prob: dict, stand_ins: tuple, fitted: list[Model]) -> dict:
    """A specimen's out-of-box reading: the verdict, side, load cases, bounds and remedy
    (``ev`` its :func:`box_evidence`, ``prob`` its shared-out probabilities, ``stand_ins``
    the chosen model's effects' and discrepancy's readings, ``fitted`` its models, the chosen
    first: where the verdict's effects take their forms from)."""
    shapes, gap = stand_ins
    named = prob["outside_box"] > NAMED
    kept = [e for e, p in prob["inclusion"].items() if p > NAMED]
    model: list[str] = []
    for f in (f for m in fitted for f in m):
        if base_name(f) in kept and base_name(f) not in map(base_name, model):
            model.append(f)
    tail = [UNEXPLAINED] if prob["outside_library"] > NAMED else []
    lcs = set(ev["outside_load_cases"])
    for s in shapes.values():
        if s["stand_in"] >= 0.5:
            lcs.update(s["stand_in_load_cases"])
    if gap is not None and gap["stand_in"] >= 0.5:
        lcs.update(
            lc for lc, f in gap["flatness"].items() if stand_in_ramp(np.array([f]))[0] >= 0.5
        )
    space = state.base.space
    bounds = [
        {
            "parameter": name,
            "bound": which,
            "value": float(space.lower[k] if which == "lower" else space.upper[k]),
        }
        for k, name in enumerate(space.names)
        if (which := ev["on_bounds"].get(name))
    ]
    reading = {
        "named": named,
        "verdict": "+".join([*map(base_name, model), OUTSIDE_BOX, *tail]) if named else None,
        "model": model if named else None,
        "probability": prob["outside_box"],
        "side": ev["side"],
        "load_cases": [lc for lc in LOAD_CASES if lc in lcs],
        "on_bounds": bounds,
        "outside_points": ev["outside_points"],
        "outside_load_cases": ev["outside_load_cases"],
        "stand_ins": shapes,
        "discrepancy": gap,
        "edge": ev.get("edge"),
        "remedy": REMEDY,
    }
    reading["summary"] = summary(reading)
    return reading


def summary(reading: dict[str, Any]) -> str:
    """An out-of-box reading in words: side, probability, evidence and remedy."""
    side, p = reading["side"], reading["probability"]
    lcs = ", ".join(reading["load_cases"]) or "every load case"
    head = (
        f"a disc {side} than every disc in the parameter box"
        + (" is the most probable explanation" if reading["named"] else " is possible")
        + f" (probability {p:.2f}), in {lcs}"
    )
    why = []
    if reading["outside_points"]:
        why.append(
            f"{reading['outside_points']} points lie beyond every curve the disc produces over "
            "its box"
        )
    if reading["on_bounds"]:
        at = ", ".join(
            f"{b['parameter']} at its {b['bound']} bound {b['value']:g}"
            for b in reading["on_bounds"]
        )
        why.append(f"the disc-alone fit presses {len(reading['on_bounds'])} parameters ({at})")
    stand = [e for e, s in reading["stand_ins"].items() if s["stand_in"] >= 0.5]
    if stand:
        why.append(
            f"{', '.join(base_name(e) for e in stand)} act from about 0 Nm without engaging (a "
            f"{side} disc, not an element with a gap or a slack)"
        )
    if reading.get("edge") and reading["edge"]["probability"] >= REPORTED:
        why.append(edge_words(reading["edge"]))
    gap = reading["discrepancy"]
    if gap is not None and gap["stand_in"] >= 0.5:
        why.append("what the model misses is about the same share of every curve")
    text = head + (": " + "; ".join(why) if why else "") + "."
    return text + f" Remedy: {reading['remedy']}."


def cohort_note(readings: list[dict[str, Any]]) -> str:
    """One line for the printed summary on the specimens whose verdict names the box: how many
    on each side, the disc parameters their fits press against the box (most often first)
    and the remedy; "" when there are none.

    Parameters
    ----------
    readings : list of dict
        The out-of-box readings (:func:`assess`) of the specimens whose verdict names the box.
    """
    if not readings:
        return ""
    sides = [r["side"] for r in readings]
    counts: dict[str, int] = {}
    for r in readings:
        for b in r["on_bounds"]:
            key = f"{b['parameter']} ({b['bound']} {b['value']:g})"
            counts[key] = counts.get(key, 0) + 1
    pressed = sorted(counts, key=lambda k: -counts[k])
    shown = ", ".join(pressed[:6]) + (f" and {len(pressed) - 6} more" if len(pressed) > 6 else "")
    return (
        f"outside the box: {len(readings)} specimens ({sides.count(STIFFER)} stiffer, "
        f"{sides.count(SOFTER)} softer than every disc in the parameter box; their effects act "
        "from about 0 Nm rather than engage)"
        + (f"; their disc-alone fits press {shown}" if pressed else "")
        + f". Remedy: {REMEDY}; summary.md names each specimen's side, load cases and "
        "parameters."
    )
