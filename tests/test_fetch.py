"""Tests of femcal.fetch: mirror copies and downloads from a local HTTP server."""

from __future__ import annotations

import hashlib
import http.server
import os
import re
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from requests.exceptions import ConnectionError as RequestsConnectionError

from femcal.errors import ChecksumError, DataSourceError
from femcal.fetch import (
    BASE_URL,
    MANIFEST,
    STUDY_COMMIT,
    STUDY_REPOSITORY,
    fetch_dataset,
    mirror_from_env,
    sha256_file,
)
from femcal.prepare import SPLITS

FILES = {
    "Large/a.csv": b"0,1,2\r\n0,1.5,2.5\r\n",
    "Small/b.csv": b"x,y\n1,2\n",
    "Test/ParameterBounds.csv": b"a\n0\n1\n",
}


def _manifest(files: dict[str, bytes] = FILES) -> dict[str, str]:
    return {rel: hashlib.sha256(data).hexdigest() for rel, data in files.items()}


def _write_tree(root: Path, files: dict[str, bytes] = FILES) -> Path:
    for rel, data in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    return root


def _leftovers(root: Path, keep: tuple[str, ...] = ()) -> list[Path]:
    """Files left anywhere under ``root`` other than the data files ``keep`` (pooch's temps)."""
    return [
        p for p in root.rglob("*") if p.is_file() and p.relative_to(root).as_posix() not in keep
    ]


# ------------------------------------------------------------------ constants
def test_constants() -> None:
    assert STUDY_REPOSITORY == "matanat/IVD-CalibNN"
    assert re.fullmatch(r"[0-9a-f]{40}", STUDY_COMMIT)
    assert BASE_URL == (
        f"https://raw.githubusercontent.com/matanat/IVD-CalibNN/{STUDY_COMMIT}/datasets/"
    )


def test_manifest_covers_every_split_file() -> None:
    expected = {rel for layout in SPLITS.values() for rel in layout.relpaths()}
    assert set(MANIFEST) == expected
    assert len(MANIFEST) == 30
    assert all(re.fullmatch(r"[0-9a-f]{64}", h) for h in MANIFEST.values())
    assert "Test/ROM_Results_Flexion_TestData_64_wMoment.csv" in MANIFEST
    assert "Small/MaterialConfigurations_Small_128.csv" in MANIFEST


def test_sha256_file(tmp_path: Path) -> None:
    path = tmp_path / "f.bin"
    path.write_bytes(b"abc")
    assert sha256_file(path) == ("ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad")


# ------------------------------------------------------------ mirror_from_env
def test_mirror_from_env(tmp_path: Path) -> None:
    assert mirror_from_env({}) is None
    assert mirror_from_env({"FEMCAL_DATA_MIRROR": "  "}) is None
    assert mirror_from_env({"FEMCAL_DATA_MIRROR": str(tmp_path)}) == tmp_path
    missing = tmp_path / "nowhere"
    with pytest.raises(DataSourceError, match=r"nowhere.*is not a directory.*unset it"):
        mirror_from_env({"FEMCAL_DATA_MIRROR": str(missing)})
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(DataSourceError, match="is not a directory"):
        mirror_from_env({"FEMCAL_DATA_MIRROR": str(a_file)})


# ---------------------------------------------------------------------- mirror
def test_fetch_from_mirror(tmp_path: Path) -> None:
    mirror = _write_tree(tmp_path / "mirror")
    dest = tmp_path / "dest"
    paths = fetch_dataset(dest, mirror=mirror, manifest=_manifest())
    assert paths == [dest / rel for rel in FILES]
    for rel, data in FILES.items():
        assert (dest / rel).read_bytes() == data
    assert _leftovers(dest, tuple(FILES)) == []
    # Second run: everything present with the right hash, the mirror is not even read.
    for p in mirror.rglob("*.csv"):
        p.unlink()
    assert fetch_dataset(dest, mirror=mirror, manifest=_manifest()) == paths


def test_fetch_replaces_a_corrupted_file(tmp_path: Path) -> None:
    mirror = _write_tree(tmp_path / "mirror")
    dest = _write_tree(tmp_path / "dest", {"Large/a.csv": b"garbage"})
    fetch_dataset(dest, mirror=mirror, manifest=_manifest())
    assert (dest / "Large/a.csv").read_bytes() == FILES["Large/a.csv"]


def test_mirror_missing_file(tmp_path: Path) -> None:
    mirror = _write_tree(tmp_path / "mirror", {"Large/a.csv": FILES["Large/a.csv"]})
    with pytest.raises(DataSourceError) as info:
        fetch_dataset(tmp_path / "dest", mirror=mirror, manifest=_manifest())
    msg = str(info.value)
    assert "Small/b.csv is missing in the mirror" in msg
    assert str(mirror) in msg
    assert "FEMCAL_DATA_MIRROR" in msg and "Large/, Small/ and Test/" in msg
    assert "unset it to download" in msg
    assert not (tmp_path / "dest" / "Small" / "b.csv").exists()


def test_mirror_checksum_mismatch(tmp_path: Path) -> None:
    mirror = _write_tree(tmp_path / "mirror")
    manifest = _manifest()
    manifest["Small/b.csv"] = "0" * 64
    dest = tmp_path / "dest"
    received = hashlib.sha256(FILES["Small/b.csv"]).hexdigest()
    with pytest.raises(
        ChecksumError,
        match=rf"Small/b\.csv.*expected 0{{64}}, received {received}.*commit {STUDY_COMMIT}",
    ) as info:
        fetch_dataset(dest, mirror=mirror, manifest=manifest)
    assert STUDY_COMMIT in str(info.value)
    assert not (dest / "Small" / "b.csv").exists()
    assert _leftovers(dest, ("Large/a.csv",)) == []


def test_bad_manifest_entry(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="must be a relative path"):
        fetch_dataset(tmp_path, mirror=tmp_path, manifest={"../x.csv": "0" * 64})


def test_mirror_path_that_does_not_exist(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere"
    with pytest.raises(DataSourceError, match=r"mirror .*nowhere is not a directory.*unset it"):
        fetch_dataset(tmp_path / "dest", mirror=missing, manifest=_manifest())
    assert not (tmp_path / "dest").exists()


def test_mirror_needs_no_network(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """CI has no internet: copying from the mirror never opens a connection."""

    def no_network(*args: object, **kwargs: object) -> None:
        raise AssertionError("the mirror path opened a network connection")

    monkeypatch.setattr(socket, "create_connection", no_network)
    monkeypatch.setattr(socket.socket, "connect", no_network)
    monkeypatch.setattr("requests.get", no_network)
    mirror = _write_tree(tmp_path / "mirror")
    dest = tmp_path / "dest"
    paths = fetch_dataset(dest, mirror=mirror, manifest=_manifest())
    assert [p.read_bytes() for p in paths] == list(FILES.values())


def test_mirror_replaced_file_is_logged(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    mirror = _write_tree(tmp_path / "mirror")
    dest = _write_tree(tmp_path / "dest", {"Large/a.csv": b"garbage"})
    with caplog.at_level("INFO", logger="femcal.fetch"):
        fetch_dataset(dest, mirror=mirror, manifest=_manifest())
    assert "had the wrong SHA-256" in caplog.text
    assert "3 file(s) fetched, 0 already present" in caplog.text


# ------------------------------------------------------------------- download
class _Handler(http.server.SimpleHTTPRequestHandler):
    requests: list[str]

    def log_message(self, format: str, *args: object) -> None:
        pass

    def do_GET(self) -> None:
        self.requests.append(self.path)
        if self.path.endswith("truncated.csv"):
            self.send_response(200)
            self.send_header("Content-Length", "1000")
            self.end_headers()
            self.wfile.write(b"0,1,2\n")
            return
        super().do_GET()


@pytest.fixture
def server(tmp_path: Path) -> Iterator[tuple[str, Path, list[str]]]:
    """(base URL ending in '/', served folder, list of requested paths)."""
    root = tmp_path / "served"
    root.mkdir()
    requests: list[str] = []
    handler = type("Handler", (_Handler,), {"requests": requests})

    def factory(*args: object, **kwargs: object) -> _Handler:
        return handler(*args, directory=str(root), **kwargs)

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), factory)
    thread = threading.Thread(
        target=httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True
    )
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_port}/datasets/", root, requests
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(timeout=5)


def test_download_success(server: tuple[str, Path, list[str]], tmp_path: Path) -> None:
    base, root, requests = server
    _write_tree(root / "datasets")
    dest = tmp_path / "dest"
    paths = fetch_dataset(dest, base_url=base, manifest=_manifest(), timeout=5, progress=True)
    assert [p.read_bytes() for p in paths] == list(FILES.values())
    assert sorted(requests) == sorted(f"/datasets/{rel}" for rel in FILES)
    assert _leftovers(dest, tuple(FILES)) == []
    probe = tmp_path / "probe"
    probe.touch()  # outputs get the usual permissions, not mkstemp's owner-only 0o600
    assert os.stat(paths[0]).st_mode & 0o777 == os.stat(probe).st_mode & 0o666


def test_download_present_file_not_refetched(
    server: tuple[str, Path, list[str]], tmp_path: Path
) -> None:
    base, root, requests = server
    _write_tree(root / "datasets")
    dest = _write_tree(tmp_path / "dest", {"Large/a.csv": FILES["Large/a.csv"]})
    before = (dest / "Large/a.csv").stat().st_mtime_ns
    fetch_dataset(dest, base_url=base, manifest=_manifest(), timeout=5)
    assert "/datasets/Large/a.csv" not in requests
    assert len(requests) == 2
    assert (dest / "Large/a.csv").stat().st_mtime_ns == before
    requests.clear()
    fetch_dataset(dest, base_url=base, manifest=_manifest(), timeout=5)
    assert requests == []


def test_download_checksum_mismatch_leaves_nothing(
    server: tuple[str, Path, list[str]], tmp_path: Path
) -> None:
    base, root, _ = server
    _write_tree(root / "datasets", {"Large/a.csv": b"tampered"})
    dest = tmp_path / "dest"
    manifest = {"Large/a.csv": _manifest()["Large/a.csv"]}
    with pytest.raises(ChecksumError, match=r"SHA-256 mismatch for Large/a\.csv") as info:
        fetch_dataset(dest, base_url=base, manifest=manifest, timeout=5)
    msg = str(info.value)
    assert manifest["Large/a.csv"] in msg
    assert hashlib.sha256(b"tampered").hexdigest() in msg
    assert "re-download" in msg
    assert not (dest / "Large" / "a.csv").exists()
    assert _leftovers(dest) == []


def test_download_404(server: tuple[str, Path, list[str]], tmp_path: Path) -> None:
    base, _, _ = server
    dest = tmp_path / "dest"
    with pytest.raises(
        DataSourceError, match=rf"Downloading {re.escape(base)}Large/a\.csv failed: HTTPError.*404"
    ) as info:
        fetch_dataset(dest, base_url=base, manifest=_manifest(), timeout=5)
    assert "FEMCAL_DATA_MIRROR" in str(info.value)
    assert not (dest / "Large" / "a.csv").exists()
    assert _leftovers(dest) == []


def test_download_truncated(server: tuple[str, Path, list[str]], tmp_path: Path) -> None:
    base, _, _ = server
    dest = tmp_path / "dest"
    with pytest.raises(DataSourceError, match=r"truncated\.csv failed.*994 more expected"):
        fetch_dataset(dest, base_url=base, manifest={"Large/truncated.csv": "0" * 64}, timeout=5)
    assert not (dest / "Large" / "truncated.csv").exists()
    assert _leftovers(dest) == []


def test_download_connection_refused(tmp_path: Path) -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    base = f"http://127.0.0.1:{port}/"
    with pytest.raises(DataSourceError, match=rf"Downloading {re.escape(base)}Large/a\.csv"):
        fetch_dataset(tmp_path / "dest", base_url=base, manifest=_manifest(), timeout=5)


def test_default_download_uses_base_url(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    seen: list[str] = []

    def fake_get(url: str, timeout: float, **kwargs: object) -> object:
        seen.append(url)
        assert timeout == 60.0
        raise RequestsConnectionError("offline")

    monkeypatch.setattr("requests.get", fake_get)
    rel = "Test/ROM_Results_Flexion_TestData_64_wMoment.csv"
    with pytest.raises(DataSourceError, match="offline"):
        fetch_dataset(tmp_path, manifest={rel: MANIFEST[rel]})
    assert seen == [BASE_URL + rel]


# ------------------------------------------------------------ the real mirror
@pytest.fixture
def real_mirror() -> Path:
    mirror = mirror_from_env()
    if mirror is None:
        pytest.skip("FEMCAL_DATA_MIRROR is not set")
    return mirror


def test_real_mirror_matches_manifest(real_mirror: Path, tmp_path: Path) -> None:
    for rel, expected in MANIFEST.items():
        assert sha256_file(real_mirror / rel) == expected, rel
    paths = fetch_dataset(tmp_path / "raw", mirror=real_mirror)
    assert len(paths) == len(MANIFEST)
    assert all(p.is_file() for p in paths)
