"""Edge cohorts: specimens drawn across the edges of femcal's assumptions, not inside them.

A cohort holds eight classes of specimens. Each specimen is a disc, plus anatomical structures
whose load cases, laws and sizes are drawn per specimen. Nothing here comes from femcal (numpy
and the standard library only; a test checks the imports): the load cases each structure acts
in, its laws, its sizing and the discs' range are this module's own, taken from anatomy.

**Discs.** Inside the sampled box: one held-out FE configuration of the study's ``Test`` split
per specimen (``Test/ROM_Results_<LoadCase>_TestData_64_wMoment.csv`` under
``$FEMCAL_DATA_MIRROR``; 1..5 Nm), drawn without replacement. Outside it (class
``outside_box``): CalculiX discs of the committed store ``experiments/fe_outside_box.jsonl.gz``
(written by :mod:`experiments.fe_outside_box`: 16 discs whose five matrix and fibre
stiffnesses all lie above the box, 0.5..10 Nm), with no posterior element. Every curve is a
monotone cubic Hermite interpolation in ``log M - log phi`` (Fritsch & Carlson 1980), a power
law with the last secant's slope beyond the FE moments.

**Where each structure acts**, drawn per specimen and load case (:data:`ACTS_PRIOR`,
Bernoulli; at least one load case):

* facets: Extension (0.9) and AxialRotation (0.85), where the articular surfaces are
  compressed (Adams & Hutton 1980; Sharma et al. 1995); LateralBending (0.4), by ipsilateral
  impingement, where facet contact forces are measured in lateral bending as in extension and
  axial rotation (Wilson et al. 2006; Niosi et al. 2008); never in Flexion, where the facets
  separate;
* ligaments: Flexion (0.95) and LateralBending (0.8) (Sharma et al. 1995; Heuer et al. 2007);
  Extension (0.35), where the facet capsules strain as well (Ianuzzi et al. 2004);
* neutral zone: each load case with 0.75, at least two (Panjabi 1992; Yamamoto et al. 1989);
* out-of-library softening (truth ``unexplained``): each load case with 0.5.

**Laws** (per load case; none is a member of femcal's families, a power law from a rounded
gap, an exponential toe and a Weibull laxity):

* facets, parallel, of ``x = (phi - gap)_+``: bilinear contact ``k (x + (r - 1)(x - c)_+)``
  (cartilage, then bone; r 2.5-8) or exponential contact ``k (exp(x / x0) - 1)``;
* ligaments, parallel: trilinear (slopes ``k``, ``r2 k``, ``r2 r3 k``; r2 1.1-6.4, r3 2.4-10,
  the slope ratios of lumbar FE ligament tables, PMC8147546 Table 2: SSL 2.5 -> 5.3 -> 34
  N/mm, ITL 0.3 -> 1.8 -> 10.7, CL 36 -> 159 -> 384) or fibre recruitment (fibres with slacks
  spread uniformly over a width ``w``: ``k x^2 / 2w``, then ``k (x - w/2)``; Lanir 1983);
* neutral zone, series, at the applied moment: ``a atan(M/m0) / atan(5/m0)``, a dead band
  ``a min(M/mc, 1)``, or a logarithmic laxity ``a ln(1 + M/m0) / ln(1 + 5/m0)`` that keeps
  growing;
* softening, series: a yield ``c (M - My)_+`` (the annulus loses stiffness beyond a moment)
  or a creep-like ``c (M / 5)^p``, p 1.5-2.5, that accelerates with the load.

**Sizing.** A parallel structure carries a drawn share of the applied moment at 5 Nm
(:data:`SHARE`; the shares of a load case add up, the disc carries the rest) and engages at a
drawn fraction of the segment's rotation there (:data:`ENGAGE`). A series structure adds a
drawn rotation at 5 Nm (:data:`LAXITY_DEG`; softening: a fraction of the disc's rotation).
Parallel elements share the moment with the disc, ``M = M_d + sum M_e(phi_d(M_d))``, solved
per point by bisection in ``log M_d``.

**Noise** (the stated noise is ``--noise-deg``, 0.05 deg): per specimen ``white`` (sd s),
``offset`` (a per-curve offset of sd 0.8 s plus white noise of sd 0.6 s) or ``growing`` (sd
``s max(M / 3 Nm, 0.3)``). Per cohort, ``s`` is the stated noise times a drawn scale: 1 for
half the seeds, else 0.6-0.8 or 1.4-1.8 (the stated noise is wrong). The truth records the
true noise of every specimen.

**Protocols** (:data:`PROTOCOLS`): 1..5 Nm by 0.5, 1.25..7.5 Nm by 1.25, and mixed maxima
per load case (1 Nm steps to a maximum drawn per load case from 3, 4, 5, 6 and 7.5 Nm).

References
----------
* Adams & Hutton 1980, J Bone Joint Surg Br 62(3):358-362.
* Sharma, Langrana & Rodriguez 1995, Spine 20(8):887-900.
* Heuer, Schmidt, Klezl, Claes & Wilke 2007, J Biomech 40(2):271-280.
* Wilson, Niosi, Zhu, Oxland & Wilson 2006, J Biomech 39(2):348-353: facet loads in
  extension, lateral bending and axial rotation.
* Niosi, Wilson, Zhu, Keynan, Wilson & Oxland 2008, Spine 33(1):19-26: facet contact forces
  in extension, lateral bending and axial rotation.
* Ianuzzi, Little, Chiu, Baitner, Dawson & Khalsa 2004, Spine J 4(2):141-152: facet capsule
  strains in flexion, extension, lateral bending and axial rotation.
* Lanir 1983, J Biomech 16(1):1-12: fibre recruitment in collagenous tissue.
* Panjabi 1992, J Spinal Disord 5(4):390-396; Yamamoto et al. 1989, Spine 14(11):1256-1260:
  L4-L5 neutral zones 1.8 / 1.6 / 0.4 deg (flexion-extension, lateral bending, axial).
* Wilke et al. 1998, Eur Spine J 7:148-154: pure-moment protocols to 7.5 Nm.
* Fritsch & Carlson 1980, SIAM J Numer Anal 17(2):238-246: monotone cubic interpolation.

``python -m experiments.edge_cohorts --seed S --out DIR`` writes ``measurements.csv`` (what
``femcal diagnose --measurements`` reads), ``truth.json`` and ``cohort.json`` into ``DIR``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from experiments.edge_discs import LOAD_CASES, STORE, Disc, read_outside_store, read_test_curves

F, E, LB, AR = LOAD_CASES
HERE = Path(__file__).resolve().parent
#: Truth classes and the structures each adds to its disc.
CLASSES: dict[str, tuple[str, ...]] = {
    "none": (),
    "facets": ("facets",),
    "ligaments": ("ligaments",),
    "neutral_zone": ("laxity",),
    "facets+ligaments": ("facets", "ligaments"),
    "facets+neutral_zone": ("facets", "laxity"),
    "unexplained": ("softening",),
    "outside_box": (),
}
PARALLEL = ("facets", "ligaments")
#: Probability that a structure acts in a load case (drawn per specimen).
ACTS_PRIOR: dict[str, dict[str, float]] = {
    "facets": {F: 0.0, E: 0.9, LB: 0.4, AR: 0.85},
    "ligaments": {F: 0.95, E: 0.35, LB: 0.8, AR: 0.0},
    "laxity": dict.fromkeys(LOAD_CASES, 0.75),
    "softening": dict.fromkeys(LOAD_CASES, 0.5),
}
MIN_LOAD_CASES = {"facets": 1, "ligaments": 1, "laxity": 2, "softening": 1}
LAWS: dict[str, tuple[str, ...]] = {
    "facets": ("bilinear", "exponential"),
    "ligaments": ("trilinear", "recruitment"),
    "laxity": ("arctan", "dead_band", "logarithmic"),
    "softening": ("yield", "creep"),
}
#: Applied moment (Nm) at which every structure is sized.
REFERENCE_NM = 5.0
#: Share of the applied moment a parallel structure carries at REFERENCE_NM, per load case.
SHARE: dict[str, dict[str, tuple[float, float]]] = {
    "facets": {E: (0.2, 0.5), LB: (0.1, 0.3), AR: (0.15, 0.45)},
    "ligaments": {F: (0.2, 0.5), E: (0.08, 0.25), LB: (0.1, 0.35)},
}
#: Gap or slack as a fraction of the segment's rotation at REFERENCE_NM, per load case.
ENGAGE: dict[str, dict[str, tuple[float, float]]] = {
    "facets": {E: (0.15, 0.55), LB: (0.35, 0.7), AR: (0.05, 0.4)},
    "ligaments": {F: (0.25, 0.6), E: (0.4, 0.7), LB: (0.3, 0.6)},
}
#: Shape parameters of the laws (fractions of the engaged span, ratios, Nm, exponents).
SHAPES: dict[str, dict[str, tuple[float, float]]] = {
    "bilinear": {"knee_frac": (0.2, 0.6), "stiffening": (2.5, 8.0)},
    "exponential": {"scale_frac": (0.2, 0.6)},
    "trilinear": {
        "toe_frac": (0.15, 0.45),
        "mid_frac": (0.2, 0.4),
        "r2": (1.1, 6.4),
        "r3": (2.4, 10.0),
    },
    "recruitment": {"width_frac": (0.3, 1.0)},
    "arctan": {"moment_nm": (0.2, 0.8)},
    "dead_band": {"moment_nm": (0.5, 2.0)},
    "logarithmic": {"moment_nm": (0.3, 1.5)},
    "yield": {"yield_nm": (1.5, 3.5)},
    "creep": {"power": (1.5, 2.5)},
}
#: Neutral-zone rotation (deg) at REFERENCE_NM, per load case (about half to 1.5 x the L4-L5
#: neutral zones of Yamamoto et al. 1989).
LAXITY_DEG: dict[str, tuple[float, float]] = {
    F: (0.4, 1.3),
    E: (0.4, 1.3),
    LB: (0.35, 1.2),
    AR: (0.12, 0.45),
}
#: Softening rotation at REFERENCE_NM as a fraction of the disc's own rotation there.
SOFTENING_FRAC = (0.08, 0.25)
#: Protocols: a moment grid (Nm) for all load cases, or None for mixed maxima.
PROTOCOLS: dict[str, tuple[float, ...] | None] = {
    "1-5 Nm x 0.5": tuple(np.arange(1.0, 5.01, 0.5)),
    "1.25-7.5 Nm x 1.25": tuple(np.arange(1.25, 7.51, 1.25)),
    "mixed maxima": None,
}
MIXED_MAXIMA_NM = (3.0, 4.0, 5.0, 6.0, 7.5)
NOISE_KINDS = ("white", "offset", "growing")
STATED_NOISE_DEG = 0.05
#: A draw is redrawn when its RoM exceeds both values (deg; x the disc's own largest RoM).
ROM_CAP_DEG, ROM_CAP_GROWTH = 25.0, 1.3
REDRAWS, BISECTIONS = 30, 60


# ------------------------------------------------------------------------------------- laws
def parallel_unit(p: dict, phi: np.ndarray) -> np.ndarray:
    """Moment (Nm) of a parallel law of stiffness 1 at rotation ``phi`` (deg), shape of phi."""
    x = np.maximum(phi - p["engage_deg"], 0.0)
    span, law = p["span_deg"], p["law"]
    if law == "bilinear":
        return x + (p["stiffening"] - 1.0) * np.maximum(x - p["knee_frac"] * span, 0.0)
    if law == "exponential":
        return np.expm1(np.minimum(x / (p["scale_frac"] * span), 50.0))
    if law == "trilinear":
        t1, t2 = p["toe_frac"] * span, p["mid_frac"] * span
        third = p["r2"] * (p["r3"] - 1.0) * np.maximum(x - t1 - t2, 0.0)
        return x + (p["r2"] - 1.0) * np.maximum(x - t1, 0.0) + third
    if law == "recruitment":
        w = p["width_frac"] * span
        return np.where(x < w, x**2 / (2.0 * w), x - w / 2.0)
    raise ValueError(f"No parallel law {law!r}; choose from {LAWS['facets'] + LAWS['ligaments']}.")


def series_rotation(p: dict, moment: np.ndarray) -> np.ndarray:
    """Extra rotation (deg) of a series law at the applied moment (Nm), shape of moment."""
    law, a, ref = p["law"], p["amplitude_deg"], REFERENCE_NM
    if law == "arctan":
        return a * np.arctan(moment / p["moment_nm"]) / np.arctan(ref / p["moment_nm"])
    if law == "dead_band":
        return a * np.minimum(moment / p["moment_nm"], 1.0)
    if law == "logarithmic":
        return a * np.log1p(moment / p["moment_nm"]) / np.log1p(ref / p["moment_nm"])
    if law == "yield":
        return a * np.maximum(moment - p["yield_nm"], 0.0) / (ref - p["yield_nm"])
    if law == "creep":
        return a * (moment / ref) ** p["power"]
    raise ValueError(f"No series law {law!r}; choose from {LAWS['laxity'] + LAWS['softening']}.")


def _u(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(bounds[0] + (bounds[1] - bounds[0]) * rng.random())


def draw_load_cases(structure: str, rng: np.random.Generator) -> list[str]:
    """The load cases a structure acts in, one Bernoulli draw per load case
    (:data:`ACTS_PRIOR`); topped up with the most probable ones to its minimum count."""
    prior = ACTS_PRIOR[structure]
    acts = [lc for lc in LOAD_CASES if rng.random() < prior[lc]]
    for lc in sorted(LOAD_CASES, key=lambda c: -prior[c]):
        if len(acts) >= MIN_LOAD_CASES[structure]:
            break
        if lc not in acts:
            acts.append(lc)
    return [lc for lc in LOAD_CASES if lc in acts]


def draw_structures(labels: Sequence[str], disc: Disc, rng: np.random.Generator) -> dict:
    """Load cases, laws and sized parameters of a specimen's structures.

    Returns
    -------
    dict
        Structure -> load case -> law and parameters (deg, Nm, Nm per unit law).
    """
    out: dict[str, dict[str, dict]] = {}
    for s in labels:
        out[s] = {}
        for lc in draw_load_cases(s, rng):
            p: dict = {"law": LAWS[s][int(rng.integers(len(LAWS[s])))]}
            p.update({k: _u(rng, b) for k, b in SHAPES[p["law"]].items()})
            if s in PARALLEL:
                p["share"] = _u(rng, SHARE[s][lc])
                p["engage_frac"] = _u(rng, ENGAGE[s][lc])
            elif s == "laxity":
                p["amplitude_deg"] = _u(rng, LAXITY_DEG[lc])
            else:
                ref = float(disc.rotation(np.array([REFERENCE_NM]))[LOAD_CASES.index(lc), 0])
                p["amplitude_deg"] = _u(rng, SOFTENING_FRAC) * ref
            out[s][lc] = p
    _size_parallel(out, disc)
    return out


def _size_parallel(structures: dict, disc: Disc) -> None:
    """Gap, span and stiffness of every parallel law: the shares of a load case add up at
    REFERENCE_NM, where the segment turns by the disc's rotation at the moment left to it."""
    for j, lc in enumerate(LOAD_CASES):
        acting = [structures[s][lc] for s in PARALLEL if lc in structures.get(s, {})]
        if not acting:
            continue
        total = min(sum(p["share"] for p in acting), 0.75)
        left = np.full((4, 1), REFERENCE_NM * (1.0 - total))
        phi_star = float(disc.rotation(left)[j, 0])
        factor = total / sum(p["share"] for p in acting)
        for p in acting:
            p["share"] *= factor
            p["engage_deg"] = p["engage_frac"] * phi_star
            p["span_deg"] = phi_star - p["engage_deg"]
            p["stiffness"] = p["share"] * REFERENCE_NM / float(parallel_unit(p, np.array(phi_star)))


def specimen_rom(structures: dict, disc: Disc, moments: np.ndarray) -> np.ndarray:
    """Noise-free RoM (deg) at ``moments`` (4, q) (Nm): the disc with its structures."""
    applied = np.asarray(moments, dtype=float)
    parallel = [
        (LOAD_CASES.index(lc), p) for s in PARALLEL for lc, p in structures.get(s, {}).items()
    ]
    m_disc = applied
    if parallel:
        lo, hi = np.log(applied) - np.log(1e8), np.log(applied)
        for _ in range(BISECTIONS):
            mid = 0.5 * (lo + hi)
            phi = disc.rotation(np.exp(mid))
            total = np.exp(mid)
            for j, p in parallel:
                total[j] += p["stiffness"] * parallel_unit(p, phi[j])
            above = total > applied
            hi, lo = np.where(above, mid, hi), np.where(above, lo, mid)
        m_disc = np.exp(0.5 * (lo + hi))
    rom = disc.rotation(m_disc)
    for s in ("laxity", "softening"):
        for lc, p in structures.get(s, {}).items():
            j = LOAD_CASES.index(lc)
            rom[j] += series_rotation(p, applied[j])
    return rom


# ----------------------------------------------------------------------------- protocols
def protocol_moments(name: str, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """The moments of a protocol, shape (4, q) (NaN-padded where a load case stops earlier),
    and the maxima of a mixed protocol (load case -> Nm; empty otherwise)."""
    grid = PROTOCOLS[name]
    if grid is not None:
        return np.tile(np.asarray(grid, dtype=float), (4, 1)), {}
    maxima = {lc: float(rng.choice(MIXED_MAXIMA_NM)) for lc in LOAD_CASES}
    rows = [sorted(set(np.arange(1.0, m + 0.01, 1.0)) | {m}) for m in maxima.values()]
    out = np.full((4, max(map(len, rows))), np.nan)
    for j, r in enumerate(rows):
        out[j, : len(r)] = r
    return out, maxima


def noise_sd(kind: str, moments: np.ndarray, sd: float) -> tuple[np.ndarray, float]:
    """Per-point white sd (deg) of a noise kind at ``moments`` (4, q), and its per-curve
    offset sd (deg)."""
    if kind == "white":
        return np.full(moments.shape, sd), 0.0
    if kind == "offset":
        return np.full(moments.shape, 0.6 * sd), 0.8 * sd
    return sd * np.maximum(moments / 3.0, 0.3), 0.0


# --------------------------------------------------------------------------------- cohort
@dataclass
class CohortOptions:
    """How a cohort is drawn.

    Attributes
    ----------
    n_per_class : int
        Specimens per class (8 classes).
    stated_noise_deg : float
        The noise a user states (deg); the true noise is it times ``noise_scale``.
    noise_scale : float or None
        None: drawn from the seed (1 for half the seeds, else 0.6-0.8 or 1.4-1.8).
    """

    n_per_class: int = 6
    stated_noise_deg: float = STATED_NOISE_DEG
    noise_scale: float | None = None


@dataclass
class EdgeCohort:
    """Rows of ``measurements.csv`` (specimen, load_case, moment_nm, rom_deg), the truth per
    specimen and the cohort's metadata."""

    rows: list[tuple[str, str, float, float]]
    truth: list[dict]
    meta: dict


def _draw_scale(rng: np.random.Generator) -> float:
    if rng.random() < 0.5:
        return 1.0
    return _u(rng, (0.6, 0.8)) if rng.random() < 0.5 else _u(rng, (1.4, 1.8))


def _contributions(structures: dict, disc: Disc, moments: np.ndarray, rom: np.ndarray) -> dict:
    """Per structure and load case it acts in, the RMS (deg) of what it adds at the measured
    points: the RoM with every structure less the RoM without this one."""
    out = {}
    ok = np.isfinite(moments)
    for s in structures:
        rest = {k: v for k, v in structures.items() if k != s}
        diff = rom - specimen_rom(rest, disc, np.where(ok, moments, 1.0))
        out[s] = {
            lc: float(np.sqrt(np.mean(diff[j][ok[j]] ** 2)))
            for j, lc in enumerate(LOAD_CASES)
            if lc in structures[s]
        }
    return out


def _specimen(i: int, label: str, disc_src: dict, proto: str, rng, sd: float) -> tuple[list, dict]:
    """One specimen's measurement rows and truth record."""
    disc = Disc(disc_src["moments"], disc_src["rom"])
    moments, maxima = protocol_moments(proto, rng)
    ok = np.isfinite(moments)
    at = np.where(ok, moments, 1.0)
    alone = disc.rotation(at)
    cap = max(ROM_CAP_DEG, ROM_CAP_GROWTH * float(alone[ok].max()))
    for _ in range(REDRAWS):
        structures = draw_structures(CLASSES[label], disc, rng)
        rom = specimen_rom(structures, disc, at)
        if np.isfinite(rom[ok]).all() and rom[ok].min() > 0 and rom[ok].max() <= cap:
            break
    else:
        raise ValueError(
            f"Specimen {i} ({label}): no draw in {REDRAWS} stays within {cap:.1f} deg."
        )
    kind = NOISE_KINDS[int(rng.integers(len(NOISE_KINDS)))]
    point_sd, offset_sd = noise_sd(kind, moments, sd)
    offset = rng.normal(0.0, offset_sd, (4, 1)) if offset_sd > 0 else np.zeros((4, 1))
    noisy = np.abs(rom + offset + rng.normal(0.0, 1.0, rom.shape) * point_sd)
    name = f"E{i:03d}"
    rows = [
        (name, lc, float(moments[j, k]), float(noisy[j, k]))
        for j, lc in enumerate(LOAD_CASES)
        for k in range(moments.shape[1])
        if ok[j, k]
    ]
    dev = (rom - alone)[ok]
    truth = {
        "specimen": name,
        "truth": label,
        "structures": structures,
        "acts_in": {s: list(v) for s, v in structures.items()},
        "disc": {k: disc_src[k] for k in ("source", "config_id", "parameters") if k in disc_src},
        "protocol": proto,
        "maxima_nm": maxima,
        "n_points": int(ok.sum()),
        "noise": {
            "kind": kind,
            "sd_deg": sd,
            "offset_sd_deg": offset_sd,
            "rms_deg": float(np.sqrt(np.mean(point_sd[ok] ** 2) + offset_sd**2)),
        },
        "deviation_rms_deg": float(np.sqrt(np.mean(dev**2))),
        "deviation_max_deg": float(np.abs(dev).max()),
        "contribution_rms_deg": _contributions(structures, disc, moments, rom),
    }
    return rows, truth


def make_cohort(
    test_curves: tuple[np.ndarray, np.ndarray],
    outside: Sequence[dict],
    seed: int,
    options: CohortOptions | None = None,
) -> EdgeCohort:
    """Draw a cohort (see the module docstring); every draw comes from ``seed``.

    Parameters
    ----------
    test_curves : (ndarray (k,), ndarray (N, 4, k))
        Held-out FE moments and RoM (:func:`read_test_curves`): the discs inside the box.
    outside : sequence of dict
        Discs outside the box (:func:`read_outside_store`).
    seed : int
    options : CohortOptions, optional
    """
    opt = options or CohortOptions()
    n = opt.n_per_class
    moments, rom = test_curves
    n_inside = n * (len(CLASSES) - 1)
    if n_inside > len(rom) or n > len(outside):
        raise ValueError(
            f"{n} per class needs {n_inside} held-out curves and {n} outside discs; got "
            f"{len(rom)} and {len(outside)}. Lower n_per_class."
        )
    rng = np.random.default_rng(seed)
    scale = _draw_scale(rng) if opt.noise_scale is None else float(opt.noise_scale)
    sd = opt.stated_noise_deg * scale
    inside = iter(rng.permutation(len(rom))[:n_inside])
    out_ids = iter(rng.permutation(len(outside))[:n])
    protos = list(PROTOCOLS)
    rows, truth = [], []
    for c, label in enumerate(CLASSES):
        order = rng.permutation(n)
        for k in range(n):
            if label == "outside_box":
                d = outside[int(next(out_ids))]
                src = {**d, "source": "outside_box"}
            else:
                cfg = int(next(inside))
                src = {"moments": moments, "rom": rom[cfg], "source": "test", "config_id": cfg}
            proto = protos[(c + int(order[k])) % len(protos)]
            r, t = _specimen(len(truth), label, src, proto, rng, sd)
            rows += r
            truth.append(t)
    meta = {
        "generator": "experiments/edge_cohorts.py",
        "seed": int(seed),
        "stated_noise_deg": opt.stated_noise_deg,
        "noise_scale": scale,
        "true_noise_sd_deg": sd,
        "n_specimens": len(truth),
        "n_per_class": n,
        "classes": list(CLASSES),
        "protocols": protos,
    }
    return EdgeCohort(rows=rows, truth=truth, meta=meta)


def write_cohort(cohort: EdgeCohort, folder: Path) -> Path:
    """Write ``measurements.csv``, ``truth.json`` and ``cohort.json``; returns the first."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "measurements.csv"
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["specimen", "load_case", "moment_nm", "rom_deg"])
        w.writerows((s, lc, f"{m:g}", repr(r)) for s, lc, m, r in cohort.rows)
    (folder / "truth.json").write_text(json.dumps(cohort.truth, indent=1) + "\n")
    (folder / "cohort.json").write_text(json.dumps(cohort.meta, indent=2) + "\n")
    return path


def default_raw_dir() -> Path:
    """``$FEMCAL_DATA_MIRROR`` when set, else the project's ``data/raw``."""
    mirror = os.environ.get("FEMCAL_DATA_MIRROR")
    return Path(mirror) if mirror else HERE.parent / "data" / "raw"


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--out", type=Path, required=True, help="cohort folder to write")
    ap.add_argument("--raw-dir", type=Path, default=None, help="folder holding the study's Test/")
    ap.add_argument("--store", type=Path, default=STORE, help="CalculiX discs outside the box")
    ap.add_argument("--n-per-class", type=int, default=CohortOptions.n_per_class)
    args = ap.parse_args(argv)
    curves = read_test_curves(args.raw_dir or default_raw_dir())
    cohort = make_cohort(
        curves,
        read_outside_store(args.store),
        args.seed,
        CohortOptions(n_per_class=args.n_per_class),
    )
    path = write_cohort(cohort, args.out)
    print(f"wrote {path} ({cohort.meta['n_specimens']} specimens), truth.json, cohort.json")


if __name__ == "__main__":
    main()
