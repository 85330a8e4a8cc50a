"""The disc surrogate composed with physical effects: a :class:`~femcal.curves.CurveModel`.

:class:`EffectModel` has the interface the calibrators use (``curves``, ``curves_jacobian``,
``to_physical``, ``from_physical``, ``predict``, ``space``, ``moments``, ``dim``), over the
joint parameters ``[13 disc parameters, effect parameters...]`` in unit coordinates: the disc
part in the surrogate network's coordinates, each effect parameter in its own unit box (log
scale where declared). So ``pgd`` calibrates material and effect parameters jointly, inside all
bounds, unchanged.

Parallel elements: for each load case they act on, ``M = M_d + sum_e M_e(phi_disc(M_d))`` is
solved for the disc's share ``M_d`` by bisection in ``log M_d`` (no graph), then one Newton
step with the graph attached gives the implicit-function gradient exactly at the solution.
Series elements add ``phi_e(M)`` to the rotation.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import torch

from femcal.calibration.model import CurveModel
from femcal.effects.base import Effect, get_effect
from femcal.effects.jacobian import LOW_SLOPE, disc_partials, parameter_partials, repeated
from femcal.forward_ad import constant_like, has_tangent
from femcal.space import ParameterSpace
from femcal.surrogates.romnet import ensemble_forward, ensemble_tangents

logger = logging.getLogger(__name__)

#: Bisections of the disc's share in log M over the bracket [1e-3 M, M] (ln(1000) / 2^12 = 2e-3
#: relative), then ``_POLISH`` Newton steps kept inside the bracket, each squaring the error;
#: the Newton step of :meth:`EffectModel.curves` squares it once more: float64 rounding, so that
#: finite differences of the curves match their Jacobian.
_BISECTIONS = 12
_POLISH = 2
_JAC_ROWS = 8192
#: Shares of the rows solved so far that :meth:`EffectModel._share_of` keeps (then it starts
#: afresh).
_MAX_SHARES = 200_000
_MIN_SHARE = 1e-3  # the disc carries at least this share of the applied moment
#: Points evaluated at once by :func:`_bisect_levels` (rows x load cases x moments x midpoints):
#: small batches are bisected several levels per evaluation, large ones one level at a time.
_SECTION_POINTS = 4096


def _levels_per_round(n_points: int) -> int:
    """Bisection levels evaluated together on ``n_points`` brackets (at least 1)."""
    levels = 1
    while levels < _BISECTIONS and n_points * (2 ** (levels + 1) - 1) <= _SECTION_POINTS:
        levels += 1
    return levels


def _bisect_levels(above, lo: torch.Tensor, hi: torch.Tensor, levels: int):
    """``levels`` steps of bisection of ``[lo, hi]`` (B, c, m, in log M) with one evaluation.

    ``above(md)`` maps moments (B, c, m * q) to bool (B, c, m * q): whether the root lies
    below (each bracket's ``q`` points consecutive on the last axis). Every midpoint that
    ``levels`` successive bisections could visit (``2 ** levels - 1`` per bracket, each
    ``0.5 * (left + right)`` of its neighbours as bisection computes it) is evaluated at once;
    then the bisection's path through them is followed. Returns the new ``lo, hi`` (B, c, m).
    """
    if levels == 1:  # one midpoint per bracket: the same operations in torch
        mid = 0.5 * (lo + hi)
        up = above(torch.exp(mid))
        return torch.where(up, lo, mid), torch.where(up, mid, hi)
    points = np.stack([lo.numpy(), hi.numpy()], axis=-1)  # (B, c, m, 2 ** level + 1)
    half = points.dtype.type(0.5)
    for _ in range(levels):
        grid = np.empty((*points.shape[:-1], 2 * points.shape[-1] - 1), dtype=points.dtype)
        grid[..., 0::2] = points
        grid[..., 1::2] = half * (points[..., :-1] + points[..., 1:])
        points = grid
    inner = torch.from_numpy(np.ascontiguousarray(points[..., 1:-1]))
    moments = torch.exp(inner).reshape(*lo.shape[:-1], inner.shape[-2] * inner.shape[-1])
    up = above(moments).reshape(inner.shape).numpy()
    # Where the bisection's path ends: below the first point above the root when the points
    # above it follow those below (as for a monotone g), else by following it level by level.
    i_lo = (~up).sum(axis=-1, keepdims=True)
    if not (up[..., 1:] >= up[..., :-1]).all():
        i_lo = np.zeros((*lo.shape, 1), dtype=np.int64)
        i_hi = np.full_like(i_lo, 2**levels)
        for _ in range(levels):
            i_mid = (i_lo + i_hi) // 2
            go_down = np.take_along_axis(up, i_mid - 1, axis=-1)
            i_hi = np.where(go_down, i_mid, i_hi)
            i_lo = np.where(go_down, i_lo, i_mid)
    i_hi = i_lo + 1
    new_lo = np.take_along_axis(points, i_lo, axis=-1)[..., 0]
    new_hi = np.take_along_axis(points, i_hi, axis=-1)[..., 0]
    return torch.from_numpy(new_lo), torch.from_numpy(new_hi)


class EffectModel:
    """The disc surrogate with physical effects added (a :class:`~femcal.curves.CurveModel`).

    Parameters
    ----------
    base : SurrogateCurveModel
        The disc surrogate on the moment grid.
    effects : sequence of str
        Registered effect names (:func:`~femcal.effects.available_effects`), or their split
        forms (``facet_contact:split``, :mod:`femcal.effects.split`); empty = the disc.
    """

    def __init__(self, base: CurveModel, effects: Sequence[str]) -> None:
        self.base = base
        self.effects: list[Effect] = [get_effect(name)() for name in effects]
        self.effect_names = [e.name for e in self.effects]
        self._lc_masks = [e.load_case_mask() for e in self.effects]
        self.moments = base.moments
        self.net = base.net
        self.n_disc = base.dim
        self._slices = []
        start = self.n_disc
        for e in self.effects:
            self._slices.append(slice(start, start + len(e.parameters)))
            start += len(e.parameters)
        self.dim = start
        effect_spaces = [e.space() for e in self.effects]
        #: Physical bounds of the joint parameters (the disc's calibration box, then each
        #: effect's), used to clip.
        self.space = ParameterSpace.concat(base.space.linear(), *effect_spaces)
        #: The joint coordinates ``v``: the disc network's input space, then each effect's.
        self.unit_space = ParameterSpace.concat(base.unit_space, *effect_spaces)
        self.n_evaluations = 0
        # The disc's share at the rows solved so far, by the rows' bytes (in their own
        # dtype): a Gauss-Newton step evaluates the curves at the new point, then its Jacobian
        # there; the best of a fit's starts is evaluated again at its end.
        self._shares: dict[bytes, torch.Tensor] = {}
        #: Lowest trained moment: below it the disc curve is continued as a power law.
        self.m_low = float(getattr(base.surrogate, "moment_range_", (1.0, 5.0))[0])

    # ------------------------------------------------------------ coordinates
    def to_physical(self, v: np.ndarray | torch.Tensor) -> np.ndarray:
        """Joint coordinates (n, dim) -> physical parameters (n, dim), float64, in the box."""
        v64 = np.clip(np.asarray(v, dtype=float), 0.0, 1.0)
        return self.space.clip(self.unit_space.from_unit(v64))

    def from_physical(self, x: np.ndarray, *, clip: bool = True) -> torch.Tensor:
        """Physical (n, 13) or (n, dim) -> unit coordinates (n, dim); effect parameters that
        are not given take their ``start`` values (the weak end: the disc alone first)."""
        x = np.asarray(x, dtype=float)
        disc = self.base.from_physical(x[:, : self.n_disc], clip=clip)
        parts = [disc]
        for e, sl in zip(self.effects, self._slices):
            if x.shape[1] >= sl.stop:
                u = e.to_unit(x[:, sl])
                parts.append(torch.tensor(np.clip(u, 0, 1) if clip else u, dtype=torch.float32))
            else:
                start = torch.tensor([q.start for q in e.parameters], dtype=torch.float32)
                parts.append(start.expand(len(x), -1).clone())
        return torch.cat(parts, dim=1)

    # ------------------------------------------------------------ evaluation
    def _disc(
        self,
        v_disc: torch.Tensor,
        coef: torch.Tensor | None = None,
        cases: list[int] | None = None,
    ):
        """A function ``phi(M, detached=False, slope=True)`` of the disc at ``v_disc`` (B, 13):
        M (B, c, m) -> (rotation, d rotation / dM or None), ``c`` = 4 or ``len(cases)``.

        ``coef`` (K, B, 4, p): the members' coefficients when already computed (the Jacobian
        passes them as a dual tensor, differentiated by :func:`ensemble_tangents`).
        ``cases``: only these load cases (indices into
        :data:`~femcal.schema.LOAD_CASES`; the bisection needs only those of its parallel
        effects). ``detached``: without graph or forward-mode tangent (the bisection);
        ``slope=False`` skips the derivative.
        """
        net = self.net
        b = v_disc.shape[0]
        p = net.moment_degree + 1
        if coef is None:
            coef = self._coefficients(v_disc)
        if cases is not None:
            coef = coef[:, :, cases]
        n_cases = coef.shape[2]
        # The output scaling folded into the coefficients: Horner's rule then gives the
        # network's target t (log RoM or RoM) directly; and t's derivative in z.
        loc, inv_scale, y_scale, y_loc, dpowers = (
            constant_like(x, coef)
            for x in (
                net.moment_loc,
                1.0 / net.moment_scale,
                net.y_scale,
                torch.eye(p, dtype=coef.dtype)[0] * net.y_loc,
                torch.arange(1, p, dtype=coef.dtype),
            )
        )
        prepared = {False: coef * y_scale + y_loc}
        prepared[True] = prepared[False].detach()  # no graph, no tangent: for the bisection
        derivative = {False: prepared[False][..., 1:] * dpowers}
        derivative[True] = derivative[False].detach()
        log_low = float(np.log(self.m_low))

        def members(detached: bool, z: torch.Tensor, slope: bool):
            # Each member's cubic in z by Horner's rule (K, B, 4, m), the members' mean RoM
            # and, with ``slope``, its derivative in z.
            c = prepared[detached]
            t = c[..., p - 1, None]
            if detached and p > 1:  # no graph: the same operations, in place
                t = t * z
                t.add_(c[..., p - 2, None])
                for j in range(p - 3, -1, -1):
                    t.mul_(z).add_(c[..., j, None])
                deg = t.exp_() if net.log_target else t
            else:
                for j in range(p - 2, -1, -1):
                    t = t * z + c[..., j, None]
                deg = torch.exp(t) if net.log_target else t
            if not slope:
                return deg.mean(0), None
            if p == 1:
                return deg.mean(0), torch.zeros_like(deg[0])
            dc = derivative[detached]
            dt = dc[..., p - 2, None]
            for j in range(p - 3, -1, -1):
                dt = dt * z + dc[..., j, None]
            return deg.mean(0), (deg * dt if net.log_target else dt).mean(0)

        def z_of(log_m: torch.Tensor) -> torch.Tensor:
            return (log_m - loc) * inv_scale

        # Below the lowest trained moment the curve continues as the power law through the
        # origin with the log-log slope there (a cubic extrapolated far down can blow up):
        # that slope, once per (row, load case).
        ends: dict[bool, torch.Tensor] = {}

        def low_end(detached: bool) -> torch.Tensor:
            if detached not in ends:
                log_m = constant_like(torch.full((b, n_cases, 1), log_low), coef)
                deg, ddeg = members(detached, z_of(log_m), True)
                ends[detached] = (ddeg * inv_scale / deg).clamp(*LOW_SLOPE)
            return ends[detached]

        def phi(moment: torch.Tensor, detached: bool = False, slope: bool = True):
            log_m = torch.log(moment if detached else constant_like(moment, coef))
            log_mc = log_m.clamp_min(log_low)
            deg, ddeg = members(detached, z_of(log_mc), slope)
            low = log_m < log_low
            if not low.any():
                return deg, None if ddeg is None else ddeg * inv_scale / torch.exp(log_m)
            b_low = low_end(detached)
            out = deg * torch.exp(b_low * (log_m - log_mc))  # = deg where M >= m_low
            if ddeg is None:
                return out, None
            return out, torch.where(low, out * b_low, ddeg * inv_scale) / torch.exp(log_m)

        return phi

    def _coefficients(self, v_disc: torch.Tensor) -> torch.Tensor:
        """The disc members' polynomial coefficients (K, B, 4, p) at ``v_disc`` (B, 13)."""
        net = self.net
        shape = (v_disc.shape[0], net.n_load_cases, net.moment_degree + 1)
        if torch.is_grad_enabled() or has_tangent(v_disc):
            return torch.stack([m(v_disc).reshape(shape) for m in net.members])
        return ensemble_forward(net.members, v_disc).reshape(len(net.members), *shape)

    def _disc_share(
        self,
        v: torch.Tensor,
        coef: torch.Tensor | None = None,
        params: list[dict[str, torch.Tensor]] | None = None,
    ) -> torch.Tensor:
        """The disc's share of the applied moment (n, 4, m) by bisection, no graph, no tangent
        (the Newton step in :meth:`curves` gives the exact derivative at the solution).

        ``coef`` (K, n, 4, p) and ``params`` (each effect's physical parameters by name, (n,)
        each): the disc members' coefficients and the effects' parameters at ``v`` when
        already computed. The bisection's midpoints are evaluated several levels at a time
        (:func:`_bisect_levels`): the same iterates as one midpoint at a time.
        """
        v = v.detach()
        b = v.shape[0]
        applied = self.moments.to(v.dtype).expand(b, 4, -1)
        if params is None:
            params = [e.from_unit(v[:, sl]) for e, sl in zip(self.effects, self._slices)]
        else:
            params = [{k: t.detach() for k, t in p.items()} for p in params]
        parallel = [
            (e, p, lc)
            for e, p, lc in zip(self.effects, params, self._lc_masks)
            if e.kind == "parallel"
        ]
        if not parallel:
            return applied.clone()
        lc_mask = torch.zeros(4, dtype=torch.bool)
        for _, _, lc in parallel:
            lc_mask |= lc
        # Only the load cases a parallel effect acts in (elsewhere the disc carries it all).
        cases = torch.nonzero(lc_mask).flatten().tolist()
        with torch.no_grad():
            coef = None if coef is None else coef.detach()
            phi_disc = self._disc(v[:, : self.n_disc], coef, cases=cases)
            target = applied[:, cases]
            lo = torch.log(target * _MIN_SHARE)
            hi = torch.log(target).clone()
            masks = [lc[None, cases, None].to(v.dtype) for _, _, lc in parallel]
            parallel = [(e, p) for e, p, _ in parallel]

            def above(md: torch.Tensor) -> torch.Tensor:
                # md (B, c, q): whether md + sum M_e(phi(md)) exceeds the applied moment
                phi = phi_disc(md, detached=True, slope=False)[0]
                g = md - target.repeat_interleave(md.shape[2] // target.shape[2], 2)
                for (e, p), lc in zip(parallel, masks):
                    g = g + e.moment_at(phi, p, cases) * lc
                return g > 0

            per_round = _levels_per_round(target.numel())
            done = 0
            while done < _BISECTIONS:
                levels = min(per_round, _BISECTIONS - done)
                lo, hi = _bisect_levels(above, lo, hi, levels)
                done += levels
            md = torch.exp(0.5 * (lo + hi))
            low, high = torch.exp(lo), torch.exp(hi)
            for _ in range(_POLISH):
                md = self._newton_in_bracket(
                    phi_disc, parallel, masks, cases, md, target, low, high
                )
            share = applied.clone()
            share[:, cases] = md
            return share

    @staticmethod
    def _newton_in_bracket(phi_disc, parallel, masks, cases, md, target, low, high) -> torch.Tensor:
        """One Newton step on ``md + sum M_e(phi(md)) = target`` (B, c, m), clipped to the
        bracket ``[low, high]`` that bisection left around the root."""
        phi, slope = phi_disc(md, detached=True, slope=True)
        phi = phi.detach().requires_grad_(True)
        with torch.enable_grad():
            carried = sum(e.moment_at(phi, p, cases) * lc for (e, p), lc in zip(parallel, masks))
            (dm,) = torch.autograd.grad(carried.sum(), phi)
        g = md + carried.detach() - target
        step = md - g / (1.0 + dm * slope)
        step = torch.where(torch.isfinite(step), step, md)
        return torch.minimum(torch.maximum(step, low), high)

    def _remember(self, v: torch.Tensor, share: torch.Tensor) -> None:
        """Keep the disc's share (n, 4, m) at the rows ``v`` (n, dim) for :meth:`_share_of`
        (at most :data:`_MAX_SHARES` rows)."""
        if len(self._shares) + len(v) > _MAX_SHARES:
            self._shares = {}
        rows = v.detach().cpu().numpy()
        self._shares.update((r.tobytes(), share[i]) for i, r in enumerate(rows))

    def _share_of(self, v: torch.Tensor) -> torch.Tensor:
        """:meth:`_disc_share` at ``v`` (n, dim); the rows that :meth:`curves` or
        :meth:`_share_of` solved before are taken from there (the solve is row by row: the
        same values up to float32 rounding)."""
        keys = [r.tobytes() for r in v.detach().cpu().numpy()]
        known = [self._shares.get(k) for k in keys]
        missing = [i for i, s in enumerate(known) if s is None]
        if len(missing) == len(keys):
            share = self._disc_share(v)
            self._remember(v, share)
            return share
        if missing:
            solved = self._disc_share(v[missing])
            self._remember(v[missing], solved)
            for j, i in enumerate(missing):
                known[i] = solved[j]
        return torch.stack(known)

    def curves(
        self,
        v: torch.Tensor,
        *,
        share: torch.Tensor | None = None,
        coef: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Composite RoM curves, shape (n, dim) -> (n, 4, m); differentiable in ``v``.

        ``share`` (n, 4, m): the disc's share of the moment from :meth:`_disc_share` at the
        same ``v`` (computed here when omitted; the Jacobian passes it, bisected once per row).
        ``coef`` (K, n, 4, p): the disc members' coefficients at ``v`` (see :meth:`_disc`).
        """
        self.n_evaluations += int(v.shape[0])
        b = v.shape[0]
        if coef is None:
            coef = self._coefficients(v[:, : self.n_disc])
        phi_disc = self._disc(v[:, : self.n_disc], coef)
        applied = constant_like(self.moments.to(v.dtype).expand(b, 4, -1), v)
        params = [e.from_unit(v[:, sl]) for e, sl in zip(self.effects, self._slices)]
        parallel = [(e, p) for e, p in zip(self.effects, params) if e.kind == "parallel"]
        masks = dict(zip(self.effect_names, self._lc_masks))
        if parallel:
            lc_mask = torch.zeros(4, dtype=torch.bool)
            for e, _ in parallel:
                lc_mask |= masks[e.name]

            def extra(phi: torch.Tensor, p_detach: bool) -> torch.Tensor:
                total = None
                for e, p in parallel:
                    pp = {k: t.detach() for k, t in p.items()} if p_detach else p
                    mask = constant_like(masks[e.name][None, :, None], phi)
                    term = e.moment_at(phi, pp) * mask
                    total = term if total is None else total + term
                return total

            if share is None:
                md0 = self._disc_share(v, coef, params)
                self._remember(v, md0)
            else:
                md0 = constant_like(share, v)
            # One Newton step with the graph: exact implicit gradient at the solution.
            phi0, slope = phi_disc(md0)
            phi_req = phi0.detach().requires_grad_(True)
            with torch.enable_grad():
                (dme,) = torch.autograd.grad(extra(phi_req, True).sum(), phi_req)
            g = md0 + extra(phi0, False) - applied
            gprime = constant_like(1.0 + dme * slope.detach(), v)
            md = md0 - g / gprime
            md = torch.where(lc_mask[None, :, None], md, applied)
            phi, _ = phi_disc(md, slope=False)
        else:
            phi, _ = phi_disc(applied, slope=False)
        for e, p in zip(self.effects, params):
            if e.kind == "series":
                mask = constant_like(masks[e.name][None, :, None], v)
                phi = phi + e.rotation_at(applied, p) * mask
        return phi

    def curves_jacobian(
        self, v: torch.Tensor, *, jacobian_members: int | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Curves (n, 4, m) and their Jacobian (n, 4, m, dim).

        The curves are those of :meth:`curves`. The Jacobian follows from the implicit-function
        theorem at the disc's share of the moment (:mod:`femcal.effects.jacobian`): the disc
        network's coefficients and their derivatives once per distinct disc, the disc's terms
        in closed form, each effect's parameter derivatives by forward-mode AD over its own
        parameters. ``jacobian_members`` (k): the disc's curve moves along its parameters as
        the mean of the first k ensemble members' does (about ``n_members / k`` times cheaper
        to differentiate; approximate); the curves, the disc's share, its slope and the
        effects' terms stay the ensemble's. Default: exact.
        """
        b, d = v.shape
        step = max(1, _JAC_ROWS // d)  # chunks bound the memory of the temporaries
        members = len(self.net.members)
        members = min(int(jacobian_members or members), members)
        values, jacs = [], []
        for start in range(0, b, step):
            vc = v[start : start + step].detach()
            value, jac = self._jacobian_chunk(vc, members)
            self.n_evaluations += vc.shape[0] * d
            values.append(value)
            jacs.append(jac)
        return torch.cat(values), torch.cat(jacs)

    def _jacobian_chunk(self, v: torch.Tensor, members: int) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`curves_jacobian` of the rows ``v`` (n, dim), without chunking, the disc's
        curve differentiated through its first ``members`` ensemble members."""
        net, nd = self.net, self.n_disc
        n, d = v.shape
        share = self._share_of(v)  # (n, 4, m): the applied moment where no parallel effect acts
        # Each distinct disc once: a fit's starts from one grid share the disc's parameters.
        disc, inverse = torch.unique(v[:, :nd], dim=0, return_inverse=True)
        h, t = ensemble_tangents(net.members[:members], disc)  # (k, u, out), (k, u, nd, out)
        if members < len(net.members):
            rest = ensemble_forward(net.members[members:], disc)
            h = torch.cat([h, rest])
        k, p = h.shape[0], net.moment_degree + 1
        coef = h[:, inverse].reshape(k, n, net.n_load_cases, p)
        dcoef = t[:, inverse].reshape(members, n, nd, net.n_load_cases, p)
        with torch.no_grad():
            value = self.curves(v, share=share, coef=coef)
        log_low = float(np.log(self.m_low))
        if members < k:  # the share's slope from every member, its tangents from ``members``
            phi, slope, _ = disc_partials(net, coef, dcoef[:, :, :0], share, log_low)
            along = disc_partials(net, coef[:members], dcoef, share, log_low)[2]
        else:
            phi, slope, along = disc_partials(net, coef, dcoef, share, log_low)
        m = share.shape[-1]
        jac = v.new_zeros((n, d, 4, m))  # columns first, moved last at the end
        jac[:, :nd] = along
        params = [e.from_unit(v[:, sl]) for e, sl in zip(self.effects, self._slices)]
        parallel = [
            (e, q, sl, lc[None, :, None].to(v.dtype))
            for e, q, sl, lc in zip(self.effects, params, self._slices, self._lc_masks)
            if e.kind == "parallel"
        ]
        if parallel:
            # k_e = sum_e dM_e/dphi at the solution, then dM_d along every column.
            phi_req = phi.detach().requires_grad_(True)
            with torch.enable_grad():
                carried = sum(e.moment_at(phi_req, q) * lc for e, q, _, lc in parallel)
                (stiff,) = torch.autograd.grad(carried.sum(), phi_req)
            d_g = stiff[:, None] * along  # (n, nd, 4, m); the effects' columns below
            d_g = torch.cat([d_g, v.new_zeros((n, d - nd, 4, m))], dim=1)
            for e, _, sl, lc in parallel:
                law = _masked_law(e.moment_at, phi, lc, sl.stop - sl.start)
                d_g[:, sl] += parameter_partials(e, v[:, sl], law)
            d_share = -d_g / (1.0 + stiff * slope)[:, None]
            jac = jac + slope[:, None] * d_share
        for e, sl, lc in zip(self.effects, self._slices, self._lc_masks):
            if e.kind == "series":
                mask = lc[None, :, None].to(v.dtype)
                applied = self.moments.to(v.dtype).expand(n, 4, -1)
                law = _masked_law(e.rotation_at, applied, mask, sl.stop - sl.start)
                jac[:, sl] += parameter_partials(e, v[:, sl], law)
        return value.detach(), jac.permute(0, 2, 3, 1).contiguous()

    def predict(self, x: np.ndarray, *, clip: bool = True) -> np.ndarray:
        v = self.from_physical(np.asarray(x, dtype=float).reshape(len(x), -1), clip=clip)
        with torch.no_grad():
            return self.curves(v).double().numpy()


def _masked_law(law, x: torch.Tensor, mask: torch.Tensor, k: int):
    """``law(x, params) * mask`` in the form :func:`parameter_partials` takes: each row of
    ``x`` (n, 4, m) repeated ``k`` times, ``x`` and ``mask`` constants of the dual input."""
    return lambda q, like: law(repeated(x, k, like), q) * constant_like(mask, like)
