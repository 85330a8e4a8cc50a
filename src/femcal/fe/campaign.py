"""Simulation campaigns: a design over the bounds, one FE job per configuration x load case.

A campaign turns a design (configurations in physical units) into FE jobs, runs them on Dask
(a local cluster by default, any Dask cluster by its scheduler address) and appends every
finished job to a durable store as it arrives:

* the store is a JSON-lines file, one record per finished job, appended by the client
  process with ``flush`` + ``os.fsync``: a ``kill -9`` loses nothing finished (a torn last
  line is cut off, with a warning, when the store is next opened);
* a rerun skips every job already in the store with the same job hash (configuration,
  load case, levels, solver and adapter settings): nothing finished is computed twice;
* failed simulations are records with ``status = "failed"`` and the reason (and the tail of
  the solver's log), never zeros; a failure is data and is not retried by a rerun unless
  ``retry_failed`` is set. A job whose worker raised (solver missing, worker died) is not
  stored: a rerun runs it again.

Each worker runs :func:`femcal.fe.base.simulate` in a per-job scratch folder, deleted on
success and kept for failed jobs.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import math
import os
import shutil
import socket
import tempfile
import time
import uuid
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from scipy.stats import qmc

from femcal.errors import ConfigError, InputDataError, SolverError
from femcal.fe.base import COMPRESSION, FEJob
from femcal.schema import LOAD_CASES, STATUS_FAILED, STATUS_OK
from femcal.space import ParameterSpace

logger = logging.getLogger(__name__)

#: Environment variable naming a Dask scheduler (``tcp://host:8786``) to run campaigns on.
DASK_ADDRESS_ENV_VAR = "FEMCAL_DASK_ADDRESS"
#: Version of the store's record layout.
STORE_VERSION = 1
#: How a split of a study-like design is sampled (the study: LHS for Large/Small, random Test).
SPLIT_SAMPLING: dict[str, str] = {"large": "lhs", "small": "lhs", "test": "uniform"}
#: Characters of a failed job's solver log kept in its record.
LOG_TAIL_CHARS = 2000
_LOG_SUFFIXES = (".sta", ".log", ".out", ".err", ".txt", ".cvg")


# --------------------------------------------------------------------------- designs
def latin_hypercube(space: ParameterSpace, n: int, rng: np.random.Generator) -> np.ndarray:
    """A Latin hypercube of ``n`` points over the parameter box (:class:`scipy.stats.qmc`).

    :class:`scipy.stats.qmc.LatinHypercube` draws the points in the unit cube, one per
    stratum ``[j/n, (j+1)/n)`` of every parameter, each placed at random inside its cell
    (``scramble=True``); :func:`scipy.stats.qmc.scale` maps them to the bounds.

    Parameters
    ----------
    space : ParameterSpace
        Names and bounds (physical units).
    n : int
        Number of points (>= 1).
    rng : numpy.random.Generator
        Drives the sampler (and is advanced by it): the same generator state gives the same
        points.

    Returns
    -------
    ndarray, shape (n, d)
        Physical units, within the bounds (``qmc.scale`` maps [0, 1) to [lower, upper)).
    """
    # ``seed=`` (not ``rng=``, scipy >= 1.15 only): the keyword of every scipy >= 1.11;
    # a Generator is used as is by both.
    sampler = qmc.LatinHypercube(d=space.dim, scramble=True, seed=rng)
    return qmc.scale(sampler.random(int(n)), space.lower, space.upper)


def design(
    space: ParameterSpace, n: int, rng: np.random.Generator, *, method: str = "lhs"
) -> pd.DataFrame:
    """A design of ``n`` configurations over the parameter box.

    Parameters
    ----------
    space : ParameterSpace
        Names and bounds (physical units).
    n : int
        Number of configurations (>= 1).
    rng : numpy.random.Generator
        The only source of randomness: the same generator state gives the same design.
    method : {"lhs", "uniform"}, optional
        Latin hypercube (default, :func:`latin_hypercube`) or independent uniform draws.

    Returns
    -------
    pandas.DataFrame, shape (n, 1 + d)
        ``config_id`` (0 .. n-1) and the d parameters in physical units, in ``space.names``
        order.
    """
    if int(n) < 1:
        raise ConfigError(f"A design needs at least one configuration; got n={n}.")
    if method == "lhs":
        x = latin_hypercube(space, int(n), rng)
    elif method == "uniform":
        x = space.sample_uniform(int(n), rng)
    else:
        raise ConfigError(f"Unknown design method {method!r}; use 'lhs' or 'uniform'.")
    x = space.clip(x)  # guard against rounding at the upper bound
    df = pd.DataFrame(x, columns=list(space.names))
    df.insert(0, "config_id", np.arange(int(n), dtype=np.int64))
    return df


def split_design(space: ParameterSpace, counts: Mapping[str, int], seed: int) -> pd.DataFrame:
    """One design holding the splits of a study-like dataset (Large, Small, Test).

    Every split is sampled with its own generator ``default_rng([seed, k])`` (k = index of
    the split name in ``("large", "small", "test")``), so changing one split's size leaves
    the others unchanged. Large and Small are Latin hypercubes, Test is uniform random, as in
    the study (:data:`SPLIT_SAMPLING`).

    Parameters
    ----------
    space : ParameterSpace
    counts : mapping of str to int
        Configurations per split, e.g. ``{"large": 96, "small": 24, "test": 16}``.
    seed : int

    Returns
    -------
    pandas.DataFrame, shape (sum(counts), 2 + d)
        ``config_id`` (0 .. N-1 over all splits, in split order), ``split`` and the
        parameters.
    """
    order = list(SPLIT_SAMPLING)
    unknown = sorted(set(counts) - set(order))
    if unknown:
        raise ConfigError(
            f"Unknown split(s) {unknown} in fe.splits; use {order} (the study's folders)."
        )
    frames = []
    for k, name in enumerate(order):
        n = int(counts.get(name, 0) or 0)
        if n < 0:
            raise ConfigError(f"fe.splits.{name} must be a number of configurations >= 0.")
        if n == 0:
            continue
        part = design(space, n, np.random.default_rng([int(seed), k]), method=SPLIT_SAMPLING[name])
        part.insert(1, "split", name)
        frames.append(part)
    if not frames:
        raise ConfigError("fe.splits asks for no configurations; give at least one split > 0.")
    df = pd.concat(frames, ignore_index=True)
    df["config_id"] = np.arange(len(df), dtype=np.int64)
    return df


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
def _nan_to_none(values: Sequence[float]) -> list[float | None]:
    return [None if (v is None or not math.isfinite(float(v))) else float(v) for v in values]


class CampaignStore:
    """An append-only JSON-lines file of finished jobs (one record per line).

    Parameters
    ----------
    path : Path
        The ``.jsonl`` file; created with its folder when first written.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fh: Any = None

    # reading ---------------------------------------------------------------
    def read(self) -> list[dict]:
        """All records, in file order; a torn last line (killed writer) is skipped.

        Raises
        ------
        InputDataError
            A line other than the last is not a JSON record (the file was edited or
            corrupted): the message names the file and line.
        """
        if not self.path.is_file():
            return []
        raw = self.path.read_bytes()
        lines = raw.split(b"\n")
        records: list[dict] = []
        for i, line in enumerate(lines):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
                if not isinstance(rec, dict) or "job_hash" not in rec:
                    raise ValueError("not a job record")
            except ValueError:
                last = i == len(lines) - 1 or all(not x.strip() for x in lines[i + 1 :])
                if last:
                    logger.warning(
                        "%s: ignoring a torn last line (%d bytes; a writer was killed while "
                        "appending); that job will run again.",
                        self.path,
                        len(line),
                    )
                    continue
                raise InputDataError(
                    f"{self.path}, line {i + 1}: not a job record of a campaign store. The "
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

        Raises
        ------
        ConfigError
            Another process holds the store open for writing.
        """
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(self.path, "a+b")  # noqa: SIM115 - closed below
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
            yield self
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
            self.path,
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
        "finished_at",
        "job_hash",
        "settings_hash",
        "campaign_run",
    ]
    df = pd.DataFrame([{c: r.get(c) for c in columns} for r in records], columns=columns)
    if len(df):
        df["config_id"] = df["config_id"].astype(np.int64)
    return df


# --------------------------------------------------------------------- worker side
_ADAPTERS: dict[str, Any] = {}


def _adapter(name: str, settings: Mapping[str, Any], digest: str) -> Any:
    """One adapter instance per worker process and settings."""
    from femcal.fe.base import make_solver

    if digest not in _ADAPTERS:
        _ADAPTERS[digest] = make_solver(name, **dict(settings))
    return _ADAPTERS[digest]


def _log_tail(folder: Path) -> str:
    """The last characters of the newest solver log in ``folder`` (recursive), or ''."""
    try:
        files = [p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in _LOG_SUFFIXES]
    except OSError:
        return ""
    if not files:
        return ""
    newest = max(files, key=lambda p: p.stat().st_mtime)
    try:
        text = newest.read_text(errors="replace")
    except OSError:
        return ""
    return f"[{newest.name}] " + text[-LOG_TAIL_CHARS:]


def run_job(
    solver: str,
    settings: Mapping[str, Any],
    digest: str,
    job: FEJob,
    job_digest: str,
    scratch_root: str | None,
    keep_failed: bool,
) -> dict:
    """Run one job on a worker; return its store record (the client appends it).

    Parameters
    ----------
    solver, settings, digest
        Adapter registry name, its settings and their :func:`settings_hash`.
    job : FEJob
    job_digest : str
        :func:`job_hash` of the job.
    scratch_root : str or None
        Folder for per-job scratch folders (None: the worker's temporary folder).
    keep_failed : bool
        Keep the scratch folder of a failed job (its path is in the record).

    Returns
    -------
    dict
        The record: job inputs, status, reason, outputs per level (None for NaN), solver
        version, deck hash, attempts, CPU and wall seconds, worker, host.
    """
    from femcal.fe.base import simulate

    os.environ["OMP_NUM_THREADS"] = "1"
    root = Path(scratch_root) if scratch_root else Path(tempfile.gettempdir()) / "femcal-fe"
    workdir = root / f"{job.key}-{job_digest[:10]}-{uuid.uuid4().hex[:8]}"
    workdir.mkdir(parents=True, exist_ok=True)
    started = time.time()
    py_cpu = time.process_time()
    adapter = _adapter(solver, settings, digest)
    result = simulate(adapter, job, workdir)
    py_cpu = time.process_time() - py_cpu  # deck writing and parsing (the worker's own CPU)
    try:
        from distributed import get_worker

        worker = str(get_worker().address)
    except (ImportError, ValueError):
        worker = "local"
    record: dict[str, Any] = {
        "v": STORE_VERSION,
        "job_hash": job_digest,
        "settings_hash": digest,
        "config_id": int(job.config_id),
        "load_case": job.load_case,
        "levels": [float(v) for v in job.levels],
        "parameters": {k: float(v) for k, v in job.parameters.items()},
        "status": STATUS_OK if result.ok else STATUS_FAILED,
        "reason": str(result.reason or ""),
        "rom_deg": _nan_to_none(np.asarray(result.rom_deg, dtype=float).tolist()),
        "idp_mpa": _nan_to_none(np.asarray(result.idp_mpa, dtype=float).tolist()),
        "solver": solver,
        "solver_version": str(result.solver_version),
        "deck_hash": str(result.deck_hash),
        "attempts": int(result.attempts),
        "cpu_seconds": float(result.cpu_seconds),
        "worker_cpu_seconds": float(py_cpu),
        "wall_seconds": float(result.wall_seconds),
        "worker": worker,
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "started_at": started,
        "finished_at": time.time(),
    }
    if result.ok:
        shutil.rmtree(workdir, ignore_errors=True)
    else:
        record["log_tail"] = _log_tail(workdir)
        if keep_failed:
            record["scratch"] = str(workdir)
        else:
            shutil.rmtree(workdir, ignore_errors=True)
    return record


# --------------------------------------------------------------------- client side
@dataclass
class CampaignResult:
    """What a campaign did.

    Attributes
    ----------
    store : Path
        The JSON-lines store.
    records : pandas.DataFrame
        One row per job of this campaign's design (see :func:`records_frame`), from the store.
    n_jobs, n_skipped, n_run : int
        Jobs of the design; already in the store (not recomputed); run now.
    errors : list of str
        Jobs whose worker raised (not stored; a rerun runs them).
    wall_seconds : float
        Wall time of this call (cluster start-up included).
    n_workers : int
        Worker threads of the cluster used.
    scheduler : str
        Address of the Dask scheduler used.
    """

    store: Path
    records: pd.DataFrame
    n_jobs: int
    n_skipped: int
    n_run: int
    errors: list[str] = field(default_factory=list)
    wall_seconds: float = 0.0
    n_workers: int = 0
    scheduler: str = ""

    @property
    def complete(self) -> bool:
        """Every job of the design is in the store."""
        return len(self.records) == self.n_jobs

    @property
    def failure_rate(self) -> float:
        """Fraction of stored jobs with status failed (NaN when none is stored)."""
        if not len(self.records):
            return float("nan")
        return float(np.mean(self.records["status"] == STATUS_FAILED))

    def failures(self) -> pd.DataFrame:
        """``config_id, load_case, reason, attempts`` of every failed job."""
        df = self.records[self.records["status"] == STATUS_FAILED]
        return df[["config_id", "load_case", "reason", "attempts"]].reset_index(drop=True)

    def cpu_seconds_per_config(self) -> pd.Series:
        """Solver CPU seconds per configuration (summed over its load cases and attempts)."""
        return self.records.groupby("config_id")["cpu_seconds"].sum()

    def summary(self) -> dict[str, Any]:
        """JSON-ready figures: counts, failure rate and reasons, CPU seconds per configuration."""
        cpu = self.cpu_seconds_per_config()
        return {
            "n_jobs": self.n_jobs,
            "n_stored": int(len(self.records)),
            "n_skipped": self.n_skipped,
            "n_run": self.n_run,
            "n_errors": len(self.errors),
            "n_failed": int((self.records["status"] == STATUS_FAILED).sum()),
            "failure_rate": self.failure_rate,
            "failures": self.failures().to_dict(orient="records"),
            "cpu_seconds_per_config_mean": float(cpu.mean()) if len(cpu) else float("nan"),
            "cpu_seconds_total": float(self.records["cpu_seconds"].sum()),
            "wall_seconds": self.wall_seconds,
            "n_workers": self.n_workers,
            "solver_versions": sorted(set(self.records["solver_version"].dropna().astype(str))),
        }


def scheduler_address_from_env(environ: Mapping[str, str] = os.environ) -> str | None:
    """The Dask scheduler named by ``FEMCAL_DASK_ADDRESS``, or None."""
    return environ.get(DASK_ADDRESS_ENV_VAR, "").strip() or None


@contextlib.contextmanager
def dask_client(scheduler_address: str | None, n_workers: int) -> Iterator[Any]:
    """A Dask client: on ``scheduler_address``, or on a new local cluster of processes.

    The local cluster has ``n_workers`` single-threaded worker processes (one FE solver
    each, ``OMP_NUM_THREADS=1``) and no dashboard.
    """
    from distributed import Client, LocalCluster

    if scheduler_address:
        try:
            client = Client(scheduler_address, timeout="30s")
        except OSError as exc:
            raise ConfigError(
                f"Cannot reach the Dask scheduler at {scheduler_address} ({exc}). Start the "
                f"cluster, or unset fe.scheduler_address / {DASK_ADDRESS_ENV_VAR} to use a "
                "local cluster."
            ) from None
        with client:
            yield client
        return
    if int(n_workers) < 1:
        raise ConfigError(f"fe.n_workers must be >= 1; got {n_workers}.")
    cluster = LocalCluster(
        n_workers=int(n_workers),
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=logging.ERROR,
        env={"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"},
    )
    with cluster, Client(cluster) as client:
        yield client


def _abort_error(exc: BaseException) -> bool:
    """Errors that would repeat for every job: stop the campaign at once."""
    return isinstance(exc, (SolverError, ConfigError, ImportError))


def run_campaign(
    adapter_name: str,
    adapter_settings: Mapping[str, Any],
    design_df: pd.DataFrame,
    *,
    store: str | Path,
    names: Sequence[str] | None = None,
    load_cases: Sequence[str] = LOAD_CASES,
    moments: Sequence[float] = (1.0, 2.0, 3.0, 4.0, 5.0),
    forces: Sequence[float] = (),
    scheduler_address: str | None = None,
    n_workers: int = 2,
    scratch_dir: str | Path | None = None,
    keep_failed: bool = True,
    retry_failed: bool = False,
    progress: bool = True,
) -> CampaignResult:
    """Run every job of a design on Dask, appending each result to the store as it arrives.

    Parameters
    ----------
    adapter_name : str
        Registry name of the solver adapter (``"calculix"``).
    adapter_settings : mapping
        Keyword arguments of the adapter (e.g. ``{"geometry": "coarse"}``); part of the
        job hash.
    design_df : pandas.DataFrame, shape (n, >= 1 + d)
        ``config_id`` and the parameters (see :func:`design`).
    store : str or Path
        The JSON-lines store (created if missing; resumed if present).
    names : sequence of str, optional
        Parameter columns; default: the study's 13 parameters.
    load_cases : sequence of str, optional
        Load cases per configuration (default: the four pure moments).
    moments, forces : sequence of float, optional
        Levels of the pure-moment load cases (Nm) and of ``"Compression"`` (N).
    scheduler_address : str, optional
        Dask scheduler to use; None: ``FEMCAL_DASK_ADDRESS``, else a local cluster.
    n_workers : int, optional
        Worker processes of the local cluster.
    scratch_dir : str or Path, optional
        Parent of the per-job scratch folders (default: the worker's temporary folder).
    keep_failed : bool, optional
        Keep failed jobs' scratch folders.
    retry_failed : bool, optional
        Run stored failed jobs again (default: a failure is a result and is kept).
    progress : bool, optional
        tqdm progress bar.

    Returns
    -------
    CampaignResult

    Raises
    ------
    SolverError
        Some jobs could not run (worker raised); the finished ones are in the store and a
        rerun resumes.
    """
    from femcal.schema import PARAMETER_NAMES

    t0 = time.perf_counter()
    names = list(names or PARAMETER_NAMES)
    digest = settings_hash(adapter_name, adapter_settings)
    jobs = make_jobs(design_df, names, load_cases=load_cases, moments=moments, forces=forces)
    hashes = [job_hash(job, digest) for job in jobs]
    if len(set(hashes)) != len(hashes):
        raise InputDataError("The design holds the same job twice (same config_id and inputs).")
    cstore = CampaignStore(store)
    address = scheduler_address or scheduler_address_from_env()
    run_id = uuid.uuid4().hex
    errors: list[str] = []
    n_run = 0
    n_workers_used = 0
    with cstore.writer():
        done = cstore.finished(include_failed=not retry_failed)
        todo = [(job, h) for job, h in zip(jobs, hashes) if h not in done]
        n_skipped = len(jobs) - len(todo)
        if n_skipped:
            logger.info(
                "%s: %d of %d jobs already finished; running the other %d.",
                cstore.path,
                n_skipped,
                len(jobs),
                len(todo),
            )
        if todo:
            from distributed import as_completed
            from tqdm.auto import tqdm

            with dask_client(address, n_workers) as client:
                n_workers_used = sum(client.nthreads().values())
                scheduler = str(client.scheduler.address)
                futures = {
                    client.submit(
                        run_job,
                        adapter_name,
                        dict(adapter_settings),
                        digest,
                        job,
                        h,
                        None if scratch_dir is None else str(scratch_dir),
                        keep_failed,
                        key=f"femcal-fe-{job.key}-{h[:10]}-{run_id[:8]}",
                        pure=False,
                        retries=0,
                    ): job
                    for job, h in todo
                }
                bar = tqdm(
                    total=len(jobs),
                    initial=n_skipped,
                    desc="FE campaign",
                    unit="job",
                    disable=not progress,
                )
                try:
                    for fut in as_completed(futures):
                        job = futures[fut]
                        try:
                            record = fut.result()
                        except Exception as exc:  # noqa: BLE001 - reported below
                            errors.append(f"{job.key}: {type(exc).__name__}: {exc}")
                            logger.error("FE job %s did not run: %s", job.key, exc)
                            if _abort_error(exc):
                                for other in futures:
                                    other.cancel()
                                break
                            continue
                        record["campaign_run"] = run_id
                        cstore.append(record)
                        n_run += 1
                        bar.update(1)
                        if record["status"] != STATUS_OK:
                            logger.warning("FE job %s failed: %s", job.key, record["reason"])
                finally:
                    bar.close()
        else:
            scheduler = address or ""
    stored = cstore.finished()
    records = [stored[h] for h in hashes if h in stored]
    result = CampaignResult(
        store=cstore.path,
        records=records_frame(records),
        n_jobs=len(jobs),
        n_skipped=n_skipped,
        n_run=n_run,
        errors=errors,
        wall_seconds=time.perf_counter() - t0,
        n_workers=n_workers_used,
        scheduler=scheduler,
    )
    if errors:
        raise SolverError(
            f"{len(errors)} of {len(todo)} FE jobs could not run (first: {errors[0]}). The "
            f"{n_run} finished jobs are in {cstore.path}; fix the cause and rerun to resume."
        )
    return result


def load_records(store: str | Path, hashes: Sequence[str] | None = None) -> list[dict]:
    """Stored records (the last one per job), optionally only those of ``hashes`` in order."""
    stored = CampaignStore(store).finished()
    if hashes is None:
        return list(stored.values())
    return [stored[h] for h in hashes if h in stored]
