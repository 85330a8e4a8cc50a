"""Model discrepancy: what a calibrated model still misses, as a smooth curve with a band.

Kennedy & O'Hagan's form: ``measured = model(v) + delta(M) + noise``, with ``delta`` a Gaussian
process per load case, in rotation (degrees), over ``x = ln M``:

    k(x, x') = s^2 exp(-(x - x')^2 / (2 l^2)),   noise ~ N(0, sigma(M)^2).

The model parameters ``v`` are fitted jointly with ``delta``: ``delta`` enters linearly with a
Gaussian prior, so it is profiled out exactly and ``v`` minimises the generalised least squares
``r^T C^-1 r`` with ``C = K + diag(sigma^2)`` (:func:`fit_discrepancy`, a projected
Levenberg-Marquardt in the model's unit box). The posterior of ``delta`` anywhere (the kriging
mean, and its variance including the uncertainty of ``v``, Rasmussen & Williams eq. 2.42 with the
model's Jacobian as the explicit basis) is :func:`discrepancy_posterior`.

:func:`describe` turns the posterior into words: per load case, laxity or stiffening, from which
moment, how large, and whether it grows with the moment; and which registered effect's signature
it resembles.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from femcal.figures import dense_grid as dense_grid  # the diagnosis' curves
from femcal.schema import LOAD_CASES

#: Correlation length of the discrepancy in ln(moment): smooth over a factor e^0.5 = 1.6.
LENGTH_SCALE = 0.5


@dataclass
class DiscrepancyFit:
    """A model fitted jointly with a GP discrepancy, for a batch of specimens.

    Attributes
    ----------
    v : Tensor, shape (n, d)
        Model parameters (unit coordinates) at the joint optimum.
    pred : Tensor, shape (n, 4, m)
        The model's curves there.
    jac : Tensor, shape (n, 4, m, d)
        Their Jacobian.
    amplitude_deg : ndarray, shape (n, 4)
        The GP amplitude ``s`` used per specimen and load case.
    alpha : ndarray, shape (n, 4 m)
        ``C^-1 r``: the weights of the kriging mean.
    chol : ndarray, shape (n, 4 m, 4 m)
        Cholesky factor of ``C`` (unmeasured points decoupled, unit variance).
    delta_at_points : ndarray, shape (n, 4, m)
        Posterior mean of the discrepancy at the measured points (NaN elsewhere).
    mae_deg : ndarray, shape (n,)
        MAE of model + discrepancy against the measurements.
    cost : ndarray, shape (n,)
        The profiled generalised least squares ``r^T C^-1 r`` at the optimum (the data term
        of -2 log marginal likelihood; ``log det C`` is the same for every model fitted with
        the same amplitude, mask and noise).
    """

    v: torch.Tensor
    pred: torch.Tensor
    jac: torch.Tensor
    amplitude_deg: np.ndarray
    alpha: np.ndarray
    chol: np.ndarray
    delta_at_points: np.ndarray
    mae_deg: np.ndarray
    cost: np.ndarray
    log_det: np.ndarray | None = None

    @property
    def neg2_log_ml(self) -> np.ndarray:
        """``r^T C^-1 r + log det C`` (n,): -2 log marginal likelihood up to a constant."""
        return self.cost + (0.0 if self.log_det is None else self.log_det)


#: Amplitudes tried by the type-II maximum likelihood (``amplitude_deg="ml"``), in units of
#: the smallest sigma; 0 = no discrepancy.
ML_AMPLITUDES = (0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0)


def ml_amplitude(
    residual: np.ndarray,
    mask: np.ndarray,
    sigma: np.ndarray,
    x: np.ndarray,
    *,
    length_scale: float = LENGTH_SCALE,
    grid: Sequence[float] | None = None,
    cap: np.ndarray | None = None,
) -> np.ndarray:
    """Type-II maximum likelihood amplitude of the discrepancy, per specimen and load case.

    The kernel is block-diagonal over load cases, so each load case's amplitude maximises its
    own marginal likelihood ``N(r | 0, s^2 K + diag(sigma^2))``, over a grid of amplitudes.

    Parameters
    ----------
    residual : ndarray, shape (n, 4, m)
        Measured minus model (0 where not measured).
    mask : ndarray of bool, shape (n, 4, m)
    sigma : ndarray, shape (n, 4, m)
        Noise sd of every point.
    x : ndarray, shape (m,)
        ln(moment) of the grid.
    grid : sequence of float, optional
        Amplitudes to try (deg); default :data:`ML_AMPLITUDES` times the smallest sigma.
    cap : ndarray, shape (n, 4), optional
        Largest amplitude allowed per specimen and load case (``inf``: free): the maximum
        likelihood among the grid's amplitudes up to it (0 is always allowed).

    Returns
    -------
    ndarray, shape (n, 4)
    """
    s_min = float(np.min(sigma))
    amps = np.asarray(
        [a * s_min for a in ML_AMPLITUDES] if grid is None else list(grid), dtype=float
    )
    amps = np.minimum(amps, 5.0)
    n, n_lc, m = residual.shape
    base = np.exp(-0.5 * ((x[:, None] - x[None, :]) / length_scale) ** 2)  # (m, m)
    mk = mask.astype(float)
    outer = mk[..., :, None] * mk[..., None, :]  # (n, 4, m, m)
    diag = np.where(mask, sigma**2, 1.0)  # (n, 4, m)
    eye = np.eye(m)
    r = np.where(mask, residual, 0.0)
    nll = np.empty((len(amps), n, n_lc))
    for g, a in enumerate(amps):
        c = a**2 * base * outer + diag[..., :, None] * eye
        chol = np.linalg.cholesky(c)
        w = np.linalg.solve(chol, r[..., None])[..., 0]
        logdet = 2 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1)
        nll[g] = (w**2).sum(-1) + logdet
    if cap is not None:
        cap = np.broadcast_to(np.asarray(cap, dtype=float), (n, n_lc))
        over = (amps[:, None, None] > cap[None] * (1 + 1e-9)) & (amps[:, None, None] > 0)
        nll = np.where(over, np.inf, nll)
    return amps[np.argmin(nll, axis=0)]


def _kernel(xa: np.ndarray, xb: np.ndarray, amp: np.ndarray, length: float) -> np.ndarray:
    """Block-diagonal (over load cases) SE kernel, shape (n, 4 a, 4 b).

    ``amp`` is the amplitude per specimen (n,) or per specimen and load case (n, 4).
    """
    n_lc = len(LOAD_CASES)
    amp = np.asarray(amp, dtype=float)
    amp = np.broadcast_to(amp[:, None] if amp.ndim == 1 else amp, (amp.shape[0], n_lc))
    base = np.exp(-0.5 * ((xa[:, None] - xb[None, :]) / length) ** 2)  # (a, b)
    block = np.kron(np.eye(n_lc), base)  # (4a, 4b), load-case major
    sa = np.repeat(amp, len(xa), axis=1)  # (n, 4a)
    sb = np.repeat(amp, len(xb), axis=1)
    return sa[:, :, None] * block[None] * sb[:, None, :]


def _covariance(
    mask: np.ndarray, sigma: np.ndarray, x: np.ndarray, amp: np.ndarray, length: float
) -> np.ndarray:
    """``C = K + diag(sigma^2)`` on the measured points; unmeasured points decoupled (1)."""
    n = mask.shape[0]
    flat = mask.reshape(n, -1).astype(float)
    k = _kernel(x, x, amp, length) * flat[:, :, None] * flat[:, None, :]
    s2 = np.broadcast_to(sigma**2, mask.shape).reshape(n, -1)
    diag = np.where(flat > 0, s2, 1.0)
    return k + np.einsum("ni,ij->nij", diag, np.eye(flat.shape[1]))


def _whiten(chol: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``L^-1 a`` for a batch of lower-triangular ``L`` (n, P, P) and ``a`` (n, P, ...)."""
    return np.linalg.solve(chol, a)  # chol is small (P <= 4 x 20); solve is exact enough


def _start_amplitude(
    amplitude_deg: np.ndarray | float | str | None,
    r3: np.ndarray,
    mask: np.ndarray,
    sig: np.ndarray,
) -> np.ndarray:
    """The GP amplitude (n, 4) in degrees that :func:`fit_discrepancy` starts from.

    ``r3`` (n, 4, m) are the residuals at the start (0 where not measured), ``mask`` (n, 4, m)
    the measured points and ``sig`` (n, 4, m) their noise sd (deg). With ``amplitude_deg``
    None or ``"ml"``: per load case, the RMS misfit beyond the noise, clipped to
    [min(sig), 5] deg; otherwise ``amplitude_deg`` broadcast to (n, 4).

    Raises
    ------
    ValueError
        On a string other than ``"ml"``.
    """
    n, n_lc, _ = r3.shape
    ml = isinstance(amplitude_deg, str)
    if ml and amplitude_deg != "ml":
        raise ValueError(
            f"amplitude_deg must be a number, an array or 'ml'; got {amplitude_deg!r}."
        )
    if amplitude_deg is None or ml:
        # Per load case: the RMS misfit the model leaves there beyond the noise.
        count = mask.sum(2).clip(1)  # (n, 4)
        noise2 = (np.where(mask, sig, 0.0) ** 2).sum(2)
        amp = np.sqrt(np.clip(((r3**2).sum(2) - noise2) / count, 0.0, None))
        return np.clip(amp, float(np.min(sig)), 5.0)
    amp = np.asarray(amplitude_deg, dtype=float)
    return np.broadcast_to(amp[:, None] if amp.ndim == 1 else amp, (n, n_lc)).copy()


def _levenberg_marquardt(
    model,
    state: tuple[torch.Tensor, torch.Tensor, torch.Tensor, np.ndarray],
    chol: np.ndarray,
    residual: Callable[[torch.Tensor], np.ndarray],
    flat_mask: np.ndarray,
    max_iter: int,
) -> np.ndarray:
    """Projected Levenberg-Marquardt of the model's parameters under the covariance with
    Cholesky factor ``chol`` (n, P, P), at most ``max_iter`` iterations.

    ``state`` holds the parameters ``v`` (n, d, unit coordinates), the curves ``pred``
    (n, 4, m), their Jacobian ``jac`` and the residuals ``r`` (n, P), all updated in place
    where a step lowers the cost. ``residual`` maps curves to residuals (n, P); ``flat_mask``
    (n, P) marks the measured points. Returns the cost ``r^T C^-1 r`` (n,) at the end.
    """
    v, pred, jac, r = state
    n, d = v.shape

    def cost_of(res: np.ndarray) -> np.ndarray:
        w = _whiten(chol, res[..., None])[..., 0]
        return (w**2).sum(1)

    cost = cost_of(r)
    lam = np.full(n, 1e-3)
    for _ in range(max_iter):
        jm = (jac.double().numpy().reshape(n, -1, d)) * flat_mask[..., None]
        rw = _whiten(chol, r[..., None])[..., 0]  # (n, P)
        jw = _whiten(chol, jm)  # (n, P, d)
        hess = np.einsum("npi,npj->nij", jw, jw)
        grad = np.einsum("npi,np->ni", jw, rw)  # descent direction of r = y - f: +J^T r
        vn = v.double().numpy()
        blocked = ((vn <= 0) & (grad < 0)) | ((vn >= 1) & (grad > 0))
        free = (~blocked).astype(float)
        hf = hess * free[:, :, None] * free[:, None, :]
        damp = lam[:, None] * (np.diagonal(hf, axis1=1, axis2=2) + 1e-6) + 1e-9
        system = hf + np.einsum("ni,ij->nij", damp + (1 - free), np.eye(d))
        step = np.linalg.solve(system, (grad * free)[..., None])[..., 0]
        v_new = torch.tensor(np.clip(vn + step, 0.0, 1.0), dtype=torch.float32)
        with torch.no_grad():
            p_new = model.curves(v_new)
        r_new = residual(p_new)
        c_new = np.nan_to_num(cost_of(r_new), nan=np.inf)
        ok = c_new < cost
        if not ok.any():
            lam *= 4
            if np.all(lam > 1e6):
                break
            continue
        idx = torch.as_tensor(np.flatnonzero(ok))
        v[idx] = v_new[idx]
        pn, jn = model.curves_jacobian(v[idx])
        pred[idx], jac[idx] = pn, jn
        r[ok] = r_new[ok]
        gain = (cost - c_new) / np.maximum(cost, 1e-30)
        cost = np.where(ok, c_new, cost)
        lam = np.where(ok, lam / 3, lam * 4)
        if np.all(~ok | (gain < 1e-5)):
            break
    return cost


def fit_discrepancy(
    model,
    v0: torch.Tensor,
    measured: np.ndarray,
    sigma: np.ndarray,
    *,
    amplitude_deg: np.ndarray | float | None = None,
    length_scale: float = LENGTH_SCALE,
    max_iter: int = 8,
    ml_rounds: int = 2,
    amplitude_cap: np.ndarray | None = None,
) -> DiscrepancyFit:
    """Fit the model and a GP discrepancy jointly (see the module docstring).

    Parameters
    ----------
    model : CurveModel or EffectModel
        Differentiable curves on the measured moment grid (``curves_jacobian``).
    v0 : Tensor, shape (n, d)
        Start (unit coordinates), e.g. the model's own best fit.
    measured : ndarray, shape (n, 4, m)
        Measured RoM (deg), NaN where not measured.
    sigma : ndarray, shape (m,) or (n, 4, m)
        Noise sd of each point (deg): measurement noise and the surrogate's own error.
    amplitude_deg : float or ndarray (n,) or (n, 4) or "ml", optional
        GP amplitude ``s`` (per specimen, or per specimen and load case). Default: per load
        case, the RMS misfit the model leaves there beyond the noise at ``v0`` (at least the
        smallest sigma), so that a model that fits gets a small ``s``. ``"ml"``: type-II
        maximum likelihood per load case (:func:`ml_amplitude`), alternated ``ml_rounds``
        times with the fit of the model's parameters; then :attr:`DiscrepancyFit.neg2_log_ml`
        compares models that each got the discrepancy they need.
    length_scale : float
        Correlation length in ln(moment).
    max_iter : int
        Levenberg-Marquardt iterations (per round).
    ml_rounds : int
        Rounds of amplitude / parameter updates with ``amplitude_deg="ml"``.
    amplitude_cap : ndarray, shape (n, 4), optional
        With ``amplitude_deg="ml"``: the largest amplitude allowed per specimen and load case
        (``inf`` where free), e.g. what a larger model needed there, so that the discrepancy
        cannot take over what an effect explained in its own load cases.

    Returns
    -------
    DiscrepancyFit
    """
    meas = np.asarray(measured, dtype=float)
    n, n_lc, m = meas.shape
    mask = np.isfinite(meas)
    y = np.where(mask, meas, 0.0)
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), meas.shape)
    x = np.log(model.moments.double().numpy())
    flat_mask = mask.reshape(n, -1)
    v = v0.detach().clone().float()

    def residual(pred: torch.Tensor) -> np.ndarray:
        return np.where(mask, y - pred.double().numpy(), 0.0).reshape(n, -1)

    pred, jac = model.curves_jacobian(v)
    r = residual(pred)
    ml = isinstance(amplitude_deg, str)
    amp = _start_amplitude(amplitude_deg, r.reshape(n, n_lc, m), mask, sig)
    for _round in range(ml_rounds if ml else 1):
        if ml:
            amp = ml_amplitude(
                r.reshape(n, n_lc, m),
                mask,
                sig,
                x,
                length_scale=length_scale,
                cap=amplitude_cap,
            )
        cov = _covariance(mask, sig, x, amp, length_scale)
        chol = np.linalg.cholesky(cov)
        cost = _levenberg_marquardt(model, (v, pred, jac, r), chol, residual, flat_mask, max_iter)
    alpha = np.linalg.solve(np.swapaxes(chol, 1, 2), _whiten(chol, r[..., None]))[..., 0]
    k_pts = _kernel(x, x, amp, length_scale) * flat_mask[:, :, None] * flat_mask[:, None, :]
    delta = np.einsum("nij,nj->ni", k_pts, alpha).reshape(n, n_lc, m)
    delta = np.where(mask, delta, np.nan)
    err = np.abs(np.where(mask, meas - pred.double().numpy() - np.nan_to_num(delta), np.nan))
    log_det = 2 * np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(1)
    return DiscrepancyFit(
        v=v,
        pred=pred.detach(),
        jac=jac.detach(),
        amplitude_deg=amp,
        alpha=alpha,
        chol=chol,
        delta_at_points=delta,
        mae_deg=np.nanmean(err.reshape(n, -1), axis=1),
        cost=cost,
        log_det=log_det,
    )


def discrepancy_posterior(
    fit: DiscrepancyFit,
    moments: np.ndarray,
    at: np.ndarray,
    mask: np.ndarray,
    *,
    length_scale: float = LENGTH_SCALE,
) -> tuple[np.ndarray, np.ndarray]:
    """Posterior mean and sd of the discrepancy at moments ``at``.

    Parameters
    ----------
    fit : DiscrepancyFit
    moments : ndarray, shape (m,)
        The measured moment grid of the fit.
    at : ndarray, shape (q,)
        Where to evaluate (Nm).
    mask : ndarray of bool, shape (n, 4, m)
        The measured points.

    Returns
    -------
    mean, sd : ndarray, shape (n, 4, q)
        The sd includes the uncertainty of the model parameters (their unit-box prior).
    """
    n = fit.alpha.shape[0]
    x = np.log(np.asarray(moments, dtype=float))
    xs = np.log(np.asarray(at, dtype=float))
    q = len(xs)
    flat = mask.reshape(n, -1).astype(float)
    ks = _kernel(xs, x, fit.amplitude_deg, length_scale) * flat[:, None, :]  # (n, 4q, P)
    mean = np.einsum("nqp,np->nq", ks, fit.alpha)
    # Var = k** - k*^T C^-1 k* + G Sigma_v G^T, G = k*^T C^-1 J.
    a = _whiten(fit.chol, np.swapaxes(ks, 1, 2))  # L^-1 k*: (n, P, 4q)
    d = fit.v.shape[1]
    jm = fit.jac.double().numpy().reshape(n, -1, d) * flat[..., None]
    bj = _whiten(fit.chol, jm)  # L^-1 J: (n, P, d)
    sigma_v = np.linalg.inv(np.einsum("npi,npj->nij", bj, bj) + np.eye(d))
    g = np.einsum("npq,npd->nqd", a, bj)  # (n, 4q, d)
    var = (
        np.repeat(fit.amplitude_deg**2, q, axis=1)
        - (a**2).sum(1)
        + np.einsum("nqi,nij,nqj->nq", g, sigma_v, g)
    )
    sd = np.sqrt(np.clip(var, 0.0, None))
    return mean.reshape(n, len(LOAD_CASES), q), sd.reshape(n, len(LOAD_CASES), q)


def describe(
    moments: np.ndarray,
    mean: np.ndarray,
    sd: np.ndarray,
    sigma_deg: float,
    *,
    z: float = 2.0,
) -> list[str]:
    """What is missing, in words, one sentence per load case where the band excludes zero.

    Parameters
    ----------
    moments : ndarray, shape (q,)
        Increasing moments (Nm) of the posterior; NaN columns are skipped.
    mean, sd : ndarray, shape (4, q)
        Discrepancy posterior (measured - model, deg).
    sigma_deg : float
        The noise sd, to say the size in sigma.
    z : float
        A point is significant where ``|mean| > z sd``.

    Returns
    -------
    list of str
    """
    out = []
    for j, lc in enumerate(LOAD_CASES):
        ok = np.isfinite(mean[j]) & np.isfinite(sd[j])
        sig = ok & (np.abs(mean[j]) > z * sd[j]) & (np.abs(mean[j]) > sigma_deg)
        if not sig.any():
            continue
        idx = np.flatnonzero(sig)
        peak = idx[np.argmax(np.abs(mean[j][idx]))]
        value = float(mean[j][peak])
        sign = np.sign(value)
        same = idx[np.sign(mean[j][idx]) == sign]
        onset = float(moments[same[0]])
        upto = float(moments[same[-1]])
        kind = (
            "more rotation than the model (laxity or softening)"
            if sign > 0
            else "less rotation than the model (stiffening)"
        )
        first_ok = np.flatnonzero(ok)
        low_end = abs(float(mean[j][first_ok[0]]))
        high_end = abs(float(mean[j][first_ok[-1]]))
        if high_end > 1.5 * max(low_end, 1e-9) and same[-1] == first_ok[-1]:
            shape = "growing with the moment"
        elif low_end >= 0.7 * high_end and same[0] == first_ok[0]:
            shape = "already at the lowest moment, then about constant (an offset)"
        else:
            shape = "largest mid-range"
        out.append(
            f"{lc}: {kind} from {onset:.2g} to {upto:.2g} Nm, up to {abs(value):.2f} deg "
            f"({abs(value) / sigma_deg:.0f} sigma) at {float(moments[peak]):.2g} Nm, {shape}"
        )
    return out


def similarity(delta: np.ndarray, signatures: Mapping[str, np.ndarray], sigma: np.ndarray):
    """Cosine similarity of a discrepancy with each effect's signature, in units of sigma.

    Parameters
    ----------
    delta : ndarray, shape (4, m)
        Discrepancy at the measured points (NaN elsewhere).
    signatures : mapping of str to ndarray (4, m)
        What each registered effect adds to the disc-alone fit (its fit minus the disc's).
    sigma : ndarray, shape (m,) or (4, m)

    Returns
    -------
    dict of str to float
    """
    ok = np.isfinite(delta)
    a = np.where(ok, delta / sigma, 0.0).reshape(-1)
    na = float(np.linalg.norm(a))
    out = {}
    for name, sgn in signatures.items():
        b = np.where(ok, np.nan_to_num(sgn) / sigma, 0.0).reshape(-1)
        nb = float(np.linalg.norm(b))
        out[name] = float(a @ b / (na * nb)) if na > 0 and nb > 0 else 0.0
    return out


def runs_p_value(residuals: np.ndarray) -> float:
    """One-sided Wald-Wolfowitz runs test pooled over load cases: too few sign runs.

    Parameters
    ----------
    residuals : ndarray, shape (4, m)
        Residuals ordered by moment per load case (NaN: not measured).

    Returns
    -------
    float
        P(runs <= observed) under random signs (normal approximation); 1 when untestable.
    """
    runs = expected = var = 0.0
    for row in residuals:
        s = np.sign(row[np.isfinite(row)])
        s = s[s != 0]
        n1, n2 = int((s > 0).sum()), int((s < 0).sum())
        total = n1 + n2
        if total < 2:
            continue
        runs += 1 + int(np.sum(s[1:] != s[:-1]))
        expected += 1 + 2.0 * n1 * n2 / total
        var += 2.0 * n1 * n2 * (2.0 * n1 * n2 - total) / (total**2 * (total - 1))
    if var <= 0:
        return 1.0
    zval = (runs - expected) / math.sqrt(var)
    return 0.5 * math.erfc(-zval / math.sqrt(2))
