"""The last steps of a diagnosis: adequacy of the chosen models, the discrepancy and what is
missing, continuous curves, rankings and what to measure next."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from femcal.diagnose.discrepancy import (
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
from femcal.diagnose.fits import (
    _solutions,
)
from femcal.diagnose.probabilities import specimen_probabilities
from femcal.diagnose.result import (
    NONE,
    RESEMBLES,
    Diagnosis,
    SpecimenDiagnosis,
    model_label,
    verdict_label,
)
from femcal.effects.split import base_name


def _outside_criteria(base, effect_model, finals, per_spec, measured, sigma, cost) -> np.ndarray:
    """Per specimen (n,): the criterion of its final model with a smooth discrepancy,
    ``-2 log ML - sum ln sigma^2 + (k + a) ln n`` (``k`` the model's effective parameters,
    ``a`` the load cases whose discrepancy amplitude is not zero), comparable with the
    models' ``chi^2 + k ln n``."""
    out = np.full(len(per_spec), np.inf)
    for effects, members in finals.items():
        rows = np.asarray(members)
        model = base if not effects else effect_model(effects)
        v = _solutions(per_spec, rows, effects)
        dfit = fit_discrepancy(model, v, measured[rows], sigma[rows], amplitude_deg="ml")
        ok = np.isfinite(measured[rows])
        log_noise = np.where(ok, np.log(sigma[rows] ** 2), 0.0).sum(axis=(1, 2))
        n_amp = (np.asarray(dfit.amplitude_deg) > 0).sum(axis=1)
        for pos, i in enumerate(rows):
            f, at = per_spec[i][effects]
            k = float(f.trace[at]) + float(n_amp[pos])
            out[i] = float(dfit.neg2_log_ml[pos] - log_noise[pos]) + k * float(cost[i])
    return out


def _assemble(
    *,
    base,
    specimens,
    candidates,
    measured,
    mask,
    n_points,
    cost,
    sigma,
    sigma_m,
    sur,
    moments,
    chosen,
    per_spec,
    fits,
    pred0,
    v_disc,
    effect_model,
    alpha,
    min_delta,
    further_delta,
    penalty,
    discrepancy,
    curve_points,
    noise_used,
    noise_sd,
    moment_policy,
    t0,
    n,
) -> Diagnosis:
    """Steps 3-5 of :func:`diagnose` for the models it chose: adequacy, the discrepancy and
    what is missing, continuous curves, rankings and what to measure next."""
    # 3. Adequacy of the final models (and of the disc alone), with the exact Jacobian.
    out: list[SpecimenDiagnosis] = []
    finals: dict[tuple[str, ...], list[int]] = {}
    for i in range(n):
        finals.setdefault(chosen[i], []).append(i)
    # One Jacobian per fitted batch (all its specimens at once): effective parameters and
    # the parameter covariance of every model in every ranking.
    for i in range(n):
        for f, _ in per_spec[i].values():
            f.ensure_trace(mask, sigma)

    adequacy: list[dict[str, Any]] = []
    f0 = fits[()]
    for i in range(n):
        f, pos = per_spec[i][chosen[i]]
        res = measured[i] - f.pred[pos].double().numpy()
        adequacy.append(
            {
                "final": _adequacy(res, sigma[i], float(n_points[i] - f.trace[pos]), alpha),
                "disc_alone": _adequacy(
                    measured[i] - pred0[i].double().numpy(),
                    sigma[i],
                    float(n_points[i] - f0.trace[i]),
                    alpha,
                ),
            }
        )

    # 3'. How probable each explanation is: every fitted model, and each final model with the
    # discrepancy it needs (type-II maximum likelihood), by its marginal likelihood
    # (femcal.diagnose.probabilities). The verdict says `unexplained` where that is more
    # probable than the model alone.
    outside = _outside_criteria(base, effect_model, finals, per_spec, measured, sigma, cost)
    probabilities = [
        specimen_probabilities(
            {
                m: f.criterion(pos, float(cost[i]), penalty, mask, sigma)
                for m, (f, pos) in per_spec[i].items()
            },
            (chosen[i], outside[i]),
            min_delta,
            further_delta,
        )
        for i in range(n)
    ]

    # 4. The discrepancy on top of each final model.
    dense = dense_grid(moments, curve_points)
    disc_info: list[dict[str, Any] | None] = [None] * n
    if discrepancy:
        signatures = _signatures(per_spec, candidates, pred0, n)
        for effects, members in finals.items():
            rows = np.asarray(members)
            model = base if not effects else effect_model(effects)
            v = _solutions(per_spec, rows, effects)
            dfit = fit_discrepancy(model, v, measured[rows], sigma[rows])
            mean, sd = discrepancy_posterior(dfit, moments, dense, mask[rows])
            for pos, i in enumerate(rows):
                own = _own_range(dense, moments, mask[i])
                mu = np.where(own, mean[pos], np.nan)
                sdev = np.where(own, sd[pos], np.nan)
                sim = similarity(dfit.delta_at_points[pos], signatures[i], sigma[i])
                best_sim = max(sim, key=sim.get) if sim else None
                resembles = best_sim if best_sim and sim[best_sim] >= RESEMBLES else None
                final = probabilities[i]
                f, at = per_spec[i][effects]
                final_res = measured[i] - f.pred[at].double().numpy()
                text = _missing_text(
                    dense, mu, sdev, float(sigma_m.min()), final_res, sigma[i], final
                )
                disc_info[i] = {
                    "model": model_label(effects),
                    "mean": mu,
                    "sd": sdev,
                    "mae_deg": float(dfit.mae_deg[pos]),
                    "amplitude_deg": [float(a) for a in dfit.amplitude_deg[pos]],
                    "description": text,
                    "summary": _summary(text, resembles, sim, adequacy[i]["final"], final),
                    "similarity": sim,
                    "resembles": resembles,
                }

    # 5. Continuous curves, rankings, what to measure next.
    dense_base = _dense_base(base, dense)
    curves0 = _dense_curves(dense_base, (), v_disc)
    final_curves: dict[int, np.ndarray] = {}
    for effects, members in finals.items():
        if not effects:
            for i in members:
                final_curves[i] = curves0[i]
            continue
        v = _solutions(per_spec, members, effects)
        cv = _dense_curves(dense_base, effects, v)
        for pos, i in enumerate(members):
            final_curves[i] = cv[pos]
    sigma_dense = np.interp(np.log(dense), np.log(moments), sigma_m)
    # What to measure next: over every moment the policy accepts (with the surrogate's larger
    # error there), else over the measured range.
    probe_base, probe, sigma_probe = dense_base, dense, sigma_dense
    if moment_policy is not None and dense_base is not None:
        lo, hi = moment_policy.accepted_range
        probe = np.unique(np.concatenate([np.geomspace(lo, hi, curve_points), moments]))
        probe_base = _dense_base(base, probe)
        sigma_probe = np.sqrt(noise_used**2 + moment_policy.sigma_surrogate(probe) ** 2)
    mae0 = np.nanmean(np.abs(measured - pred0.double().numpy()).reshape(n, -1), axis=1)
    unit_disc = base.space.to_unit(base.to_physical(v_disc.double().numpy()))
    for i, spec in enumerate(specimens):
        ranking = _ranking(per_spec[i], i, measured, sigma, cost, base, penalty, mask)
        effects = list(chosen[i])
        adequate = not probabilities[i]["unexplained"]
        f, pos = per_spec[i][chosen[i]]
        final_res = measured[i] - f.pred[pos].double().numpy()
        own = _own_range(dense, moments, mask[i])
        own_lc = [moments[mask[i][j]] for j in range(mask.shape[1])]
        curves = {
            "moments": dense,
            NONE: np.where(own, curves0[i], np.nan),
        }
        if effects:
            curves[model_label(effects)] = np.where(own, final_curves[i], np.nan)
        nxt = _next_measurement(
            ranking,
            per_spec[i],
            probe_base,
            probe,
            sigma_probe,
            min_delta,
            chosen[i],
            own_lc,
            noise_deg=noise_used,
        )
        resid = measured[i] - pred0[i].double().numpy()
        out.append(
            SpecimenDiagnosis(
                specimen=str(spec),
                verdict=verdict_label(effects, adequate),
                baseline_mae_deg=float(mae0[i]),
                ranking=ranking,
                residuals=resid,
                failures=_failures(resid, sigma[i], moments, unit_disc[i], base.space.names),
                effects=[base_name(e) for e in effects],
                model=effects,
                adequate=adequate,
                adequacy=adequacy[i],
                final_mae_deg=float(np.nanmean(np.abs(final_res))),
                final_residuals=final_res,
                curves=curves,
                discrepancy=disc_info[i],
                next_measurement=nxt,
                probabilities=probabilities[i],
                sigma=np.where(mask[i], sigma[i], np.nan),
            )
        )
    return Diagnosis(
        specimens=out,
        sigma_deg=float(sigma_m.min()),
        noise_deg=noise_used,
        noise_sd_deg=float(noise_sd),
        surrogate_error_deg=float(sur.min()),
        moments=moments,
        seconds=time.perf_counter() - t0,
        sigma_by_moment=sigma_m,
        alpha=alpha,
    )
