"""Open-world elimination, step 2b of :func:`femcal.diagnose.diagnose`.

Where the chosen effects still leave a specimen's data unexplained, each effect must pay beyond
a smooth discrepancy (the Gaussian process of :mod:`femcal.diagnose.discrepancy`) sized for every
model by its own marginal likelihood (or to the larger model's misfit): an effect that only let
the disc bend towards physics nobody registered is dropped (backward elimination), one that
explains its own load cases stays, and so does one that removes most of the disc-alone misfit
(an effect that does not finish the job keeps its place beside ``unexplained``).
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from femcal.diagnose.discrepancy import fit_discrepancy
from femcal.diagnose.explain import _adequate_quick
from femcal.diagnose.fits import _columns, _Fit, _fit_from, _solutions
from femcal.diagnose.state import DiagnosisState
from femcal.effects.base import get_effect

logger = logging.getLogger(__name__)


def _explains_most(
    fits: dict, current: tuple[str, ...], rest: tuple[str, ...], n_points: float
) -> bool:
    """Whether the effects ``current`` has and ``rest`` lacks remove most of the disc-alone
    misfit: refitted without them, the chi-square rises by more than half of the disc alone's
    excess over its expectation (its ``n_points`` measured points). Such an effect is needed,
    even where a smooth discrepancy would take its place; ``fits`` is one specimen's fitted
    models."""
    if rest not in fits or () not in fits:
        return False
    chi2 = {m: float(fits[m][0].chi2[fits[m][1]]) for m in (current, rest, ())}
    excess = chi2[()] - n_points
    return excess > 0 and chi2[rest] - chi2[current] > 0.5 * excess


def open_world_elimination(state: DiagnosisState) -> None:
    """Drop, specimen by specimen, the effects that do not pay beyond a smooth discrepancy.

    Updates ``state.chosen`` (per specimen, the effects kept) and ``state.per_spec`` (every
    fitted model of every specimen) in place.
    """
    base, specimens, measured = state.base, state.specimens, state.measured
    weight, mask, sigma = state.weight, state.mask, state.sigma
    n_points, log_n = state.n_points, state.log_n
    chosen, per_spec = state.chosen, state.per_spec
    min_delta, max_effects = state.options.min_delta, state.options.max_effects
    max_iter, elimination_cap = state.options.max_iter, state.options.elimination_cap
    alpha = state.options.alpha
    n = len(chosen)
    # 2b. Open world: where the chosen effects still leave the data unexplained, keep an effect
    # only if it pays beyond a smooth discrepancy (the GP of step 4) sized to what the chosen
    # model leaves unexplained: effects that merely let the disc bend towards physics nobody
    # registered are dropped (backward elimination, BIC of the GLS fit with that GP).
    for i in range(n):
        per_spec[i][chosen[i]][0].ensure_trace(mask, sigma)
    pending = [
        i
        for i in range(n)
        if chosen[i]
        and not _adequate_quick(*per_spec[i][chosen[i]], i, measured, sigma, n_points, alpha)
    ]
    gls: dict[tuple[int, tuple[str, ...]], tuple[float, torch.Tensor]] = {}
    gls_amp: dict[tuple[int, tuple[str, ...]], np.ndarray] = {}  # (4,) GP amplitude per LC
    reached: dict[int, torch.Tensor] = {}  # where elimination left a specimen (unit coords)

    def gls_fit(
        effects: tuple[str, ...],
        rows: list[int],
        v: torch.Tensor,
        again: bool = False,
        cap: np.ndarray | None = None,
    ) -> None:
        """The fit of ``effects`` with its maximum-likelihood GP from ``v`` (keeps the better
        with ``again``).

        ``cap`` (len(rows), 4): the largest GP amplitude per load case (``inf``: free).
        """
        todo = [(k, i) for k, i in enumerate(rows) if again or (i, effects) not in gls]
        if not todo:
            return
        idx = [k for k, _ in todo]
        ids = np.asarray([i for _, i in todo])
        model = base if not effects else state.model(effects)
        # Each model gets the discrepancy it needs (type-II maximum likelihood per load case)
        # and pays for it in log det C: -2 log marginal likelihood.
        fit = fit_discrepancy(
            model,
            v[idx],
            measured[ids],
            sigma[ids],
            amplitude_deg="ml",
            amplitude_cap=None if cap is None else cap[idx],
        )
        score = fit.neg2_log_ml
        for pos, i in enumerate(ids):
            key = (int(i), effects)
            if key not in gls or float(score[pos]) < gls[key][0]:
                gls[key] = (float(score[pos]), fit.v[pos])
                gls_amp[key] = fit.amplitude_deg[pos]

    def ensure_fitted() -> None:
        """Fit (without the GP) the models elimination reached that were never fitted."""
        missing: dict[tuple[str, ...], list[int]] = {}
        for i in range(n):
            if chosen[i] not in per_spec[i]:
                missing.setdefault(chosen[i], []).append(i)
        for effects, members in missing.items():
            rows = np.asarray(members)
            model = state.model(effects)
            v0 = torch.stack([reached[i] for i in members])
            v, pred, chi2 = _fit_from(model, measured, weight, sigma, rows, v0, 1, max_iter)
            fit = _Fit(effects, model, v, rows, pred, chi2, model.dim)
            for pos, i in enumerate(rows):
                per_spec[i][effects] = (fit, pos)

    for _round in range(max_effects):
        if not pending:
            break
        groups = {}
        for i in pending:
            groups.setdefault(chosen[i], []).append(i)
        still = []
        gls.clear()  # the GP's size changes with the model under test
        for current, members in groups.items():
            v_cur = _solutions(per_spec, members, current)
            gls_fit(current, members, v_cur)
            v_gls = torch.stack([gls[(i, current)][1] for i in members])
            for drop in current:
                rest = tuple(e for e in current if e != drop)
                cols = _columns(base.dim, current, rest)
                # In the dropped effect's own load cases the discrepancy may be no larger than
                # the model with the effect needed there: it may not take over what the effect
                # explained; elsewhere it is free, so the disc can stop bending towards physics
                # nobody registered (which is what a compensating effect was doing).
                cap = None
                if elimination_cap:
                    own_lc = get_effect(drop).load_case_mask().numpy()
                    cap = np.stack(
                        [
                            np.where(own_lc, elimination_cap * gls_amp[(i, current)], np.inf)
                            for i in members
                        ]
                    )
                gls_fit(rest, members, v_gls[:, cols], cap=cap)
                # The reduced model's own fit is a second start: from the larger model's
                # parameters the disc may stay bent towards what the dropped effect did.
                own = [i for i in members if rest in per_spec[i]]
                if own:
                    v_own = _solutions(per_spec, own, rest)
                    sel = [members.index(i) for i in own]
                    gls_fit(
                        rest,
                        own,
                        v_own,
                        again=True,
                        cap=None if cap is None else cap[sel],
                    )
            k_cur = base.dim + sum(len(get_effect(e).parameters) for e in current)
            for i in members:
                here = gls[(i, current)][0] + k_cur * log_n[i]
                losses = {}
                for drop in current:
                    rest = tuple(e for e in current if e != drop)
                    k_rest = k_cur - len(get_effect(drop).parameters)
                    losses[rest] = gls[(i, rest)][0] + k_rest * log_n[i] - here
                rest = min(losses, key=losses.get)
                logger.debug(
                    "%s: GP-BIC loss of dropping from %s: %s", specimens[i], current, losses
                )
                if losses[rest] < min_delta and not _explains_most(
                    per_spec[i], current, rest, float(n_points[i])
                ):
                    logger.info(
                        "%s: %s does not pay beyond a smooth discrepancy (%.1f); dropped",
                        specimens[i],
                        set(current) - set(rest),
                        losses[rest],
                    )
                    chosen[i] = rest
                    reached[i] = gls[(i, rest)][1]
                    if rest:
                        still.append(i)
        ensure_fitted()
        pending = still
