"""Named data sets: the registry, the mirror, the cache and the download path (against a
local HTTP server on 127.0.0.1: a wrong checksum is refused and leaves nothing behind)."""

from __future__ import annotations

import functools
import hashlib
import http.server
import threading
from pathlib import Path

import pytest

from tests.test_cli import call
from torchslam.data import files

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture
def server(tmp_path):
    """A folder served over HTTP on 127.0.0.1 (an ephemeral port): (folder, base URL)."""
    root = tmp_path / "origin"
    root.mkdir()
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(root))
    handler.log_message = lambda *args: None  # quiet
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        yield root, f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(timeout=10)


def _dataset(monkeypatch, base_url: str, contents: dict[str, bytes], wrong: str = "") -> None:
    entries = tuple(
        files.DataFile(
            path,
            hashlib.sha256(data + (b"x" if path == wrong else b"")).hexdigest(),
            len(data),
        )
        for path, data in contents.items()
    )
    dataset = files.Dataset("toy", "toy/set", "a toy data set", base_url, "public", entries)
    monkeypatch.setitem(files.DATASETS, "toy", dataset)


def test_download_is_checked_and_cached(server, tmp_path, monkeypatch):
    root, url = server
    contents = {"a.txt": b"alpha\n", "sub/b.bin": bytes(range(256))}
    for path, data in contents.items():
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_bytes(data)
    _dataset(monkeypatch, url, contents)
    monkeypatch.setenv("TORCHSLAM_DATA", str(tmp_path / "cache"))
    monkeypatch.delenv("TORCHSLAM_DATA_MIRROR", raising=False)
    assert files.status("toy") == "missing"
    with pytest.raises(files.DatasetUnavailableError, match="torchslam data fetch toy"):
        files.fetch("toy", download=False)
    folder = files.fetch("toy")
    assert folder == tmp_path / "cache" / "toy" / "set"
    for path, data in contents.items():
        assert (folder / path).read_bytes() == data
    assert files.status("toy") == "cached"
    (root / "a.txt").unlink()  # the cache serves it now, no download
    assert files.fetch("toy") == folder
    (folder / "a.txt").write_bytes(b"alphA\n")  # a corrupted cache file is refused
    with pytest.raises(ValueError, match="not the registered file"):
        files.fetch("toy")


def test_wrong_checksum_is_refused_and_leaves_nothing(server, tmp_path, monkeypatch):
    root, url = server
    contents = {"a.txt": b"alpha\n"}
    (root / "a.txt").write_bytes(contents["a.txt"])
    _dataset(monkeypatch, url, contents, wrong="a.txt")
    cache = tmp_path / "cache"
    monkeypatch.setenv("TORCHSLAM_DATA", str(cache))
    monkeypatch.delenv("TORCHSLAM_DATA_MIRROR", raising=False)
    with pytest.raises(ValueError, match="hash"):
        files.fetch("toy")
    left = [p for p in cache.rglob("*") if p.is_file()]
    assert left == []  # no half-written or unverified file in the cache


def test_unreachable_origin_says_how_to_get_the_data(tmp_path, monkeypatch):
    _dataset(monkeypatch, "http://127.0.0.1:9", {"a.txt": b"alpha\n"})  # discard port
    monkeypatch.setenv("TORCHSLAM_DATA", str(tmp_path / "cache"))
    monkeypatch.delenv("TORCHSLAM_DATA_MIRROR", raising=False)
    with pytest.raises(files.DatasetUnavailableError, match="TORCHSLAM_DATA_MIRROR"):
        files.fetch("toy")


def test_mirror_is_used_in_place_and_checked(tmp_path, monkeypatch):
    contents = {"a.txt": b"alpha\n"}
    _dataset(monkeypatch, "http://127.0.0.1:9", contents)
    mirror = tmp_path / "mirror"
    (mirror / "toy" / "set").mkdir(parents=True)
    (mirror / "toy" / "set" / "a.txt").write_bytes(b"alpha\n")
    monkeypatch.setenv("TORCHSLAM_DATA_MIRROR", str(mirror))
    monkeypatch.setenv("TORCHSLAM_DATA", str(tmp_path / "cache"))
    assert files.status("toy") == "mirror"
    assert files.fetch("toy") == mirror / "toy" / "set"
    (mirror / "toy" / "set" / "a.txt").write_bytes(b"alphA\n")
    with pytest.raises(ValueError, match="sha256"):
        files.fetch("toy")
    with pytest.raises(ValueError, match="unknown data set 'nope'"):
        files.fetch("nope")


def test_registry_lists_every_data_set_with_origin_and_checksums():
    expected = {"bunny", "posegraph", "bal-ladybug-21", "rgbd-7scenes", "lidar-quick-shack"}
    assert set(files.DATASETS) >= expected | {"lidar-hku2-loop", "lidar-pair"}
    for dataset in files.DATASETS.values():
        assert dataset.files and dataset.base_url.startswith("https://")
        assert all(len(f.sha256) == 64 and f.size > 0 for f in dataset.files)
        assert dataset.licence
    # the shared copy matches the registry, byte for byte (checked the way users' are)
    if SHARED.is_dir():
        for name in ("posegraph", "bal-ladybug-21"):
            dataset = files.DATASETS[name]
            for f in dataset.files:
                path = SHARED / dataset.folder / f.path
                assert hashlib.sha256(path.read_bytes()).hexdigest() == f.sha256


def test_cli_lists_and_locates(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("TORCHSLAM_DATA", str(tmp_path / "cache"))
    monkeypatch.delenv("TORCHSLAM_DATA_MIRROR", raising=False)
    code, out, _ = call(["data", "list"], capsys)
    assert code == 0 and "bunny" in out and "missing" in out and "licence:" in out
    code, _, err = call(["data", "fetch"], capsys)
    assert code == 2 and "--all" in err
