"""`dvc metrics show` fits a terminal and `dvc plots show/diff` render every declared plot.

Real DVC on a temporary Git repository holding this project's dvc.yaml, params.yaml, plot
templates (.dvc/plots) and the reports the stages wrote: the committed ones (metrics, tables,
reports/plots/) and, when present, the stage outputs of `dvc repro` or `dvc pull`
(reports/calibration/test/curves.csv, reports/diagnosis/residuals.csv).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from femcal.headlines import MAX_KEYS

ROOT = Path(__file__).resolve().parents[1]
DVC = Path(sys.executable).parent / "dvc"
#: `dvc metrics show` prints one column per key of a metrics file: at most this many per stage.
MAX_COLUMNS = 40


def _run(args: list, cwd: Path) -> subprocess.CompletedProcess:
    proc = subprocess.run(args, cwd=cwd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise AssertionError(
            f"{' '.join(map(str, args))} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
        )
    return proc


def _declared_plots() -> dict[str, dict]:
    """Top-level plots of dvc.yaml: id -> definition."""
    plots = yaml.safe_load((ROOT / "dvc.yaml").read_text()).get("plots") or []
    return {k: v for entry in plots for k, v in entry.items()}


def _plot_sources(definition: dict) -> list[str]:
    y = definition["y"]
    return list(y) if isinstance(y, dict) else []


def _metrics_files() -> list[str]:
    """The metrics files dvc.yaml declares, ``foreach`` and ``${...}`` resolved."""
    params = yaml.safe_load((ROOT / "params.yaml").read_text())
    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]

    def value(name: str, item=None, key=None) -> str:
        if name in ("item", "key"):
            return str(item if name == "item" else key)
        node = params
        for part in name.split("."):
            node = node[part]
        return str(node)

    def resolve(text: str, item=None, key=None) -> str:
        return re.sub(r"\$\{([^}]+)\}", lambda m: value(m.group(1).strip(), item, key), text)

    declared = []
    for spec in stages.values():
        body = spec.get("do", spec)
        names = [next(iter(m)) if isinstance(m, dict) else m for m in body.get("metrics") or []]
        if "foreach" in spec:
            loop = spec["foreach"]
            if isinstance(loop, str):  # "${calibrate.datasets}"
                node = params
                for part in loop.strip("${} ").split("."):
                    node = node[part]
                loop = node
            pairs = loop.items() if isinstance(loop, dict) else [(x, x) for x in loop]
            declared += [resolve(n, item=i, key=k) for k, i in pairs for n in names]
        else:
            declared += [resolve(n) for n in names]
    return sorted(declared)


def _stand_in(header: str, rows: list[str]) -> str:
    return "\n".join([header, *rows]) + "\n"


#: What `calibrate@test` and `diagnose` write (the columns of femcal.calibration.report and
#: femcal.diagnose.report), a few rows each.
_STAND_INS = {
    "reports/calibration/test/curves.csv": _stand_in(
        "specimen,load_case,moment_nm,measured_rom_deg,calibrated_rom_deg,holdout_rom_deg",
        [
            f"{s},{lc},{m:.1f},{0.9 * m + s * 0.1:.4f},{0.9 * m + s * 0.1 + 0.01:.4f},"
            f"{0.9 * m + s * 0.1 - 0.01:.4f}"
            for s in range(2)
            for lc in ("Flexion", "Extension")
            for m in (1.0, 2.0, 3.0)
        ],
    ),
    "reports/diagnosis/residuals.csv": _stand_in(
        "specimen,load_case,moment_nm,residual_deg,residual_sigma,final_residual_deg,"
        "final_residual_sigma,verdict",
        [
            f"P{s:03d},{lc},{m:.1f},0.01,0.2,0.005,0.1,none"
            for s in range(2)
            for lc in ("Flexion", "Extension")
            for m in (1.0, 2.0)
        ],
    ),
}


@pytest.fixture(scope="module")
def repo(tmp_path_factory) -> Path:
    """A Git + DVC repository with the pipeline's definitions and reports, committed."""
    root = tmp_path_factory.mktemp("dvcreports") / "repo"
    files = ["dvc.yaml", "params.yaml", ".dvc/config", *_metrics_files()]
    files += [str(p.relative_to(ROOT)) for p in (ROOT / ".dvc/plots").glob("*.json")]
    for definition in _declared_plots().values():
        files += [s for s in _plot_sources(definition) if (ROOT / s).is_file()]
    for rel in files:
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / rel, root / rel)
    # A fresh clone (CI) has no stage outputs (they come from `dvc repro` or `dvc pull`): small
    # stand-ins with the columns the stages write, so the plot definitions are still rendered.
    for rel, text in _STAND_INS.items():
        if not (root / rel).is_file():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            (root / rel).write_text(text)
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    _run(["git", "init", "-q"], root)
    _run([*git, "add", "-A"], root)
    _run([*git, "commit", "-qm", "reports"], root)
    return root


def _flatten(value, prefix: str = "") -> dict:
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: value}


def test_metrics_show_fits_a_terminal(repo):
    shown = json.loads(_run([DVC, "metrics", "show", "--json"], repo).stdout)
    data = shown[""]["data"]
    assert sorted(data) == _metrics_files(), "every declared metrics file is shown"
    for path, entry in data.items():
        assert "error" not in entry, (path, entry)
        metrics = entry["data"]
        assert isinstance(metrics, dict), (path, type(metrics))
        columns = _flatten(metrics)
        assert len(columns) <= MAX_COLUMNS, (path, len(columns), sorted(columns))
        assert not [k for k, v in columns.items() if isinstance(v, list)], path
        if not Path(path).name.startswith("train"):  # train.py writes its own summary
            assert len(columns) <= MAX_KEYS and columns == metrics, (path, sorted(columns))
    # The keys the docs, tests and benchmarks read (femcal.dvc_metrics.VOCABULARY).
    cal = data["reports/calibrate-test.json"]["data"]
    assert {"n", "mae_deg", "ref_mae_deg", "failed"} <= set(cal)
    assert {"mae_deg", "ref_mae_deg", "n"} <= set(data["reports/surrogates.json"]["data"])
    assert {"n", "flagged"} <= set(data["reports/diagnose.json"]["data"])


def _rendered(repo: Path, *args: str) -> dict:
    """`dvc plots show/diff --json`: plot id -> its vega specs (one per definition)."""
    out = json.loads(_run([DVC, "plots", *args, "--json"], repo).stdout)
    assert not out.get("errors"), out["errors"]
    return out["data"]


def _missing_sources(repo: Path) -> list[str]:
    return [
        s
        for definition in _declared_plots().values()
        for s in _plot_sources(definition)
        if not (repo / s).is_file()
    ]


def test_every_declared_plot_renders_with_its_data(repo):
    declared = _declared_plots()
    assert {
        "training_curves",
        "surrogate_vs_fe",
        "calibration_curves",
        "residual_heatmap",
    } <= set(declared)
    missing = _missing_sources(repo)
    if missing:
        pytest.skip(f"stage outputs not in this checkout: {missing}; run `dvc pull`")
    data = _rendered(repo, "show")
    for plot_id, definition in declared.items():
        (spec,) = data[plot_id]
        assert spec["type"] == "vega", plot_id
        content = spec["content"]
        values = content["data"]["values"]
        assert values, plot_id
        (source,) = _plot_sources(definition)
        n_rows = len((repo / source).read_text().strip().splitlines()) - 1
        assert len(values) == n_rows, (plot_id, len(values), n_rows)
        assert {definition["x"], *definition["y"].values(), "rev"} <= set(values[0]), plot_id
        assert "<DVC_METRIC" not in json.dumps(content), f"{plot_id}: an anchor left unfilled"
    # The HTML page holds every plot.
    _run([DVC, "plots", "show", "-o", "html"], repo)
    page = (repo / "html" / "index.html").read_text()
    for plot_id in declared:
        assert f'id = "{plot_id}"' in page or plot_id in page, plot_id
    assert page.count("vegaEmbed(") >= len(declared)


def test_plots_diff_compares_two_revisions(repo):
    missing = _missing_sources(repo)
    if missing:
        pytest.skip(f"stage outputs not in this checkout: {missing}; run `dvc pull`")
    # Another "experiment": the workspace's predictions shifted by 0.1 deg.
    path = repo / "reports/plots/surrogate_test_predictions.csv"
    before = path.read_text()
    lines = before.strip().splitlines()
    head = lines[0].split(",")
    col = head.index("predicted_rom_deg")
    rows = [r.split(",") for r in lines[1:]]
    for r in rows:
        r[col] = str(float(r[col]) + 0.1)
    path.write_text("\n".join([lines[0], *(",".join(r) for r in rows)]) + "\n")
    try:
        data = _rendered(repo, "diff", "HEAD")
    finally:
        path.write_text(before)
    for plot_id in _declared_plots():
        (spec,) = data[plot_id]
        revs = {v["rev"] for v in spec["content"]["data"]["values"]}
        assert revs == {"HEAD", "workspace"}, (plot_id, revs)
