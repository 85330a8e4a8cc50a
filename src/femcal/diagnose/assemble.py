"""The last steps of a diagnosis: adequacy of the chosen models, how probable each explanation
is, the discrepancy and what is missing, continuous curves, rankings and what to measure next."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from femcal.diagnose.discrepancy import (
    DiscrepancyFit,
    dense_grid,
    discrepancy_posterior,
    fit_discrepancy,
    similarity,
)
from femcal.diagnose.explain import (
    _adequacy,
    _dense_base,
    _dense_curves,
    _failures,
    _missing_text,
    _next_measurement,
    _own_range,
    _ranking,
    _signatures,
    _summary,
)
from femcal.diagnose.fits import _Fit
from femcal.diagnose.outside import assess
from femcal.diagnose.probabilities import bootstrap_rng, outside_label, specimen_probabilities
from femcal.diagnose.result import (
    NONE,
    RESEMBLES,
    UNEXPLAINED,
    Diagnosis,
    SpecimenDiagnosis,
    model_label,
    verdict_label,
)
from femcal.diagnose.state import DiagnosisState, Model
from femcal.diagnose.where import not_engaged
from femcal.effects.split import base_name
from femcal.effects.terms import cases_of


def _assemble(
    state: DiagnosisState,
    *,
    disc: _Fit,
    sur: np.ndarray,
    noise_used: float,
    noise_sd: float,
    moment_policy,
    t0: float,
) -> Diagnosis:
    """The verdicts of the models the search chose (``disc``: the disc alone's fit of every
    specimen; ``sur`` (m,) the surrogate's error; ``t0`` the start, for the time taken)."""
    n, measured, mask, sigma = state.n, state.measured, state.mask, state.sigma
    finals: dict[Model, list[int]] = {}
    for i in range(n):
        finals.setdefault(state.chosen[i], []).append(i)
    # One Jacobian per fitted batch: effective parameters and covariance of every model.
    for i in range(n):
        for f, _ in state.per_spec[i].values():
            f.ensure_trace(mask, sigma)
    options = state.options
    # Each final model with the discrepancy it needs (type-II maximum likelihood): how
    # probable something outside the library is, and what it looks like.
    gp = {effects: _gp_fit(state, effects, rows) for effects, rows in finals.items()}
    probabilities = _probabilities(state, finals, gp)
    # The verdict is the most probable explanation: where a fitted model is more probable
    # than the search's choice with or without a discrepancy, that model is the verdict.
    switched = [
        i
        for i, p in enumerate(probabilities)
        if not p["most_probable"].endswith(UNEXPLAINED)
        and tuple(p["most_probable_effects"]) != state.chosen[i]
    ]
    if switched:
        for i in switched:
            state.chosen[i] = tuple(probabilities[i]["most_probable_effects"])
        old, finals = finals, {}
        for i in range(n):
            finals.setdefault(state.chosen[i], []).append(i)
        for effects, rows in finals.items():
            if rows != old.get(effects):  # the fits are per group, in its order
                gp[effects] = _gp_fit(state, effects, rows)
        probabilities = _probabilities(state, finals, gp)
    probabilities, outside = _outside_box(state, disc, finals, gp, probabilities)
    adequacy = _adequacies(state, disc)
    moments = state.base.moments.double().numpy()
    dense = dense_grid(moments, options.curve_points)
    described: list[dict[str, Any] | None] = [None] * n
    if options.discrepancy:
        described = _describe(state, finals, gp, dense, adequacy, probabilities, disc.pred)
    curves0, final_curves = _curves(state, finals, dense, disc.v)
    probe_base, probe, sigma_probe = _probe(state, dense, noise_used, moment_policy)
    pred0 = disc.pred.double().numpy()
    mae0 = np.nanmean(np.abs(measured - pred0).reshape(n, -1), axis=1)
    base = state.base
    unit_disc = base.space.to_unit(base.to_physical(disc.v.double().numpy()))
    out: list[SpecimenDiagnosis] = []
    for i, spec in enumerate(state.specimens):
        ranking = _ranking(state.per_spec[i], i, measured, sigma, state.log_n, base, mask)
        effects = list(state.chosen[i])
        adequate = not probabilities[i]["unexplained"]
        verdict, model = verdict_label(effects, adequate), effects
        if outside[i] is not None and outside[i]["named"]:
            # The box, not the stand-ins: the verdict keeps the effects that engage.
            verdict, adequate, model = outside[i]["verdict"], False, outside[i]["model"]
        f, pos = state.per_spec[i][state.chosen[i]]
        final_res = measured[i] - f.pred[pos].double().numpy()
        own = _own_range(dense, moments, mask[i])
        curves = {"moments": dense, NONE: np.where(own, curves0[i], np.nan)}
        if model and model == effects:
            curves[model_label(effects)] = np.where(own, final_curves[i], np.nan)
        nxt = _next_measurement(
            ranking,
            state.per_spec[i],
            probe_base,
            probe,
            sigma_probe,
            options.min_delta,
            state.chosen[i],
            [moments[mask[i][j]] for j in range(mask.shape[1])],
            noise_deg=noise_used,
        )
        resid = measured[i] - pred0[i]
        out.append(
            SpecimenDiagnosis(
                specimen=str(spec),
                verdict=verdict,
                baseline_mae_deg=float(mae0[i]),
                ranking=ranking,
                residuals=resid,
                failures=_failures(resid, sigma[i], moments, unit_disc[i], base.space.names),
                effects=[base_name(e) for e in model],
                model=model,
                load_cases={base_name(e): list(cases_of(e)) for e in model},
                adequate=adequate,
                adequacy=adequacy[i],
                final_mae_deg=float(np.nanmean(np.abs(final_res))),
                final_residuals=final_res,
                curves=curves,
                discrepancy=described[i],
                next_measurement=nxt,
                probabilities=probabilities[i],
                sigma=np.where(mask[i], sigma[i], np.nan),
                surrogate_sd=np.where(mask[i], state.surrogate_sd[i], np.nan),
                outside_box=outside[i],
            )
        )
    return Diagnosis(
        specimens=out,
        sigma_deg=float(state.sigma_m.min()),
        noise_deg=noise_used,
        noise_sd_deg=float(noise_sd),
        surrogate_error_deg=float(sur.min()),
        moments=moments,
        seconds=time.perf_counter() - t0,
        sigma_by_moment=state.sigma_m,
        alpha=options.alpha,
    )


def _outside_box(state: DiagnosisState, disc: _Fit, finals, gp, probabilities):
    """The out-of-box reading (:func:`femcal.diagnose.outside.assess`) with each specimen's
    discrepancy and curves of its final model (``finals``, ``gp`` per final model): the
    probabilities shared out, and per specimen the reading or None. Where the box is named,
    ``unexplained`` says whether a discrepancy is named beside it."""
    delta = np.full(state.measured.shape, np.nan)
    pred = np.full(state.measured.shape, np.nan)
    for effects, rows in finals.items():
        for pos, i in enumerate(rows):
            delta[i] = gp[effects].delta_at_points[pos]
            f, at = state.per_spec[i][effects]
            pred[i] = f.pred[at].double().numpy()
    probabilities, outside = assess(state, disc, probabilities, delta, pred)
    for p, reading in zip(probabilities, outside):
        if reading is not None and reading["named"]:
            p["unexplained"] = UNEXPLAINED in reading["verdict"].split("+")
    return probabilities, outside


def _adequacies(state: DiagnosisState, disc: _Fit) -> list[dict[str, Any]]:
    """Per specimen: the chi-square and runs tests of the final model and of the disc alone."""
    out = []
    alpha = state.options.alpha
    for i in range(state.n):
        f, pos = state.per_spec[i][state.chosen[i]]
        res = state.measured[i] - f.pred[pos].double().numpy()
        res0 = state.measured[i] - disc.pred[i].double().numpy()
        n_i = float(state.n_points[i])
        out.append(
            {
                "final": _adequacy(res, state.sigma[i], n_i - float(f.trace[pos]), alpha),
                "disc_alone": _adequacy(res0, state.sigma[i], n_i - float(disc.trace[i]), alpha),
            }
        )
    return out


def _gp_fit(state: DiagnosisState, effects: Model, rows: list[int]) -> DiscrepancyFit:
    """Model ``effects`` refitted to specimens ``rows`` with the discrepancy it needs."""
    rows_a = np.asarray(rows)
    v = state.solutions(rows_a, effects)
    return fit_discrepancy(
        state.model(effects),
        v,
        state.measured[rows_a],
        state.sigma[rows_a],
        amplitude_deg="ml",
    )


def _probabilities(state: DiagnosisState, finals, gp) -> list[dict[str, Any]]:
    """Per specimen, :func:`~femcal.diagnose.probabilities.specimen_probabilities` of every
    fitted model and of its final model with its discrepancy (``gp``, per final model, fitted
    to ``finals[model]`` in that order). A model with an effect in a load case beyond its
    likely ones where it does not engage is left out (:func:`femcal.diagnose.where.not_engaged`),
    as the search leaves it out."""
    outside = _outside_criteria(state, finals, gp)
    aside = not_engaged(state)
    pointwise = _pointwise(state, finals, gp)
    return [
        specimen_probabilities(
            {
                m: state.criterion(m, i)
                for m in state.per_spec[i]
                if m == state.chosen[i] or not (_idle_effect(state, m, i) or (i, m) in aside)
            },
            (state.chosen[i], outside[i]),
            state.options.min_delta,
            state.options.min_delta_inadequate,
            pointwise=pointwise[i],
            rng=bootstrap_rng(state.options.seed, state.specimens[i]),
        )
        for i in range(state.n)
    ]


def _pointwise(state: DiagnosisState, finals, gp) -> list[dict[str, np.ndarray]]:
    """Per specimen, each fitted model's chi-square contribution at each measured point
    (label -> (p,)), and its final model's with the discrepancy's mean added (the
    discrepancy's label): what the Bayesian bootstrap of the probabilities reweighs."""
    out: list[dict[str, np.ndarray]] = [{} for _ in range(state.n)]
    for i in range(state.n):
        ok = state.mask[i]
        for m, (f, at) in state.per_spec[i].items():
            r = (state.measured[i] - f.pred[at].double().numpy()) / state.sigma[i]
            out[i][model_label(m)] = r[ok] ** 2
    for effects, rows in finals.items():
        for pos, i in enumerate(rows):
            f, at = state.per_spec[i][effects]
            r = state.measured[i] - f.pred[at].double().numpy() - gp[effects].delta_at_points[pos]
            out[i][outside_label(effects)] = (r / state.sigma[i])[state.mask[i]] ** 2
    return out


#: An effect is idle in a fit when removing it raises the chi-square by less than this and
#: lowers the effective number of parameters by less than :data:`IDLE_PARAMETERS`.
IDLE_CHI2 = 1.0
IDLE_PARAMETERS = 0.5


def _idle_effect(state: DiagnosisState, effects: Model, i: int) -> bool:
    """Whether model ``effects`` holds an effect that does nothing for specimen ``i``: the
    fitted model without it has (almost) the same chi-square and effective parameters. Such a
    model is its sub-model under another name, and is left out of the probabilities (counted,
    it would give the idle effect the prior odds of a further effect, about 0.27, however
    little the data say for it)."""
    fits = state.per_spec[i]
    f, at = fits[effects]
    for drop in effects:
        rest = tuple(e for e in effects if e != drop)
        if rest not in fits:
            continue
        g, bt = fits[rest]
        if (
            float(g.chi2[bt]) - float(f.chi2[at]) < IDLE_CHI2
            and float(f.trace[at]) - float(g.trace[bt]) < IDLE_PARAMETERS
        ):
            return True
    return False


def _outside_criteria(
    state: DiagnosisState, finals: dict[Model, list[int]], gp: dict[Model, DiscrepancyFit]
) -> np.ndarray:
    """Per specimen (n,): the criterion of its final model with its discrepancy,
    ``-2 log ML - sum ln sigma^2 + (k + a) ln n`` (``k`` the model's effective parameters,
    ``a`` the load cases whose discrepancy amplitude is not zero), comparable with the
    models' ``chi^2 + k ln n``."""
    out = np.full(state.n, np.inf)
    for effects, members in finals.items():
        rows = np.asarray(members)
        dfit = gp[effects]
        ok = state.mask[rows]
        log_noise = np.where(ok, np.log(state.sigma[rows] ** 2), 0.0).sum(axis=(1, 2))
        n_amp = (np.asarray(dfit.amplitude_deg) > 0).sum(axis=1)
        for pos, i in enumerate(rows):
            f, at = state.per_spec[i][effects]
            k = float(f.trace[at]) + float(n_amp[pos])
            out[i] = float(dfit.neg2_log_ml[pos] - log_noise[pos]) + k * float(state.log_n[i])
    return out


def _describe(state, finals, gp, dense, adequacy, probabilities, pred0) -> list:
    """Per specimen: the discrepancy on top of its final model on ``dense`` (q,) and what is
    missing, in words, compared with each registered effect's signature."""
    out: list[dict[str, Any] | None] = [None] * state.n
    moments = state.base.moments.double().numpy()
    signatures = _signatures(state.per_spec, state.candidates, pred0, state.n)
    sigma_deg = float(state.sigma_m.min())
    for effects, members in finals.items():
        rows = np.asarray(members)
        dfit = gp[effects]
        mean, sd = discrepancy_posterior(dfit, moments, dense, state.mask[rows])
        for pos, i in enumerate(rows):
            own = _own_range(dense, moments, state.mask[i])
            mu = np.where(own, mean[pos], np.nan)
            sdev = np.where(own, sd[pos], np.nan)
            sim = similarity(dfit.delta_at_points[pos], signatures[i], state.sigma[i])
            best_sim = max(sim, key=sim.get) if sim else None
            resembles = best_sim if best_sim and sim[best_sim] >= RESEMBLES else None
            f, at = state.per_spec[i][effects]
            final_res = state.measured[i] - f.pred[at].double().numpy()
            text = _missing_text(
                dense, mu, sdev, sigma_deg, final_res, state.sigma[i], probabilities[i]
            )
            out[i] = {
                "model": model_label(effects),
                "mean": mu,
                "sd": sdev,
                "mae_deg": float(dfit.mae_deg[pos]),
                "amplitude_deg": [float(a) for a in dfit.amplitude_deg[pos]],
                "description": text,
                "summary": _summary(text, resembles, sim, adequacy[i]["final"], probabilities[i]),
                "similarity": sim,
                "resembles": resembles,
            }
    return out


def _curves(state: DiagnosisState, finals, dense: np.ndarray, v_disc):
    """Continuous curves on ``dense`` of the disc alone (n, 4, q) and, per specimen, of its
    final model (4, q)."""
    dense_base = _dense_base(state.base, dense)
    curves0 = _dense_curves(dense_base, (), v_disc)
    final_curves: dict[int, np.ndarray] = {}
    for effects, members in finals.items():
        if not effects:
            for i in members:
                final_curves[i] = curves0[i]
            continue
        cv = _dense_curves(dense_base, effects, state.solutions(members, effects))
        for pos, i in enumerate(members):
            final_curves[i] = cv[pos]
    return curves0, final_curves


def _probe(state: DiagnosisState, dense: np.ndarray, noise_used: float, moment_policy):
    """Where a next measurement may be taken: every moment the policy accepts (with the
    surrogate's larger error there), else the measured range. The dense model, the moments
    and their sigma."""
    moments = state.base.moments.double().numpy()
    dense_base = _dense_base(state.base, dense)
    sigma_dense = np.interp(np.log(dense), np.log(moments), state.sigma_m)
    if moment_policy is None or dense_base is None:
        return dense_base, dense, sigma_dense
    lo, hi = moment_policy.accepted_range
    probe = np.unique(np.concatenate([np.geomspace(lo, hi, state.options.curve_points), moments]))
    sigma_probe = np.sqrt(noise_used**2 + moment_policy.sigma_surrogate(probe) ** 2)
    return _dense_base(state.base, probe), probe, sigma_probe
