"""What a diagnosis says of each specimen besides its verdict: adequacy tests, the ranking of
models, what each effect adds, where the disc fails, and what to measure next."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from femcal.calibration.base import chi2_p_value
from femcal.calibration.model import SurrogateCurveModel
from femcal.diagnose.box_edge import AT_BOUND
from femcal.diagnose.discrepancy import (
    describe,
    runs_p_value,
)
from femcal.diagnose.fits import (
    Fit,
)
from femcal.diagnose.result import (
    model_label,
)
from femcal.effects.composite import EffectModel
from femcal.effects.terms import Model, Term
from femcal.schema import LOAD_CASES


# ------------------------------------------------------------------------- adequacy
def adequacy_tests(
    res: np.ndarray, sigma: np.ndarray, dof: float, alpha: float, per_load_case: bool = False
) -> dict[str, Any]:
    """Chi-square and runs tests of residuals (4, m) against the noise.

    With ``per_load_case``, also a chi-square test in each load case (Bonferroni: level
    ``alpha / 4``, the model's effective parameters shared out by the load case's points): an
    effect missing in one or two load cases drowns in the pooled test when the others fit well.

    Parameters
    ----------
    res : ndarray, shape (4, m)
        Residuals in degrees, NaN where not measured.
    sigma : ndarray, shape (4, m)
        Noise sd in degrees.
    dof : float
        Degrees of freedom of the pooled chi-square test (at least 1 is used).
    alpha : float
        Significance level.

    Returns
    -------
    dict
        ``chi2``, ``dof``, ``p_chi2``, ``p_runs``, ``adequate`` (bool) and, with
        ``per_load_case``, ``p_chi2_load_case`` (4 p-values).
    """
    z = res / sigma
    chi2 = float(np.nansum(z**2))
    n = int(np.isfinite(z).sum())
    dof = max(dof, 1.0)
    p_chi2 = float(chi2_p_value(chi2, dof))
    p_runs = runs_p_value(res)
    # Runs of one sign only matter where the residuals are not small against the noise: a
    # smooth surrogate error well inside sigma makes runs, not missing physics.
    runs_bad = p_runs < alpha and chi2 > dof
    out = {"chi2": chi2, "dof": dof, "p_chi2": p_chi2, "p_runs": p_runs}
    lc_bad = False
    if per_load_case and n:
        used = n - dof  # effective parameters
        p_lc = []
        for row in z:
            ok = np.isfinite(row)
            n_j = int(ok.sum())
            if n_j < 2:
                p_lc.append(1.0)
                continue
            p_lc.append(float(chi2_p_value(np.sum(row[ok] ** 2), n_j - used * n_j / n)))
        out["p_chi2_load_case"] = p_lc
        lc_bad = min(p_lc) < alpha / len(p_lc)
    out["adequate"] = bool(p_chi2 >= alpha and not runs_bad and not lc_bad)
    return out


def adequate_quick(
    fit: Fit, pos: int, i: int, measured, sigma, n_points, alpha, per_load_case: bool = False
) -> bool:
    """Adequacy during the search: the final test's degrees of freedom (``n - trace`` of the
    hat matrix, one Jacobian per fitted batch) where the fit has them, else ``n - k/2``.

    The search and the verdict must ask the same question: with ``n - k/2`` a short protocol
    (16 points, 15 parameters) passed a model during the search that the final test rejected,
    and the verdict said ``+unexplained`` where the next effect had never been tried.

    Parameters
    ----------
    fit : Fit
        A batch fit; ``pos`` is specimen ``i``'s row in it.
    pos, i : int
        Row in ``fit`` and specimen index.
    measured, sigma : ndarray, shape (n, 4, m)
        Measured RoM and noise sd in degrees (NaN where not measured).
    n_points : ndarray of int, shape (n,)
        Measured points per specimen.
    alpha, per_load_case : float, bool
        As in :func:`adequacy_tests`.

    Returns
    -------
    bool
        Whether the model is adequate for specimen ``i``.
    """
    res = measured[i] - fit.pred[pos].double().numpy()
    used = fit.k / 2 if fit.trace is None else float(fit.trace[pos])
    dof = float(n_points[i] - used)
    return bool(adequacy_tests(res, sigma[i], dof, alpha, per_load_case)["adequate"])


# ------------------------------------------------------------------------ reporting
def effect_ranking(
    fits: dict,
    i: int,
    measured: np.ndarray,
    sigma: np.ndarray,
    cost: np.ndarray,
    base,
    mask: np.ndarray,
) -> list[dict[str, Any]]:
    """Every model fitted for specimen ``i`` (``fits``: Model -> (fit, row)) as the result
    holds it: its label and terms written, MAE, the search's criterion (``cost`` (n,) per
    parameter, :meth:`femcal.diagnose.fits.Fit.criterion`), its effective number of
    parameters and the effect parameters ± sd. ``mask`` (n, 4, m): the cohort's measured
    points; every fit's trace is known (:meth:`~femcal.diagnose.fits.Fit.ensure_trace`)."""
    rows = []
    for effects, (f, pos) in fits.items():
        pred = f.pred[pos].double().numpy()
        mae = float(np.nanmean(np.abs(measured[i] - pred)))
        entry = {
            "effect": model_label(effects),
            "effects": [str(t) for t in effects],
            "mae_deg": mae,
            "criterion": f.criterion(pos, float(cost[i]), mask, sigma),
            "effective_parameters": float(f.trace[pos]),
            "parameters": {},
        }
        if effects:
            model = f.model
            vi = f.v[pos : pos + 1]
            finite = bool(f.finite[pos])
            cov = f.cov[pos : pos + 1]
            v64 = np.clip(vi.double().numpy(), 0.0, 1.0)
            x = model.to_physical(v64)[0]
            # d x / d v of the model's one transform: a unit-box sd in physical units
            dxdv = model.unit_space.from_unit_jacobian(v64)[0]
            col = base.dim
            for e in model.effects:
                for par in e.parameters:
                    sd_u = float(np.sqrt(max(cov[0, col, col], 0.0))) if finite else float("nan")
                    entry["parameters"][par.name] = {
                        "value": float(x[col]),
                        "sd": sd_u * float(dxdv[col]),
                        "unit": par.unit,
                    }
                    col += 1
        rows.append(entry)
    rows.sort(key=lambda r: r["criterion"])
    return rows


def effect_signatures(
    per_spec, candidates: list[Term], pred0: torch.Tensor, n: int
) -> list[dict[str, np.ndarray]]:
    """What each single effect adds to the disc-alone fit, per specimen (4, m), by the
    candidate's written term.

    Parameters
    ----------
    per_spec : list of dict, length n
        Per specimen, every fitted model -> (fit, row in the fit).
    candidates : list of Term
        The candidate effects; those never fitted alone for a specimen are left out.
    pred0 : Tensor, shape (n, 4, m)
        The disc-alone fit's curves in degrees.
    n : int
        Number of specimens.

    Returns
    -------
    list of dict of str to ndarray, length n
        Per specimen, the effect's written term -> curves minus ``pred0`` (4, m) in degrees.
    """
    out = []
    for i in range(n):
        sig = {}
        for name in candidates:
            if Model.of(name) in per_spec[i]:
                f, pos = per_spec[i][Model.of(name)]
                sig[str(name)] = (f.pred[pos] - pred0[i]).double().numpy()
        out.append(sig)
    return out


def missing_text(
    dense: np.ndarray,
    mean: np.ndarray,
    sd: np.ndarray,
    sigma_deg: float,
    residuals: np.ndarray,
    sigma: np.ndarray,
    probabilities: dict[str, Any],
) -> list[str]:
    """What is missing, in words (:func:`~femcal.diagnose.discrepancy.describe`). Where
    something outside the library is the more probable explanation (``probabilities``,
    :func:`~femcal.diagnose.probabilities.specimen_probabilities`) but no deviation stands out
    at two sd, the description says so at one sd and, failing that, names the load case of the
    largest residuals (``residuals`` and ``sigma`` (4, m); ``sigma_deg`` the noise that sizes
    a deviation in words): the report never says "nothing
    missing" beside an ``unexplained`` verdict."""
    text = describe(dense, mean, sd, sigma_deg)
    if text or not probabilities["unexplained"]:
        return text
    text = [f"{t} (at one sd)" for t in describe(dense, mean, sd, sigma_deg, z=1.0)]
    if text:
        return text
    z = residuals / sigma
    rms = np.sqrt(np.nanmean(z**2, axis=1))
    j = int(np.nanargmax(rms))
    return [
        f"{LOAD_CASES[j]}: residuals of {rms[j]:.1f} sigma (RMS) with no smooth trend the "
        "discrepancy resolves (scatter beyond the noise, or a small misfit spread over the "
        "moments)"
    ]


def summary_text(
    text: list[str],
    resembles: str | None,
    sim: dict[str, float],
    adequacy: dict[str, Any] | None = None,
    probabilities: dict[str, Any] | None = None,
) -> str:
    """One specimen's discrepancy in one sentence: where it is, what it resembles.

    Parameters
    ----------
    text : list of str
        ``"<load case>: <description>"`` per load case with a discrepancy beyond the noise.
    resembles : str or None
        The registered effect whose signature the discrepancy resembles, if any.
    sim : dict of str to float
        Similarity (cosine, -1..1) of the discrepancy with each effect's signature.
    adequacy : dict, optional
        The adequacy tests (:func:`adequacy_tests`); its ``p_chi2`` is quoted.
    probabilities : dict, optional
        The specimen's probabilities; with ``unexplained`` set, the probability that
        something outside the library is missing is quoted.

    Returns
    -------
    str
        The sentence.
    """
    sure = ""
    if probabilities is not None and probabilities["unexplained"]:
        sure = (
            " Something outside the library is missing with probability "
            f"{probabilities['outside_library']:.2f}"
            + (f" (chi-square test p = {adequacy['p_chi2']:.2g})." if adequacy else ".")
        )
    if not text:
        return "nothing missing beyond the noise" + sure
    lcs = [t.split(":")[0] for t in text]
    what = "; ".join(text)
    if resembles:
        tail = f"resembles the signature of {resembles} (similarity {sim[resembles]:.2f})"
    elif sim:
        best = max(sim, key=sim.get)
        tail = (
            f"resembles no registered effect (closest: {best}, similarity {sim[best]:.2f}): "
            "a candidate for a new effect"
        )
    else:
        tail = "no registered effect to compare with"
    return f"missing in {', '.join(lcs)}: {what}. It {tail}.{sure}"


def own_range(dense: np.ndarray, moments: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Bool (4, q): the dense moments within each load case's own measured range."""
    out = np.zeros((len(LOAD_CASES), len(dense)), dtype=bool)
    for j in range(len(LOAD_CASES)):
        got = moments[mask[j]]
        if got.size:
            out[j] = (dense >= got.min() * (1 - 1e-9)) & (dense <= got.max() * (1 + 1e-9))
    return out


def dense_base_model(base, dense: np.ndarray):
    """The base model's surrogate evaluated on the dense moment grid ``dense`` (q,) in Nm.

    Parameters
    ----------
    base : CurveModel
        The base (disc) model; only a surrogate model has a dense counterpart.
    dense : ndarray, shape (q,)
        Moments in Nm.

    Returns
    -------
    SurrogateCurveModel or None
        Curves (.., 4, q) at ``dense``; None when ``base`` has no surrogate.
    """
    surrogate = getattr(base, "surrogate", None)
    if surrogate is None:
        return None
    return SurrogateCurveModel(surrogate, dense, space=base.space)


def dense_curves(dense_base, effects: Model, v: torch.Tensor) -> np.ndarray:
    """The curves of model ``effects`` on the dense grid at parameters ``v``.

    Parameters
    ----------
    dense_base : SurrogateCurveModel or None
        The dense base model (:func:`dense_base_model`).
    effects : Model
        The effects added to the base (none: the base alone).
    v : Tensor, shape (r, dim)
        Parameters in unit coordinates.

    Returns
    -------
    ndarray, shape (r, 4, q)
        RoM in degrees, float64; all NaN with shape (r, 4, 1) when ``dense_base`` is None.
    """
    if dense_base is None:
        return np.full((v.shape[0], len(LOAD_CASES), 1), np.nan)
    model = dense_base if not effects else EffectModel(dense_base, list(effects))
    with torch.no_grad():
        return model.curves(v).double().numpy()


def _dense_prediction(dense_base, effects: Model, fit, pos: int, sd: bool = True):
    """One fitted model's curves (4, q) on the dense grid and their linearised sd (4, q).

    The sd propagates the fit's parameter covariance (``fit.cov``, unit box prior) through
    the exact Jacobian of the dense curves; zero (shape (4, 1)) without a covariance or with
    ``sd=False`` (the curves alone, no Jacobian).
    """
    model = dense_base if not effects else EffectModel(dense_base, list(effects))
    v = fit.v[pos : pos + 1]
    if fit.cov is None or not sd:
        with torch.no_grad():
            return model.curves(v).double().numpy()[0], np.zeros((len(LOAD_CASES), 1))
    curves, jac = model.curves_jacobian(v)
    j = jac.detach().double().numpy()[0]  # (4, q, d)
    var = np.einsum("lqd,de,lqe->lq", j, fit.cov[pos], j)
    return curves.detach().double().numpy()[0], np.sqrt(np.clip(var, 0.0, None))


def _repeats_grid(
    needed: float, difference_deg: np.ndarray, noise_deg: np.ndarray, shared_var: np.ndarray
) -> np.ndarray:
    """Measurements repeated at a point that move two models' criteria ``needed`` apart on
    average; ``inf`` where no number of them does (arrays broadcast together).

    The diagnosis scores the mean of ``k`` repeats as one point of variance ``noise^2 / k +
    surrogate^2`` (the surrogate's error there does not average out), and both models refit,
    each prediction moving by up to its own prediction sd: ``k`` repeats part the criteria by
    ``difference^2 / (noise^2 / k + shared)``, ``shared`` the surrogate's and both models'
    prediction variance, so ``k = noise^2 / (difference^2 / needed - shared)``, rounded up,
    where that is positive. With nothing shared this is ``needed / d^2`` for a point ``d``
    noise sd apart.
    """
    room = np.asarray(difference_deg, dtype=float) ** 2 / needed - shared_var
    noise2 = np.broadcast_to(np.asarray(noise_deg, dtype=float) ** 2, room.shape)
    k = np.full(room.shape, np.inf)
    ok = np.isfinite(room) & (room > 1e-12 * noise2)
    # (1 - 1e-9): a whole number plus float noise is not one more
    k[ok] = np.maximum(1.0, np.ceil(noise2[ok] / room[ok] * (1 - 1e-9)))
    return k


def next_measurement(
    ranking,
    fits,
    dense_base,
    dense,
    sigma_dense,
    min_delta,
    chosen,
    measured_moments=None,
    noise_deg=None,
):
    """Where to measure to tell the chosen model from a close rival (criterion within
    ``min_delta``), and how many times.

    ``dense`` (shape (q,)) are the moments searched and ``sigma_dense`` (shape (q,)) the sigma
    of one measurement there (``noise_deg``, the measurement noise, and the surrogate's error;
    all noise when ``noise_deg`` is None), to which both models' own prediction sd is added in
    quadrature (``prediction_sd_deg``; their parameter covariance through the Jacobian);
    ``measured_moments`` (one array per load case) mark whether the point found lies within
    the specimen's own measured range of that load case (``within_measured_range``); where it
    does not, ``within_protocol`` holds the best point within that range too.

    The point named is the one where the fewest measurements repeated there settle the
    question (``repeats_to_settle``, :func:`_repeats_grid`: they move the two criteria
    ``min_delta + gap`` apart on average, leaving the two ``min_delta`` apart whichever is
    right; the surrogate's error and the models' own uncertainty there do not average out),
    else, where no number does (``None``), where the two differ most in sigma
    (``difference_sigma``, one measurement). Of the rivals within ``min_delta``, the one that
    the fewest measurements settle is named: the closest rival in criterion is often the
    chosen model with a further effect fitted to nothing, which predicts the same curves
    everywhere.
    """
    if len(ranking) < 2 or dense_base is None:
        return None
    best = next(r for r in ranking if r["effect"] == model_label(chosen))
    rivals = [
        r for r in ranking if r is not best and abs(r["criterion"] - best["criterion"]) < min_delta
    ]
    if not rivals:
        return None

    noise = sigma_dense if noise_deg is None else np.minimum(float(noise_deg), sigma_dense)
    surrogate_var = sigma_dense**2 - noise**2  # (q,): shared by repeats at one moment
    best_curve, pick = _closest_rival(
        best, rivals, fits, dense_base, sigma_dense, (noise, surrogate_var), min_delta
    )
    if pick is None:
        return None
    return _measurement_report(best, best_curve, pick, dense, sigma_dense, measured_moments)


def _closest_rival(
    best: dict[str, Any],
    rivals: list[dict[str, Any]],
    fits,
    dense_base,
    sigma_dense: np.ndarray,
    noise_parts: tuple[np.ndarray, np.ndarray],
    min_delta: float,
) -> tuple[np.ndarray, tuple | None]:
    """The rival of :func:`next_measurement` that the fewest measurements settle against the
    chosen model ``best`` (ties: the larger difference in sigma, then the smaller criterion
    gap).

    ``noise_parts`` holds the measurement noise (q,) in degrees and the surrogate's error
    variance (q,) in deg². Returns the chosen model's curves on the dense grid (4, q) and
    ``(key, rival, its curves (4, q), the two models' prediction variance (4, q), repeats to
    settle (4, q))``, or None where no rival has a finite difference.
    """
    noise, surrogate_var = noise_parts
    models = {model_label(m): m for m in fits}  # a ranking's entry names its model

    def prediction(r: dict[str, Any], sd: bool = True) -> tuple[np.ndarray, np.ndarray]:
        model = models[r["effect"]]
        f, pos = fits[model]
        return _dense_prediction(dense_base, model, f, pos, sd)

    def repeats(r: dict[str, Any], delta: np.ndarray, var: np.ndarray) -> np.ndarray:
        """(4, q) measurements to settle ``r`` against the chosen model at each point. What
        repeats share: the surrogate's error there, and the two models' own prediction
        variance ``var``: a model whose prediction there the data do not pin refits to the
        new points at a cost of ``delta^2 / var`` elsewhere, so the criteria part by at most
        ``delta^2 / (noise^2 / k + surrogate^2 + var)`` (planted P005: five measurements at
        the point of a rival with a 0.22 deg prediction sd left the rival closer than
        before)."""
        g = abs(r["criterion"] - best["criterion"])
        return _repeats_grid(min_delta + g, delta, noise[None, :], surrogate_var[None, :] + var)

    def key(r: dict[str, Any], k: np.ndarray, d: np.ndarray) -> tuple[float, float, float]:
        """(measurements to settle, minus the largest difference in sigma, criterion gap):
        the rival with the smallest is named (where none settles, the most different)."""
        gap = abs(r["criterion"] - best["criterion"])
        return (float(np.nanmin(k)), -float(np.nanmax(np.abs(d))), gap)

    best_curve, best_sd = prediction(best)
    # The models' own prediction sd only adds repeats and lowers the difference in sigma, so
    # the curves alone bound each rival's key from below: the rivals are tried in that order,
    # and the Jacobians (the sd) computed only while a rival could still beat the best found
    # (the same rival as trying them all).
    bounds = []
    for r in rivals:
        c, _ = prediction(r, sd=False)
        delta = best_curve - c
        d_upper = delta / sigma_dense[None, :]
        bounds.append((key(r, repeats(r, delta, np.zeros_like(c)), d_upper), r))
    pick = None  # (key, rival, its curves, variance, repeats)
    for bound, r in sorted(bounds, key=lambda b: b[0]):
        if pick is not None and bound >= pick[0]:
            break
        c, sd = prediction(r)
        v = np.broadcast_to(best_sd**2 + sd**2, c.shape)  # sd (4, 1) without a covariance
        delta = best_curve - c
        if not np.isfinite(delta).any():
            continue
        k_grid = repeats(r, delta, v)
        k = key(r, k_grid, delta / np.sqrt(sigma_dense[None, :] ** 2 + v))
        if pick is None or k < pick[0]:
            pick = (k, r, c, v, k_grid)
    return best_curve, pick


def _measurement_report(
    best: dict[str, Any],
    best_curve: np.ndarray,
    pick: tuple,
    dense: np.ndarray,
    sigma_dense: np.ndarray,
    measured_moments,
) -> dict[str, Any]:
    """The point of :func:`next_measurement` for the rival ``pick`` of :func:`_closest_rival`
    (the chosen model's curves ``best_curve`` (4, q) on the moments ``dense`` (q,), Nm): where
    the fewest repeats settle the two, else where they differ most in sigma; with
    ``measured_moments``, whether it lies within the specimen's measured range and, where it
    does not, the best point within it (``within_protocol``)."""
    (_, _, gap), second, rival_curve, var, k_grid = pick
    curves = [best_curve, rival_curve]
    # The two models' own uncertainty counts too: where a rival's parameters are not pinned
    # by the data (a ligament slack beyond the protocol), its prediction there is not either.
    total = np.sqrt(sigma_dense[None, :] ** 2 + var)
    diff = (curves[0] - curves[1]) / total

    def point(d: np.ndarray, k_at: np.ndarray) -> tuple[tuple[int, int], dict[str, Any]]:
        # the fewest repeats (ties: the larger difference), else the largest difference
        if np.isfinite(k_at).any():
            order = np.lexsort((-np.nan_to_num(np.abs(d)).ravel(), k_at.ravel()))
            j, k = np.unravel_index(order[0], d.shape)
        else:
            j, k = np.unravel_index(np.nanargmax(np.abs(d)), d.shape)
        n_rep = k_at[j, k]
        return (int(j), int(k)), {
            "load_case": LOAD_CASES[j],
            "moment_nm": float(dense[k]),
            "difference_deg": float(curves[0][j, k] - curves[1][j, k]),
            "difference_sigma": float(abs(d[j, k])),
            "sigma_deg": float(total[j, k]),
            "prediction_sd_deg": float(np.sqrt(var[j, k])),
            "repeats_to_settle": int(n_rep) if np.isfinite(n_rep) else None,
        }

    where, found = point(diff, k_grid)
    out = {"between": [best["effect"], second["effect"]], "criterion_gap": float(gap), **found}
    if measured_moments is not None:
        own = np.zeros(diff.shape, dtype=bool)
        for j, got in enumerate(measured_moments):
            got = np.asarray(got, dtype=float)
            if got.size:
                own[j] = (dense >= got.min() * (1 - 1e-9)) & (dense <= got.max() * (1 + 1e-9))
        out["within_measured_range"] = bool(own[where])
        inside = np.where(own, diff, np.nan)
        if not own[where] and np.isfinite(inside).any():
            out["within_protocol"] = point(inside, np.where(own, k_grid, np.inf))[1]
    return out


def failures(
    resid: np.ndarray, sigma: np.ndarray, moments: np.ndarray, x_unit: np.ndarray, names
) -> dict[str, Any]:
    """Where the disc alone fails: points beyond 2 sigma, sign runs, parameters on bounds.

    Parameters
    ----------
    resid, sigma : ndarray, shape (4, m)
        Residuals (NaN where not measured) and noise sd, in degrees.
    moments : ndarray, shape (m,)
        Moments in Nm.
    x_unit : ndarray, shape (d,)
        The disc's parameters in unit coordinates.
    names : sequence of str, length d
        The parameters' names.

    Returns
    -------
    dict
        ``beyond_2_sigma`` (per load case: moments and largest ``|z|``), ``sign_pattern``
        (load case -> ``"+-..."``) and ``on_bounds`` (names within ``AT_BOUND`` of a bound).
    """
    z = resid / sigma
    out: dict[str, Any] = {"beyond_2_sigma": [], "sign_pattern": {}, "on_bounds": []}
    for j, lc in enumerate(LOAD_CASES):
        ok = np.isfinite(z[j])
        if not ok.any():
            continue
        bad = ok & (np.abs(z[j]) > 2)
        if bad.any():
            out["beyond_2_sigma"].append(
                {
                    "load_case": lc,
                    "moments_nm": moments[bad].tolist(),
                    "max_abs_z": float(np.max(np.abs(z[j][ok]))),
                }
            )
        out["sign_pattern"][lc] = "".join("+" if v > 0 else "-" for v in resid[j][ok])
    out["on_bounds"] = [n for n, u in zip(names, x_unit) if u < AT_BOUND or u > 1 - AT_BOUND]
    return out
