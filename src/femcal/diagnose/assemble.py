"""The description step of a diagnosis: adequacy of the chosen models, the discrepancy and
what is missing, continuous curves, rankings and what to measure next.

It reads the search's state and the decision (:mod:`femcal.diagnose.decide`: each specimen's
model, verdict, probabilities and out-of-box reading) and changes neither; it writes each model
as a string (``str(model)``) into the result.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from femcal.diagnose.decide import Decision
from femcal.diagnose.discrepancy import (
    dense_grid,
    discrepancy_posterior,
    similarity,
)
from femcal.diagnose.explain import (
    adequacy_tests,
    dense_base_model,
    dense_curves,
    effect_ranking,
    effect_signatures,
    failures,
    missing_text,
    next_measurement,
    own_range,
    summary_text,
)
from femcal.diagnose.fits import Fit
from femcal.diagnose.result import NONE, RESEMBLES, Diagnosis, SpecimenDiagnosis, model_label
from femcal.diagnose.state import DiagnosisState


def assemble_result(
    state: DiagnosisState,
    decision: Decision,
    *,
    disc: Fit,
    sur: np.ndarray,
    noise_used: float,
    noise_sd: float,
    moment_policy,
    t0: float,
) -> Diagnosis:
    """The verdicts and descriptions of the models the decision chose (``disc``: the disc
    alone's fit of every specimen; ``sur`` (m,) the surrogate's error; ``t0`` the start, for
    the time taken).

    Reads ``state`` (its fits), ``decision`` and ``disc``; changes none of them.
    """
    n, measured, mask, sigma = state.n, state.measured, state.mask, state.sigma
    options = state.options
    finals, decided = decision.finals, decision.specimens
    adequacy = _adequacies(state, decided, disc)
    moments = state.base.moments.double().numpy()
    dense = dense_grid(moments, options.curve_points)
    described: list[dict[str, Any] | None] = [None] * n
    if options.discrepancy:
        described = _describe(state, decision, dense, adequacy, disc.pred)
    curves0, final_curves = _curves(state, finals, dense, disc.v)
    probe_base, probe, sigma_probe = _probe(state, dense, noise_used, moment_policy)
    pred0 = disc.pred.double().numpy()
    mae0 = np.nanmean(np.abs(measured - pred0).reshape(n, -1), axis=1)
    base = state.base
    unit_disc = base.space.to_unit(base.to_physical(disc.v.double().numpy()))
    out: list[SpecimenDiagnosis] = []
    for i, spec in enumerate(state.specimens):
        d = decided[i]
        ranking = effect_ranking(state.per_spec[i], i, measured, sigma, state.log_n, base, mask)
        f, pos = state.per_spec[i][d.chosen]
        final_res = measured[i] - f.pred[pos].double().numpy()
        own = own_range(dense, moments, mask[i])
        curves = {"moments": dense, NONE: np.where(own, curves0[i], np.nan)}
        if d.model and d.model == tuple(d.chosen):
            curves[model_label(d.chosen)] = np.where(own, final_curves[i], np.nan)
        nxt = next_measurement(
            ranking,
            state.per_spec[i],
            probe_base,
            probe,
            sigma_probe,
            options.min_delta,
            d.chosen,
            [moments[mask[i][j]] for j in range(mask.shape[1])],
            noise_deg=noise_used,
        )
        resid = measured[i] - pred0[i]
        out.append(
            SpecimenDiagnosis(
                specimen=str(spec),
                verdict=d.verdict,
                baseline_mae_deg=float(mae0[i]),
                ranking=ranking,
                residuals=resid,
                failures=failures(resid, sigma[i], moments, unit_disc[i], base.space.names),
                effects=[t.effect for t in d.model],
                model=[str(t) for t in d.model],
                load_cases={t.effect: list(t.acting) for t in d.model},
                adequate=d.adequate,
                adequacy=adequacy[i],
                final_mae_deg=float(np.nanmean(np.abs(final_res))),
                final_residuals=final_res,
                curves=curves,
                discrepancy=described[i],
                next_measurement=nxt,
                probabilities=d.probabilities,
                sigma=np.where(mask[i], sigma[i], np.nan),
                surrogate_sd=np.where(mask[i], state.surrogate_sd[i], np.nan),
                outside_box=_written(d.outside_box),
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


def _written(reading: dict[str, Any] | None) -> dict[str, Any] | None:
    """An out-of-box reading (:func:`femcal.diagnose.outside.assess`) as the result holds it:
    its effects' terms written (``stand_ins`` by term, ``model``)."""
    if reading is None:
        return None
    out = dict(reading)
    out["stand_ins"] = {str(t): v for t, v in reading["stand_ins"].items()}
    if reading["model"] is not None:
        out["model"] = [str(t) for t in reading["model"]]
    return out


def _adequacies(state: DiagnosisState, decided, disc: Fit) -> list[dict[str, Any]]:
    """Per specimen: the chi-square and runs tests of its decided model (``decided``, per
    specimen a :class:`~femcal.diagnose.decide.SpecimenDecision`) and of the disc alone."""
    out = []
    alpha = state.options.alpha
    for i in range(state.n):
        f, pos = state.per_spec[i][decided[i].chosen]
        res = state.measured[i] - f.pred[pos].double().numpy()
        res0 = state.measured[i] - disc.pred[i].double().numpy()
        n_i = float(state.n_points[i])
        out.append(
            {
                "final": adequacy_tests(res, state.sigma[i], n_i - float(f.trace[pos]), alpha),
                "disc_alone": adequacy_tests(
                    res0, state.sigma[i], n_i - float(disc.trace[i]), alpha
                ),
            }
        )
    return out


def _describe(state, decision: Decision, dense, adequacy, pred0) -> list:
    """Per specimen: the discrepancy on top of its final model on ``dense`` (q,) and what is
    missing, in words, compared with each registered effect's signature (``pred0`` (n, 4, m)
    the disc alone's curves)."""
    finals, gp = decision.finals, decision.gp
    probabilities = [d.probabilities for d in decision.specimens]
    out: list[dict[str, Any] | None] = [None] * state.n
    moments = state.base.moments.double().numpy()
    signatures = effect_signatures(state.per_spec, state.candidates, pred0, state.n)
    sigma_deg = float(state.sigma_m.min())
    for effects, members in finals.items():
        rows = np.asarray(members)
        dfit = gp[effects]
        mean, sd = discrepancy_posterior(dfit, moments, dense, state.mask[rows])
        for pos, i in enumerate(rows):
            own = own_range(dense, moments, state.mask[i])
            mu = np.where(own, mean[pos], np.nan)
            sdev = np.where(own, sd[pos], np.nan)
            sim = similarity(dfit.delta_at_points[pos], signatures[i], state.sigma[i])
            best_sim = max(sim, key=sim.get) if sim else None
            resembles = best_sim if best_sim and sim[best_sim] >= RESEMBLES else None
            f, at = state.per_spec[i][effects]
            final_res = state.measured[i] - f.pred[at].double().numpy()
            text = missing_text(
                dense, mu, sdev, sigma_deg, final_res, state.sigma[i], probabilities[i]
            )
            out[i] = {
                "model": model_label(effects),
                "mean": mu,
                "sd": sdev,
                "mae_deg": float(dfit.mae_deg[pos]),
                "amplitude_deg": [float(a) for a in dfit.amplitude_deg[pos]],
                "description": text,
                "summary": summary_text(
                    text, resembles, sim, adequacy[i]["final"], probabilities[i]
                ),
                "similarity": sim,
                "resembles": resembles,
            }
    return out


def _curves(state: DiagnosisState, finals, dense: np.ndarray, v_disc):
    """Continuous curves on ``dense`` of the disc alone (n, 4, q) and, per specimen, of its
    final model (4, q)."""
    dense_base = dense_base_model(state.base, dense)
    curves0 = dense_curves(dense_base, (), v_disc)
    final_curves: dict[int, np.ndarray] = {}
    for effects, members in finals.items():
        if not effects:
            for i in members:
                final_curves[i] = curves0[i]
            continue
        cv = dense_curves(dense_base, effects, state.solutions(members, effects))
        for pos, i in enumerate(members):
            final_curves[i] = cv[pos]
    return curves0, final_curves


def _probe(state: DiagnosisState, dense: np.ndarray, noise_used: float, moment_policy):
    """Where a next measurement may be taken: every moment the policy accepts (with the
    surrogate's larger error there), else the measured range. The dense model, the moments
    and their sigma."""
    moments = state.base.moments.double().numpy()
    dense_base = dense_base_model(state.base, dense)
    sigma_dense = np.interp(np.log(dense), np.log(moments), state.sigma_m)
    if moment_policy is None or dense_base is None:
        return dense_base, dense, sigma_dense
    lo, hi = moment_policy.accepted_range
    probe = np.unique(np.concatenate([np.geomspace(lo, hi, state.options.curve_points), moments]))
    sigma_probe = np.sqrt(noise_used**2 + moment_policy.sigma_surrogate(probe) ** 2)
    return dense_base_model(state.base, probe), probe, sigma_probe
