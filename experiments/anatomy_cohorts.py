"""Anatomy cohorts: benchmark specimens whose missing physics has per-load-case parameters.

Every specimen is one held-out FE configuration of the study (the ``Test`` split, which
femcal never trains on), read straight from the study's ``ROM_Results_<LoadCase>_TestData_64_
wMoment.csv`` files, plus one class of posterior-element physics written here in numpy. Nothing
is imported from ``femcal.effects``; the laws, their parameterization and the topology are this
module's own:

* **The disc** (:class:`DiscCurve`): a monotone cubic (PCHIP) interpolation of the FE curve in
  ``log M - log phi``; beyond the FE moments a power law with the end slope of that curve.
* **Facet contact** (``facets``), parallel with the disc in Extension and AxialRotation, each
  load case with its own law, gap and stiffness. Extension compresses the articular surfaces;
  axial rotation impinges the contralateral facet, which engages earlier (the axial neutral zone
  of L4-L5 is the smallest of all planes, Yamamoto et al. 1989). Laws: Hertzian
  ``k x^1.5`` or a bilinear contact ``k (x + (r - 1)(x - c)_+)`` (cartilage, then bone),
  ``x = (phi - gap)_+``.
* **Ligament tension** (``ligaments``), parallel in Flexion (supraspinous, interspinous,
  flavum, capsules) and LateralBending (intertransverse, capsules), each load case with its own
  law, slack and stiffness. Laws: the trilinear force-strain curve of lumbar ligaments
  (slopes ``k``, ``r2 k``, ``r2 r3 k``; ratios of the ligament tables of lumbar FE models) or
  a bilinear toe (quadratic toe of length ``t``, then linear).
* **Neutral zone** (``laxity``), in series in every load case, amplitude and transition moment
  per load case (per plane, Panjabi 1992; L4-L5 values of Yamamoto et al. 1989). Laws: tanh
  laxity ``a tanh(M / m0)``, a hyperbolic laxity ``a M / (M + m0)`` or a piecewise-linear one
  ``a min(M / mc, 1)``.
* **Out of the library** (``annulus_yield``, truth ``unexplained``): series softening beyond a
  yield moment in Flexion and AxialRotation, ``c (M - My)_+^p`` or ``c (exp((M - My)_+ / w) -
  1)``, accelerating with the moment (no built-in effect adds rotation that grows faster than
  the load).

A parallel element shares the applied moment with the disc: ``M = M_d + M_e(phi_disc(M_d))``
is solved per point by bisection in ``log M_d``; a series element adds its rotation at the
applied moment. Every parallel element is sized by the ratio of segment RoM to disc-only RoM at
5 Nm in its load case (:data:`ROM_RATIO`), the quantity stepwise-reduction experiments measure
(Heuer et al. 2007), and engages at a fraction of that rotation (:data:`ENGAGE_FRACTION`).

References
----------
* Adams & Hutton 1980, J Bone Joint Surg Br 62(3):358-362: the facets resist about 16 % of the
  compressive force in lordotic standing, none when flexed.
* Sharma, Langrana & Rodriguez 1995, Spine 20(8):887-900: ligaments resist flexion, facets
  extension.
* Zeng et al. 2017, J Healthc Eng 7981513: bilateral facetectomy raises L4-L5 extension
  rotation by 41 % (segment-to-disc ratio about 0.71).
* Heuer, Schmidt, Klezl, Claes & Wilke 2007, J Biomech 40(2):271-280: stepwise reduction of
  L4-L5 segments; RoM grows as ligaments and facets are removed, by load case.
* Ligament force-strain laws of lumbar FE models: trilinear (PMC8147546, Table 2: SSL 2.5 ->
  5.3 -> 34 N/mm, ITL 0.3 -> 1.8 -> 10.7, CL 36 -> 159 -> 384; slope ratios 1.1-6.4, then
  2.4-10) and bilinear moduli (PMC5592017, Table 2: ISL 10 -> 11.6 MPa, SSL 8 -> 15, ITL 10 ->
  58.7, CL 7.5 -> 32.9 at 6-25 % strain): flexion and lateral-bending ligaments differ. They
  rest on Pintar et al. 1992 (J Biomech 25:1351) and Chazal et al. 1985 (J Biomech 18:167);
  Rohlmann et al. 2004 (J Biomech 37:1107): literature stiffnesses vary widely.
* Hindle, Pearcy & Cross 1990, J Biomed Eng 12:340-344: interspinous and supraspinous
  ligaments carry very little load in the first half of flexion.
* Panjabi 1992, J Spinal Disord 5(4):390-396: the neutral zone, per plane. Yamamoto et al.
  1989, Spine 14(11):1256-1260: L4-L5 neutral zones 1.8 deg (flexion-extension), 1.6 (lateral
  bending), 0.4 (axial rotation); RoM at 10 Nm 8.9 / 5.8 / 5.7 / 2.2 deg (F / E / LB / AR).
* Wilke et al. 1998, Eur Spine J 7:148-154: the pure-moment in-vitro protocol (up to 7.5 Nm).

``python -m experiments.anatomy_cohorts --seed S --out DIR`` writes a cohort folder.
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.interpolate import PchipInterpolator

from femcal.errors import ConfigError

LOAD_CASES: tuple[str, ...] = ("Flexion", "Extension", "LateralBending", "AxialRotation")
NONE = "none"
UNEXPLAINED = "unexplained"
#: Truth classes in report order.
CLASSES: tuple[str, ...] = (
    NONE,
    "facet_contact",
    "ligament_tension",
    "neutral_zone",
    "facet_contact+ligament_tension",
    "facet_contact+neutral_zone",
    UNEXPLAINED,
)
#: The anatomical structures each class adds to the disc.
STRUCTURES: dict[str, tuple[str, ...]] = {
    NONE: (),
    "facet_contact": ("facets",),
    "ligament_tension": ("ligaments",),
    "neutral_zone": ("laxity",),
    "facet_contact+ligament_tension": ("facets", "ligaments"),
    "facet_contact+neutral_zone": ("facets", "laxity"),
    UNEXPLAINED: ("annulus_yield",),
}
#: The femcal effect a structure should be named as (None: outside femcal's library).
EFFECT_NAME: dict[str, str | None] = {
    "facets": "facet_contact",
    "ligaments": "ligament_tension",
    "laxity": "neutral_zone",
    "annulus_yield": None,
}
PARALLEL = ("facets", "ligaments")
ACTS_ON: dict[str, tuple[str, ...]] = {
    "facets": ("Extension", "AxialRotation"),
    "ligaments": ("Flexion", "LateralBending"),
    "laxity": LOAD_CASES,
    "annulus_yield": ("Flexion", "AxialRotation"),
}
LAWS: dict[str, tuple[str, ...]] = {
    "facets": ("hertz", "bilinear_contact"),
    "ligaments": ("trilinear", "toe_linear"),
    "laxity": ("tanh", "hyperbolic", "piecewise_linear"),
    "annulus_yield": ("power_yield", "exp_yield"),
}
#: Applied moment (Nm) at which parallel elements are sized and yield amplitudes are drawn.
REFERENCE_NM = 5.0
#: Segment RoM / disc-only RoM at REFERENCE_NM, per structure and load case (uniform draws).
ROM_RATIO: dict[tuple[str, str], tuple[float, float]] = {
    ("facets", "Extension"): (0.55, 0.85),
    ("facets", "AxialRotation"): (0.35, 0.75),
    ("ligaments", "Flexion"): (0.55, 0.85),
    ("ligaments", "LateralBending"): (0.70, 0.92),
}
#: Gap or slack as a fraction of the segment's own rotation at REFERENCE_NM.
ENGAGE_FRACTION: dict[tuple[str, str], tuple[float, float]] = {
    ("facets", "Extension"): (0.25, 0.70),
    ("facets", "AxialRotation"): (0.05, 0.45),
    ("ligaments", "Flexion"): (0.30, 0.65),
    ("ligaments", "LateralBending"): (0.25, 0.60),
}
#: Shape parameters of the parallel laws (fractions of the engaged span phi* - gap, or ratios).
SHAPE_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "hertz": {},
    "bilinear_contact": {"cartilage_frac": (0.2, 0.6), "stiffening": (3.0, 8.0)},
    "trilinear": {
        "toe_frac": (0.2, 0.5),
        "mid_frac": (0.2, 0.4),
        "r2": (1.1, 6.4),
        "r3": (2.4, 10.0),
    },
    "toe_linear": {"toe_frac": (0.3, 1.0)},
}
#: One-sided neutral-zone amplitude (deg) per load case: half the L4-L5 neutral zone of
#: Yamamoto et al. 1989 up to about 1.6 times it (laxity the disc model lacks).
LAXITY_DEG: dict[str, tuple[float, float]] = {
    "Flexion": (0.45, 1.4),
    "Extension": (0.45, 1.4),
    "LateralBending": (0.40, 1.3),
    "AxialRotation": (0.15, 0.5),
}
LAXITY_MOMENT_NM: dict[str, tuple[float, float]] = {
    "tanh": (0.2, 0.8),
    "hyperbolic": (0.1, 0.5),
    "piecewise_linear": (0.5, 2.0),
}
#: Out of the library: yield moment (Nm), extra rotation at REFERENCE_NM as a fraction of the
#: disc's RoM there, and the law's shape.
YIELD_RANGES: dict[str, tuple[float, float]] = {
    "yield_nm": (2.0, 3.8),
    "extra_frac": (0.06, 0.2),
    "power": (1.5, 2.5),
    "width_nm": (0.7, 1.5),
}
#: Measurement protocols (moments in Nm).
PROTOCOLS: dict[str, tuple[float, ...]] = {
    "1-5 Nm x 0.5": (1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0),
    "1.25-5 Nm x 1.25": (1.25, 2.5, 3.75, 5.0),
    "1.25-7.5 Nm x 1.25": (1.25, 2.5, 3.75, 5.0, 6.25, 7.5),
    "0.5-5 Nm x 0.5": (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0),
}
NOISE_DEG = 0.05
#: A draw is redrawn when its RoM exceeds both ROM_MAX_DEG and ROM_GROWTH x the disc's own.
ROM_MAX_DEG, ROM_GROWTH = 20.0, 1.25
REDRAWS, BISECTIONS = 25, 60
TEST_FOLDER, TEST_INFIX = "Test", "TestData_64_"


def expected_effects(label: str) -> frozenset[str]:
    """femcal effects a verdict should name for a truth class (empty for none/unexplained)."""
    names = (EFFECT_NAME[s] for s in STRUCTURES[label])
    return frozenset(n for n in names if n is not None)


# ------------------------------------------------------------------------------------ disc
def read_heldout_curves(raw_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """The study's held-out FE RoM curves, read from its ``Test`` files.

    Parameters
    ----------
    raw_dir : Path
        Folder holding the study's ``Test/`` folder (``data/raw`` or a mirror).

    Returns
    -------
    moments : ndarray, shape (k,)
        Loaded moments (Nm), the 0 Nm column dropped.
    rom : ndarray, shape (N, 4, k)
        RoM (deg) of the N configurations whose four curves are positive and finite, load
        cases in :data:`LOAD_CASES` order.

    Raises
    ------
    ConfigError
        A file is missing or the files disagree on their moments.
    """
    curves, moments = [], None
    for lc in LOAD_CASES:
        path = Path(raw_dir) / TEST_FOLDER / f"ROM_Results_{lc}_{TEST_INFIX}wMoment.csv"
        if not path.is_file():
            raise ConfigError(
                f"No held-out FE curves at {path}. Pass the folder holding the study's Test/ "
                "(data/raw after `dvc repro fetch`, or FEMCAL_DATA_MIRROR)."
            )
        table = pd.read_csv(path)
        m = table.columns.astype(float).to_numpy()
        if moments is not None and not np.array_equal(m, moments):
            raise ConfigError(f"{path}: moments {m.tolist()} differ from {moments.tolist()}.")
        moments = m
        curves.append(table.to_numpy(dtype=float))
    rom = np.stack(curves, axis=1)  # (N, 4, k + 1)
    loaded = moments > 0
    rom = rom[..., loaded]
    ok = np.isfinite(rom).all(axis=(1, 2)) & (rom > 0).all(axis=(1, 2))
    return moments[loaded], rom[ok]


class DiscCurve:
    """One configuration's FE RoM as a monotone function of the applied moment.

    Parameters
    ----------
    moments : ndarray, shape (k,)
        FE moments (> 0, Nm, increasing).
    rom : ndarray, shape (4, k)
        FE RoM (deg, > 0) per load case.
    """

    def __init__(self, moments: np.ndarray, rom: np.ndarray) -> None:
        self.log_m = np.log(np.asarray(moments, dtype=float))
        log_r = np.log(np.maximum.accumulate(np.asarray(rom, dtype=float), axis=1))
        self.curves = [PchipInterpolator(self.log_m, row) for row in log_r]
        self.ends = [
            ((c(self.log_m[0]), c(self.log_m[0], 1)), (c(self.log_m[-1]), c(self.log_m[-1], 1)))
            for c in self.curves
        ]

    def rotation(self, moment: np.ndarray) -> np.ndarray:
        """Disc rotation (deg) at moments ``moment`` (Nm, > 0), shape (4, q) or (q,) -> (4, q)."""
        m = np.broadcast_to(np.asarray(moment, dtype=float), (4, np.shape(moment)[-1]))
        x = np.log(m)
        out = np.empty_like(x)
        lo, hi = self.log_m[0], self.log_m[-1]
        for j, c in enumerate(self.curves):
            (y0, s0), (y1, s1) = self.ends[j]
            inside = c(np.clip(x[j], lo, hi))
            out[j] = np.where(
                x[j] < lo, y0 + s0 * (x[j] - lo), np.where(x[j] > hi, y1 + s1 * (x[j] - hi), inside)
            )
        return np.exp(out)

    def moment(self, rotation: np.ndarray) -> np.ndarray:
        """The disc moment (Nm) giving ``rotation`` (deg), shape (4, q): bisection in log M."""
        target = np.asarray(rotation, dtype=float)
        return _bisect_log(lambda m: self.rotation(m) - target, np.full(target.shape, 1e3))


def _bisect_log(g, upper: np.ndarray) -> np.ndarray:
    """Root in (upper * 1e-8, upper) of an increasing ``g(m)``, elementwise, by bisection in
    ``log m``; shape of ``upper``."""
    lo = np.log(upper) - np.log(1e8)
    hi = np.log(upper)
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        above = g(np.exp(mid)) > 0
        hi = np.where(above, mid, hi)
        lo = np.where(above, lo, mid)
    return np.exp(0.5 * (lo + hi))


# ------------------------------------------------------------------------------------ laws
def parallel_unit_moment(p: dict[str, float | str], phi: np.ndarray) -> np.ndarray:
    """Moment (Nm) of a parallel law with stiffness 1 at disc rotation ``phi`` (deg)."""
    x = np.maximum(phi - float(p["engage_deg"]), 0.0)
    span = float(p["span_deg"])
    law = p["law"]
    if law == "hertz":
        return x**1.5
    if law == "bilinear_contact":
        c = float(p["cartilage_frac"]) * span
        return x + (float(p["stiffening"]) - 1.0) * np.maximum(x - c, 0.0)
    if law == "trilinear":
        t1, t2 = float(p["toe_frac"]) * span, float(p["mid_frac"]) * span
        r2, r3 = float(p["r2"]), float(p["r3"])
        last = r2 * (r3 - 1.0) * np.maximum(x - t1 - t2, 0.0)
        return x + (r2 - 1.0) * np.maximum(x - t1, 0.0) + last
    if law == "toe_linear":
        t = float(p["toe_frac"]) * span
        return np.where(x < t, x**2 / (2.0 * t), x - t / 2.0)
    raise ConfigError(f"No parallel law '{law}'; choose from {LAWS['facets'] + LAWS['ligaments']}.")


def series_rotation(p: dict[str, float | str], moment: np.ndarray) -> np.ndarray:
    """Extra rotation (deg) of a series law at the applied moment ``moment`` (Nm)."""
    law = p["law"]
    if law == "tanh":
        return float(p["amplitude_deg"]) * np.tanh(moment / float(p["moment_nm"]))
    if law == "hyperbolic":
        return float(p["amplitude_deg"]) * moment / (moment + float(p["moment_nm"]))
    if law == "piecewise_linear":
        return float(p["amplitude_deg"]) * np.minimum(moment / float(p["moment_nm"]), 1.0)
    over = np.maximum(moment - float(p["yield_nm"]), 0.0)
    if law == "power_yield":
        return float(p["compliance"]) * over ** float(p["power"])
    if law == "exp_yield":
        return float(p["compliance"]) * np.expm1(over / float(p["width_nm"]))
    known = LAWS["laxity"] + LAWS["annulus_yield"]
    raise ConfigError(f"No series law '{law}'; choose from {known}.")


def _uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    lo, hi = bounds
    return float(lo + (hi - lo) * rng.random())


def draw_structure(
    structure: str, disc: DiscCurve, rng: np.random.Generator
) -> dict[str, dict[str, float | str]]:
    """Law and parameters of one structure, drawn independently for each of its load cases.

    Parameters
    ----------
    structure : str
        ``facets``, ``ligaments``, ``laxity`` or ``annulus_yield``.
    disc : DiscCurve
        The specimen's disc (sizes the parallel elements and the yield amplitude).
    rng : numpy.random.Generator

    Returns
    -------
    dict
        Load case -> ``law`` and its parameters (deg, Nm, Nm/deg^n).
    """
    out: dict[str, dict[str, float | str]] = {}
    ref = np.array([REFERENCE_NM])
    for lc in ACTS_ON[structure]:
        j = LOAD_CASES.index(lc)
        laws = LAWS[structure]
        p: dict[str, float | str] = {"law": laws[int(rng.integers(len(laws)))]}
        disc_ref = float(disc.rotation(ref)[j, 0])
        if structure in PARALLEL:
            ratio = _uniform(rng, ROM_RATIO[(structure, lc)])
            phi_star = ratio * disc_ref
            engage = _uniform(rng, ENGAGE_FRACTION[(structure, lc)]) * phi_star
            p.update(rom_ratio=ratio, engage_deg=engage, span_deg=phi_star - engage)
            for name, bounds in SHAPE_RANGES[str(p["law"])].items():
                p[name] = _uniform(rng, bounds)
            m_disc = float(disc.moment(np.full((4, 1), phi_star))[j, 0])
            unit = float(parallel_unit_moment(p, np.array(phi_star)))
            p["stiffness"] = (REFERENCE_NM - m_disc) / unit
        elif structure == "laxity":
            p["amplitude_deg"] = _uniform(rng, LAXITY_DEG[lc])
            p["moment_nm"] = _uniform(rng, LAXITY_MOMENT_NM[str(p["law"])])
        else:
            p["yield_nm"] = _uniform(rng, YIELD_RANGES["yield_nm"])
            p["extra_frac"] = _uniform(rng, YIELD_RANGES["extra_frac"])
            key = "power" if p["law"] == "power_yield" else "width_nm"
            p[key] = _uniform(rng, YIELD_RANGES[key])
            p["compliance"] = 1.0
            unit = float(series_rotation(p, ref)[0])
            p["compliance"] = p["extra_frac"] * disc_ref / unit
        out[lc] = p
    return out


def specimen_rom(
    structures: dict[str, dict[str, dict[str, float | str]]],
    disc: DiscCurve,
    moments: np.ndarray,
) -> np.ndarray:
    """Noise-free RoM (deg) of the disc with its structures, shape (4, q).

    Parallel elements share the applied moment with the disc (``M = M_d + sum M_e(phi(M_d))``,
    bisection in ``log M_d`` per point); series elements add rotation at the applied moment.
    """
    applied = np.broadcast_to(np.asarray(moments, dtype=float), (4, len(moments))).copy()
    parallel = {s: v for s, v in structures.items() if s in PARALLEL}

    def excess(m_disc: np.ndarray) -> np.ndarray:
        phi = disc.rotation(m_disc)
        carried = np.zeros_like(phi)
        for per_lc in parallel.values():
            for lc, p in per_lc.items():
                j = LOAD_CASES.index(lc)
                carried[j] += float(p["stiffness"]) * parallel_unit_moment(p, phi[j])
        return m_disc + carried - applied

    m_disc = _bisect_log(excess, applied) if parallel else applied
    rom = disc.rotation(m_disc)
    for s, per_lc in structures.items():
        if s in PARALLEL:
            continue
        for lc, p in per_lc.items():
            rom[LOAD_CASES.index(lc)] += series_rotation(p, applied[0])
    return rom


# ---------------------------------------------------------------------------------- cohort
@dataclass
class AnatomyCohort:
    """A cohort with known physics.

    Attributes
    ----------
    measurements : DataFrame
        femcal's long layout: ``specimen, load_case, moment_nm, rom_deg`` (noisy).
    answers : DataFrame
        One row per specimen: ``specimen, config_id, truth, expected_effects`` ("+"-joined,
        "" for none), ``out_of_library, protocol, n_points, effect_rms_deg, effect_max_deg``
        (noise-free deviation from the specimen's own disc at its measured points) and
        ``<structure>_<load case>_<parameter>`` for every drawn law and parameter.
    seed, noise_deg : int, float
        The seed of every draw; the sd of the Gaussian noise (deg).
    """

    measurements: pd.DataFrame
    answers: pd.DataFrame
    seed: int
    noise_deg: float


def assign_protocols(
    n_classes: int, n_per_class: int, protocols: Sequence[str], rng: np.random.Generator
) -> list[str]:
    """Protocols per specimen, class by class: within a class counts differ by at most one,
    and the protocols that get the extra specimen rotate between classes."""
    out: list[str] = []
    k = len(protocols)
    for c in range(n_classes):
        turn = [protocols[(c + j) % k] for j in range(n_per_class)]
        out += [turn[i] for i in rng.permutation(n_per_class)]
    return out


def make_cohort(
    fe_moments: np.ndarray,
    fe_rom: np.ndarray,
    *,
    seed: int,
    n_per_class: int = 9,
    classes: Sequence[str] = CLASSES,
    protocols: Sequence[str] = tuple(PROTOCOLS),
    noise_deg: float = NOISE_DEG,
) -> AnatomyCohort:
    """Draw a cohort (see the module docstring); every random draw comes from ``seed``.

    Parameters
    ----------
    fe_moments : ndarray, shape (k,)
    fe_rom : ndarray, shape (N, 4, k)
        Held-out FE curves (:func:`read_heldout_curves`); each specimen uses its own one.
    seed : int
    n_per_class : int
    classes : sequence of str
        Classes of :data:`CLASSES`.
    protocols : sequence of str
        Keys of :data:`PROTOCOLS`, balanced within each class.
    noise_deg : float
        Sd of the Gaussian measurement noise (deg).

    Raises
    ------
    ConfigError
        Unknown class or protocol, too few FE configurations, or no draw within 0..20 deg.
    """
    for name, known in (("class", CLASSES), ("protocol", PROTOCOLS)):
        bad = [x for x in (classes if name == "class" else protocols) if x not in known]
        if bad:
            raise ConfigError(f"Unknown {name} {bad}; choose from {list(known)}.")
    n = len(classes) * n_per_class
    if n > len(fe_rom):
        raise ConfigError(
            f"{n} specimens need {n} FE curves; got {len(fe_rom)}. Lower n_per_class."
        )
    rng = np.random.default_rng(seed)
    configs = rng.permutation(len(fe_rom))[:n]
    labels = [c for c in classes for _ in range(n_per_class)]
    assigned = assign_protocols(len(classes), n_per_class, protocols, rng)
    rows, frames = [], []
    for i, (label, cfg, proto) in enumerate(zip(labels, configs, assigned)):
        moments = np.asarray(PROTOCOLS[proto], dtype=float)
        disc = DiscCurve(fe_moments, fe_rom[cfg])
        alone = disc.rotation(moments)
        ceiling = max(ROM_MAX_DEG, ROM_GROWTH * float(alone.max()))
        for _ in range(REDRAWS):
            drawn = {s: draw_structure(s, disc, rng) for s in STRUCTURES[label]}
            rom = specimen_rom(drawn, disc, moments)
            if np.isfinite(rom).all() and rom.min() > 0 and rom.max() <= ceiling:
                break
        else:
            raise ConfigError(
                f"Specimen {i} ({label}, configuration {cfg}): no draw in {REDRAWS} keeps the "
                f"RoM within 0..{ceiling:.1f} deg; narrow the ranges or use other curves."
            )
        deviation = rom - alone
        name = f"A{i:03d}"
        noisy = rom + rng.normal(0.0, noise_deg, rom.shape)
        frames.append(
            pd.DataFrame(
                {
                    "specimen": name,
                    "load_case": np.repeat(LOAD_CASES, len(moments)),
                    "moment_nm": np.tile(moments, 4),
                    "rom_deg": noisy.reshape(-1),
                }
            )
        )
        flat = {
            f"{s}_{c}_{k}": v for s, d in drawn.items() for c, p in d.items() for k, v in p.items()
        }
        rows.append(
            {
                "specimen": name,
                "config_id": int(cfg),
                "truth": label,
                "expected_effects": "+".join(sorted(expected_effects(label))),
                "out_of_library": label == UNEXPLAINED,
                "protocol": proto,
                "n_points": int(rom.size),
                "effect_rms_deg": float(np.sqrt(np.mean(deviation**2))),
                "effect_max_deg": float(np.abs(deviation).max()),
                **flat,
            }
        )
    return AnatomyCohort(
        measurements=pd.concat(frames, ignore_index=True),
        answers=pd.DataFrame(rows),
        seed=int(seed),
        noise_deg=float(noise_deg),
    )


def write_cohort(cohort: AnatomyCohort, folder: Path, source: str = "") -> Path:
    """Write ``measurements.csv``, ``answers.csv`` and ``cohort.json`` into ``folder``.

    Returns
    -------
    Path
        The measurement file (what ``femcal diagnose --measurements`` takes).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "measurements.csv"
    cohort.measurements.to_csv(path, index=False)
    cohort.answers.to_csv(folder / "answers.csv", index=False)
    meta = {
        "generator": "experiments/anatomy_cohorts.py",
        "seed": cohort.seed,
        "noise_deg": cohort.noise_deg,
        "n_specimens": len(cohort.answers),
        "classes": cohort.answers["truth"].value_counts().to_dict(),
        "protocols": cohort.answers["protocol"].value_counts().to_dict(),
        "source": source,
    }
    (folder / "cohort.json").write_text(json.dumps(meta, indent=2) + "\n")
    return path


def default_raw_dir(repo: Path) -> Path:
    """``FEMCAL_DATA_MIRROR`` when set, else ``<repo>/data/raw``."""
    mirror = os.environ.get("FEMCAL_DATA_MIRROR")
    return Path(mirror) if mirror else Path(repo) / "data" / "raw"


def main(argv: Sequence[str] | None = None) -> None:
    repo = Path(__file__).resolve().parents[1]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, required=True)
    ap.add_argument("--out", type=Path, required=True, help="cohort folder to write")
    ap.add_argument("--raw-dir", type=Path, default=None, help="folder holding the study's Test/")
    ap.add_argument("--n-per-class", type=int, default=9)
    ap.add_argument("--protocols", default=",".join(PROTOCOLS), help="comma-separated keys")
    args = ap.parse_args(argv)
    raw = args.raw_dir or default_raw_dir(repo)
    moments, rom = read_heldout_curves(raw)
    protocols = [p for p in args.protocols.split(",") if p]
    cohort = make_cohort(
        moments, rom, seed=args.seed, n_per_class=args.n_per_class, protocols=protocols
    )
    path = write_cohort(cohort, args.out, source=str(raw))
    print(f"wrote {path} ({len(cohort.answers)} specimens) and answers.csv")


if __name__ == "__main__":
    main()
