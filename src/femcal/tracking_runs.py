"""MLflow runs of killed processes: tagged with their process, closed as KILLED later.

A process killed with ``kill -9`` (or by the machine going down) cannot end its MLflow runs:
they stay RUNNING for good. femcal therefore tags every run a command starts with the process
id, the host and the process's start time (:func:`tag_runs_with_process`, through MLflow's
``MLFLOW_RUN_CONTEXT`` environment variable, which :func:`mlflow.start_run` reads for every
new run, nested ones included), and every command, before it starts its own runs, closes the
RUNNING runs of its experiment whose process on this host is gone
(:func:`close_killed_runs`): status KILLED, end time now, and a tag ``femcal.killed`` saying
why. Runs of other hosts, of live processes and runs without these tags are left alone.

The same variable gives every run a command starts, nested ones included, the tag
``femcal.stage`` (:func:`tag_runs_with_stage`: the command's name), so that the MLflow UI can
group all of them; a stage that tags its run more precisely (``train-large``) sets the tag
again on its run.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
from collections.abc import Iterator, Sequence
from datetime import datetime, timezone
from pathlib import Path

from femcal.outputs import pid_alive

__all__ = [
    "HOST_TAG",
    "PID_TAG",
    "STAGE_TAG",
    "START_TAG",
    "close_killed_runs",
    "process_tags",
    "tag_runs_with_process",
    "tag_runs_with_stage",
]

logger = logging.getLogger(__name__)

PID_TAG = "femcal.pid"
HOST_TAG = "femcal.host"
#: The process's start time (Linux: clock ticks after boot), so that a reused pid is not
#: mistaken for the process that started the run.
START_TAG = "femcal.pid_start"
#: Why a run was closed as KILLED.
KILLED_TAG = "femcal.killed"
#: The femcal command (pipeline stage) that started a run.
STAGE_TAG = "femcal.stage"
_CONTEXT_VARIABLE = "MLFLOW_RUN_CONTEXT"


def _process_start(pid: int) -> str | None:
    """The start time of process ``pid`` (Linux ``/proc``), or None where unknown."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[-1].split()
    return fields[19] if len(fields) > 19 else None  # field 22 of proc(5), after the name


def process_tags() -> dict[str, str]:
    """Tags naming this process: ``femcal.pid``, ``femcal.host`` and ``femcal.pid_start``."""
    tags = {PID_TAG: str(os.getpid()), HOST_TAG: socket.gethostname()}
    start = _process_start(os.getpid())
    if start is not None:
        tags[START_TAG] = start
    return tags


def _tag_new_runs(tags: dict[str, str]) -> dict[str, str]:
    """Add ``tags`` to ``MLFLOW_RUN_CONTEXT`` (MLflow's run-context environment variable: a
    JSON object of tags that :func:`mlflow.start_run` adds to each new run), keeping the
    other tags it already holds; returns all of them."""
    try:
        context = json.loads(os.environ.get(_CONTEXT_VARIABLE) or "{}")
    except ValueError:
        context = {}
    if not isinstance(context, dict):
        context = {}
    context.update(tags)
    os.environ[_CONTEXT_VARIABLE] = json.dumps(context)
    return context


def tag_runs_with_process() -> dict[str, str]:
    """Make every MLflow run this process starts carry :func:`process_tags`.

    Returns
    -------
    dict
        The tags every new run gets.
    """
    return _tag_new_runs(process_tags())


@contextlib.contextmanager
def tag_runs_with_stage(stage: str) -> Iterator[dict[str, str]]:
    """Within the block, every MLflow run this process (and a child it starts) starts
    carries ``femcal.stage = stage`` (:data:`STAGE_TAG`); afterwards ``MLFLOW_RUN_CONTEXT``
    is as before.

    Yields
    ------
    dict
        The tags every new run gets.
    """
    before = os.environ.get(_CONTEXT_VARIABLE)
    try:
        yield _tag_new_runs({STAGE_TAG: str(stage)})
    finally:
        if before is None:
            os.environ.pop(_CONTEXT_VARIABLE, None)
        else:
            os.environ[_CONTEXT_VARIABLE] = before


def _dead(pid_text: str | None, start: str | None) -> bool:
    try:
        pid = int(pid_text or "")
    except ValueError:
        return False  # not femcal's tag: leave the run alone
    if not pid_alive(pid):
        return True
    now = _process_start(pid)
    return start is not None and now is not None and now != start  # pid reused since


def close_killed_runs(experiment_ids: Sequence[str]) -> list[str]:
    """Close as KILLED the RUNNING runs whose process on this host is gone.

    Parameters
    ----------
    experiment_ids : sequence of str
        The experiments to look in (the command's).

    Returns
    -------
    list of str
        The ids of the runs closed.
    """
    from mlflow import MlflowClient
    from mlflow.entities import ViewType
    from mlflow.exceptions import MlflowException

    host = socket.gethostname()
    client = MlflowClient()
    query = f"attributes.status = 'RUNNING' and tags.`{HOST_TAG}` = '{host}'"
    closed: list[str] = []
    token = None
    while True:
        try:
            page = client.search_runs(
                list(experiment_ids),
                filter_string=query,
                run_view_type=ViewType.ACTIVE_ONLY,
                max_results=1000,
                page_token=token,
            )
        except MlflowException as exc:  # housekeeping: never the reason a command fails
            logger.warning("Could not look for runs of killed processes: %s", exc.message)
            return closed
        for run in page:
            tags = run.data.tags
            if tags.get(HOST_TAG) != host or not _dead(tags.get(PID_TAG), tags.get(START_TAG)):
                continue
            when = datetime.now(timezone.utc).isoformat(timespec="seconds")
            client.set_tag(
                run.info.run_id,
                KILLED_TAG,
                f"process {tags.get(PID_TAG)} on {host} was gone at {when}; closed by process "
                f"{os.getpid()}",
            )
            client.set_terminated(run.info.run_id, status="KILLED")
            closed.append(run.info.run_id)
            logger.warning(
                "MLflow run %s (%s) was left RUNNING by process %s on %s, which is gone: "
                "closed as KILLED.",
                run.info.run_id,
                run.info.run_name,
                tags.get(PID_TAG),
                host,
            )
        token = page.token
        if not token:
            break
    return closed
