"""A flat effect inside the box: an element, or a disc whose balance between load cases the
library's disc does not hold.

One disc parameter vector sets the stiffness of all four load cases at once. A specimen whose
balance between them lies outside what the disc can produce (softer in one load case through
physics outside the library, laxer in another than any laxity law gives, stiffer in one than
the others allow) is still fitted within the noise by the search: the disc moves, and a
parallel element makes up the rest in a load case, acting from about 0 Nm with a law near the
disc's own. Such an effect carries about the same share of the moment at every moment
(:class:`femcal.diagnose.outside.ShapeReader`); an element with a gap, a slack or a knee
carries next to nothing at low moments and a clear share beyond its onset.

The shape cannot settle it: a facet already in contact at the neutral posture, or a ligament
without slack, also acts from about 0 Nm. So a flat effect's probability is shared evenly
between the element and something outside the library: an effect of the fitted models with
stand-in probability ``s`` (:meth:`~femcal.diagnose.outside.ShapeReader.effect_stand_ins`,
the stiffer side) stands in with probability :data:`SHARE` ``* s``, and its model's
probability is shared out between it and the model with ``unexplained`` in that effect's place
(:func:`femcal.diagnose.outside.split_probabilities`). The verdict is the search's; the
inclusion probabilities say how far the data back each named effect. Laxities (series
effects) saturate by their nature and are not read here. Specimens that look beyond the box
are read by :func:`femcal.diagnose.outside.assess` instead.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from femcal.diagnose.box_edge import STIFFER
from femcal.diagnose.outside import FLAT_DISC, FLAT_ELEMENT, ShapeReader, split_probabilities
from femcal.diagnose.result import UNEXPLAINED, model_label
from femcal.effects.terms import Model

#: The share of a flat effect's probability that goes to something outside the library: the
#: element and the stand-in cannot be told apart by the shape alone.
SHARE = 0.5
#: The probability a model needs to be read for its shape.
MODEL_FLOOR = 1e-3
#: A load case is named as flat from this flatness on: its stand-in probability is at least
#: 0.5 on the ramp of :mod:`femcal.diagnose.outside`.
FLAT_READ = (FLAT_ELEMENT + FLAT_DISC) / 2


def balance_stand_ins(state, probabilities: list[dict], skip: list[bool]) -> list[dict]:
    """Every specimen's probabilities with its flat effects shared out (module docstring).

    Parameters
    ----------
    state : DiagnosisState
        The search's state: every fitted model, the chosen ones.
    probabilities : list of dict, length n
        Each specimen's probabilities
        (:func:`~femcal.diagnose.probabilities.specimen_probabilities`).
    skip : list of bool, length n
        Specimens left as they are (those read for a disc beyond the box).

    Returns
    -------
    list of dict
        A copy of ``probabilities``, each specimen's shared out by :func:`shared_out`; as
        given where the disc model has no network to read the shapes with.
    """
    out = list(probabilities)
    if getattr(state.base, "surrogate", None) is None:
        return out
    reader = ShapeReader(state.base, state.mask)
    for i, prob in enumerate(probabilities):
        if skip[i] or not prob.get("models"):
            continue
        fitted = {}
        for m, (fit, pos) in state.per_spec[i].items():
            if m and model_label(m) in prob["models"]:
                fitted[model_label(m)] = (m, fit.v[pos].double().numpy())
        out[i] = shared_out(prob, fitted, state.chosen[i], reader, i) or prob
    return out


def shared_out(
    prob: dict[str, Any], fitted: dict[str, tuple[Model, np.ndarray]], chosen: Model, reader, i: int
) -> dict[str, Any] | None:
    """One specimen's probabilities with its flat effects shared out, or None where no effect
    of its fitted models stands in.

    Parameters
    ----------
    prob : dict
        The specimen's probabilities (``models``: label -> probability, ``inclusion``).
    fitted : dict
        Model label -> the model and its fitted unit coordinates, shape (dim,).
    chosen : Model
        The model the search chose.
    reader : ShapeReader
        Reads the shapes; ``i`` is the specimen's row in it.

    Returns
    -------
    dict or None
        A copy of ``prob`` shared out (:func:`femcal.diagnose.outside.split_probabilities`,
        ``unexplained`` in place of the parts that stand in), with ``stand_ins``: the chosen
        model's effects that stand in (stand-in probability at least 0.5 before the
        :data:`SHARE`), each with its flatness per load case and its share.
    """
    parts: dict[str, list[tuple[str, float]]] = {}
    stand_ins: dict[str, dict[str, Any]] = {}
    for label, p in prob["models"].items():
        if p < MODEL_FLOOR or label not in fitted:
            continue
        m, v = fitted[label]
        st = reader.effect_stand_ins(m, v, i, STIFFER, False)
        parts[label] = [(str(e), SHARE * st[e]["stand_in"]) for e in m]
        if m == chosen:
            stand_ins = {
                str(e): {"flatness": r["flatness"], "stand_in": round(SHARE * r["stand_in"], 4)}
                for e, r in st.items()
                if r["stand_in"] >= 0.5
            }
    if not any(s > 0 for ps in parts.values() for _, s in ps):
        return None
    shared = split_probabilities(prob, parts, alternative=UNEXPLAINED)
    if stand_ins:
        shared["stand_ins"] = stand_ins
    return shared


def flat_note(probabilities: dict[str, Any]) -> str | None:
    """The chosen model's flat effects in words (``probabilities["stand_ins"]`` of
    :func:`shared_out`), for summary.md and the plots; None where there are none."""
    stand_ins = probabilities.get("stand_ins") or {}
    if not stand_ins:
        return None
    parts = []
    for term, reading in stand_ins.items():
        flat = {lc: f for lc, f in reading["flatness"].items() if f >= FLAT_READ}
        cases = ", ".join(f"{lc} (flatness {f:.2f})" for lc, f in flat.items())
        parts.append(f"{term} acts from about 0 Nm in {cases or 'its load cases'}")
    return (
        "Possibly a stand-in: "
        + "; ".join(parts)
        + ". A facet in contact at the neutral posture or a ligament without slack does so, and "
        "so does a disc whose balance between load cases the library's disc does not hold; "
        f"up to half its probability goes to `{UNEXPLAINED}` (outside the library "
        f"{probabilities.get('outside_library', 0.0):.2f})."
    )
