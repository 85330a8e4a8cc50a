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
from femcal.diagnose.fits import design_columns
from femcal.diagnose.state import DiagnosisState
from femcal.effects.base import get_effect
from femcal.effects.terms import Model

logger = logging.getLogger(__name__)


#: The share of the disc-alone misfit (chi-square beyond its expectation) an effect must
#: remove to be needed. A flexible effect absorbs part of any strong missing physics (an
#: annulus yield: 40-45 %); a real effect whose law does not quite fit removes most (85-90 %).
NEEDED_SHARE = 0.75


def _explains_most(fits: dict, current: Model, rest: Model, n_points: float) -> bool:
    """Whether the effects ``current`` has and ``rest`` lacks remove most of the disc-alone
    misfit: refitted without them, the chi-square rises by more than :data:`NEEDED_SHARE` of
    the disc alone's excess over its expectation (its ``n_points`` measured points). Such an
    effect is needed, even where a smooth discrepancy would take its place; ``fits`` is one
    specimen's fitted models."""
    disc = Model()
    if rest not in fits or disc not in fits:
        return False
    chi2 = {m: float(fits[m][0].chi2[fits[m][1]]) for m in (current, rest, disc)}
    excess = chi2[disc] - n_points
    return excess > 0 and chi2[rest] - chi2[current] > NEEDED_SHARE * excess


def open_world_elimination(state: DiagnosisState) -> None:
    """Drop, specimen by specimen, the effects that do not pay beyond a smooth discrepancy.

    Where the chosen effects leave the data unexplained, an effect stays only if the model with
    it and its discrepancy beats the model without it and its own (``-2 log ML + k ln n``, ``k``
    the parameter count) by ``min_delta``, or if it removes most of the disc-alone misfit.

    Reads ``state.chosen`` and their fits in ``state.per_spec``; changes ``state.chosen``
    (where an effect is dropped) and ``state.per_spec`` (a model it reached that was never
    fitted, fitted from where it reached it).
    """
    _Elimination(state).run()


class _Elimination:
    """The rounds of :func:`open_world_elimination` and the fits they share."""

    def __init__(self, state: DiagnosisState) -> None:
        self.state = state
        #: (specimen, model) -> (-2 log ML, unit coordinates) of the model with its discrepancy
        self.gls: dict[tuple[int, Model], tuple[float, torch.Tensor]] = {}
        #: (specimen, model) -> (4,) its discrepancy's amplitude per load case
        self.gls_amp: dict[tuple[int, Model], np.ndarray] = {}
        #: where elimination left a specimen (unit coordinates)
        self.reached: dict[int, torch.Tensor] = {}

    def run(self) -> None:
        state = self.state
        pending = []
        for i in range(state.n):
            if state.chosen[i] and not state.adequate(state.chosen[i], i):
                pending.append(i)
        for _round in range(state.options.max_effects):
            if not pending:
                return
            groups: dict[Model, list[int]] = {}
            for i in pending:
                groups.setdefault(state.chosen[i], []).append(i)
            still = []
            self.gls.clear()  # the discrepancy's size changes with the model under test
            for current, members in groups.items():
                self._fit_group(current, members)
                still += self._decide(current, members)
            self._ensure_fitted()
            pending = still

    def _gls_fit(
        self,
        effects: Model,
        rows: list[int],
        v: torch.Tensor,
        again: bool = False,
        cap: np.ndarray | None = None,
    ) -> None:
        """The fit of ``effects`` with its maximum-likelihood discrepancy from ``v`` (keeps the
        better with ``again``). ``cap`` (len(rows), 4): the largest amplitude per load case
        (``inf``: free)."""
        todo = [(k, i) for k, i in enumerate(rows) if again or (i, effects) not in self.gls]
        if not todo:
            return
        idx = [k for k, _ in todo]
        ids = np.asarray([i for _, i in todo])
        state = self.state
        # Each model gets the discrepancy it needs (type-II maximum likelihood per load case)
        # and pays for it in log det C: -2 log marginal likelihood.
        fit = fit_discrepancy(
            state.model(effects),
            v[idx],
            state.measured[ids],
            state.sigma[ids],
            amplitude_deg="ml",
            amplitude_cap=None if cap is None else cap[idx],
        )
        score = fit.neg2_log_ml
        for pos, i in enumerate(ids):
            key = (int(i), effects)
            if key not in self.gls or float(score[pos]) < self.gls[key][0]:
                self.gls[key] = (float(score[pos]), fit.v[pos])
                self.gls_amp[key] = fit.amplitude_deg[pos]

    def _fit_group(self, current: Model, members: list[int]) -> None:
        """``current`` and each model one effect smaller, with their discrepancies."""
        state, cap_factor = self.state, self.state.options.elimination_cap
        self._gls_fit(current, members, state.solutions(members, current))
        v_gls = torch.stack([self.gls[(i, current)][1] for i in members])
        for drop in current:
            rest = current.without(drop)
            cols = design_columns(state.base.dim, current, rest)
            # In the dropped effect's own load cases the discrepancy may be no larger than the
            # model with the effect needed there: it may not take over what the effect
            # explained; elsewhere it is free, so the disc can stop bending towards physics
            # nobody registered (which is what a compensating effect was doing).
            cap = None
            if cap_factor:
                own_lc = get_effect(drop).load_case_mask().numpy()
                cap = np.stack(
                    [
                        np.where(own_lc, cap_factor * self.gls_amp[(i, current)], np.inf)
                        for i in members
                    ]
                )
            self._gls_fit(rest, members, v_gls[:, cols], cap=cap)
            # The reduced model's own fit is a second start: from the larger model's
            # parameters the disc may stay bent towards what the dropped effect did.
            own = [i for i in members if rest in state.per_spec[i]]
            if own:
                sel = [members.index(i) for i in own]
                self._gls_fit(
                    rest,
                    own,
                    state.solutions(own, rest),
                    again=True,
                    cap=None if cap is None else cap[sel],
                )

    def _decide(self, current: Model, members: list[int]) -> list[int]:
        """Drop the effect whose loss is smallest where it is below ``min_delta`` and the
        effect is not needed; the specimens left with effects to examine again."""
        state = self.state
        k_cur = state.base.dim + sum(len(get_effect(e).parameters) for e in current)
        still = []
        for i in members:
            here = self.gls[(i, current)][0] + k_cur * state.log_n[i]
            losses = {}
            for drop in current:
                rest = current.without(drop)
                k_rest = k_cur - len(get_effect(drop).parameters)
                losses[rest] = self.gls[(i, rest)][0] + k_rest * state.log_n[i] - here
            rest = min(losses, key=losses.get)
            logger.debug(
                "%s: GP-BIC loss of dropping from %s: %s",
                state.specimens[i],
                current,
                {str(m): loss for m, loss in losses.items()},
            )
            needed = _explains_most(state.per_spec[i], current, rest, float(state.n_points[i]))
            if losses[rest] < state.options.min_delta and not needed:
                logger.info(
                    "%s: %s does not pay beyond a smooth discrepancy (%.1f); dropped",
                    state.specimens[i],
                    sorted(set(current.key) - set(rest.key)),
                    losses[rest],
                )
                state.chosen[i] = rest
                self.reached[i] = self.gls[(i, rest)][1]
                if rest:
                    still.append(i)
        return still

    def _ensure_fitted(self) -> None:
        """Fit (without the discrepancy) the models elimination reached that were never
        fitted, from where it reached them."""
        state = self.state
        missing: dict[Model, list[int]] = {}
        for i in range(state.n):
            if state.chosen[i] not in state.per_spec[i]:
                missing.setdefault(state.chosen[i], []).append(i)
        for effects, members in missing.items():
            starts = torch.stack([self.reached[i] for i in members])[:, None]
            state.fit(effects, np.asarray(members), starts)
