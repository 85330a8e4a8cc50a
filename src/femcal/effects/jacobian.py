"""The Jacobian of the composite curves, from one evaluation per row.

With parallel elements the disc carries the share ``M_d`` of the applied moment ``M`` that
solves ``G = M_d + sum_e M_e(phi_d(M_d; c); p_e) - M = 0``. At the solution the implicit-function
theorem gives, along any direction of the parameters,

    d phi = s dM_d + A,    dM_d = -(k A + sum_e dM_e/dp_e dp_e) / (1 + k s),

with ``s = d phi_d / dM`` the disc's slope, ``A`` the change of the disc's curve when its
polynomial coefficients ``c`` move along their tangents (at a fixed moment), and
``k = sum_e d M_e / d phi`` the elements' stiffness. Series elements add
``d phi_e / dp_e dp_e``. The disc's terms follow in closed form from the members'
polynomials in ``z = (log M - moment_loc) / moment_scale`` (and the power law that continues a
curve below its lowest trained moment); the elements' parameter derivatives come from
forward-mode AD over each element's own parameters only. So no quantity is evaluated once per
column, as a forward pass with one dual row per column would.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.autograd.forward_ad as fwad

from femcal.forward_ad import constant_like

#: Bounds of the log-log slope that continues the disc's curve below its lowest trained
#: moment (:meth:`femcal.effects.composite.EffectModel._disc`).
LOW_SLOPE = (0.05, 3.0)


def disc_partials(
    net, coef: torch.Tensor, dcoef: torch.Tensor, moment: torch.Tensor, log_low: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The disc's rotation, its slope in the moment and its derivative along ``dcoef``.

    Parameters
    ----------
    net : RomNet
        The disc network (its moment and output scaling, ``log_target``).
    coef : Tensor, shape (K, n, c, p)
        The members' polynomial coefficients (network outputs) per row and load case.
    dcoef : Tensor, shape (K, n, q, c, p)
        Their tangents along ``q`` directions.
    moment : Tensor, shape (n, c, m)
        The moment (Nm) the disc carries.
    log_low : float
        ``log`` of the lowest trained moment; below it the curve continues as the power law
        through the origin with the log-log slope there (clipped to :data:`LOW_SLOPE`).

    Returns
    -------
    phi : Tensor, shape (n, c, m)
        The members' mean rotation (deg).
    slope : Tensor, shape (n, c, m)
        ``d phi / dM`` (deg/Nm).
    along : Tensor, shape (n, q, c, m)
        ``d phi`` along each direction of ``dcoef``, at a fixed moment.
    """
    n_members, p = coef.shape[0], coef.shape[-1]
    dtype = coef.dtype
    y_scale, y_loc = net.y_scale.to(dtype), net.y_loc.to(dtype)
    inv_scale = 1.0 / net.moment_scale.to(dtype)
    c = coef * y_scale
    c[..., 0] += y_loc
    dc = dcoef * y_scale
    log_m = torch.log(moment)
    log_mc = log_m.clamp_min(log_low)
    z = (log_mc - net.moment_loc.to(dtype)) * inv_scale
    powers = z[..., None] ** torch.arange(p, dtype=dtype)  # (n, c, m, p)
    dpowers = powers[..., :-1] * torch.arange(1, p, dtype=dtype)  # d z^j / dz, j >= 1
    t = torch.einsum("kncj,ncmj->kncm", c, powers)
    dt_dz = torch.einsum("kncj,ncmj->kncm", c[..., 1:], dpowers)
    along_t = torch.einsum("knqcj,ncmj->knqcm", dc, powers)
    if net.log_target:
        deg = torch.exp(t)
        weight = deg
    else:
        deg = t
        weight = torch.ones_like(t)
    phi = deg.mean(0)
    dphi_dz = (weight * dt_dz).mean(0)
    along = torch.einsum("kncm,knqcm->nqcm", weight, along_t) / n_members
    moment_ = torch.exp(log_m)
    low = log_m < log_low
    if not bool(low.any()):
        return phi, dphi_dz * inv_scale / moment_, along
    # Below the lowest trained moment: phi_low exp(b (log M - log_low)), b the log-log slope
    # at the lowest trained moment (where log_mc = log_low, so phi, dphi_dz and along are there).
    raw = dphi_dz * inv_scale / phi
    b = raw.clamp(*LOW_SLOPE)
    free = (raw >= LOW_SLOPE[0]) & (raw <= LOW_SLOPE[1])
    along_dt_dz = torch.einsum("knqcj,ncmj->knqcm", dc[..., 1:], dpowers)
    if net.log_target:
        along_dphi_dz = (deg[:, :, None] * (dt_dz[:, :, None] * along_t + along_dt_dz)).mean(0)
    else:
        along_dphi_dz = along_dt_dz.mean(0)
    ratio = phi[:, None]
    along_b = inv_scale * (along_dphi_dz / ratio - dphi_dz[:, None] * along / ratio**2)
    along_b = torch.where(free[:, None], along_b, torch.zeros_like(along_b))
    span = log_m - log_mc
    grow = torch.exp(b * span)
    out = phi * grow
    along_low = grow[:, None] * along + out[:, None] * span[:, None] * along_b
    slope = torch.where(low, out * b, dphi_dz * inv_scale) / moment_
    return out, slope, torch.where(low[:, None], along_low, along)


def parameter_partials(
    effect, unit: torch.Tensor, law: Callable[[dict[str, torch.Tensor], torch.Tensor], torch.Tensor]
) -> torch.Tensor:
    """Derivatives of ``law(params, like)`` in an effect's own unit coordinates.

    Parameters
    ----------
    effect : Effect
        The effect whose :meth:`~femcal.effects.base.Effect.from_unit` maps ``unit``.
    unit : Tensor, shape (n, k)
        The effect's parameters in its unit box.
    law : callable
        ``law(params, like)`` -> Tensor (n * k, ...): the effect's moment or rotation for the
        rows of ``unit`` each repeated ``k`` times (``params`` by name, (n * k,) each); constants
        are made with :func:`~femcal.forward_ad.constant_like` of ``like``.

    Returns
    -------
    Tensor, shape (n, k, ...)
    """
    n, k = unit.shape
    with fwad.dual_level():
        dual = fwad.make_dual(
            unit.detach().repeat_interleave(k, 0), torch.eye(k, dtype=unit.dtype).repeat(n, 1)
        )
        out = law(effect.from_unit(dual), dual)
        primal, tangent = fwad.unpack_dual(out)
    if tangent is None:  # the law does not depend on these parameters
        tangent = torch.zeros_like(primal)
    return tangent.reshape(n, k, *tangent.shape[1:])


def repeated(x: torch.Tensor, k: int, like: torch.Tensor) -> torch.Tensor:
    """``x`` (n, ...) with each row repeated ``k`` times, as a constant of ``like``."""
    return constant_like(x.repeat_interleave(k, 0), like)
