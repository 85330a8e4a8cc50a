"""A diagnosis' result: the verdict of each specimen and the cohort's."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from femcal.effects.split import base_name
from femcal.effects.terms import DISC_ALONE, Model, Term
from femcal.schema import LOAD_CASES

#: The verdict and the label of the disc alone.
NONE = DISC_ALONE


UNEXPLAINED = "unexplained"

#: The verdict of a disc outside the sampled parameter box (:mod:`femcal.diagnose.outside`).
OUTSIDE_BOX = "outside_box"


#: Similarity (cosine, in sigma units) above which a discrepancy "resembles" an effect.
RESEMBLES = 0.8


def verdict_label(effects: Sequence[Term | str], adequate: bool) -> str:
    """``none``, ``unexplained``, ``a+b`` or ``a+b+unexplained``: the effects by name, tied or
    split alike (``facet_contact:split`` is ``facet_contact``); ``effects`` terms or their
    strings."""
    parts = [base_name(e) for e in effects]
    if not adequate:
        parts.append(UNEXPLAINED)
    return "+".join(parts) if parts else NONE


def model_label(effects: Model | Sequence[str]) -> str:
    """A fitted model's name in rankings and plots: ``none`` (the disc alone) or ``a+b``
    (``str(model)``; a result's written terms joined alike)."""
    if isinstance(effects, Model):
        return str(effects)
    return "+".join(effects) if effects else NONE


@dataclass
class SpecimenDiagnosis:
    """Diagnosis of one specimen (see :func:`diagnose`).

    Attributes
    ----------
    verdict : str
        ``none``, ``unexplained``, the effects found joined by ``+``, possibly ending in
        ``+unexplained``; ``outside_box`` (after the effects that engage, if any) where a disc
        outside the parameter box is the most probable explanation.
    effects : list of str
        The registered effects found, by name.
    model : list of str
        The chosen model's effects as fitted, each tied or in its split form
        (``facet_contact:split``): what ``femcal calibrate --effects`` takes.
    load_cases : dict of str to list of str
        Per effect of ``model`` (by registered name), the load cases it acts in as fitted:
        its likely ones or others its ``load_case_prior`` allows (:mod:`femcal.effects.terms`);
        ``probabilities["acts_in"]`` gives the probability of each.
    adequate : bool
        The final model explains the data within the noise.
    ranking : list of dict
        Every model fitted (``effect`` = its label, ``effects``, ``mae_deg``, ``criterion``
        (BIC, ``chi^2 + k ln n`` with ``k`` the ``effective_parameters`` by default),
        ``effective_parameters`` (trace of the hat matrix), ``parameters`` of its effects
        ± sd), best first.
    residuals : ndarray, shape (4, m)
        Disc-alone residuals, measured - model (deg, NaN where not measured).
    final_residuals : ndarray, shape (4, m)
        The same for the final model as fitted (with an ``outside_box`` verdict, the chosen
        model with the effects that stand in for the disc).
    sigma : ndarray, shape (4, m), or None
        Each point's sigma (deg): the noise over the square root of the point's weight (the
        mean of ``k`` repeated measurements weighs ``k``) with the surrogate's error.
    surrogate_sd : ndarray, shape (4, m), or None
        The surrogate's part of each point's sigma (deg), NaN where not measured:
        ``diagnosis.json`` shows both parts (``sigma_parts``).
    curves : dict
        ``moments`` (q,) over the specimen's own measured range and the continuous curves
        (4, q) of the disc alone (``none``) and of the final model (its label).
    discrepancy : dict or None
        ``mean``, ``sd`` (4, q) on ``curves["moments"]``, ``mae_deg`` (model + discrepancy),
        ``amplitude_deg``, ``description`` (sentences), ``similarity`` (effect -> cosine),
        ``resembles`` (an effect name or None), ``model`` (the label it sits on).
    next_measurement : dict or None
        Where the two closest explanations (criteria within ``min_delta``) differ most:
        ``between`` (the chosen model, its rival), ``criterion_gap``, ``load_case``,
        ``moment_nm``, ``difference_deg`` and ``difference_sigma`` (in the sigma at that
        moment); with a moment policy also ``within_measured_range`` and, when the point lies
        beyond the specimen's protocol, ``within_protocol`` (the best point within it).
    probabilities : dict
        ``models`` (label -> posterior probability of every model fitted, and of the chosen
        one with a discrepancy, ``<model>+unexplained``), ``inclusion`` (effect ->
        probability), ``acts_in`` (effect -> load case -> the probability that it acts there
        given that it is present), ``outside_library`` and ``most_probable``
        (:mod:`femcal.diagnose.probabilities`); where the specimen looks beyond the
        parameter box, also ``outside_box`` (the probability of a disc outside it) and the
        models' out-of-box alternatives (``facet_contact+outside_box``, ``outside_box``).
    outside_box : dict or None
        Where the specimen lies beyond the disc's reach or its disc-alone fit presses against
        the box (:func:`femcal.diagnose.outside.assess`): ``named`` (the verdict names the
        box), ``probability``, ``side`` (``stiffer`` or ``softer``), ``load_cases``,
        ``on_bounds`` (``parameter``, ``bound``, ``value``), ``outside_points``,
        ``stand_ins`` (per effect of the chosen model: ``flatness`` per load case,
        ``stand_in`` probability), ``discrepancy``, ``remedy`` and ``summary``; None
        elsewhere.
    """

    specimen: str
    verdict: str
    baseline_mae_deg: float
    ranking: list[dict[str, Any]]
    residuals: np.ndarray
    failures: dict[str, Any] = field(default_factory=dict)
    effects: list[str] = field(default_factory=list)
    model: list[str] = field(default_factory=list)
    load_cases: dict[str, list[str]] = field(default_factory=dict)
    adequate: bool = True
    adequacy: dict[str, Any] = field(default_factory=dict)
    final_mae_deg: float = float("nan")
    final_residuals: np.ndarray | None = None
    curves: dict[str, Any] = field(default_factory=dict)
    discrepancy: dict[str, Any] | None = None
    next_measurement: dict[str, Any] | None = None
    probabilities: dict[str, Any] = field(default_factory=dict)
    sigma: np.ndarray | None = None
    surrogate_sd: np.ndarray | None = None
    outside_box: dict[str, Any] | None = None

    @property
    def discrepancy_mae_deg(self) -> float | None:
        return None if self.discrepancy is None else self.discrepancy["mae_deg"]

    @property
    def final_label(self) -> str:
        return model_label(self.model or self.effects)

    def to_dict(self) -> dict[str, Any]:
        disc = None
        if self.discrepancy is not None:
            disc = {
                k: v
                for k, v in self.discrepancy.items()
                if k not in ("mean", "sd") and not isinstance(v, np.ndarray)
            }
        return {
            "specimen": self.specimen,
            "verdict": self.verdict,
            "effects": list(self.effects),
            "model": list(self.model),
            "load_cases": self.load_cases,
            "adequate": bool(self.adequate),
            "adequacy": self.adequacy,
            "baseline_mae_deg": self.baseline_mae_deg,
            "final_mae_deg": self.final_mae_deg,
            "ranking": self.ranking,
            "discrepancy": disc,
            "next_measurement": self.next_measurement,
            "probabilities": self.probabilities,
            "failures": self.failures,
            "outside_box": self.outside_box,
            "sigma_parts": self.sigma_parts(),
        }

    def sigma_parts(self) -> dict[str, Any] | None:
        """The parts of the specimen's sigma (deg), averaged over its measured points and per
        load case: the total, the measurement noise's and the surrogate's."""
        if self.sigma is None or self.surrogate_sd is None:
            return None
        total, sur = np.asarray(self.sigma, dtype=float), np.asarray(self.surrogate_sd, float)
        noise = np.sqrt(np.clip(total**2 - sur**2, 0.0, None))
        out: dict[str, Any] = {}
        for key, part in (("sigma_deg", total), ("noise_deg", noise), ("surrogate_deg", sur)):
            ok = np.isfinite(part)
            out[key] = float(part[ok].mean()) if ok.any() else None
            out[f"{key[:-4]}_by_load_case_deg"] = {
                lc: float(part[j][ok[j]].mean()) for j, lc in enumerate(LOAD_CASES) if ok[j].any()
            }
        return out


#: The median chi-square per degree of freedom of the final fits above which the stated noise
#: is said to be too small (1.5: the residuals' sd is 1.22 x what the noise allows). With the
#: noise right the median lies near or below 1: the fits' effective parameters are counted in
#: their degrees of freedom, and the search fits part of the noise.
NOISE_TOO_SMALL = 1.5
#: Specimens a cohort needs for :meth:`Diagnosis.noise_check`: the median of fewer is too
#: uncertain to say the noise is wrong.
NOISE_CHECK_MIN = 8


@dataclass
class Diagnosis:
    """Diagnosis of a cohort.

    ``sigma_deg`` is the noise sd inside the surrogate's trained moments; ``sigma_by_moment``
    (m,) the sd at each moment of the grid (larger where the surrogate extrapolates).
    """

    specimens: list[SpecimenDiagnosis]
    sigma_deg: float
    noise_deg: float
    noise_sd_deg: float
    surrogate_error_deg: float
    moments: np.ndarray
    seconds: float
    sigma_by_moment: np.ndarray | None = None
    alpha: float = 0.01

    def verdicts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for s in self.specimens:
            out[s.verdict] = out.get(s.verdict, 0) + 1
        return out

    def effect_counts(self) -> dict[str, int]:
        """How many specimens name each registered effect, ``unexplained`` and
        ``outside_box``."""
        out: dict[str, int] = {}
        for s in self.specimens:
            parts = s.verdict.split("+")
            box = [OUTSIDE_BOX] if OUTSIDE_BOX in parts else []
            missing = not s.adequate and (not box or UNEXPLAINED in parts)
            for e in [*s.effects, *box, *([UNEXPLAINED] if missing else [])]:
                out[e] = out.get(e, 0) + 1
        return out

    def found_effects(self) -> list[str]:
        """Registered effects named for at least one specimen, most frequent first."""
        counts = {
            k: v for k, v in self.effect_counts().items() if k not in (UNEXPLAINED, OUTSIDE_BOX)
        }
        return sorted(counts, key=lambda k: (-counts[k], k))

    def found_forms(self) -> list[str]:
        """The found effects as ``femcal calibrate --effects`` takes them: each in the form
        (tied or split) most of its specimens were fitted with, most frequent first."""
        counts: dict[str, dict[str, int]] = {}
        for s in self.specimens:
            for form in s.model:
                by_form = counts.setdefault(base_name(form), {})
                by_form[form] = by_form.get(form, 0) + 1
        return [
            max(counts[e], key=lambda f, e=e: (counts[e][f], f)) if e in counts else e
            for e in self.found_effects()
        ]

    def noise_check(self) -> dict[str, Any] | None:
        """Whether the residuals of the final fits say the stated noise is too small.

        Returns None for fewer than :data:`NOISE_CHECK_MIN` specimens with a final fit; else
        ``median_chi2_per_dof`` of the final fits, ``factor`` (its square root: about how many
        times the noise the residuals' sd is), ``too_small`` (the median exceeds
        :data:`NOISE_TOO_SMALL`) and ``message`` (None unless ``too_small``).
        """
        ratios = [
            f["chi2"] / f["dof"]
            for s in self.specimens
            if (f := (s.adequacy or {}).get("final")) and f.get("dof", 0) > 0
        ]
        if len(ratios) < NOISE_CHECK_MIN:
            return None
        median = float(np.median(ratios))
        factor = float(np.sqrt(median))
        too_small = median > NOISE_TOO_SMALL
        message = None
        if too_small:
            message = (
                f"the stated noise looks too small: the final fits' median chi-square per "
                f"degree of freedom is {median:.2f} over {len(ratios)} specimens (about 1 or "
                f"below when the noise is right), so the residuals' sd is about {factor:.2g} "
                f"times the {self.noise_deg:.3g} deg counted. Effects named at this noise may "
                "be false alarms: give the sd of one measurement with --noise-deg, or set "
                "diagnose.noise_deg: null to estimate it from the data"
            )
        return {
            "median_chi2_per_dof": round(median, 4),
            "factor": round(factor, 4),
            "too_small": too_small,
            "message": message,
        }

    def cohort_verdict(self) -> str:
        """The most frequent verdict other than ``none`` if it covers at least a quarter of
        the cohort, else ``none``."""
        counts = {k: v for k, v in self.verdicts().items() if k != NONE}
        if not counts:
            return NONE
        best = max(counts, key=counts.get)
        return best if counts[best] >= 0.25 * len(self.specimens) else NONE

    def to_dict(self) -> dict[str, Any]:
        return {
            "sigma_deg": self.sigma_deg,
            "sigma_by_moment": None
            if self.sigma_by_moment is None
            else [float(s) for s in self.sigma_by_moment],
            "noise_deg": self.noise_deg,
            "noise_sd_deg": self.noise_sd_deg,
            "surrogate_error_deg": self.surrogate_error_deg,
            "alpha": self.alpha,
            "noise_check": self.noise_check(),
            "cohort_verdict": self.cohort_verdict(),
            "verdicts": self.verdicts(),
            "effects": self.effect_counts(),
            "seconds": self.seconds,
            "specimens": [s.to_dict() for s in self.specimens],
        }
