"""Posterior elements of the motion segment in the CalculiX deck: facet joints and ligaments.

The disc model (:mod:`femcal.fe.calculix`) joins a fixed lower endplate to a rigid upper one.
The posterior elements join the same two bodies: every element connects a node rigidly tied
to the upper endplate (added to its ``*RIGID BODY`` node set, so it moves with the reference
node) with a node of the lower vertebra (fixed in all translations, like the lower endplate).
The vertebrae themselves stay rigid; only the joints and ligaments between them deform.

Facet joints (:class:`~femcal.fe.calculix_settings.FacetSettings`)
    one ``GAPUNI`` element per side, both nodes at the facet's centre. CalculiX's gap condition
    ``d + n . (u2 - u1) >= 0`` (node 1 upper, node 2 lower, fixed) closes when the upper node
    has moved the clearance ``d`` along the contact normal ``n``: for the right facet
    ``n = (cos a cos i, sin a cos i, -sin i)`` and for the left ``(-cos a cos i, sin a cos i,
    -sin i)``, with ``a`` the joint plane's angle to the sagittal plane and ``i`` the
    normal's downward tilt. So the inferior articular process of the upper vertebra closes on
    the lower one when it moves laterally-anteriorly (axial rotation, one side at a time) or
    down (extension), and lifts off in flexion. A closed gap is a linear spring of the contact
    stiffness.
Ligaments (:class:`~femcal.fe.calculix_settings.LigamentSettings`)
    one ``SPRINGA`` element (two for a bilateral ligament, ``lateral_mm > 0``), vertical, with
    a ``*SPRING, NONLINEAR`` force-elongation table (:func:`ligament_curve`): no force up to the
    slack elongation, a quadratic toe, then linear. CalculiX keeps the force constant beyond the
    table, so the table runs from the slack point (force 0 below it) to far beyond any
    elongation a load case reaches.

Units: mm, N. Axes: x lateral (right), y anterior, z cranial; lower endplate at z = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from femcal.fe.calculix_settings import FacetSettings, LigamentSettings, PosteriorSettings

#: Toe-region samples of a ligament's force-elongation table.
TOE_POINTS = 6
#: The table's last elongation, beyond the linear region's start, in rest lengths (plus 50 mm).
TABLE_REACH = 10.0


def _real(value: float) -> str:
    """A number with a decimal point (CalculiX tells reals from integers by it)."""
    text = f"{value:.9g}"
    if "." in text or "n" in text:
        return text
    if "e" in text:
        mantissa, exponent = text.split("e")
        return f"{mantissa}.e{exponent}"
    return text + "."


def ligament_curve(ligament: LigamentSettings) -> np.ndarray:
    """The force-elongation table of one ligament spring.

    Parameters
    ----------
    ligament : LigamentSettings

    Returns
    -------
    ndarray of shape (n, 2)
        Rows ``(force N, elongation mm)`` in increasing elongation: 0 N at the slack elongation
        ``slack_strain * length_mm``, ``k e^2 / (2 t)`` over the toe (``e`` past slack, ``t =
        toe_strain * length_mm``), then ``k (e - t / 2)`` with ``k = stiffness_n_per_mm``.
    """
    length = ligament.length_mm
    k = ligament.stiffness_n_per_mm
    slack = ligament.slack_strain * length
    toe = ligament.toe_strain * length
    past = [0.0]
    if toe > 0:
        past += [toe * i / TOE_POINTS for i in range(1, TOE_POINTS + 1)]
    past.append(toe + TABLE_REACH * length + 50.0)
    rows = []
    for e in past:
        force = k * e * e / (2.0 * toe) if e <= toe and toe > 0 else k * (e - toe / 2.0)
        rows.append((force, slack + e))
    return np.asarray(rows, dtype=float)


def facet_normal(facets: FacetSettings, side: float) -> np.ndarray:
    """Unit contact normal of the right (``side = +1``) or left (``-1``) facet, shape (3,)."""
    a = math.radians(facets.axial_angle_deg)
    i = math.radians(facets.inclination_deg)
    return np.array([side * math.cos(a) * math.cos(i), math.sin(a) * math.cos(i), -math.sin(i)])


@dataclass
class PosteriorDeck:
    """The deck lines of the posterior elements and the node set of the rigid upper body.

    Attributes
    ----------
    lines : list of str
        Nodes, node sets, elements, ``*GAP`` / ``*SPRING`` cards and the lower nodes'
        ``*BOUNDARY``; model data, placed before ``*RIGID BODY``.
    rigid_set : str
        Name of the node set of the rigid upper body: the upper endplate and every upper node.
    upper, lower : ndarray of shape (n_elements, 3)
        Attachment points of each element (mm).
    names : list of str
        Element set of each element.
    """

    lines: list[str] = field(default_factory=list)
    rigid_set: str = "TOP_POSTERIOR"
    upper: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    lower: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    names: list[str] = field(default_factory=list)


def _ids(labels: list[int], per_line: int = 16) -> list[str]:
    return [
        ", ".join(str(v) for v in labels[i : i + per_line]) for i in range(0, len(labels), per_line)
    ]


def _elements(posterior: PosteriorSettings) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """(element set, element type, upper point, lower point) of every element."""
    out = []
    facets = posterior.facets
    if facets is not None:
        for side, tag in ((1.0, "R"), (-1.0, "L")):
            point = np.array([side * facets.lateral_mm, -facets.posterior_mm, facets.height_mm])
            out.append((f"FACET_{tag}", "GAPUNI", point, point.copy()))
    for name, lig in posterior.ligaments.items():
        sides = (1.0, -1.0) if lig.lateral_mm > 0 else (0.0,)
        for side in sides:
            centre = np.array([side * lig.lateral_mm, -lig.posterior_mm, lig.height_mm])
            half = np.array([0.0, 0.0, lig.length_mm / 2.0])
            out.append((f"LIG_{name.upper()}", "SPRINGA", centre + half, centre - half))
    return out


def posterior_deck(
    posterior: PosteriorSettings, top_nodes: np.ndarray, first_node: int, first_element: int
) -> PosteriorDeck:
    """The deck lines of ``posterior``'s elements.

    Parameters
    ----------
    posterior : PosteriorSettings
        The elements present (none: an empty deck).
    top_nodes : ndarray of int, shape (n_top,)
        0-based indices of the upper endplate's nodes (deck labels are index + 1).
    first_node, first_element : int
        First free node and element labels of the deck.

    Returns
    -------
    PosteriorDeck
    """
    elements = _elements(posterior)
    if not elements:
        return PosteriorDeck(rigid_set="TOP")
    n = len(elements)
    upper_ids = [first_node + i for i in range(n)]
    lower_ids = [first_node + n + i for i in range(n)]
    upper = np.array([e[2] for e in elements])
    lower = np.array([e[3] for e in elements])
    lines = [
        "** Posterior elements (femcal.fe.posterior): nodes tied to the rigid upper body",
        "*NODE, NSET=POSTERIOR_UPPER",
        *(f"{i}, {_real(x)}, {_real(y)}, {_real(z)}" for i, (x, y, z) in zip(upper_ids, upper)),
        "** and nodes of the fixed lower vertebra",
        "*NODE, NSET=POSTERIOR_LOWER",
        *(f"{i}, {_real(x)}, {_real(y)}, {_real(z)}" for i, (x, y, z) in zip(lower_ids, lower)),
        "*NSET, NSET=TOP_POSTERIOR",
        *_ids([int(i) + 1 for i in top_nodes] + upper_ids),
        "*BOUNDARY",
        "POSTERIOR_LOWER, 1, 3",
    ]
    by_set: dict[tuple[str, str], list[int]] = {}
    for i, (elset, kind, _, _) in enumerate(elements):
        by_set.setdefault((elset, kind), []).append(i)
    for (elset, kind), members in by_set.items():
        lines.append(f"*ELEMENT, TYPE={kind}, ELSET={elset}")
        lines += [f"{first_element + i}, {upper_ids[i]}, {lower_ids[i]}" for i in members]
    facets = posterior.facets
    for elset, _ in by_set:
        if elset.startswith("FACET_"):
            assert facets is not None
            normal = facet_normal(facets, 1.0 if elset.endswith("R") else -1.0)
            lines += [
                f"*GAP, ELSET={elset}",
                f"{_real(facets.gap_mm)}, {_real(normal[0])}, {_real(normal[1])}, "
                f"{_real(normal[2])}, , {_real(facets.stiffness_n_per_mm)}",
            ]
        else:
            ligament = posterior.ligaments[elset[len("LIG_") :].lower()]
            lines += [f"*SPRING, ELSET={elset}, NONLINEAR", ""]
            lines += [f"{_real(f)}, {_real(e)}" for f, e in ligament_curve(ligament)]
    names = [e[0] for e in elements]
    return PosteriorDeck(
        lines=lines, rigid_set="TOP_POSTERIOR", upper=upper, lower=lower, names=names
    )
