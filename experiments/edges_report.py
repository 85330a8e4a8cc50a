"""The report of :mod:`experiments.bench_edges`: ``docs/benchmarks/edges.md`` from one or more
results folders (each holding ``bench_edges.json``), one section per folder.

``python -m experiments.edges_report --results DIR [DIR ...] --out docs/benchmarks/edges.md``
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

#: Headline rows: key of bench_edges.headline -> (label, the issue's bar).
BARS: dict[str, tuple[str, str]] = {
    "box_said": (
        "outside the box: out-of-box verdict (or `unexplained` naming the box)",
        ">= 75 %",
    ),
    "box_said_visible": ("  the same, visible discs (disc-alone MAE > 2 x true noise)", ""),
    "box_confident_builtin": ("  outside the box: a built-in effect with inclusion >= 0.9", "0"),
    "box_reported": ("  outside the box: out-of-box reading reported (p >= 0.1), any verdict", ""),
    "box_false_none": ("  class `none`: out-of-box verdict (or `unexplained` naming the box)", ""),
    "box_reported_none": ("  class `none`: out-of-box reading reported (p >= 0.1)", ""),
    "box_false_inside": ("  Test discs (every class but outside): out-of-box said", ""),
    "beyond_right_named": ("beyond the old assignment: right effect named, visible", ">= 80 %"),
    "facets_lb_right_named": ("  facets in lateral bending: facet_contact named", ""),
    "facets_lb_strict": ("  facets in lateral bending, class facets: strict", ""),
    "ligaments_ext_right_named": ("  ligaments in extension: ligament_tension named", ""),
    "ligaments_ext_strict": ("  ligaments in extension, class ligaments: strict", ""),
    "confident_wrong": ("confidently wrong (absent effect, inclusion >= 0.9), all", "<= 5 %"),
    "combos_strict_visible": ("combinations exactly right, each member visible", ">= 70 %"),
    "facets_ligaments_strict_visible": ("  facet + ligament", ">= 70 %"),
    "facets_nz_strict_visible": ("  facet + neutral zone", ">= 70 %"),
    "single_strict_visible": ("single effects strict, visible", ">= 90 %"),
    "none_given_effect_visible": ("`none` given to a visible specimen with structures", "<= 10 %"),
    "false_alarm": ("false alarm (truth `none`, verdict not `none`)", ""),
    "unexplained_right_visible": ("out-of-library softening: `unexplained`, no effect", ""),
}

INTRO = """# Benchmarks: edge cohorts

`femcal diagnose`, run as a user runs it, on cohorts that sample the library's assumptions
instead of sharing them (`experiments/edge_cohorts.py`, numpy only, nothing from femcal):

- **where each element acts** is drawn per specimen from anatomy: facets in extension and
  axial rotation, and in 40 % of specimens in lateral bending (ipsilateral impingement);
  ligaments in flexion and lateral bending, and in 35 % of specimens in extension (facet
  capsules); the neutral zone in two to four load cases; softening in one to four;
- **laws from outside the library's families**: bilinear and exponential contact, trilinear
  and fibre-recruitment ligaments, arctan, dead-band and logarithmic laxity, yield and
  creep-like softening;
- **discs outside the box**: CalculiX discs of `experiments/fe_outside_box.jsonl.gz`, whose
  five matrix and fibre stiffnesses all lie above the sampled box (no scaled curves); the other
  discs are the study's held-out Test configurations;
- **noise that is not white**: per-curve offsets, noise growing with the moment, and cohorts
  whose true noise is 0.6-0.8 or 1.4-1.8 x the stated 0.05 deg (half the seeds; the truth
  records the true noise);
- **protocols**: 1-5 Nm by 0.5, 1.25-7.5 Nm by 1.25, and maxima drawn per load case (3-7.5 Nm).

Eight classes of six specimens per cohort (48): `none`, facets, ligaments, neutral zone,
facets + ligaments, facets + neutral zone, out-of-library softening (truth `unexplained`) and
discs outside the box. Scoring (`experiments/bench_edges.py`): a specimen is **visible** where
the disc alone misses (the diagnosis' disc-alone MAE exceeds 2 x the specimen's true noise RMS)
and each of its structures shows (what it adds, the RoM with every structure less the RoM
without it, has an RMS above the same threshold in a load case it acts in); a structure beyond
the old assignment where the disc alone misses and it shows in that load case.
**Strict**: the exact effect set, neither `unexplained` nor `outside_box`. Inclusion
probabilities are summed over an effect's forms (`x`, `x:split`).

Caveats. The discs outside the box come from the open CalculiX model, but the command
diagnoses them with the default surrogate, trained on the study's FE model; the disc-alone MAE
column tells how far outside that surrogate's reach they lie. The Test curves end at 5 Nm;
beyond it they follow a power law with their last slope, and the surrogate extrapolates there
too (its error is counted in sigma).
"""


def _fmt(r: dict[str, Any] | None) -> str:
    if not r or not r.get("n"):
        return "-"
    return f"{r['k']}/{r['n']} ({100 * r['rate']:.0f} %)"


def _num(x: Any, digits: int = 1) -> str:
    try:
        return f"{float(x):.{digits}f}"
    except (TypeError, ValueError):
        return "-"


def _headline(runs: list[dict], pooled: dict) -> list[str]:
    head = ["criterion", *(f"seed {r['seed']}" for r in runs), "pooled", "bar"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for key, (label, bar) in BARS.items():
        if key not in pooled["headline"]:  # a results folder scored before the row existed
            continue
        cells = [_fmt(r["summary"]["headline"].get(key)) for r in runs]
        lines.append("| " + " | ".join([label, *cells, _fmt(pooled["headline"][key]), bar]) + " |")
    return lines


def _timing(runs: list[dict]) -> list[str]:
    lines = [
        "| seed | specimens | wall (s) | CPU user+sys (s) | wall per 50 | CPU per 50 | peak RSS "
        "(MB) | noise scale | exit |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        c = r.get("cohort", {})
        lines.append(
            f"| {r['seed']} | {r['n_specimens']} | {_num(r.get('time_wall_s'))} | "
            f"{_num(r.get('cpu_s'))} | {_num(r.get('time_wall_s_per_50'))} | "
            f"{_num(r.get('cpu_s_per_50'))} | {_num(r.get('max_rss_mb'), 0)} | "
            f"{_num(c.get('noise_scale'), 2)} | {r['returncode']} |"
        )
    return lines


def _groups(rows: list[dict], key: str) -> list[str]:
    cols = ("strict_visible", "confident_wrong", "verdict_none_visible", "box_said")
    lines = [
        f"| {key} | n | visible | strict (visible) | confidently wrong | verdict `none` (visible)"
        " | out-of-box said |",
        "|---" * 7 + "|",
    ]
    for r in rows:
        cells = " | ".join(_fmt(r[c]) for c in cols)
        lines.append(f"| {r[key]} | {r['n']} | {r['visible']} | {cells} |")
    return lines


def _verdicts(counts: dict[str, dict[str, int]]) -> list[str]:
    lines = ["| truth | verdicts (count) |", "|---|---|"]
    for truth, c in counts.items():
        text = ", ".join(f"`{v}` {n}" for v, n in sorted(c.items(), key=lambda kv: -kv[1]))
        lines.append(f"| {truth} | {text} |")
    return lines


def _mae(mae: dict) -> list[str]:
    lines = [
        f"Floor (class `none`, final MAE): {_num(mae['floor_deg'], 4)} deg (bar: classes the "
        "library covers <= 1.5 x).",
        "",
        "| class | disc-alone MAE (deg) | final MAE (deg) | ratio to the floor |",
        "|---|---|---|---|",
    ]
    for c, v in mae["classes"].items():
        lines.append(
            f"| {c} | {_num(v['disc_alone_mae_deg'], 4)} | {_num(v['final_mae_deg'], 4)} | "
            f"{_num(v['ratio'], 2)} |"
        )
    return lines


def section(payload: dict, folder: Path | str = "") -> list[str]:
    """The Markdown section of one results folder (its ``box_edge.md`` appended, if any)."""
    meta, pooled = payload["meta"], payload["pooled"]
    runs = [r for r in payload["runs"] if r.get("summary")]
    lib = meta.get("library", {})
    if lib.get("pythonpath"):  # a snapshot of the library ran, not the working tree
        dirty = f" (femcal imported from `{lib.get('femcal_imported_from', '?')}`)"
    elif lib.get("src_femcal_changes"):
        dirty = " (with uncommitted changes under src/femcal)"
    else:
        dirty = ""
    lines = [
        f"## {meta['label']}: seeds {', '.join(map(str, meta['seeds']))}",
        "",
        meta.get("note", ""),
        "",
        f"Library at `{lib.get('commit', '?')[:10]}` ({lib.get('committed_at', '?')}: "
        f"{lib.get('subject', '?')}){dirty}; run started {meta.get('started_at', '?')}. "
        f"Command: `{meta['command']}`.",
        "",
    ]
    if pooled is None:
        return lines + ["No run finished: nothing scored.", ""]
    lines += _headline(runs, pooled)
    scores = pooled.get("inclusion_scores")  # absent in folders scored before it existed
    if scores:
        lines += [
            "",
            f"Inclusion probabilities of the built-in effects against the truth, over "
            f"{scores['pairs']} (specimen, effect) pairs: Brier score "
            f"{_num(scores['brier'], 4)}, log loss {_num(scores['log_loss'], 3)}; present "
            f"effects at >= 0.9: {_fmt(scores['present_confident'])}, absent effects at "
            f">= 0.9: {_fmt(scores['absent_confident'])}.",
        ]
    lines += ["", "### Time of the whole command", ""] + _timing(payload["runs"])
    lines += ["", "### Per class (pooled)", ""] + _groups(pooled["by_class"], "truth")
    lines += ["", "### Per noise kind (pooled)", ""] + _groups(pooled["by_noise"], "noise_kind")
    lines += ["", "### Per protocol (pooled)", ""] + _groups(pooled["by_protocol"], "protocol")
    lines += ["", "### Verdicts per class (pooled)", ""] + _verdicts(pooled["verdicts_by_class"])
    lines += ["", "### Final MAE over the `none` floor (pooled)", ""] + _mae(pooled["mae"])
    extra = Path(folder) / "box_edge.md"  # experiments.box_edge_measure's tables
    if folder and extra.exists():
        lines += ["", *extra.read_text().rstrip().splitlines()]
    return lines + [""]


def written_sections(page: Path) -> dict[str, list[str]]:
    """The sections of an existing page by label (``## <label>: seeds ...`` up to the next
    ``## ``); empty where the page does not exist."""
    sections: dict[str, list[str]] = {}
    label = None
    for line in page.read_text().splitlines() if page.exists() else []:
        if line.startswith("## "):
            label = line[3:].split(":", 1)[0]
            sections[label] = []
        if label is not None:
            sections[label].append(line)
    return sections


def write_page(folders: Sequence[Path], out: Path) -> None:
    """Write the page from the results folders, in the order given.

    A folder without ``bench_edges.json`` (a run whose results are no longer on this machine)
    keeps its section as ``out`` has it, found by the folder's name as its label; a folder
    with neither is an error."""
    given = " ".join(str(f) for f in folders)
    lines = [
        INTRO,
        f"This page is written by `python -m experiments.edges_report --results {given} --out "
        f"{out}`, one section per results folder.",
        "",
    ]
    kept = written_sections(out)
    for folder in folders:
        result = Path(folder) / "bench_edges.json"
        if not result.exists() and Path(folder).name in kept:
            lines += kept[Path(folder).name]
            continue
        if not result.exists():
            raise FileNotFoundError(
                f"{result} does not exist and {out} has no section {Path(folder).name!r}: run "
                f"python -m experiments.bench_edges --out {folder} first"
            )
        lines += section(json.loads(result.read_text()), folder)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines).rstrip() + "\n")


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--results", type=Path, nargs="+", required=True)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    write_page(args.results, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
