"""The campaign store without a solver: the committed ``.gz`` form, its journal and folds."""

from __future__ import annotations

import gzip
import json

import pytest

from femcal.errors import InputDataError
from femcal.fe.store import CampaignStore


def _record(i: int, status: str = "ok") -> dict:
    return {"v": 1, "job_hash": f"h{i:04d}", "config_id": i, "status": status}


def _fill(store: CampaignStore, ids) -> None:
    with store.writer():
        for i in ids:
            store.append(_record(i))


def test_gz_store_appends_to_a_journal_and_folds_on_close(tmp_path):
    store = CampaignStore(tmp_path / "runs.jsonl.gz", fold_every=1000)
    assert store.journal == tmp_path / "runs.jsonl"
    with store.writer():
        for i in range(3):
            store.append(_record(i))
        # Before the fold the records are in the journal, and read sees them.
        assert len(store.journal.read_bytes().splitlines()) == 3
        assert [r["config_id"] for r in store.read()] == [0, 1, 2]
    assert not store.journal.exists()  # folded and removed
    with gzip.open(store.path, "rb") as fh:
        assert [json.loads(x)["config_id"] for x in fh.read().splitlines()] == [0, 1, 2]
    _fill(store, [3])
    assert [r["config_id"] for r in CampaignStore(store.path).read()] == [0, 1, 2, 3]


def test_gz_store_folds_every_n_records_while_writing(tmp_path):
    store = CampaignStore(tmp_path / "runs.jsonl.gz", fold_every=2)
    with store.writer():
        for i in range(5):
            store.append(_record(i))
        # Two folds (after records 2 and 4): one record waits in the journal.
        assert len(store.journal.read_bytes().splitlines()) == 1
        with gzip.open(store.path, "rb") as fh:
            assert len(fh.read().splitlines()) == 4
    assert len(store.read()) == 5


def test_gz_store_is_byte_reproducible(tmp_path):
    """No time stamp in the gzip header: the same records give the same committed bytes."""
    a = CampaignStore(tmp_path / "a" / "runs.jsonl.gz")
    b = CampaignStore(tmp_path / "b" / "runs.jsonl.gz")
    _fill(a, range(4))
    _fill(b, range(4))
    assert a.path.read_bytes() == b.path.read_bytes()


def test_killed_writer_journal_is_read_and_folded_without_duplicates(tmp_path):
    """A kill between the rename of the new .gz and the emptying of the journal leaves the
    same records in both files: they are read once, and the next writer folds them once."""
    store = CampaignStore(tmp_path / "runs.jsonl.gz")
    _fill(store, range(3))
    lines = gzip.decompress(store.path.read_bytes()).splitlines()
    # The journal holds two records already folded, one new one and a torn line.
    new = json.dumps(_record(3), separators=(",", ":")).encode()
    store.journal.write_bytes(lines[1] + b"\n" + lines[2] + b"\n" + new + b'\n{"v":1,"job')
    assert [r["config_id"] for r in store.read()] == [0, 1, 2, 3]
    with store.writer():
        pass
    assert not store.journal.exists()
    assert len(gzip.decompress(store.path.read_bytes()).splitlines()) == 4


def test_plain_store_is_unchanged_by_the_compressed_form(tmp_path):
    store = CampaignStore(tmp_path / "runs.jsonl", fold_every=1)
    assert store.journal == store.path
    _fill(store, range(3))
    assert len(store.path.read_bytes().splitlines()) == 3
    assert not (tmp_path / "runs.jsonl.gz").exists()


def test_a_corrupt_gz_store_names_the_file_and_the_fix(tmp_path):
    path = tmp_path / "runs.jsonl.gz"
    path.write_bytes(b"not gzip at all")
    with pytest.raises(InputDataError, match=r"runs\.jsonl\.gz: not a readable gzip file.*git"):
        CampaignStore(path).read()


def test_a_bad_line_inside_the_gz_store_names_the_line(tmp_path):
    path = tmp_path / "runs.jsonl.gz"
    good = json.dumps(_record(0)).encode()
    path.write_bytes(gzip.compress(good + b"\nnot json\n" + good + b"\n"))
    with pytest.raises(InputDataError, match=r"runs\.jsonl\.gz, line 2: not a job record"):
        CampaignStore(path).read()


def test_append_and_fold_outside_the_writer_are_refused(tmp_path):
    store = CampaignStore(tmp_path / "runs.jsonl.gz")
    with pytest.raises(RuntimeError, match="outside `with store.writer"):
        store.append(_record(0))
    with pytest.raises(RuntimeError, match="outside `with store.writer"):
        store.fold()


def test_a_bad_journal_line_is_named_by_its_line_in_the_file(tmp_path):
    """Lines skipped as already folded still count: the message gives the file's line."""
    store = CampaignStore(tmp_path / "runs.jsonl.gz")
    _fill(store, range(2))
    folded = gzip.decompress(store.path.read_bytes()).splitlines()
    store.journal.write_bytes(folded[0] + b"\n" + folded[1] + b"\nnot json\n" + folded[0] + b"\n")
    with pytest.raises(InputDataError, match=r"runs\.jsonl, line 3: not a job record"):
        store.read()


def test_gz_store_grows_in_segments_each_under_the_limit(tmp_path):
    """A fold starts a new segment once the last one holds segment_bytes: the earlier
    segments' bytes never change, and read sees every record once, in order."""
    store = CampaignStore(tmp_path / "runs.jsonl.gz", fold_every=1, segment_bytes=60)
    _fill(store, range(2))
    first = store.path.read_bytes()
    assert len(first) >= 60  # one compressed record fills a segment: one per fold
    _fill(store, range(2, 5))
    names = [p.name for p in store.segments()]
    assert names == ["runs.jsonl.gz"] + [f"runs-{k:03d}.jsonl.gz" for k in range(2, 6)]
    assert store.path.read_bytes() == first
    assert [r["config_id"] for r in CampaignStore(store.path).read()] == list(range(5))
    # A kill between a segment's rename and the journal's truncation: read once, folded once.
    line = gzip.decompress(store.segment_path(5).read_bytes()).splitlines()[-1]
    store.journal.write_bytes(line + b"\n")
    assert [r["config_id"] for r in store.read()] == list(range(5))
    with store.writer():
        pass
    assert [r["config_id"] for r in store.read()] == list(range(5))


def test_missing_segment_is_named(tmp_path):
    store = CampaignStore(tmp_path / "runs.jsonl.gz", fold_every=1, segment_bytes=60)
    _fill(store, range(5))
    store.segment_path(2).unlink()
    with pytest.raises(InputDataError, match=r"runs-002\.jsonl\.gz: a segment .* is missing"):
        store.read()


def test_corrupt_segment_is_named(tmp_path):
    store = CampaignStore(tmp_path / "runs.jsonl.gz", fold_every=1, segment_bytes=60)
    _fill(store, range(5))
    store.segment_path(3).write_bytes(b"not gzip")
    with pytest.raises(InputDataError, match=r"runs-003\.jsonl\.gz: not a readable gzip"):
        store.read()
