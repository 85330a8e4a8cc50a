"""The default MLflow store follows its folder: locations a copy or move left behind, resolved.

MLflow records absolute artifact locations (experiments, runs, logged models, model versions).
After ``cp -r`` or ``mv`` of a project they still name the original folder; every start of the
default store resolves them to its own folder first (:func:`relocate_store`, called by
:func:`femcal.tracking.configure_tracking`). Plain SQLite: no MLflow import.
"""

from __future__ import annotations

import logging
import sqlite3
from pathlib import Path

logger = logging.getLogger(__name__)

#: The default store folder (``mlflow.db`` and ``artifacts/``), relative to the current folder.
DEFAULT_STORE_DIR = Path("mlruns")


#: Columns of MLflow's SQL store that hold artifact locations: (table, column).
_LOCATION_COLUMNS: tuple[tuple[str, str], ...] = (
    ("experiments", "artifact_location"),
    ("runs", "artifact_uri"),
    ("logged_models", "artifact_location"),
    ("model_versions", "source"),
    ("model_versions", "storage_location"),
)


def local_path(location: str) -> Path | None:
    """The local path of an artifact location (``file://`` URI or absolute path), or None."""
    from urllib.parse import unquote, urlparse

    if location.startswith("file:"):
        return Path(unquote(urlparse(location).path))
    if location.startswith("/"):
        return Path(location)
    return None


def _foreign_roots(db: sqlite3.Connection, root: Path) -> list[Path]:
    """Store folders other than ``root`` that this store's experiments keep artifacts in.

    femcal creates experiments with the artifact root ``<store>/artifacts``; a store whose
    experiments name ``<other>/artifacts``, with ``<other>`` a folder of the same name as
    ``root``, was copied or moved from ``<other>``.
    """
    found = set()
    for (location,) in db.execute("SELECT artifact_location FROM experiments"):
        path = local_path(str(location or ""))
        if (
            path is not None
            and path.name == "artifacts"
            and path.parent.name == root.name
            and path.parent != root
        ):
            found.add(path.parent)
    return sorted(found)


def relocate_store(store_dir: str | Path = DEFAULT_STORE_DIR) -> dict[str, int]:
    """Resolve a copied or moved default store's artifact locations to its own folder.

    MLflow records absolute locations: the experiment's artifact root, every run's artifact
    URI, every logged model's and model version's location. After ``cp -r`` or ``mv`` of a
    project these still name the original folder, so runs would be written into it and
    registered models read from it. This rewrites every location under another store folder
    ``<other>`` (found from the experiments' ``<other>/artifacts`` roots) to the same place
    under ``store_dir``, in one transaction, and does nothing when all point here already.

    Parameters
    ----------
    store_dir : str or Path
        The store folder holding ``mlflow.db`` and ``artifacts/``.

    Returns
    -------
    dict of str to int
        Rewritten values per ``"table.column"`` (empty when nothing pointed elsewhere).
    """
    root = Path(store_dir).resolve()
    db_file = root / "mlflow.db"
    if not db_file.is_file():
        return {}
    counts: dict[str, int] = {}
    db = sqlite3.connect(db_file, timeout=60, isolation_level=None)
    try:
        try:
            if not _foreign_roots(db, root):  # the usual case: a read, no lock taken
                return {}
            db.execute("BEGIN IMMEDIATE")  # one writer; re-read under the lock
            olds = _foreign_roots(db, root)
        except sqlite3.OperationalError:  # not (yet) an MLflow store: nothing to resolve
            return {}
        if not olds:  # another process resolved them while this one waited for the lock
            return {}
        pairs = []
        for old in olds:
            new = root
            pairs += [(str(old), str(new)), (old.as_uri(), new.as_uri())]
        for table, column in _LOCATION_COLUMNS:
            columns = {row[1] for row in db.execute(f"PRAGMA table_info({table})")}
            if column not in columns:
                continue
            for old_prefix, new_prefix in pairs:
                n = len(old_prefix)
                cur = db.execute(
                    f"UPDATE {table} SET {column} = ? || substr({column}, ?) "
                    f"WHERE {column} = ? OR substr({column}, 1, ?) = ?",
                    (new_prefix, n + 1, old_prefix, n + 1, old_prefix + "/"),
                )
                if cur.rowcount:
                    key = f"{table}.{column}"
                    counts[key] = counts.get(key, 0) + cur.rowcount
        db.execute("COMMIT")
    finally:
        if db.in_transaction:
            db.execute("ROLLBACK")
        db.close()
    logger.warning(
        "The MLflow store %s was copied or moved from %s: %d recorded artifact locations now "
        "point into %s (%s).",
        root,
        ", ".join(map(str, olds)),
        sum(counts.values()),
        root,
        ", ".join(f"{k} {v}" for k, v in sorted(counts.items())),
    )
    return counts
