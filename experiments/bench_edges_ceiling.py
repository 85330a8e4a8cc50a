"""The ceiling of the edge cohorts' selection bars: every candidate model fitted thoroughly,
then the diagnosis' criterion picks (issue 55).

For each specimen of a ``bench_edges`` run of class facets, ligaments, neutral zone, facets +
ligaments or facets + neutral zone that is visible (or shows a structure beyond the old
load-case assignment), every model of at most two effects is fitted in every form: each
effect tied or split per load case, facets and ligaments in their likely load cases or in
every load case their prior allows (``facet_contact@Extension,LateralBending,AxialRotation``;
the generator's facets act in extension and axial rotation, its ligaments in flexion and
lateral bending, each with or without the one further load case). The fits are the
diagnosis' own (forward selection: Gauss-Newton from the start grid, the start bank and
combination rounds) with a wider search (:class:`Budget`; every model of a level extended),
then every form the search did not reach fitted from its tied form and its members' fits.
Each model is scored as the diagnosis scores it: ``chi^2 + k ln n`` (``k`` the effective
number of parameters, the stated noise 0.05 deg and the surrogate's error) plus its prior
cost (:func:`prior_cost`), the lower of this fit's and the diagnosis' own (every model of the
diagnosis' ranking counts, its three-effect models too).

* **ORACLE-FIT**: the true effect set's best score is lower than every other effect set's:
  the most any search with this criterion gets right. The oracle's pick (the lowest score)
  scores the bench's rows: combinations and single effects strict, the right effect named
  beyond the old assignment. Variants: a form beyond its likely load cases only where it
  engages there (:func:`femcal.diagnose.where.engaged`, as the diagnosis counts it); the
  truth within :data:`TIE` of the best; every model scored with the true noise RMS.
* **within the noise**: the truth's best fit has ``chi^2`` (with the true noise RMS and the
  surrogate's error) that a chi-square with ``n - k`` degrees of freedom accepts at
  :data:`ALPHA`; where it does not, the library's laws cannot represent the generator's.

Writes ``bench_edges_ceiling.json``, ``specimens.csv`` and ``bench_edges_ceiling.md`` to
``--out``; ``--bench`` is a ``bench_edges`` run of the same seeds (its diagnoses' rankings
count). The fits use the diagnosis' internals as of commit 9731e30 (models as tuples of term
strings), the library of the ``dev-item4`` diagnoses, so the run imports that snapshot. Dev
seeds only, one process (the default budget: 40 specimens of seeds 101 and 102 in 10.7
CPU-min, 27 min wall beside other jobs on 2 cores; ``--bank-starts 8 --shape-starts 8
--rounds 2 --max-iter 40``: 7.6 CPU-min, 16 min wall)::

    git archive 9731e30 src/femcal | tar -x -C /tmp/snap
    PYTHONPATH=/tmp/snap/src:. FEMCAL_DATA_MIRROR=/work/shared/data/ivd-calibnn \\
        OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python -m experiments.bench_edges_ceiling \\
        --bench experiments/results/bench_edges/dev-item4 --seeds 101,102 \\
        --out experiments/results/bench_edges_ceiling
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from scipy import stats

from experiments.common import REPO, reproduce_command, screened_cohort

#: The cohorts issue 55's closing figures were measured on: never fitted here.
FRESH_SEEDS = (
    *(285572, 847237, 310379, 406164, 636007, 866352),
    *(126342, 395602, 154743, 749727, 973235, 901506),
    *(631497, 121571, 898715, 316067, 263252, 524140),
)
CLASSES = ("facets", "ligaments", "neutral_zone", "facets+ligaments", "facets+neutral_zone")
SINGLE, COMBOS = CLASSES[:3], CLASSES[3:]
EFFECT_OF = {"facets": "facet_contact", "ligaments": "ligament_tension", "laxity": "neutral_zone"}
#: The diagnosis' prior costs: the first effect, each further effect or split form.
FIRST, FURTHER = 10.0, 2.0
#: Level of the chi-square test of the truth's fit.
ALPHA = 0.01
#: Criterion differences within this are ties: what one further effect's prior cost moves.
TIE = 2.0
#: The diagnosis' stated noise (sd, deg).
NOISE_DEG = 0.05


@dataclass(frozen=True)
class Budget:
    """How thoroughly each model is fitted (:class:`femcal.diagnose.DiagnoseOptions` fields)."""

    bank_starts: int = 16
    shape_starts: int = 16
    combination_rounds: int = 3
    max_iter: int = 50


# ------------------------------------------------------------------------------- the forms
def effect_forms(effect: str) -> list[str]:
    """The terms of one effect: tied and split, in its likely load cases and (where its prior
    allows more) in every load case it allows."""
    from femcal.effects.base import get_effect
    from femcal.effects.terms import as_split, with_cases

    prior = get_effect(effect).load_case_prior
    wide = with_cases(effect, [lc for lc, p in prior.items() if p > 0.0])
    tied = [effect, *([wide] if wide != effect else [])]
    return [*tied, *(as_split(t) for t in tied)]


def all_forms(effects: Sequence[str]) -> list[tuple[str, ...]]:
    """Every model of at most two of ``effects`` in every form (:func:`effect_forms`), the
    disc alone first; each a sorted tuple of terms."""
    forms: list[tuple[str, ...]] = [()]
    for k in (1, 2):
        for combo in itertools.combinations(sorted(effects), k):
            forms += [tuple(sorted(p)) for p in itertools.product(*map(effect_forms, combo))]
    return forms


def effect_set(model: Sequence[str]) -> str:
    """The effects a model holds, sorted and joined by ``+`` (``""``: the disc alone)."""
    from femcal.effects.terms import parse_term

    return "+".join(sorted({parse_term(t).effect for t in model}))


# ------------------------------------------------------------------------------- the fits
def build_state(cohort: Path, specimens: list[str], budget: Budget):
    """The diagnosis' state for ``specimens`` of a cohort, prepared as ``femcal diagnose``
    prepares it (moment screening, the surrogate's error per point, the stated noise), with
    the search's options widened (``budget``; every model of a level extended, the first
    effect needing no gain so that every specimen reaches two effects)."""

    from femcal.calibration import SurrogateCurveModel
    from femcal.datasets import training_configurations
    from femcal.diagnose import DiagnoseOptions
    from femcal.diagnose.fits import point_weights
    from femcal.diagnose.search import _point_weight
    from femcal.diagnose.state import DiagnosisState
    from femcal.effects import available_effects

    params, sur_model, policy, meas = screened_cohort(
        cohort / "measurements.csv", noise_deg=NOISE_DEG
    )
    idx = [meas.specimens.index(s) for s in specimens]
    sur = np.broadcast_to(policy.sigma_surrogate(meas.moments, meas.rom_deg), meas.rom_deg.shape)
    measured = np.asarray(meas.rom_deg, dtype=float)[idx]
    w = _point_weight(None if meas.weight is None else meas.weight[idx], measured)
    measured = np.where(w > 0, measured, np.nan)
    w = np.where(w > 0, w, 1.0)
    options = DiagnoseOptions(
        min_delta=0.0,
        backward_delta=0.0,
        beam_delta=1e9,
        max_effects=2,
        workers=1,
        **vars(budget),
    )
    sigma = np.sqrt(NOISE_DEG**2 / w + sur[idx] ** 2)
    state = DiagnosisState(
        base=SurrogateCurveModel(sur_model, meas.moments),
        specimens=list(specimens),
        measured=measured,
        weight=np.ascontiguousarray(point_weights(sigma, measured.shape)),
        sigma=sigma,
        sigma_m=np.full(measured.shape[2], NOISE_DEG),
        surrogate_sd=np.ascontiguousarray(sur[idx]),
        options=options,
        candidates=list(available_effects()),
        start_bank=training_configurations(REPO / params["calibrate"]["start_bank"]),
        rng=np.random.default_rng(options.seed),
    )
    return state, w


def search(state) -> None:
    """The disc alone, then forward selection with the widened options (every form it
    reaches recorded in ``state.per_spec``)."""
    from femcal.diagnose.fits import Fit, chi_square
    from femcal.diagnose.forward import forward_selection
    from femcal.diagnose.search import disc_fit

    v, pred = disc_fit(state, state.weight)
    rows = np.arange(state.n)
    chi2 = chi_square(pred, state.measured, state.sigma)
    state.per_spec = [{} for _ in range(state.n)]
    state.record(Fit((), state.base, v, rows, pred, chi2, state.base.dim))
    state.chosen = [() for _ in range(state.n)]
    forward_selection(state)


def _starts(state, form: tuple[str, ...], rows: list[int]) -> torch.Tensor:
    """Starts (r, g, dim) of ``form`` for specimens ``rows``: from its all-tied form's fit
    (split terms' per-load-case copies at the grid levels), from its members' own fits side by
    side (the disc of the better one), and, for a term new to the better member, its grid and
    the start bank."""
    from femcal.diagnose.fits import split_starts
    from femcal.diagnose.forward import _members_start, _new_effect_starts
    from femcal.effects.split import is_split
    from femcal.effects.terms import parse_term

    parts = []
    tied = tuple(sorted(str(replace(parse_term(t), split=False)) for t in form))
    if any(is_split(t) for t in form) and all(tied in state.per_spec[i] for i in rows):
        v0, g = split_starts(state.solutions(rows, tied), tied, form, state.options.effect_levels)
        parts.append(v0.reshape(len(rows), g, -1))
    singles = [(t,) for t in form]
    if len(form) > 1 and all(s in state.per_spec[i] for s in singles for i in rows):
        parts.append(_members_start(state, rows, form))
        for parent in singles:
            new = next(t for t in form if (t,) != parent)
            parts.append(_new_effect_starts(state, np.asarray(rows), parent, new, {}))
    if len(form) == 1 and not parts:
        parts.append(_new_effect_starts(state, np.asarray(rows), (), form[0], {}))
    return torch.cat(parts, dim=1)


def fill_forms(state, forms: list[tuple[str, ...]]) -> None:
    """Fit every form of ``forms`` the search did not reach (singles first, then pairs), each
    pair then given the combination rounds."""
    from femcal.diagnose.forward import _refine_combination

    for form in sorted(forms, key=len):
        rows = [i for i in range(state.n) if form not in state.per_spec[i]]
        if not rows or not form:
            continue
        v0 = _starts(state, form, rows)
        g = v0.shape[1]
        fit = state.fit(form, np.asarray(rows), v0.reshape(len(rows) * g, -1), g)
        if len(form) > 1:
            _refine_combination(state, fit)


# ----------------------------------------------------------------------------- the scores
def prior_cost(label: str) -> float:
    """The diagnosis' prior cost of the model ``label`` (terms joined by ``+``, ``none``):
    :data:`FIRST` for the first effect, :data:`FURTHER` for each further effect and each split
    form, and what its terms' load cases cost against their likely ones (as
    :func:`femcal.diagnose.probabilities.model_prior_cost` prices them)."""
    from femcal.effects.terms import case_prior_cost, parse_term

    terms = [] if label == "none" else label.split("+")
    if not terms:
        return 0.0
    n_split = sum(parse_term(t).split for t in terms)
    cases = sum(case_prior_cost(t) for t in terms)
    return FIRST + FURTHER * (len(terms) - 1 + n_split) + cases


def form_scores(state, own: list[dict[str, float]]) -> tuple[list[dict], list[dict]]:
    """Per specimen, each model's score: the lower of this fit's criterion and the
    diagnosis' own (``own``: per specimen, model label -> criterion) plus its prior cost
    (:func:`prior_cost`). Returned twice: as the criterion alone scores them, and with a form
    acting beyond its likely load cases left out (inf) where it does not engage there, as the
    diagnosis leaves it out (:func:`femcal.diagnose.where.engaged`)."""
    from femcal.diagnose.result import model_label
    from femcal.diagnose.where import engaged

    scores: list[dict[str, float]] = [{} for _ in range(state.n)]
    idle: list[set[str]] = [set() for _ in range(state.n)]
    forms = sorted({f for spec in state.per_spec for f in spec})
    for form in forms:
        rows = [i for i in range(state.n) if form in state.per_spec[i]]
        label = model_label(tuple(sorted(form)))
        for i, fine in zip(rows, engaged(state, form, rows)):
            scores[i][label] = state.criterion(form, i)
            if not fine:
                idle[i].add(label)
    for i, theirs in enumerate(own):
        for label, crit in theirs.items():
            scores[i][label] = min(scores[i].get(label, np.inf), float(crit))
    scores = [{k: v + prior_cost(k) for k, v in spec.items()} for spec in scores]
    engaged_only = [{k: v for k, v in s.items() if k not in no} for s, no in zip(scores, idle)]
    return scores, engaged_only


def true_noise_scores(state, sigma_true: np.ndarray) -> list[dict[str, float]]:
    """Per specimen, each model this run fitted scored with the true noise instead of the
    stated one: ``chi^2`` and the effective number of parameters with ``sigma_true``
    (n, 4, m), plus the prior cost (the diagnosis' own fits, scored with the stated noise,
    left out)."""
    from femcal.calibration.base import hat_trace_and_cov
    from femcal.diagnose.result import model_label

    scores: list[dict[str, float]] = [{} for _ in range(state.n)]
    fits = {id(f): f for spec in state.per_spec for f, _ in spec.values()}
    for fit in fits.values():
        rows = np.asarray(fit.rows)
        if fit.effects:
            _, jac = fit.model.curves_jacobian(fit.v)
            trace = hat_trace_and_cov(jac, state.mask[rows], sigma_true[rows])[0]
        else:
            trace = np.full(len(rows), float(state.base.dim))
        z = np.where(state.mask[rows], state.measured[rows] - fit.pred.double().numpy(), 0.0)
        chi2 = ((z / sigma_true[rows]) ** 2).sum(axis=(1, 2))
        label = model_label(tuple(sorted(fit.effects)))
        for pos, i in enumerate(rows):
            if state.per_spec[i].get(fit.effects, (None,))[0] is not fit:
                continue  # a later fit of the same model replaced this one
            crit = chi2[pos] + trace[pos] * state.log_n[i] + prior_cost(label)
            scores[i][label] = float(crit) if np.isfinite(crit) else np.inf
    return scores


def truth_fit(state, i: int, truth: set[str], noise_rms: float, w: np.ndarray) -> dict:
    """The truth's best fit of this run (the lowest chi-square with the true noise) for
    specimen ``i``: its form, ``chi^2`` with the stated and with the true noise, ``n``, ``k``
    and the chi-square test's p-value at ``n - k`` degrees of freedom."""
    mask = state.mask[i]
    sigma_true = np.sqrt(noise_rms**2 / w[i] + state.surrogate_sd[i] ** 2)
    best: dict[str, Any] = {}
    for form, (fit, pos) in state.per_spec[i].items():
        if effect_set(form).split("+") != sorted(truth):
            continue
        fit.ensure_trace(state.mask, state.sigma)
        r = np.where(mask, state.measured[i] - fit.pred[pos].double().numpy(), 0.0)
        chi2_true = float(((r / sigma_true) ** 2).sum())
        if best and chi2_true >= best["chi2_true"]:
            continue
        n, k = int(mask.sum()), float(fit.trace[pos])
        dof = max(n - k, 1.0)
        best = {
            "form": "+".join(form),
            "chi2_stated": float(fit.chi2[pos]),
            "chi2_true": chi2_true,
            "n_points": n,
            "k": k,
            "chi2_true_per_dof": chi2_true / dof,
            "p_true": float(stats.chi2.sf(chi2_true, dof)),
        }
    return best


def judge(scores: dict[str, float], truth: str) -> dict[str, Any]:
    """The effect sets' best scores for one specimen: the oracle's pick, whether the truth's
    set beats every other, the margin (best other minus the truth's) and the best form of
    each."""
    best: dict[str, tuple[float, str]] = {}
    for label, s in scores.items():
        key = effect_set(() if label == "none" else label.split("+"))
        if key not in best or s < best[key][0]:
            best[key] = (s, label)
    pick = min(best, key=lambda k: best[k][0])
    t = best.get(truth, (np.inf, ""))[0]
    other = min((v[0] for k, v in best.items() if k != truth), default=np.inf)
    return {
        "oracle_pick": pick,
        "oracle_right": bool(t < other),
        "margin": float(other - t),
        "truth_form": best.get(truth, (np.inf, ""))[1],
        "truth_score": float(t),
        "best_other": min((k for k in best if k != truth), key=lambda k: best[k][0]),
        "best_other_score": float(other),
    }


# ------------------------------------------------------------------------------- a cohort
def one_cohort(bench: Path, seed: int, budget: Budget, max_specimens: int | None) -> dict:
    """Fit every form to the specimens of one cohort of the five classes that are visible or
    show a structure beyond the old assignment (the first ``max_specimens``); score, judge."""
    t0, c0 = time.perf_counter(), time.process_time()
    root = bench / f"seed-{seed}"
    table = pd.read_csv(bench / "specimens.csv")  # the five classes, visible or beyond
    table = table[(table["seed"] == seed) & table["truth"].isin(CLASSES)]
    table = table[table["visible"] | table["facets_lb_visible"] | table["ligaments_ext_visible"]]
    table = table.head(max_specimens) if max_specimens else table
    names = [str(s) for s in table["specimen"]]
    truth = {r["specimen"]: r for r in json.loads((root / "cohort/truth.json").read_text())}
    diag = {r["specimen"]: r for r in json.loads((root / "diagnosis/diagnosis.json").read_text())}
    state, w = build_state(root / "cohort", names, budget)
    search(state)
    fill_forms(state, all_forms(state.candidates))
    own = [{x["effect"]: x["criterion"] for x in diag[s]["ranking"]} for s in names]
    scores, engaged_only = form_scores(state, own)
    rms = np.array([float(truth[s]["noise"]["rms_deg"]) for s in names])
    sigma_true = np.sqrt(rms[:, None, None] ** 2 / w + state.surrogate_sd**2)
    true_noise = true_noise_scores(state, sigma_true)
    rows = []
    for i, (_, r) in enumerate(table.iterrows()):
        tr = truth[names[i]]
        expected = {EFFECT_OF[s] for s in tr["structures"]}
        verdict = str(diag[names[i]]["verdict"])
        fit = truth_fit(state, i, expected, float(tr["noise"]["rms_deg"]), w)
        rows.append(
            {
                "seed": seed,
                "specimen": names[i],
                "truth": r["truth"],
                "expected": "+".join(sorted(expected)),
                "acts_in": json.dumps(tr["acts_in"]),
                "protocol": r["protocol"],
                "noise_kind": r["noise_kind"],
                "noise_rms_deg": float(tr["noise"]["rms_deg"]),
                "visible": bool(r["visible"]),
                "facets_lb_visible": bool(r["facets_lb_visible"]),
                "ligaments_ext_visible": bool(r["ligaments_ext_visible"]),
                "verdict": verdict,
                "strict": bool(r["strict"]),
                "facet_named": bool(r["facet_named"]),
                "ligament_named": bool(r["ligament_named"]),
                "verdict_score": scores[i].get("+".join(diag[names[i]]["model"]) or "none"),
                **judge(scores[i], "+".join(sorted(expected))),
                **{
                    f"{k}_engaged": v
                    for k, v in judge(engaged_only[i], "+".join(sorted(expected))).items()
                },
                **{
                    f"{k}_true_noise": v
                    for k, v in judge(true_noise[i], "+".join(sorted(expected))).items()
                },
                **{f"truth_{k}": v for k, v in fit.items()},
            }
        )
        rows[-1]["truth_within_noise"] = bool(fit and fit["p_true"] >= ALPHA)
    return {
        "seed": seed,
        "n": len(names),
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "specimens": rows,
    }


# -------------------------------------------------------------------------------- summary
def _rate(flags: pd.Series) -> dict[str, Any]:
    ok = flags.dropna().astype(bool)
    return {"k": int(ok.sum()), "n": int(ok.size)}


def bar_rows(t: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """The specimens of each bench row the ceiling bounds: combinations (each, both), single
    effects (visible), and structures beyond the old assignment (with the effect that should
    be named in ``beyond_effect``)."""
    vis = t[t["visible"]]
    lb = t[t["facets_lb_visible"]].assign(beyond_effect="facet_contact")
    ext = t[t["ligaments_ext_visible"]].assign(beyond_effect="ligament_tension")
    return {
        "combinations exactly right": vis[vis["truth"].isin(COMBOS)],
        "  facet + ligament": vis[vis["truth"] == COMBOS[0]],
        "  facet + neutral zone": vis[vis["truth"] == COMBOS[1]],
        "single effects strict": vis[vis["truth"].isin(SINGLE)],
        "beyond the old assignment: right effect named": pd.concat([lb, ext]),
    }


def summarize(t: pd.DataFrame) -> dict[str, dict[str, Any]]:
    """Per bench row: the diagnosis' rate, ORACLE-FIT, the oracle's pick right, the truth
    within the noise, and ORACLE-FIT among the specimens whose truth fits within the noise."""
    out = {}
    for name, g in bar_rows(t).items():
        if "beyond_effect" in g:
            named = [e in str(p).split("+") for e, p in zip(g["beyond_effect"], g["oracle_pick"])]
            said = np.where(
                g["beyond_effect"] == "facet_contact", g["facet_named"], g["ligament_named"]
            )
            pick, diagnosis = pd.Series(named, dtype=bool), pd.Series(said, dtype=bool)
        else:
            pick, diagnosis = g["oracle_pick"] == g["expected"], g["strict"]
        fits = g[g["truth_within_noise"]]
        out[name] = {
            "diagnosis": _rate(diagnosis),
            "oracle_fit": _rate(g["oracle_right"]),
            "oracle_fit_engaged": _rate(g["oracle_right_engaged"]),
            "within_tie": _rate(g["margin"] > -TIE),
            "oracle_fit_true_noise": _rate(g.get("oracle_right_true_noise", g["truth"][:0])),
            "oracle_pick": _rate(pick),
            "within_noise": _rate(g["truth_within_noise"]),
            "oracle_fit_within_noise": _rate(fits["oracle_right"]),
            "oracle_fit_misfit": _rate(g[~g["truth_within_noise"]]["oracle_right"]),
        }
    return out


def _cell(r: dict[str, Any]) -> str:
    return f"{r['k']}/{r['n']} ({100 * r['k'] / r['n']:.0f} %)" if r["n"] else "-"


def write(rows: list[dict[str, Any]], meta: dict[str, Any], out: Path) -> None:
    """``bench_edges_ceiling.json``, ``specimens.csv`` and ``bench_edges_ceiling.md``."""
    out.mkdir(parents=True, exist_ok=True)
    t = pd.DataFrame([s for r in rows for s in r["specimens"]])
    summary = summarize(t)
    payload = {**meta, "summary": summary, "cohorts": [{**r, "specimens": None} for r in rows]}
    (out / "bench_edges_ceiling.json").write_text(json.dumps(payload, indent=1) + "\n")
    t.to_csv(out / "specimens.csv", index=False)
    lines = [
        "# The ceiling of the edge cohorts' selection bars",
        "",
        f"Reproduce: `{meta['command']}`. Seeds {', '.join(map(str, meta['seeds']))} "
        f"(dev); {len(t)} specimens; {sum(r['cpu_s'] for r in rows) / 60:.0f} CPU-min, "
        f"{sum(r['wall_s'] for r in rows) / 60:.0f} min wall.",
        "",
        "| bench row | diagnosis | ORACLE-FIT | ORACLE-FIT, further load cases where engaged | "
        f"truth within {TIE:g} of the best | ORACLE-FIT, true noise | oracle's pick right | "
        "truth fits within the noise | ORACLE-FIT where it does | ORACLE-FIT where it does not |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, s in summary.items():
        keys = ("diagnosis", "oracle_fit", "oracle_fit_engaged", "within_tie")
        keys += ("oracle_fit_true_noise", "oracle_pick", "within_noise")
        cells = [s[k] for k in keys]
        cells += [s["oracle_fit_within_noise"], s["oracle_fit_misfit"]]
        lines.append(f"| {name.strip()} | " + " | ".join(map(_cell, cells)) + " |")
    lines += ["", "| class | n | ORACLE-FIT | within the noise | median chi2/dof (true noise) |"]
    lines.append("|---|---|---|---|---|")
    for c, g in t.groupby("truth", sort=False):
        med = float(np.nanmedian(g["truth_chi2_true_per_dof"]))
        lines.append(
            f"| {c} | {len(g)} | {_cell(_rate(g['oracle_right']))} | "
            f"{_cell(_rate(g['truth_within_noise']))} | {med:.2f} |"
        )
    lines += [
        "",
        "| seed | specimen | truth | acts in | verdict | oracle's pick | margin | truth's form | "
        "chi2/dof (true noise) | p |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for _, r in t.iterrows():
        lines.append(
            f"| {r['seed']} | {r['specimen']} | {r['truth']} | {r['acts_in']} | {r['verdict']} | "
            f"{r['oracle_pick'] or 'none'} | {r['margin']:.1f} | {r['truth_form']} | "
            f"{r['truth_chi2_true_per_dof']:.2f} | {r['truth_p_true']:.3g} |"
        )
    (out / "bench_edges_ceiling.md").write_text("\n".join(lines) + "\n")


def rewrite(out: Path, sources: Sequence[Path]) -> None:
    """Write the report of finished runs again from their json and csv (``sources``, default
    ``out``): with several, per specimen the truth counts where any run's fits let it win
    (margins their largest, the oracle's pick from the run where the truth fares best)."""
    tables, cohorts, commands = [], {}, []
    for src in sources or [out]:
        payload = json.loads((src / "bench_edges_ceiling.json").read_text())
        tables.append(pd.read_csv(src / "specimens.csv", keep_default_na=False, na_values=[""]))
        commands.append(payload["command"])
        for c in payload.pop("cohorts"):
            old = cohorts.setdefault(c["seed"], {**c, "cpu_s": 0.0, "wall_s": 0.0})
            old.update(cpu_s=old["cpu_s"] + c["cpu_s"], wall_s=old["wall_s"] + c["wall_s"])
    t = pd.concat(tables).fillna({"oracle_pick": ""}).sort_values("margin", ascending=False)
    agg = {c: "max" if c.startswith(("oracle_right", "margin")) else "first" for c in t}
    t = t.groupby(["seed", "specimen"], as_index=False).agg(
        {k: v for k, v in agg.items() if k not in ("seed", "specimen")}
    )
    rows = [{**c, "specimens": t[t["seed"] == k].to_dict("records")} for k, c in cohorts.items()]
    payload.pop("summary")
    write(rows, {**payload, "command": "` and `".join(commands)}, out)


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--bench", type=Path, required=True, help="a bench_edges results folder")
    ap.add_argument("--seeds", required=True, help="comma-separated dev seeds of that folder")
    ap.add_argument("--out", type=Path, required=True, help="results folder")
    ap.add_argument("--max-specimens", type=int, default=None, help="per cohort (quick runs)")
    ap.add_argument("--bank-starts", type=int, default=Budget.bank_starts)
    ap.add_argument("--shape-starts", type=int, default=Budget.shape_starts)
    ap.add_argument("--rounds", type=int, default=Budget.combination_rounds)
    ap.add_argument("--max-iter", type=int, default=Budget.max_iter)
    ap.add_argument("--rewrite", action="store_true", help="write the report of --out again")
    ap.add_argument("--from", dest="sources", type=Path, action="append", default=[])
    args = ap.parse_args(argv)
    if args.rewrite:
        rewrite(args.out, args.sources)
        return
    seeds = [int(s) for s in args.seeds.split(",") if s]
    fresh = sorted(set(seeds) & set(FRESH_SEEDS))
    if fresh:
        ap.error(f"--seeds {fresh} are issue 55's fresh cohorts, run once: give dev seeds")
    budget = Budget(args.bank_starts, args.shape_starts, args.rounds, args.max_iter)
    torch.set_num_threads(1)
    import femcal

    path = os.environ.get("PYTHONPATH", "")
    meta = {
        "command": (f"PYTHONPATH={path} " if path else "")
        + reproduce_command("bench_edges_ceiling", argv),
        "femcal_imported_from": femcal.__file__,
        "commit": subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True
        ).stdout.strip(),
        "bench": str(args.bench),
        "seeds": seeds,
        "budget": vars(budget),
        "started_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    rows = []
    for seed in seeds:
        rows.append(one_cohort(args.bench, seed, budget, args.max_specimens))
        print(f"seed {seed}: {rows[-1]['n']} specimens, {rows[-1]['cpu_s']:.0f} CPU-s", flush=True)
        write(rows, meta, args.out)  # after every cohort: a long run leaves what it has


if __name__ == "__main__":
    main()
