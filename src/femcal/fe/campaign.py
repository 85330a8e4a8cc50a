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
  ``retry_failed`` says so (every failure, or those a predicate picks, e.g.
  :func:`timed_out`: a record made under a wall-clock limit depends on the machine's load).
  A job whose worker raised (solver missing, worker died) is not stored: a rerun runs it
  again.

Each worker runs :func:`femcal.fe.base.simulate` in a per-job scratch folder, deleted on
success and kept for failed jobs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import shutil
import socket
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from femcal.errors import ConfigError, InputDataError, SolverError
from femcal.fe.base import FEJob
from femcal.fe.options import CampaignOptions
from femcal.fe.store import (
    STORE_VERSION,
    CampaignStore,
    job_hash,
    make_jobs,
    records_frame,
    settings_hash,
)
from femcal.schema import LOAD_CASES, STATUS_FAILED, STATUS_OK

logger = logging.getLogger(__name__)

#: Environment variable naming a Dask scheduler (``tcp://host:8786``) to run campaigns on.
DASK_ADDRESS_ENV_VAR = "FEMCAL_DASK_ADDRESS"
#: Characters of a failed job's solver log kept in its record.
LOG_TAIL_CHARS = 2000
_LOG_SUFFIXES = (".sta", ".log", ".out", ".err", ".txt", ".cvg")


# --------------------------------------------------------------------- worker side
_ADAPTERS: dict[str, Any] = {}


def _nan_to_none(values: Sequence[float]) -> list[float | None]:
    """``values`` as JSON-ready floats, None where NaN, infinite or None."""
    return [None if (v is None or not math.isfinite(float(v))) else float(v) for v in values]


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
@dataclass(frozen=True)
class PerConfigSettings:
    """Adapter settings that differ between configurations (e.g. posterior elements).

    Attributes
    ----------
    base : mapping
        Keyword arguments of the adapter shared by every configuration.
    by_config : mapping of int to mapping
        ``config_id`` -> keyword arguments that override ``base`` for that configuration
        (absent: ``base`` alone).
    """

    base: Mapping[str, Any]
    by_config: Mapping[int, Mapping[str, Any]] = field(default_factory=dict)

    def of(self, config_id: int) -> dict[str, Any]:
        """The adapter settings of one configuration."""
        return {**dict(self.base), **dict(self.by_config.get(int(config_id), {}))}


def _settings_of(
    adapter_settings: Mapping[str, Any] | PerConfigSettings, config_id: int
) -> dict[str, Any]:
    if isinstance(adapter_settings, PerConfigSettings):
        return adapter_settings.of(config_id)
    return dict(adapter_settings)


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
    each, ``OMP_NUM_THREADS=1``); its dashboard listens on a free port, so that two clusters
    on one machine do not compete for Dask's default 8787 (``None`` does not turn it off:
    dask/distributed#8136).
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
        dashboard_address=":0",
        silence_logs=logging.ERROR,
        env={"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"},
    )
    with cluster, Client(cluster) as client:
        yield client


def timed_out(record: Mapping[str, Any]) -> bool:
    """Whether a stored job failed on its time limit (``retry_failed=timed_out``)."""
    return record.get("status") != STATUS_OK and str(record.get("reason", "")).startswith(
        "timeout after"
    )


def _abort_error(exc: BaseException) -> bool:
    """Errors that would repeat for every job: stop the campaign at once."""
    return isinstance(exc, (SolverError, ConfigError, ImportError))


def run_campaign(
    adapter_name: str,
    adapter_settings: Mapping[str, Any] | PerConfigSettings,
    design_df: pd.DataFrame,
    options: CampaignOptions | None = None,
    *,
    store: str | Path,
    names: Sequence[str] | None = None,
    load_cases: Sequence[str] = LOAD_CASES,
    moments: Sequence[float] = (1.0, 2.0, 3.0, 4.0, 5.0),
    forces: Sequence[float] = (),
    **overrides: Any,
) -> CampaignResult:
    """Run every job of a design on Dask, appending each result to the store as it arrives.

    Parameters
    ----------
    adapter_name : str
        Registry name of the solver adapter (``"calculix"``).
    adapter_settings : mapping or PerConfigSettings
        Keyword arguments of the adapter (e.g. ``{"geometry": "coarse"}``), the same for
        every configuration or per configuration; part of the job hash.
    design_df : pandas.DataFrame, shape (n, >= 1 + d)
        ``config_id`` and the parameters (see :func:`design`).
    options : CampaignOptions, optional
        Cluster, scratch folders, retries and progress bar (default:
        :class:`~femcal.fe.options.CampaignOptions`'s).
    store : str or Path
        The JSON-lines store (created if missing; resumed if present).
    names : sequence of str, optional
        Parameter columns; default: the study's 13 parameters.
    load_cases : sequence of str, optional
        Load cases per configuration (default: the four pure moments).
    moments, forces : sequence of float, optional
        Levels of the pure-moment load cases (Nm) and of ``"Compression"`` (N).
    **overrides
        Fields of :class:`~femcal.fe.options.CampaignOptions` replacing those of ``options``
        (``n_workers=1``, ``progress=False``, ...).

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

    o = dataclasses.replace(options or CampaignOptions(), **overrides)
    t0 = time.perf_counter()
    names = list(names or PARAMETER_NAMES)
    jobs = make_jobs(design_df, names, load_cases=load_cases, moments=moments, forces=forces)
    job_settings = [_settings_of(adapter_settings, job.config_id) for job in jobs]
    digests = [settings_hash(adapter_name, settings) for settings in job_settings]
    hashes = [job_hash(job, digest) for job, digest in zip(jobs, digests)]
    if len(set(hashes)) != len(hashes):
        raise InputDataError("The design holds the same job twice (same config_id and inputs).")
    cstore = CampaignStore(store)
    address = o.scheduler_address or scheduler_address_from_env()
    errors: list[str] = []
    n_run = 0
    n_workers_used = 0
    with cstore.writer():
        done = _finished(cstore, o.retry_failed)
        todo = [
            (job, h, settings, digest)
            for job, h, settings, digest in zip(jobs, hashes, job_settings, digests)
            if h not in done
        ]
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
            n_run, n_workers_used, scheduler = _run_jobs(
                adapter_name, todo, cstore, address, o, (len(jobs), n_skipped), errors
            )
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


def _finished(
    cstore: CampaignStore, retry_failed: bool | Callable[[Mapping[str, Any]], bool]
) -> dict[str, dict]:
    """The stored jobs not to run again, by job hash: every success, and the failures
    ``retry_failed`` does not pick (all of them when it is False, none when True)."""
    if callable(retry_failed):
        return {
            h: rec
            for h, rec in cstore.finished().items()
            if rec.get("status") == STATUS_OK or not retry_failed(rec)
        }
    return cstore.finished(include_failed=not retry_failed)


#: A job to run: the job, its hash, its adapter settings and their hash.
_Todo = tuple[FEJob, str, Mapping[str, Any], str]


def _run_jobs(
    adapter_name: str,
    todo: Sequence[_Todo],
    cstore: CampaignStore,
    address: str | None,
    o: CampaignOptions,
    counts: tuple[int, int],
    errors: list[str],
) -> tuple[int, int, str]:
    """Run ``todo`` on a Dask cluster, appending each record to the store as it arrives.

    ``counts`` are the design's jobs and those skipped (for the progress bar). A job whose
    worker raised goes to ``errors``; an error that would repeat for every job cancels the
    rest. Returns the jobs run, the cluster's worker threads and the scheduler's address.
    """
    from distributed import as_completed
    from tqdm.auto import tqdm

    run_id = uuid.uuid4().hex
    n_run = 0
    n_jobs, n_skipped = counts
    with dask_client(address, o.n_workers) as client:
        n_workers_used = sum(client.nthreads().values())
        scheduler = str(client.scheduler.address)
        futures = _submit(client, adapter_name, todo, o, run_id)
        bar = tqdm(
            total=n_jobs,
            initial=n_skipped,
            desc="FE campaign",
            unit="job",
            disable=not o.progress,
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
    return n_run, n_workers_used, scheduler


def _submit(
    client: Any, adapter_name: str, todo: Sequence[_Todo], o: CampaignOptions, run_id: str
) -> dict[Any, FEJob]:
    """Submit every job of ``todo`` to ``client`` (:func:`run_job`); future -> job."""
    return {
        client.submit(
            run_job,
            adapter_name,
            settings,
            digest,
            job,
            h,
            None if o.scratch_dir is None else str(o.scratch_dir),
            o.keep_failed,
            key=f"femcal-fe-{job.key}-{h[:10]}-{run_id[:8]}",
            pure=False,
            retries=0,
        ): job
        for job, h, settings, digest in todo
    }
