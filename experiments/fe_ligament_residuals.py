"""Why the FE-made ligament specimens stay above the floor after the diagnosed model.

``python -m femcal.fe.hidden`` calibrates each specimen of the FE-made cohort with its
verdict's terms; the ligament class and the class with both elements end at about twice the
disc-only floor. For the specimens of those classes whose MAE after the found model exceeds
``1.5`` floors, this script measures four candidate causes apart:

``tables``
    the MAE after the found model, split by moment band (0.5-5, 5.5-10 Nm) and load case, read
    from the loop's calibration folders (``found-*/calibration/curves.csv``), beside the disc
    alone's (``disc-alone``);
``fe``
    (a) CalculiX runs of the disc alone at each specimen's true disc parameters
    (``answers.csv``; the cohort's settings without ``posterior``, one worker, its own store),
    and the surrogate's error there, by band and load case;
``oracle``
    (c) the best the library's law families do with the true disc: the element parameters
    alone fitted (disc fixed) to the specimen's noisy curves, in every load case the effect's
    prior allows, two ways: the disc given by the surrogate at the true parameters, and the
    disc given by its own CalculiX curve (``fe``), so that the family's own shortfall is
    measured without the surrogate's error;
``rerun``
    (b, d) the calibration of each specimen again as ``femcal.fe.hidden`` runs it
    (:class:`femcal.jobs.calibrate.CalibrationJob` from ``params.yaml``) with its verdict's
    terms, with other start banks (``--bank``) and other terms (``--terms``).

Every MAE is in degrees against the noisy curves the loop fitted (noise sd 0.05 deg) unless a
column says ``clean``. Writes ``<out>/<command>.json`` and prints its tables.

``report`` prints the table of ``docs/benchmarks/fe.md`` ("Why the ligaments stay above the
floor") from the JSON files in ``--out``. Usage (from the project root; one at a time)::

    export OMP_NUM_THREADS=1
    H=fe/reports/hidden C=fe/data/cohort M=fe/models/surrogate-large S=DIR/runs.jsonl.gz
    python -m experiments.fe_ligament_residuals tables --hidden $H --cohort $C --out OUT
    python -m experiments.fe_ligament_residuals fe --cohort $C --store $S --out OUT  # CalculiX
    python -m experiments.fe_ligament_residuals oracle --hidden $H --cohort $C --model $M \\
        --store $S --out OUT
    python -m experiments.fe_ligament_residuals rerun --hidden $H --cohort $C --model $M \\
        --root . [--terms class] [--bank fe/data/prepared/large.csv] --tag T --out OUT
    python -m experiments.fe_ligament_residuals report --out OUT
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.schema import LOAD_CASES

#: Moment bands of the tables, Nm (inclusive).
BANDS = {"0.5-5": (0.5, 5.0), "5.5-10": (5.5, 10.0)}
#: After-MAE over the disc-only floor beyond which a specimen is examined.
RATIO = 1.5
#: The classes examined (answers.csv ``class``).
CLASSES = ("ligaments", "both")


# ----------------------------------------------------------------------------- tables
def point_errors(curves: pd.DataFrame) -> pd.DataFrame:
    """A calibration's ``curves.csv`` (n, >= 5) as ``specimen``, ``load_case``,
    ``moment_nm``, ``abs_deg`` (|calibrated - measured|, deg; rows with both values)."""
    ok = curves.dropna(subset=["measured_rom_deg", "calibrated_rom_deg"])
    return pd.DataFrame(
        {
            "specimen": ok["specimen"].astype(str).to_numpy(),
            "load_case": ok["load_case"].to_numpy(),
            "moment_nm": ok["moment_nm"].astype(float).to_numpy(),
            "abs_deg": (ok["calibrated_rom_deg"] - ok["measured_rom_deg"]).abs().to_numpy(),
        }
    )


def split_mae(errors: pd.DataFrame) -> pd.DataFrame:
    """Per specimen (rows) of :func:`point_errors`' table: ``mae``, ``mae_<band>``
    (:data:`BANDS`) and ``mae_<load case>``, deg (NaN where no point)."""
    rows = {}
    for name, part in errors.groupby("specimen", sort=False):
        a, m = part["abs_deg"], part["moment_nm"]
        row = {"mae": a.mean(), **{f"mae_{b}": a[m.between(*r)].mean() for b, r in BANDS.items()}}
        row.update({f"mae_{lc}": a[part["load_case"] == lc].mean() for lc in LOAD_CASES})
        rows[str(name)] = {k: float(v) for k, v in row.items()}
    return pd.DataFrame.from_dict(rows, orient="index").rename_axis("specimen")


def _read_curves(folders: Sequence[Path]) -> pd.DataFrame:
    frames = [
        pd.read_csv(f / "calibration" / "curves.csv", dtype={"specimen": str}) for f in folders
    ]
    return pd.concat(frames, ignore_index=True)


def examined(hidden: Mapping[str, Any], ratio: float = RATIO) -> list[str]:
    """The specimens of :data:`CLASSES` in ``hidden.json`` (``hidden``) whose MAE after the
    found model exceeds ``ratio`` floors, in its order."""
    limit = ratio * float(hidden["disc_only_floor_mae_deg"])
    return [
        str(r["specimen"])
        for r in hidden["specimens"]
        if r["class"] in CLASSES and float(r["after_mae_deg"]) > limit
    ]


def tables(hidden_dir: Path, cohort: Path) -> dict[str, Any]:
    """The after-model MAE of the examined specimens by band and load case (``tables``)."""
    hidden = json.loads((hidden_dir / "hidden.json").read_text())
    names = examined(hidden)
    diagnosis = {
        str(r["specimen"]): r
        for r in json.loads((hidden_dir / "diagnosis/diagnosis.json").read_text())
    }
    after = split_mae(point_errors(_read_curves(sorted(hidden_dir.glob("found-*")))))
    disc = split_mae(point_errors(_read_curves([hidden_dir / "disc-alone"])))
    none_floor = [r["specimen"] for r in hidden["specimens"] if r["class"] == "none"]
    floor = disc.loc[disc.index.isin(none_floor)].mean()
    answers = pd.read_csv(cohort / "answers.csv", dtype={"specimen": str}).set_index("specimen")
    rows = []
    for name in names:
        rec = diagnosis[name]
        source = after if name in after.index else disc
        row = {
            "specimen": name,
            "class": str(answers.loc[name, "class"]),
            "model": "+".join(rec.get("model") or []) or "none",
            "disc_mae": float(disc.loc[name, "mae"]),
        }
        row.update({k.replace("mae", "after", 1): float(v) for k, v in source.loc[name].items()})
        rows.append(row)
    return {
        "floor": {k: float(v) for k, v in floor.items()},
        "floor_mae_deg": float(hidden["disc_only_floor_mae_deg"]),
        "specimens": rows,
    }


# ----------------------------------------------------------------------------- (a) FE disc
def _answers(cohort: Path, names: Sequence[str]) -> pd.DataFrame:
    answers = pd.read_csv(cohort / "answers.csv", dtype={"specimen": str}).set_index("specimen")
    return answers.loc[list(names)]


def fe_disc_alone(
    cohort: Path, names: Sequence[str], store: Path, fe_params: Path
) -> dict[str, np.ndarray]:
    """CalculiX runs of the disc alone at the specimens' true disc parameters: the cohort's
    settings (``fe.settings`` of ``fe_params``, the shared-machine timeout) without
    ``posterior``, one worker, into ``store`` (resumed). Specimen -> RoM (4, m), deg, at
    ``fe.moments`` (NaN where not reached)."""
    from femcal.config import load_params
    from femcal.fe.campaign import run_campaign
    from femcal.fe.runtime import SHARED_MACHINE_TIMEOUT_S, fe_space

    params = load_params(fe_params)
    space, moments = fe_space(params["fe"]["bounds"]), list(params["fe"]["moments"])
    answers = _answers(cohort, names)
    design = answers[["config_id", *space.names]].reset_index(drop=True)
    settings = {**params["fe"]["settings"], "timeout_s": SHARED_MACHINE_TIMEOUT_S}
    store.parent.mkdir(parents=True, exist_ok=True)
    result = run_campaign(
        params["fe"]["solver"],
        settings,
        design,
        store=store,
        names=space.names,
        load_cases=LOAD_CASES,
        moments=moments,
        n_workers=1,
        progress=False,
    )
    return _curves_by_specimen(result.records, answers, len(moments))


def _curves_by_specimen(
    records: pd.DataFrame, answers: pd.DataFrame, n_levels: int
) -> dict[str, np.ndarray]:
    out = {}
    for name, cid in answers["config_id"].items():
        rom = np.full((len(LOAD_CASES), n_levels), np.nan)
        for rec in records[records["config_id"] == cid].to_dict(orient="records"):
            values = np.array([np.nan if v is None else v for v in rec["rom_deg"]], float)
            rom[LOAD_CASES.index(rec["load_case"]), : len(values)] = values
        out[str(name)] = rom
    return out


def _read_fe(store: Path, cohort: Path, names: Sequence[str], n_levels: int) -> dict:
    from femcal.fe.store import load_records, records_frame

    return _curves_by_specimen(
        records_frame(load_records(store)), _answers(cohort, names), n_levels
    )


# ----------------------------------------------------------------------------- (c) oracle
#: The terms of each class in every load case its effects' priors allow, split.
ORACLE_TERMS = {
    "ligaments": ("ligament_tension@Flexion,Extension,LateralBending:split",),
    "both": (
        "facet_contact@Extension,LateralBending,AxialRotation:split",
        "ligament_tension@Flexion,Extension,LateralBending:split",
    ),
}
#: Sobol starts of the element parameters, and the best of them polished by L-BFGS-B.
N_STARTS, N_POLISH = 512, 6


def band_mae(residual: np.ndarray, moments: np.ndarray) -> dict[str, float]:
    """``mae``, ``mae_<band>``, ``mae_<load case>`` (NaN where no point) of residuals (4, m),
    deg, in :data:`~femcal.schema.LOAD_CASES` order at ``moments`` (m,), Nm."""
    a = np.abs(np.asarray(residual, dtype=float))

    def mean(x: np.ndarray) -> float:
        return float(np.nanmean(x)) if np.isfinite(x).any() else float("nan")

    out = {"mae": mean(a)}
    for band, (lo, hi) in BANDS.items():
        out[f"mae_{band}"] = mean(a[:, (moments >= lo) & (moments <= hi)])
    for i, lc in enumerate(LOAD_CASES):
        out[f"mae_{lc}"] = mean(a[i])
    return out


def parallel_curves(
    disc_rom: np.ndarray,
    moments: np.ndarray,
    effects: Sequence[Any],
    units: Sequence[np.ndarray],
    n_grid: int = 400,
) -> np.ndarray:
    """RoM of a disc given by its own curves with parallel elements beside it.

    In each load case ``M = M_d + sum_e M_e(phi_d(M_d))``: the disc's rotation ``phi_d`` at
    its share ``M_d`` interpolated in log-log between the disc's points (a power law through
    its first two points below them), the total moment tabulated on ``n_grid`` shares and
    inverted at ``moments``.

    Parameters
    ----------
    disc_rom : ndarray, shape (4, m)
        The disc alone's RoM at ``moments``, degrees (NaN where not reached: the disc's share
        stays below its last point).
    moments : ndarray, shape (m,)
        Nm, increasing.
    effects : sequence of Effect
        Parallel effects (instances; their ``load_cases`` say where each acts).
    units : sequence of ndarray, shape (p_e,)
        Each effect's parameters in its unit box.

    Returns
    -------
    ndarray, shape (4, m)
        NaN where the total moment needs the disc beyond its last point.
    """
    import torch

    out = np.full(disc_rom.shape, np.nan)
    params = [
        e.from_unit(torch.tensor(np.asarray(u, float)[None], dtype=torch.float64))
        for e, u in zip(effects, units)
    ]
    for i, lc in enumerate(LOAD_CASES):
        ok = np.isfinite(disc_rom[i]) & (disc_rom[i] > 0)
        if ok.sum() < 2:
            continue
        lm, lp = np.log(moments[ok]), np.log(disc_rom[i][ok])
        share = np.exp(np.linspace(np.log(1e-3 * moments[0]), lm[-1], n_grid))
        slope = (lp[1] - lp[0]) / (lm[1] - lm[0])
        ls = np.log(share)
        phi = np.exp(np.where(ls < lm[0], lp[0] + slope * (ls - lm[0]), np.interp(ls, lm, lp)))
        total = share.copy()
        for e, p in zip(effects, params):
            if lc not in e.load_cases:
                continue
            rot = torch.tensor(phi[None, None, :], dtype=torch.float64)
            with torch.no_grad():
                carried = e.moment_at(rot, p, [i]).numpy()[0, 0]
            total = total + carried
        total = np.maximum.accumulate(total)
        inside = moments <= total[-1]
        out[i, inside] = np.interp(moments[inside], total, phi)
    return out


def fit_units(
    curves: Any, dim: int, target: np.ndarray, start: np.ndarray, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Least squares over the unit box: Sobol starts, the best polished by L-BFGS-B.

    Parameters
    ----------
    curves : callable
        ``u (B, dim) -> RoM (B, 4, m)`` in degrees (NaN where undefined).
    dim : int
    target : ndarray, shape (4, m)
        Degrees (NaN: no point).
    start : ndarray, shape (dim,)
        The effects' own starts (their weak ends), tried beside the design.
    seed : int
        Seed of the scrambled Sobol design.

    Returns
    -------
    u : ndarray, shape (dim,)
    rom : ndarray, shape (4, m)
        The curves at ``u``.
    """
    from scipy.optimize import minimize
    from scipy.stats import qmc

    mask = np.isfinite(target)
    penalty = 1e3  # per point the model leaves undefined where a target exists

    def loss_batch(u: np.ndarray) -> np.ndarray:
        pred = curves(np.clip(u, 0.0, 1.0))
        r = np.where(mask, pred - target, 0.0)
        r = np.where(np.isfinite(r), r, np.sqrt(penalty))
        return (r**2).sum(axis=(1, 2))

    design = np.vstack([start[None], qmc.Sobol(dim, scramble=True, seed=seed).random(N_STARTS)])
    losses = loss_batch(design)
    best_u, best = design[int(np.argmin(losses))], float(np.min(losses))
    step = 1e-4

    def fun(u: np.ndarray) -> tuple[float, np.ndarray]:
        batch = np.vstack([u[None], u[None] + step * np.eye(dim)])
        values = loss_batch(batch)
        return float(values[0]), (values[1:] - values[0]) / step

    for i in np.argsort(losses)[:N_POLISH]:
        res = minimize(fun, design[i], jac=True, method="L-BFGS-B", bounds=[(0, 1 - step)] * dim)
        if res.fun < best:
            best_u, best = np.clip(res.x, 0, 1), float(res.fun)
    return best_u, curves(best_u[None])[0]


def _effect_starts(effects: Sequence[Any]) -> np.ndarray:
    return np.concatenate([np.array([q.start for q in e.parameters], dtype=float) for e in effects])


def _oracle_row(name: str, cls: str, data: Mapping[str, Any], base: Any) -> dict[str, Any]:
    """One specimen's (a) and (c) figures; ``data``: ``target``, ``clean`` (4, m), ``truth``
    (1, 13), ``moments`` (m,), ``fe`` (4, m) or None."""
    import torch

    from femcal.effects.base import get_effect
    from femcal.effects.composite import EffectModel

    target, clean, moments, disc = data["target"], data["clean"], data["moments"], data["fe"]
    row: dict[str, Any] = {"specimen": name, "class": cls}
    at_truth = base.predict(data["truth"])[0]
    row["surrogate_vs_noisy"] = band_mae(at_truth - target, moments)
    terms = ORACLE_TERMS[cls]
    model = EffectModel(base, list(terms))
    v_disc = base.from_physical(data["truth"])
    dim = model.dim - model.n_disc

    def with_surrogate(u: np.ndarray) -> np.ndarray:
        v = torch.cat([v_disc.expand(len(u), -1), torch.tensor(u, dtype=torch.float32)], 1)
        with torch.no_grad():
            return model.curves(v).double().numpy()

    u, fit = fit_units(with_surrogate, dim, target, _effect_starts(model.effects))
    row["oracle_surrogate_disc"] = band_mae(fit - target, moments)
    row["oracle_surrogate_disc_clean"] = band_mae(fit - clean, moments)
    row["oracle_surrogate_disc_units"] = u.tolist()
    if disc is None:
        return row
    row["surrogate_vs_fe_disc"] = band_mae(at_truth - disc, moments)
    row["fe_disc_reached"] = int(np.isfinite(disc).sum())
    row["fe_disc_vs_noisy"] = band_mae(disc - target, moments)
    # the elements' share at the first level: with them over the disc alone, per load case
    row["fe_first_level_ratio"] = (clean[:, 0] / disc[:, 0]).tolist()
    effects = [get_effect(t)() for t in terms]
    sizes = np.cumsum([0] + [len(e.parameters) for e in effects])

    def with_fe(u: np.ndarray) -> np.ndarray:
        parts = [[r[a:b] for a, b in zip(sizes[:-1], sizes[1:])] for r in u]
        return np.stack([parallel_curves(disc, moments, effects, q) for q in parts])

    u, fit = fit_units(with_fe, dim, target, _effect_starts(effects))
    row["oracle_fe_disc"] = band_mae(fit - target, moments)
    row["oracle_fe_disc_clean"] = band_mae(fit - clean, moments)
    row["oracle_fe_disc_units"] = u.tolist()
    return row


def oracle(
    hidden_dir: Path, cohort: Path, model_uri: str, store: Path, names: Sequence[str]
) -> dict[str, Any]:
    """(a) and (c) for each specimen (module docstring): the surrogate against CalculiX at the
    true disc, and the element families fitted beside the true disc (surrogate or CalculiX)."""
    from femcal.calibration import SurrogateCurveModel
    from femcal.measurements import read_measurements
    from femcal.tracking import load_surrogate, open_model

    noisy = read_measurements(cohort / "measured" / "Test")
    clean = read_measurements(cohort / "clean" / "Test")
    moments = np.asarray(noisy.moments, dtype=float)
    index = {s: i for i, s in enumerate(noisy.specimens)}
    answers = _answers(cohort, names)
    base = SurrogateCurveModel(load_surrogate(open_model(model_uri)), moments)
    fe = _read_fe(store, cohort, names, len(moments)) if store.parent.is_dir() else {}
    rows = []
    for name in names:
        data = {
            "target": noisy.rom_deg[index[name]],
            "clean": clean.rom_deg[index[name]],
            "truth": answers.loc[[name], list(base.space.names)].to_numpy(dtype=float),
            "moments": moments,
            "fe": fe[name] if name in fe and np.isfinite(fe[name]).any() else None,
        }
        row = _oracle_row(name, str(answers.loc[name, "class"]), data, base)
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if not k.endswith("units")}), flush=True)
    return {"terms": ORACLE_TERMS, "specimens": rows}


# ----------------------------------------------------------------------------- (b, d) rerun
def rerun(
    hidden_dir: Path, cohort: Path, names: Sequence[str], options: Mapping[str, Any]
) -> dict[str, Any]:
    """The specimens calibrated again as ``femcal.fe.hidden`` calibrates them
    (:func:`femcal.fe.hidden.calibration_job`), grouped by their terms.

    ``options``: ``root`` (the project whose ``params.yaml`` the loop read), ``model_uri``,
    ``bank`` (a prepared table; None: ``params.yaml``'s), ``terms`` (None: each verdict's
    model in ``hidden_dir/diagnosis``; ``"class"``: :data:`ORACLE_TERMS` of its class; else
    the terms for all), ``out`` (folder), ``noise_deg``. Returns ``start_bank`` and per
    specimen its terms and :func:`split_mae`'s figures.
    """
    from femcal.config import load_params
    from femcal.fe.hidden import calibration_job
    from femcal.jobs.calibrate import run_calibration
    from femcal.jobs.common import use_project
    from femcal.measurements import read_measurements

    params = load_params(Path(options["root"]) / "params.yaml")
    use_project(params)
    diagnosis = {
        str(r["specimen"]): r
        for r in json.loads((hidden_dir / "diagnosis" / "diagnosis.json").read_text())
    }
    answers = _answers(cohort, names)
    groups: dict[tuple[str, ...], list[str]] = {}
    for name in names:
        terms = options.get("terms")
        if terms is None:
            terms = diagnosis[name].get("model") or []
        elif terms == "class":
            terms = ORACLE_TERMS[str(answers.loc[name, "class"])]
        groups.setdefault(tuple(terms), []).append(name)
    long = read_measurements(cohort / "measured" / "Test").to_long()
    job_options = {**options, "params": params, "start_bank": options.get("bank")}
    rows, bank = [], None
    for i, (terms, members) in enumerate(sorted(groups.items())):
        folder = Path(options["out"]) / f"group-{i}"
        folder.mkdir(parents=True, exist_ok=True)
        subset = folder / "measurements.csv"
        long[long["specimen"].astype(str).isin(members)].to_csv(subset, index=False)
        job = calibration_job(subset, folder / "calibration", terms, job_options)
        bank = str(job.start_bank)
        run_calibration(job)
        table = split_mae(point_errors(_read_curves([folder])))
        for name in members:
            rows.append({"specimen": name, "terms": "+".join(terms) or "none"})
            rows[-1].update({k: float(v) for k, v in table.loc[name].items()})
    return {"start_bank": bank, "specimens": rows}


# ----------------------------------------------------------------------------- report
def _f(value: Any, digits: int = 2) -> str:
    return "" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def _by_case(figures: Mapping[str, float] | None) -> str:
    if not figures:
        return ""
    return " / ".join(_f(figures.get(f"mae_{lc}")) or "-" for lc in LOAD_CASES)


def report(results: Path) -> str:
    """The markdown table of the examined specimens from the commands' JSON files in
    ``results`` (``tables``, ``oracle``, ``rerun-fe-all``, ``rerun-right``; those present)."""

    def load(name: str) -> dict[str, Any]:
        path = results / f"{name}.json"
        if not path.is_file():
            return {}
        return {str(r["specimen"]): r for r in json.loads(path.read_text())["specimens"]}

    tab, orc, bank, right = (
        load("tables"),
        load("oracle"),
        load("rerun-fe-all"),
        load("rerun-right"),
    )
    lines = [
        "| specimen | class | verdict's model | disc alone | after | after 0.5-5 / 5.5-10 Nm "
        "| after F / E / LB / AR | FE element's share F / E / LB / AR | surrogate at the true "
        "disc vs CalculiX | law family, CalculiX disc (clean) F / E / LB / AR "
        "| the class's terms | FE start bank |",
        "|" + " --- |" * 12,
    ]
    for name, t in tab.items():
        o, b, r = orc.get(name, {}), bank.get(name, {}), right.get(name, {})
        share, sur, fam = (
            o.get("fe_disc_vs_noisy"),
            o.get("surrogate_vs_fe_disc"),
            o.get("oracle_fe_disc_clean"),
        )
        cells = [
            name,
            t["class"],
            f"`{t['model']}`",
            _f(t["disc_mae"]),
            _f(t["after"], 3),
            f"{_f(t['after_0.5-5'])} / {_f(t['after_5.5-10'])}",
            " / ".join(_f(t.get(f"after_{lc}")) or "-" for lc in LOAD_CASES),
            _by_case(share),
            f"{_f(sur['mae'], 3)} ({_f(sur['mae_5.5-10'])} at 5.5-10)" if sur else "",
            f"{_f(fam['mae'], 3)}: {_by_case(fam)}" if fam else "",
            _f(r.get("mae"), 3),
            _f(b.get("mae"), 3),
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- command line
def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command line (module docstring)."""
    parser = argparse.ArgumentParser(prog="python -m experiments.fe_ligament_residuals")
    parser.add_argument("command", choices=("tables", "fe", "oracle", "rerun", "report"))
    parser.add_argument("--hidden", type=Path, default=Path("fe/reports/hidden"))
    parser.add_argument("--cohort", type=Path, default=Path("fe/data/cohort"))
    parser.add_argument("--model", default="fe/models/surrogate-large")
    parser.add_argument("--store", type=Path, default=Path("fe-disc-alone/runs.jsonl.gz"))
    parser.add_argument("--fe-params", type=Path, default=Path("fe/params.yaml"))
    parser.add_argument("--specimens", default="", help="comma-separated; default: examined")
    parser.add_argument("--out", type=Path, default=Path("fe-ligament-residuals"))
    parser.add_argument("--root", type=Path, default=Path("."))
    parser.add_argument("--bank", default=None, help="rerun: a prepared table of starts")
    parser.add_argument("--terms", default="", help="rerun: terms joined by '+', or 'class'")
    parser.add_argument("--tag", default="verdict", help="rerun: the output's name")
    args, rest = parser.parse_known_args(argv)
    if args.command == "report":
        text = report(args.out)
        print(text)
        return {"report": text}
    hidden = json.loads((args.hidden / "hidden.json").read_text())
    names = [s for s in args.specimens.split(",") if s] or examined(hidden)
    if args.command == "tables":
        result = tables(args.hidden, args.cohort)
    elif args.command == "fe":
        curves = fe_disc_alone(args.cohort, names, args.store, args.fe_params)
        result = {k: v.tolist() for k, v in curves.items()}
    elif args.command == "oracle":
        result = oracle(args.hidden, args.cohort, args.model, args.store, names)
    elif args.command == "rerun":
        options = {
            "root": args.root,
            "model_uri": args.model,
            "bank": args.bank,
            "terms": args.terms.split("+")
            if args.terms not in ("", "class")
            else args.terms or None,
            "out": args.out / f"rerun-{args.tag}",
            "noise_deg": 0.05,
        }
        result = rerun(args.hidden, args.cohort, names, options)
    else:
        raise SystemExit(f"{args.command}: {rest}")
    args.out.mkdir(parents=True, exist_ok=True)
    tag = f"-{args.tag}" if args.command == "rerun" else ""
    (args.out / f"{args.command}{tag}.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
