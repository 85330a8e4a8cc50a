"""fork_map: every piece once, in workers forked from this process (or in it, for one)."""

from __future__ import annotations

import multiprocessing
import os

import pytest

from femcal.figures import fork_map

pytestmark = pytest.mark.skipif(
    "fork" not in multiprocessing.get_all_start_methods(), reason="workers are forked"
)


def _where(piece: int) -> tuple[int, int]:
    return piece * piece, os.getpid()


def _fails_at_three(piece: int) -> int:
    if piece == 3:
        raise ValueError(f"piece {piece} failed")
    return piece


def test_every_piece_once_in_forked_workers():
    out = dict(fork_map(_where, list(range(12)), workers=2))
    assert sorted(out) == list(range(12))
    assert all(square == piece * piece for piece, (square, _) in out.items())
    pids = {pid for _, pid in out.values()}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2


def test_one_worker_is_this_process_alone():
    out = dict(fork_map(_where, [1, 2, 3], workers=1))
    assert {pid for _, pid in out.values()} == {os.getpid()}
    assert [p for p, _ in fork_map(_where, [1, 2, 3], workers=1)] == [1, 2, 3]


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_a_failing_piece_raises_its_error(workers):
    with pytest.raises(ValueError, match="piece 3 failed"):
        list(fork_map(_fails_at_three, list(range(8)), workers=workers))
