"""The Test-set table: every surrogate, trained on Large and on Small, side by side."""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.errors import InputDataError
from femcal.headlines import surrogate_headline
from femcal.metrics import surrogate_scores
from femcal.schema import LOAD_CASES, STATUS_OK

logger = logging.getLogger(__name__)

#: The study's Test MAE (degrees) and mean R² per surrogate and training set (Atad et al.,
#: Table 2 and appendix), for side-by-side reporting.
STUDY_TABLE: dict[tuple[str, str], tuple[float, float]] = {
    ("nn", "large"): (0.10, 0.99),
    ("nn", "small"): (0.43, 0.90),
    ("lightgbm", "large"): (0.28, 0.96),
    ("lightgbm", "small"): (0.57, 0.85),
    ("gaussian_process", "large"): (0.33, 0.95),
    ("gaussian_process", "small"): (0.62, 0.83),
    ("random_forest", "large"): (0.40, 0.91),
    ("random_forest", "small"): (0.65, 0.82),
    ("poly2", "large"): (0.82, 0.70),
    ("poly2", "small"): (0.96, 0.62),
    ("poly3", "large"): (0.61, 0.82),
    ("poly3", "small"): (0.94, 0.62),
    ("poly4", "large"): (0.50, 0.89),
    ("poly4", "small"): (0.99, 0.53),
    ("poly5", "large"): (0.54, 0.86),
    ("poly5", "small"): (1.07, 0.45),
    ("svr", "large"): (1.04, 0.51),
    ("svr", "small"): (1.05, 0.59),
    ("linear", "large"): (1.05, 0.55),
    ("linear", "small"): (1.03, 0.55),
}


@dataclass
class Score:
    """One row of the evaluation table."""

    model: str
    train_split: str
    scores: dict[str, float]
    n_rows: int
    extra: dict[str, Any]

    def as_dict(self) -> dict[str, Any]:
        study = STUDY_TABLE.get((self.model, self.train_split))
        return {
            "model": self.model,
            "train_split": self.train_split,
            "n_rows": self.n_rows,
            **self.scores,
            "study_mae": study[0] if study else None,
            "study_r2_mean": study[1] if study else None,
            **self.extra,
        }


def score_model(
    model: Any,
    test: pd.DataFrame,
    *,
    name: str,
    train_split: str,
    moments: Iterable[float] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> Score:
    """Score a fitted surrogate on the successful rows of a tidy test table.

    Parameters
    ----------
    model : object with ``predict(DataFrame) -> ndarray (n,)``
    test : DataFrame
        Tidy table (config_id, load_case, moment_nm, parameters, rom_deg, status).
    moments : iterable of float, optional
        Keep only these moments (for the interpolation check).
    """
    rows = test[test["status"] == STATUS_OK]
    if moments is not None:
        rows = rows[rows["moment_nm"].isin(list(moments))]
    rows = rows.reset_index(drop=True)
    pred = np.asarray(model.predict(rows), dtype=float)
    return Score(name, train_split, surrogate_scores(rows, pred), len(rows), dict(extra or {}))


def _fmt(x: Any, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "–"
    if isinstance(x, float):
        return f"{x:.{digits}f}"
    return str(x)


def markdown_table(scores: list[Score], *, title: str) -> str:
    """A Markdown table: MAE and R² per load case and their means, next to the study's."""
    head = ["model", "trained on", "MAE (°)", "mean R²", "curve R²"]
    head += [f"MAE {lc}" for lc in LOAD_CASES] + [f"R² {lc}" for lc in LOAD_CASES]
    head += ["study MAE", "study R²"]
    lines = [f"## {title}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in scores:
        d = s.as_dict()
        cells = [
            s.model,
            s.train_split,
            _fmt(d["mae"]),
            _fmt(d["r2_mean"], 4),
            _fmt(d.get("r2_curve_mean"), 4),
        ]
        cells += [_fmt(d.get(f"mae_{lc}")) for lc in LOAD_CASES]
        cells += [_fmt(d.get(f"r2_{lc}"), 4) for lc in LOAD_CASES]
        cells += [_fmt(d["study_mae"], 2), _fmt(d["study_r2_mean"], 2)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def evaluation_table(sections: Mapping[str, list[Score]]) -> dict[str, dict[str, Any]]:
    """Every row of every section: section key -> ``model@split`` -> :meth:`Score.as_dict`.

    The section key is the title's part before ":", lower case, spaces as "_"
    (``trained_on_large``, ``trained_on_small``, ``interpolation``).
    """
    data: dict[str, dict[str, Any]] = {}
    for title, scores in sections.items():
        key = title.split(":")[0].strip().lower().replace(" ", "_")
        data[key] = {f"{s.model}@{s.train_split}": s.as_dict() for s in scores}
    return data


def write_reports(
    sections: Mapping[str, list[Score]],
    *,
    markdown: Path,
    json_path: Path,
    table_path: Path,
    preamble: str = "",
) -> dict[str, Any]:
    """Write the evaluation: Markdown and a JSON table (for people), headlines (DVC metrics).

    Parameters
    ----------
    sections : mapping
        Section title -> its scores (e.g. "Trained on Large").
    markdown : Path
        The tables for people (``reports/surrogates.md``).
    json_path : Path
        The headline figures (``reports/surrogates.json``, the stage's DVC metrics: a few flat
        keys, :func:`femcal.headlines.surrogate_headline`).
    table_path : Path
        Every model x training set x load case (``reports/surrogates_table.json``).
    preamble : str
        A paragraph under the Markdown title.

    Returns
    -------
    dict
        The headline figures written to ``json_path``.
    """
    md = ["# Surrogate evaluation on the study's 64 Test configurations", "", preamble, ""]
    for title, scores in sections.items():
        md.append(markdown_table(scores, title=title))
    data = evaluation_table(sections)
    headline = surrogate_headline(data)
    for path in (markdown, json_path, table_path):
        path.parent.mkdir(parents=True, exist_ok=True)
    markdown.write_text("\n".join(md))
    table_path.write_text(json.dumps(data, indent=2, default=_json_default) + "\n")
    json_path.write_text(json.dumps(headline, indent=2, default=_json_default) + "\n")
    return headline


def prediction_table(model: Any, test: pd.DataFrame) -> pd.DataFrame:
    """Predicted vs FE RoM of every successful Test row (the data of a scatter plot).

    Parameters
    ----------
    model : object with ``predict(DataFrame) -> ndarray (n,)``
    test : DataFrame
        Tidy table (config_id, load_case, moment_nm, parameters, rom_deg, status).

    Returns
    -------
    DataFrame
        ``config_id``, ``load_case``, ``moment_nm``, ``fe_rom_deg``, ``predicted_rom_deg``,
        ``error_deg`` (predicted - FE), one row per successful Test row.
    """
    rows = test[test["status"] == STATUS_OK].reset_index(drop=True)
    pred = np.asarray(model.predict(rows), dtype=float).reshape(-1)
    if len(pred) != len(rows):
        raise InputDataError(
            f"The model returned {len(pred)} predictions for {len(rows)} Test rows; it must "
            "return one RoM per row (predict(DataFrame) -> ndarray of shape (n,))."
        )
    out = rows[["config_id", "load_case", "moment_nm"]].copy()
    out["fe_rom_deg"] = rows["rom_deg"].to_numpy(dtype=float)
    out["predicted_rom_deg"] = pred
    out["error_deg"] = pred - out["fe_rom_deg"]
    return out


#: Columns of the training-curves table (:func:`training_curves`).
CURVE_COLUMNS = ("member", "epoch", "train_loss", "val_loss", "val_mae_deg")


def training_curves(model: Any) -> pd.DataFrame:
    """Per member and epoch: the training and validation loss of a trained network.

    Parameters
    ----------
    model : NeuralSurrogate
        A fitted or loaded network (its ``history_``, saved in the model folder).

    Returns
    -------
    DataFrame
        :data:`CURVE_COLUMNS`; losses in the network's scaled units, ``val_mae_deg`` in
        degrees (empty cells where a value was not recorded).
    """
    history = getattr(model, "history_", None)
    if not history:
        raise InputDataError(
            f"{type(model).__name__} holds no training history (history_ is {history!r}); "
            "training curves need a NeuralSurrogate trained or loaded by femcal "
            "(`dvc repro train@large` writes one)."
        )
    table = pd.DataFrame(history)
    for column in CURVE_COLUMNS:
        if column not in table:
            table[column] = np.nan
    return table[list(CURVE_COLUMNS)].sort_values(["member", "epoch"]).reset_index(drop=True)


def _json_default(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    return str(x)
