"""The campaign store: one JSON line per finished job, keyed by a hash of its inputs, so that a
killed campaign resumes without recomputing or duplicating anything."""

from __future__ import annotations

import contextlib
import fcntl
import gzip
import hashlib
import json
import logging
import os
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.errors import ConfigError, InputDataError
from femcal.fe.base import COMPRESSION, FEJob
from femcal.schema import STATUS_OK

logger = logging.getLogger(__name__)

#: Version of the store's record layout.
STORE_VERSION = 1
#: A ``.gz`` store starts a new segment once its last one holds this many compressed bytes
#: (each committed file stays under the repository's 2 MB limit).
SEGMENT_BYTES = 1_500_000


# ------------------------------------------------------------------------- job keys
def _canonical(value: Any) -> Any:
    """JSON-ready, deterministic form (floats by repr, mappings sorted)."""
    if isinstance(value, Mapping):
        return {str(k): _canonical(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, Path):
        return str(value)
    return value


def settings_hash(solver: str, settings: Mapping[str, Any]) -> str:
    """SHA-256 of the solver name and its adapter settings (everything that shapes a deck)."""
    text = json.dumps(_canonical({"solver": solver, "settings": dict(settings)}), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def job_hash(job: FEJob, settings_digest: str) -> str:
    """SHA-256 identifying a job's inputs: configuration, load case, levels and settings."""
    text = json.dumps(
        _canonical(
            {
                "config_id": int(job.config_id),
                "parameters": dict(job.parameters),
                "load_case": job.load_case,
                "levels": list(job.levels),
                "settings": settings_digest,
            }
        ),
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()


def make_jobs(
    design_df: pd.DataFrame,
    names: Sequence[str],
    *,
    load_cases: Sequence[str],
    moments: Sequence[float],
    forces: Sequence[float] = (),
) -> list[FEJob]:
    """The jobs of a design: every configuration under every load case.

    Parameters
    ----------
    design_df : pandas.DataFrame, shape (n, >= 1 + d)
        ``config_id`` and the parameters ``names``.
    names : sequence of str, length d
    load_cases : sequence of str
        Pure-moment load cases (levels = ``moments``, Nm) and/or ``"Compression"`` (levels =
        ``forces``, N).
    moments, forces : sequence of float

    Returns
    -------
    list of FEJob, length n * len(load_cases)
        Configuration-major order.
    """
    missing = [c for c in ("config_id", *names) if c not in design_df.columns]
    if missing:
        raise InputDataError(
            f"The design lacks the columns {missing}; it needs config_id and every parameter."
        )
    if design_df["config_id"].duplicated().any():
        raise InputDataError("The design repeats config_id values; each configuration once.")
    if COMPRESSION in load_cases and not len(forces):
        raise ConfigError(f"Load case {COMPRESSION} needs forces (N); none given.")
    jobs = []
    for row in design_df.itertuples(index=False):
        rec = row._asdict()
        params = {n: float(rec[n]) for n in names}
        for lc in load_cases:
            levels = forces if lc == COMPRESSION else moments
            jobs.append(
                FEJob(
                    config_id=int(rec["config_id"]),
                    parameters=params,
                    load_case=str(lc),
                    levels=tuple(float(v) for v in levels),
                )
            )
    return jobs


# ---------------------------------------------------------------------------- store
class CampaignStore:
    """An append-only JSON-lines store of finished jobs (one record per line).

    Parameters
    ----------
    path : Path
        A ``.jsonl`` file, created with its folder when first written. Or a ``.jsonl.gz``
        file, the form to commit (about 4x smaller): finished jobs are then appended to a
        plain journal beside it (the same name without ``.gz``), which is folded into the
        compressed file every ``fold_every`` records and when the writer closes. A journal
        left by a killed writer is read with the compressed file and folded by the next one.
        A compressed store is a chain of segments: ``runs.jsonl.gz``, then ``runs-002.jsonl.gz``,
        ``runs-003.jsonl.gz`` ... (:meth:`segments`); a fold rewrites only the last one, and
        starts the next once the last holds ``segment_bytes`` compressed bytes, so a growing
        campaign adds files instead of rewriting (and re-committing) one large file.
    fold_every : int
        Records appended between two folds of the journal (``.gz`` stores only).
    segment_bytes : int
        Compressed size at which a ``.gz`` store starts a new segment.
    """

    def __init__(
        self, path: str | Path, *, fold_every: int = 50, segment_bytes: int = SEGMENT_BYTES
    ) -> None:
        self.path = Path(path)
        self.compressed = self.path.suffix == ".gz"
        #: The plain file that is appended to (the store itself unless it is compressed).
        self.journal = self.path.with_suffix("") if self.compressed else self.path
        self.fold_every = int(fold_every)
        self.segment_bytes = int(segment_bytes)
        self._fh: Any = None
        self._since_fold = 0

    # reading ---------------------------------------------------------------
    def segment_path(self, k: int) -> Path:
        """The ``k``-th segment of a ``.gz`` store (1: the store's own path)."""
        if k == 1:
            return self.path
        plain = Path(self.path.name[: -len(".gz")])
        return self.path.with_name(f"{plain.stem}-{k:03d}{plain.suffix}.gz")

    def segments(self) -> list[Path]:
        """The segments of a ``.gz`` store that exist, in order (empty for a plain store).

        Raises
        ------
        InputDataError
            A segment is missing between two present ones (a file was deleted or not
            checked out): the message names it.
        """
        if not self.compressed:
            return []
        found = []
        k = 1
        while self.segment_path(k).is_file():
            found.append(self.segment_path(k))
            k += 1
        plain = Path(self.path.name[: -len(".gz")])
        later = sorted(self.path.parent.glob(f"{plain.stem}-[0-9][0-9][0-9]{plain.suffix}.gz"))
        stray = [p for p in later if p not in found]
        if stray:
            raise InputDataError(
                f"{self.segment_path(k)}: a segment of the campaign store is missing, but "
                f"later ones exist ({', '.join(p.name for p in stray)}). Restore it from git "
                "(git checkout -- <file>), or delete the later segments to run their jobs again."
            )
        return found

    @staticmethod
    def _gunzip(path: Path) -> bytes:
        try:
            with gzip.open(path, "rb") as fh:
                data = fh.read()
        except (OSError, EOFError) as exc:
            raise InputDataError(
                f"{path}: not a readable gzip file ({exc}). Restore it from git "
                "(git checkout -- <file>) or delete it to run its jobs again."
            ) from None
        return data if not data or data.endswith(b"\n") else data + b"\n"

    def _sealed_bytes(self) -> bytes:
        """The decompressed content of a ``.gz`` store's segments (empty if there is none)."""
        return b"".join(self._gunzip(p) for p in self.segments())

    def read(self) -> list[dict]:
        """All records, in file order; a torn last line (killed writer) is skipped.

        Raises
        ------
        InputDataError
            A line other than the journal's last is not a JSON record (the file was edited
            or corrupted), or a ``.gz`` store is not gzip: the message names the file and
            line.
        """
        records: list[dict] = []
        known: set[bytes] = set()
        for segment in self.segments():
            lines = self._gunzip(segment).split(b"\n")
            records += self._parse(segment, lines, torn_ok=False)
            known.update(lines)
        if self.journal.is_file():
            lines = self.journal.read_bytes().split(b"\n")
            # Lines already folded (a kill between the fold's rename and truncate): read once.
            records += self._parse(self.journal, lines, torn_ok=True, skip=known)
        return records

    def _parse(
        self, path: Path, lines: list[bytes], *, torn_ok: bool, skip: set[bytes] | None = None
    ) -> list[dict]:
        records: list[dict] = []
        for i, line in enumerate(lines):
            if not line.strip() or (skip and line in skip):
                continue
            try:
                rec = json.loads(line)
                if not isinstance(rec, dict) or "job_hash" not in rec:
                    raise ValueError("not a job record")
            except ValueError:
                last = i == len(lines) - 1 or all(not x.strip() for x in lines[i + 1 :])
                if last and torn_ok:
                    logger.warning(
                        "%s: ignoring a torn last line (%d bytes; a writer was killed while "
                        "appending); that job will run again.",
                        path,
                        len(line),
                    )
                    continue
                raise InputDataError(
                    f"{path}, line {i + 1}: not a job record of a campaign store. The "
                    "file was edited or corrupted; delete that line (the job will run again) "
                    "or restore the file."
                ) from None
            records.append(rec)
        return records

    def finished(self, *, include_failed: bool = True) -> dict[str, dict]:
        """The last record of every stored job, keyed by job hash."""
        out: dict[str, dict] = {}
        for rec in self.read():
            if include_failed or rec.get("status") == STATUS_OK:
                out[rec["job_hash"]] = rec
        return out

    # writing ---------------------------------------------------------------
    @contextlib.contextmanager
    def writer(self) -> Iterator[CampaignStore]:
        """Open for appending: an exclusive lock, and a torn last line cut off first.

        A ``.gz`` store folds its journal on opening (a killed writer's records) and on
        closing.

        Raises
        ------
        ConfigError
            Another process holds the store open for writing.
        """
        self.journal.parent.mkdir(parents=True, exist_ok=True)
        fh = open(self.journal, "a+b")  # noqa: SIM115 - closed below
        try:
            try:
                fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise ConfigError(
                    f"The campaign store {self.path} is in use by another campaign process; "
                    "wait for it to finish, or give this campaign another store path."
                ) from None
            self._repair(fh)
            self._fh = fh
            self.fold()
            yield self
            self.fold()
            if self.compressed and os.fstat(fh.fileno()).st_size == 0:
                self.journal.unlink(missing_ok=True)
        finally:
            self._fh = None
            fh.close()  # releases the lock

    def _repair(self, fh: Any) -> None:
        fh.seek(0, os.SEEK_END)
        size = fh.tell()
        if size == 0:
            return
        fh.seek(max(0, size - 1))
        if fh.read(1) == b"\n":
            return
        fh.seek(0)
        data = fh.read()
        keep = data.rfind(b"\n") + 1
        logger.warning(
            "%s: cutting off a torn last line (%d bytes) left by a killed writer.",
            self.journal,
            size - keep,
        )
        fh.truncate(keep)
        fh.flush()
        os.fsync(fh.fileno())

    def append(self, record: Mapping[str, Any]) -> None:
        """Append one record durably (``write``, ``flush``, ``os.fsync``)."""
        if self._fh is None:
            raise RuntimeError("CampaignStore.append outside `with store.writer():`")
        line = json.dumps(record, allow_nan=False, separators=(",", ":"), default=str)
        self._fh.write(line.encode() + b"\n")
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._since_fold += 1
        if self._since_fold >= self.fold_every:
            self.fold()

    def fold(self) -> None:
        """Move the journal's records into the ``.gz`` store (atomically; no-op if plain).

        The last segment (a new one once the last holds ``segment_bytes``) is rewritten to a
        temporary file, synced and renamed over the old one; only then is the journal emptied,
        so a kill at any point loses nothing (records in both files are read once). The gzip
        header carries no time stamp, so the same records give the same bytes.
        """
        if self._fh is None:
            raise RuntimeError("CampaignStore.fold outside `with store.writer():`")
        self._since_fold = 0
        if not self.compressed:
            return
        self._fh.seek(0)
        journal = self._fh.read()
        if not journal.strip():
            return
        segments = self.segments()
        known = set(self._sealed_bytes().split(b"\n"))
        new = [ln for ln in journal.split(b"\n") if ln.strip() and ln not in known]
        last = segments[-1] if segments else self.path
        if segments and last.stat().st_size >= self.segment_bytes:
            last = self.segment_path(len(segments) + 1)
        sealed = self._gunzip(last) if last.is_file() else b""
        tmp = last.with_name(last.name + ".tmp")
        with open(tmp, "wb") as raw:
            with gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0) as gz:
                gz.write(sealed + b"".join(ln + b"\n" for ln in new))
            raw.flush()
            os.fsync(raw.fileno())
        os.replace(tmp, last)
        self._fh.truncate(0)
        self._fh.flush()
        os.fsync(self._fh.fileno())
        logger.info("%s: folded %d journal records into the store.", last, len(new))


def records_frame(records: Sequence[Mapping[str, Any]]) -> pd.DataFrame:
    """Store records as a table (one row per job; arrays kept as lists)."""
    columns = [
        "config_id",
        "load_case",
        "status",
        "reason",
        "levels",
        "rom_deg",
        "idp_mpa",
        "solver",
        "solver_version",
        "deck_hash",
        "attempts",
        "cpu_seconds",
        "worker_cpu_seconds",
        "wall_seconds",
        "worker",
        "host",
        "started_at",
        "finished_at",
        "job_hash",
        "settings_hash",
        "campaign_run",
    ]
    df = pd.DataFrame([{c: r.get(c) for c in columns} for r in records], columns=columns)
    if len(df):
        df["config_id"] = df["config_id"].astype(np.int64)
    return df


def load_records(store: str | Path, hashes: Sequence[str] | None = None) -> list[dict]:
    """Stored records (the last one per job), optionally only those of ``hashes`` in order."""
    stored = CampaignStore(store).finished()
    if hashes is None:
        return list(stored.values())
    return [stored[h] for h in hashes if h in stored]
