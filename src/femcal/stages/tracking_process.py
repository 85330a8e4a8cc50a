"""The MLflow run of ``femcal calibrate`` and ``femcal diagnose`` in a child process of the
command line.

``femcal calibrate`` and ``femcal diagnose`` log from a child process started first
(:class:`TrackingProcess`): it imports MLflow, opens the store and runs the calls while the
command imports torch and calibrates (diagnoses) on the other core. Library callers log in-process
(:class:`femcal.jobs.mlflow_steps.LocalTracking`). Each step of the run is a function of
picklable arguments (:data:`femcal.jobs.mlflow_steps.TRACKING_CALLS`).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import pickle
import sys
from collections.abc import Callable, Mapping
from typing import Any

from femcal.jobs.mlflow_steps import TRACKING_CALLS, end_calibration_run
from femcal.stages.store import tracking

logger = logging.getLogger(__name__)


class ImportCollector:
    """Python's cyclic garbage collector off while the command imports its libraries.

    The imports of ``femcal calibrate`` and ``femcal diagnose`` (pandas and torch in this
    process, MLflow and its SQL store in the MLflow process) build about 600,000 objects and
    free few of them: the collector, which runs every 700 new objects and scans more of them
    each time, takes about 0.9 CPU-s of ``femcal calibrate``'s 6.5 without this (0.43-0.47 s
    in each process; see docs/benchmarks/calibrate-speed.md). Entering turns it off;
    :meth:`resume`, once the imports are done, freezes what exists (:func:`gc.freeze`: never
    scanned again, nor the pages of the figures' and the diagnosis' worker processes touched
    by a scan) and turns it back on; leaving unfreezes and restores the state found.

    The MLflow process (:class:`TrackingProcess`), forked while the collector is off, keeps it
    off: it imports MLflow and logs one run, and its peak RSS is 204 MB with the collector and
    without (logging 2,000 artifacts grows it by 4 MB, with the collector or without).
    """

    def __enter__(self) -> ImportCollector:
        self._enabled = gc.isenabled()
        self._frozen = False
        gc.disable()
        return self

    def resume(self) -> None:
        """Freeze every object that exists now, and turn the collector back on (if it was)."""
        if not self._frozen:
            gc.freeze()
            self._frozen = True
        if self._enabled:
            gc.enable()

    def __exit__(self, *_: Any) -> None:
        if self._frozen:
            gc.unfreeze()
        if self._enabled:
            gc.enable()


class TrackingProcess:
    """MLflow in a child process: its imports, the store and the command's run.

    Started first, the child imports MLflow, points it at the store of ``params``
    (:func:`femcal.stages.store.tracking`: the store, the experiment, killed runs closed) while
    this process imports torch, reads and calibrates (diagnoses): on two cores that time is
    hidden. The calls of :data:`TRACKING_CALLS` then run in the child, in the order submitted;
    their errors are raised here (the child's traceback as a note), a store error at the first
    :meth:`check` or :meth:`result` after it. The run is tagged with the child's process
    (:func:`femcal.tracking_runs.tag_runs_with_process`): a killed command leaves it RUNNING,
    and the next command closes it as KILLED, as before.

    Use as a context manager: leaving it stops the child (a run still open ends FAILED).
    """

    #: Seconds to wait for the child to end after the last call.
    JOIN_TIMEOUT = 60.0

    def __init__(self, params: Mapping[str, Any]) -> None:
        import multiprocessing

        # What both processes import, once, before the fork: the child inherits it (this
        # femcal's model loading and MLflow glue), so the two cores share no import twice.
        import femcal.tracking  # noqa: F401

        methods = multiprocessing.get_all_start_methods()
        # fork: nothing heavy is imported yet, and the child inherits the logging setup and
        # the environment; spawn elsewhere.
        ctx = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
        self._conn, child = ctx.Pipe()
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        self._process = ctx.Process(
            target=_serve_tracking,
            args=(child, dict(params), _log_levels()),
            name="femcal-mlflow",
            daemon=True,
        )
        self._process.start()
        child.close()
        self._pending = 1  # the setup's answer: the tracking URI
        self._tracking_uri: str | None = None
        self._ready = False

    def __enter__(self) -> TrackingProcess:
        return self

    def __exit__(self, exc_type: Any, *_: Any) -> None:
        self.close(failed=exc_type is not None)

    # -- calls
    def submit(self, fn: Callable[..., Any], /, **kwargs: Any) -> None:
        if TRACKING_CALLS.get(fn.__name__) is not fn:
            raise ValueError(f"{fn.__name__} is not one of {sorted(TRACKING_CALLS)}.")
        self._conn.send((fn.__name__, kwargs))
        self._pending += 1

    def result(self) -> Any:
        """The result of the oldest call not yet answered (its error raised here)."""
        self._wait_ready()
        return self._receive()

    def call(self, fn: Callable[..., Any], /, **kwargs: Any) -> Any:
        self.submit(fn, **kwargs)
        return self.result()

    def check(self) -> None:
        """Raise the store's error now if the child has already met one."""
        if not self._ready and self._conn.poll():
            self._wait_ready()

    def use_store_here(self) -> None:
        """Point this process's MLflow at the child's store (to download ``models:/`` URIs)."""
        import mlflow

        self._wait_ready()
        mlflow.set_tracking_uri(self._tracking_uri)
        mlflow.set_registry_uri(self._tracking_uri)

    def abort(self) -> None:
        """End the child's open run (if any) as FAILED; the answers still due are dropped."""
        try:
            self._wait_ready()
        except Exception:  # noqa: BLE001 - the store never came up: no run to end
            return
        try:
            while self._pending:
                with contextlib.suppress(Exception):
                    self._receive()
            self.call(end_calibration_run, status="FAILED")
        except Exception as exc:  # noqa: BLE001 - the error being handled is the caller's
            logger.warning("Could not end the MLflow run as FAILED: %s", exc)

    def close(self, *, failed: bool = False) -> None:
        """Stop the child (ending an open run as FAILED first when ``failed``)."""
        if failed:
            self.abort()
        try:
            self._conn.send(None)
        except OSError:
            pass  # already gone
        self._process.join(self.JOIN_TIMEOUT)
        if self._process.is_alive():  # pragma: no cover - a hung store
            logger.warning("The MLflow process %s did not stop; terminated.", self._process.pid)
            self._process.terminate()
            self._process.join()
        self._conn.close()

    # -- internals
    def _wait_ready(self) -> None:
        if not self._ready:
            self._tracking_uri = self._receive()
            self._ready = True

    def _receive(self) -> Any:
        try:
            kind, value, trace = self._conn.recv()
        except EOFError:
            self._pending = 0
            self._process.join(5)
            raise RuntimeError(
                f"The MLflow process (pid {self._process.pid}) ended unexpectedly (exit code "
                f"{self._process.exitcode}); the command's run was not logged."
            ) from None
        self._pending -= 1
        if kind == "error":
            if trace and hasattr(value, "add_note"):
                value.add_note(f"In the MLflow process:\n{trace}")
            raise value
        return value


def _log_levels() -> tuple[int, int]:
    """The levels of the root and ``femcal`` loggers (for a spawned child)."""
    return logging.getLogger().level, logging.getLogger("femcal").level


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling, else a RuntimeError with its type and message."""
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:  # noqa: BLE001 - any unpicklable exception
        return RuntimeError(f"{type(exc).__name__}: {exc}")
    return exc


def _serve_tracking(conn: Any, params: Mapping[str, Any], levels: tuple[int, int]) -> None:
    """The child of :class:`TrackingProcess`: set up the store, then run the calls sent."""
    import signal
    import traceback

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the parent ends the run
    if not logging.getLogger().handlers:  # spawned: the parent's logging setup
        logging.basicConfig(level=levels[0], format="%(levelname)s %(name)s: %(message)s")
        logging.getLogger("femcal").setLevel(levels[1])
    try:
        import mlflow

        tracking(params)
        conn.send(("ok", mlflow.get_tracking_uri(), None))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent
        conn.send(("error", _portable(exc), traceback.format_exc()))
        return
    while True:
        try:
            request = conn.recv()
        except EOFError:  # the parent is gone: its run stays RUNNING, closed later as KILLED
            return
        if request is None:
            return
        name, kwargs = request
        try:
            conn.send(("ok", TRACKING_CALLS[name](**kwargs), None))
        except BaseException as exc:  # noqa: BLE001 - reported to the parent
            conn.send(("error", _portable(exc), traceback.format_exc()))
