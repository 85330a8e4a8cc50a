"""Where relative paths point: params.yaml's at the project root, the stores' at the repository.

* A relative path **typed on the command line** (``--out``, ``--measurements``, ``--params``,
  ``--metrics-file``, ...) starts at the current folder, as everywhere on Unix.
* A relative path **read from params.yaml** (``data.raw_dir``, ``calibrate.model_uri``,
  ``calibrate.out_dir``, ...) starts at the folder holding that params.yaml, the project root
  (the folder of ``dvc.yaml``), whatever the current folder: :func:`setting_path`.
* The **stores** (``mlflow.store_dir``, a relative ``sqlite:///`` ``train.storage``) start at
  :func:`store_root`: the project root, except in the temporary copy of the repository that
  ``dvc exp run --temp`` and ``--queue`` run in (``<repo>/.dvc/tmp/exps/...``, deleted
  afterwards). There DVC sets ``DVC_ROOT`` to the original repository, and the stores go to
  the same folder of it, so the experiment's MLflow runs, registered models and Optuna trials
  land in the project's stores instead of being lost with the copy. ``MLFLOW_TRACKING_URI`` and
  ``FEMCAL_OPTUNA_STORAGE`` override the stores entirely.

Paths that resolve to the same place stay as written (relative to the current folder when the
current folder is the project root), so what runs record and print does not change.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path

#: A URI scheme (``models:/``, ``runs:/``, ``s3://``, ``sqlite:///``): not a local path.
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]+:")
#: DVC's variable naming the repository root in a stage's environment (the original
#: repository's, in an experiment's temporary copy).
DVC_ROOT = "DVC_ROOT"


def project_root(params_path: str | Path) -> Path:
    """The project root: the folder holding the params file (absolute)."""
    return Path(params_path).resolve().parent


def _from(root: Path, value: str | Path) -> Path:
    """``value`` under ``root``; relative to the current folder when ``root`` is it."""
    path = Path(value).expanduser()
    if path.is_absolute():
        return path
    if root == Path.cwd().resolve():
        return path
    return root / path


def is_uri(value: str) -> bool:
    """Whether ``value`` is a URI (``models:/name@alias``, ``s3://...``), not a local path."""
    return bool(_SCHEME.match(value)) and not Path(value).exists()


def setting_path(params: Mapping, value: str | Path) -> Path:
    """A path read from ``params`` (loaded by :func:`femcal.config.load_params`), resolved.

    Relative: under the project root (the folder of ``params["_path"]``); absolute: as is.
    """
    return _from(project_root(params.get("_path", "params.yaml")), value)


def setting_uri(params: Mapping, value: str) -> str:
    """A model URI or folder read from ``params``: a folder as :func:`setting_path`, a URI as is."""
    return value if is_uri(value) else str(setting_path(params, value))


def _workspace_root(path: Path) -> Path | None:
    """The nearest folder at or above ``path`` that holds ``.dvc/`` (a DVC repository root)."""
    for folder in (path, *path.parents):
        if (folder / ".dvc").is_dir():
            return folder
    return None


def store_root(root: str | Path, environ: Mapping[str, str] | None = None) -> Path:
    """The folder the stores' relative paths start at, for the project root ``root``.

    ``root`` itself, unless it lies in a temporary copy of the repository that DVC runs an
    experiment in (``dvc exp run --temp``/``--queue``: ``<repo>/.dvc/tmp/exps/...``, with
    ``DVC_ROOT=<repo>`` in the stage's environment): then the same folder of ``<repo>``.

    Parameters
    ----------
    root : str or Path
        The project root (:func:`project_root`).
    environ : mapping, optional
        The environment (default: :data:`os.environ`).
    """
    root = Path(root).resolve()
    environ = os.environ if environ is None else environ
    original = (environ.get(DVC_ROOT) or "").strip()
    if not original:
        return root
    original_root = Path(original).resolve()
    workspace = _workspace_root(root)
    if workspace is None or workspace == original_root:
        return root
    if not workspace.is_relative_to(original_root / ".dvc" / "tmp"):
        return root  # DVC_ROOT of some other repository: not this copy's origin
    return original_root / root.relative_to(workspace)


def store_path(
    params: Mapping, value: str | Path, environ: Mapping[str, str] | None = None
) -> Path:
    """A store's folder or file read from ``params`` (``mlflow.store_dir``), resolved.

    Relative: under :func:`store_root` of the project root; absolute: as is.
    """
    root = project_root(params.get("_path", "params.yaml"))
    return _from(store_root(root, environ), value)


def store_url(params: Mapping, url: str, environ: Mapping[str, str] | None = None) -> str:
    """An SQLAlchemy URL read from ``params`` (``train.storage``): a relative SQLite file
    (``sqlite:///mlruns/optuna.db``) resolved as :func:`store_path`; other URLs as they are."""
    prefix = "sqlite:///"
    if not url.startswith(prefix) or url.startswith(prefix + "/"):
        return url
    file = url[len(prefix) :]
    if not file or file == ":memory:":
        return url
    return prefix + str(store_path(params, file, environ))
