"""What several stages share: settings read at the edge, checks before any heavy work.

Relative paths in params.yaml start at its folder (the project root), paths typed on the
command line at the current folder, and the stores (``mlflow.store_dir``, ``train.storage``,
``fe.store``) at the repository's root (:mod:`femcal.paths`). Nothing here imports torch,
Lightning or MLflow at module level, so that a bad setting is the first error, within a second.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from femcal.config import section, settings_of
from femcal.errors import ConfigError, InputDataError
from femcal.paths import setting_path, store_url

logger = logging.getLogger(__name__)

#: Settings that belong to the stage (its params.yaml, metrics file, the user's effect files),
#: not to the library function it calls.
STAGE_ONLY = ("params", "metrics_file", "effect_modules")


@dataclass(frozen=True)
class StageSettings:
    """Base of every stage's settings dataclass.

    A stage's fields are the keywords of the library function it calls (``run_calibration``,
    ``run_train``, ...), plus :data:`STAGE_ONLY`; :meth:`call_args` gives those keywords.

    Attributes
    ----------
    params : mapping
        The parsed params.yaml the settings were read from (keyword-only; the tracked stages
        point MLflow at its store, :func:`femcal.stages.store.tracking`).
    metrics_file : str or None
        The stage's DVC metrics file (``--metrics-file``; keyword-only), written only when
        given (:func:`write_metrics`).
    """

    params: Mapping[str, Any] = field(default_factory=dict, repr=False, kw_only=True)
    metrics_file: str | None = field(default=None, kw_only=True)

    def call_args(self) -> dict[str, Any]:
        """The library function's keywords: every field but :data:`STAGE_ONLY`."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in STAGE_ONLY}


def typed(params: Mapping[str, Any], name: str, *keys: str) -> Any:
    """Section ``name`` of the typed settings of params.yaml (:class:`femcal.settings.Settings`);
    a ConfigError names what it misses (:meth:`~femcal.settings.Settings.require`: only
    ``keys`` when given)."""
    return settings_of(params).require(name, *keys)


def path_setting(params: Mapping[str, Any], name: str, key: str) -> Path:
    """A path setting of params.yaml, relative to the project root (:mod:`femcal.paths`)."""
    return setting_path(params, getattr(typed(params, name, key), key))


def check_outputs(out: str | Path, *, label: str, metrics_file: str | None = None) -> Path:
    """The output folder and the metrics file, checked before any heavy work."""
    from femcal.outputs import check_destination, check_file_destination

    path = check_destination(out, label=label)
    if metrics_file:
        check_file_destination(metrics_file, label="--metrics-file")
    return path


def out_label(given: str | None, setting: str) -> str:
    """How an output folder is named in messages: ``--out`` or the setting it comes from."""
    return "--out" if given else f"output folder ({setting})"


def output_folder(
    params: Mapping[str, Any],
    args: Mapping[str, Any],
    section_name: str,
    *,
    subfolder: str | None = None,
) -> Path:
    """A stage's output folder, checked with its metrics file before any heavy work.

    Parameters
    ----------
    params : mapping
        The parsed params.yaml.
    args : mapping
        The command line's settings: ``out`` (``--out``) and ``metrics_file``
        (``--metrics-file``).
    section_name : str
        The params.yaml section whose ``out_dir`` is the default folder; messages name the
        folder ``--out`` or ``<section_name>.out_dir`` (:func:`out_label`).
    subfolder : str, optional
        A folder below ``<section_name>.out_dir`` (not below ``--out``).

    Returns
    -------
    Path
        ``--out`` as given, else the setting (relative to the project root), with
        ``subfolder``.

    Raises
    ------
    OutputFolderError
        The folder or the metrics file cannot receive the outputs (:func:`check_outputs`).
    """
    given = args.get("out")
    out = Path(given) if given else path_setting(params, section_name, "out_dir")
    if subfolder and not given:
        out = out / subfolder
    check_outputs(
        out,
        label=out_label(given, f"{section_name}.out_dir"),
        metrics_file=args.get("metrics_file"),
    )
    return out


def check_measurements(path: Path) -> None:
    """A missing measurement file or folder, reported before any heavy import."""
    if not path.exists():
        raise InputDataError(
            f"Measurement file {path} does not exist; check the path (relative paths on the "
            f"command line start at the current folder {Path.cwd()}, in params.yaml at its "
            "folder)."
        )


def write_metrics(
    path: str | Path | None,
    figures: Mapping[str, Any],
    kind: str | None = None,
    *,
    details: bool = False,
) -> None:
    """A stage's DVC metrics file (``--metrics-file``), written whole or not at all.

    ``figures`` on the shared vocabulary of :mod:`femcal.dvc_metrics` (a headline of
    :mod:`femcal.headlines`), or, with ``kind``, the stage's figures, mapped onto it
    (:func:`femcal.dvc_metrics.write`; ``details`` also writes them whole beside the file).

    Raises
    ------
    MetricsFileError
        A key of ``figures`` (without ``kind``) is not in the vocabulary.
    """
    if not path:
        return
    from femcal.dvc_metrics import VOCABULARY, MetricsFileError, split_run, write, write_run

    if kind is not None:
        write(path, kind, figures, details=details)
        return
    figures, run = split_run(figures)
    unknown = sorted(set(figures) - set(VOCABULARY))
    if unknown:
        raise MetricsFileError(
            f"{path}: {unknown} are not DVC metrics keys ({', '.join(VOCABULARY)}); map the "
            "figures with femcal.dvc_metrics.headline."
        )
    from femcal.outputs import write_text_atomic

    write_text_atomic(path, json.dumps(dict(figures), indent=2) + "\n")
    write_run(path, run)


def optuna_storage(params: Mapping[str, Any]) -> str:
    """FEMCAL_OPTUNA_STORAGE as given, else train.storage (a relative SQLite file under the
    repository's root, :func:`femcal.paths.store_url`); a SQLite file's folder is created."""
    storage = os.environ.get("FEMCAL_OPTUNA_STORAGE") or store_url(
        params, typed(params, "train", "storage").storage
    )
    file = storage[len("sqlite:///") :] if storage.startswith("sqlite:///") else ""
    if file and file != ":memory:":
        Path(file).parent.mkdir(parents=True, exist_ok=True)
    return storage


def moment_settings(params: Mapping[str, Any]) -> dict[str, tuple[float, float]]:
    """params.yaml's ``moments`` section (one moment policy for every command) as keywords.

    Returns ``{"error_growth": (below, above), "max_log_ratio": (below, above)}``: each
    setting is ``{below: ..., above: ...}`` in the file, or one number for both sides.
    """
    out = {}
    for key in ("error_growth", "max_log_ratio"):
        value = section(params, "moments", key)
        sides = ("below", "above")
        items = [value.get(s) for s in sides] if isinstance(value, Mapping) else [value] * 2
        try:
            pair = tuple(float(x) for x in items)
            valid = not any(isinstance(x, bool) for x in items) and all(
                x >= 0 and x != float("inf") for x in pair
            )
            valid = valid and (not isinstance(value, Mapping) or set(value) == set(sides))
        except (TypeError, ValueError):
            valid = False
        if not valid:
            raise ConfigError(
                f"{params.get('_path', 'params.yaml')}: moments.{key} must be a number >= 0 "
                f"per side of the trained moment range, {{below: ..., above: ...}} (or one "
                f"number for both); got {value!r}. Use the values measured by "
                "experiments/bench_extrapolation.py (docs/benchmarks/index.md)."
            )
        out[key] = pair
    return out


def dropped_note(n_dropped: int, out: str) -> str:
    """The line naming the points the moment policy dropped and where they are listed."""
    return (
        f"WARNING: {n_dropped} measured points lie beyond the moments the surrogate is used at "
        f"and were left out: see {out}/dropped_points.csv (moments.max_log_ratio)"
    )


def noise_setting(
    params: Mapping[str, Any], given: float | None, setting: float | None, key: str
) -> tuple[float | None, str]:
    """The measurement noise sd (deg) and where it comes from, for the log and the summary.

    Parameters
    ----------
    params : mapping
        The parsed params.yaml (its ``_path`` names the file).
    given : float or None
        ``--noise-deg``: it wins; checked to be a finite number > 0.
    setting : float or None
        The value params.yaml gives for this file (None: none).
    key : str
        The dotted key of ``setting`` (``diagnose.noise_deg``, ``calibrate.datasets.<name>.
        noise_deg``).

    Returns
    -------
    noise : float or None
        None where neither gives one.
    source : str
        ``"--noise-deg"``, ``"<key> in <absolute path of params.yaml>"`` or ``""``.

    Raises
    ------
    ConfigError
        ``given`` is not a finite number > 0.
    """
    if given is not None:
        if not (math.isfinite(given) and given > 0):
            raise ConfigError(
                "--noise-deg: the measurement noise sd must be a number > 0 in degrees; got "
                f"{given!r}. Give the sd of one measurement (e.g. 0.05), or leave it out."
            )
        return float(given), "--noise-deg"
    if setting is not None:
        where = Path(params.get("_path", "params.yaml")).resolve()
        return float(setting), f"{key} in {where}"
    return None, ""
