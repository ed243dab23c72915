"""The paper's data files: explicit path > environment > cache > download; checksums; errors that say where."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import http.server
import os
import socket
import threading
from pathlib import Path

import pytest

from pipeline.workflow import paper_data
from pipeline.workflow.paper_data import PAPER_COMMIT, PAPER_FILES, PAPER_REPO, PaperDataError, cached_path, resolve

# Read before the fixtures clear the environment: the real file, where the caller's shell names one.
REAL_TEST = os.environ.get("COGMAP_PAPER_TEST")
FAKE_TEST = b'{"question": {"world_size_x": 2}}\n'
FAKE_TRAIN = b'{"question": {"world_size_x": 3}}\n' * 3


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@pytest.fixture(autouse=True)
def clean_env(monkeypatch, tmp_path):
    """No override from the caller's shell; a fresh cache under tmp_path."""
    for name in ("COGMAP_PAPER_TEST", "COGMAP_PAPER_TRAIN", paper_data.BASE_URL_ENV, "XDG_CACHE_HOME"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv(paper_data.CACHE_ENV, str(tmp_path / "cache"))


@pytest.fixture
def pin_fake_test(monkeypatch):
    """The test set's pinned digest, made that of FAKE_TEST (the real file is not fetched in tests)."""
    monkeypatch.setitem(PAPER_FILES, "test", dataclasses.replace(PAPER_FILES["test"], sha256=_sha(FAKE_TEST)))


def _remote(root: Path, files: dict[str, bytes]) -> str:
    """A folder laid out like the raw host (repo/commit/path); its file:// base URL."""
    for name, data in files.items():
        path = root / PAPER_REPO / PAPER_COMMIT / PAPER_FILES[name].repo_path
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    return root.as_uri()


def _cache_entries(tmp_path: Path) -> list[str]:
    folder = tmp_path / "cache"
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()) if folder.exists() else []


@pytest.fixture
def http_base(tmp_path):
    """A local HTTP server over tmp_path/remote; yields (base URL, remote folder)."""
    root = tmp_path / "remote"
    root.mkdir()
    handler = functools.partial(_QuietHandler, directory=str(root))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.01}, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", root
    finally:
        server.shutdown()
        server.server_close()


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------------------------ precedence
def test_explicit_beats_env_beats_cache_beats_fetch(tmp_path, monkeypatch, pin_fake_test):
    base = _remote(tmp_path / "remote", {"test": FAKE_TEST})
    explicit, env = tmp_path / "explicit.jsonl", tmp_path / "env.jsonl"
    explicit.write_bytes(b"explicit\n")
    env.write_bytes(b"env\n")
    monkeypatch.setenv("COGMAP_PAPER_TEST", str(env))

    assert resolve("test", str(explicit), base_url=base) == paper_data.ResolvedFile(
        explicit, _sha(b"explicit\n"), "explicit", verified=False)
    assert resolve("test", None, base_url=base).source == "env"
    assert resolve("test", "paper", base_url=base).path == env  # the config word means "the paper's file"

    monkeypatch.delenv("COGMAP_PAPER_TEST")
    fetched = resolve("test", "paper", base_url=base)
    assert (fetched.source, fetched.sha256, fetched.verified) == ("fetch", _sha(FAKE_TEST), True)
    assert fetched.path == cached_path("test") and fetched.path.read_bytes() == FAKE_TEST

    cached = resolve("test", base_url="file:///nowhere")  # the cache answers: no download attempted
    assert (cached.source, cached.path, cached.verified) == ("cache", fetched.path, True)


def test_cache_folder_follows_cogmap_cache_then_xdg_then_home(monkeypatch, tmp_path):
    assert paper_data.cache_root() == tmp_path / "cache"
    monkeypatch.delenv(paper_data.CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert paper_data.cache_root() == tmp_path / "xdg" / "cogmap"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert paper_data.cache_root() == tmp_path / "home" / ".cache" / "cogmap"


def test_the_download_address_is_the_pinned_commit_on_the_raw_host_unless_overridden(monkeypatch):
    spec = PAPER_FILES["test"]
    assert spec.url() == ("https://raw.githubusercontent.com/kaistAI/language_extrapolation/"
                          "51fcec3d9c475aca4bbafdea7b6a3ec5dbfddf10/envs/gridworld/data/inference_3000_hard_20x20.jsonl")
    monkeypatch.setenv(paper_data.BASE_URL_ENV, "http://mirror.example/raw/")
    assert spec.url().startswith("http://mirror.example/raw/kaistAI/language_extrapolation/")
    assert spec.url("file:///mirror").startswith("file:///mirror/kaistAI/")


# ---------------------------------------------------------------------------------------------------- fetch
def test_training_set_fetched_over_http_records_its_digest_and_later_uses_check_it(http_base, tmp_path):
    base, root = http_base
    _remote(root, {"train": FAKE_TRAIN})

    first = resolve("train", base_url=base)
    assert (first.source, first.sha256, first.verified) == ("fetch", _sha(FAKE_TRAIN), False)
    record = first.path.with_name(first.path.name + ".sha256")
    assert record.read_text() == f"{_sha(FAKE_TRAIN)}  train_50000_hard_10x10.jsonl\n"
    assert _cache_entries(tmp_path) == [f"paper/{PAPER_COMMIT}/train_50000_hard_10x10.jsonl",
                                        f"paper/{PAPER_COMMIT}/train_50000_hard_10x10.jsonl.sha256"]

    again = resolve("train", base_url=base)
    assert (again.source, again.sha256, again.verified) == ("cache", first.sha256, True)

    first.path.write_bytes(b"tampered\n")
    with pytest.raises(PaperDataError) as caught:
        resolve("train", base_url=base)
    assert _sha(b"tampered\n") in str(caught.value) and _sha(FAKE_TRAIN) in str(caught.value)
    assert _cache_entries(tmp_path) == []  # removed: the next use fetches it again
    assert resolve("train", base_url=base).source == "fetch"


def test_a_download_with_the_wrong_bytes_names_both_digests_and_leaves_nothing_in_the_cache(http_base, tmp_path):
    base, root = http_base
    _remote(root, {"test": b"not the paper's file\n"})
    with pytest.raises(PaperDataError) as caught:
        resolve("test", base_url=base)
    message = str(caught.value)
    assert PAPER_FILES["test"].sha256 in message and _sha(b"not the paper's file\n") in message
    assert PAPER_FILES["test"].url(base) in message
    assert _cache_entries(tmp_path) == []


def test_an_unreachable_url_names_the_url_the_cache_path_and_the_override(tmp_path):
    base = f"http://127.0.0.1:{_closed_port()}"
    with pytest.raises(PaperDataError) as caught:
        resolve("test", base_url=base, timeout=5)
    message = str(caught.value)
    assert PAPER_FILES["test"].url(base) in message
    assert str(cached_path("test")) in message and "$COGMAP_PAPER_TEST" in message
    assert _cache_entries(tmp_path) == []


def test_a_missing_remote_file_names_the_http_status(http_base, tmp_path):
    base, _ = http_base
    with pytest.raises(PaperDataError, match=r"HTTP 404.*\$COGMAP_PAPER_TRAIN"):
        resolve("train", base_url=base)
    assert _cache_entries(tmp_path) == []


def test_a_corrupt_cached_test_file_is_refused_and_removed(tmp_path, pin_fake_test):
    target = cached_path("test")
    target.parent.mkdir(parents=True)
    target.write_bytes(b"half a fil")
    with pytest.raises(PaperDataError, match=f"{_sha(b'half a fil')}, expected {_sha(FAKE_TEST)}"):
        resolve("test", base_url="file:///nowhere")
    assert not target.exists()


# ------------------------------------------------------------------------------------------------ overrides
def test_an_override_is_used_as_it_is_unless_verification_is_asked(tmp_path, monkeypatch):
    modified = tmp_path / "modified.jsonl"
    modified.write_bytes(b"a deliberately edited test set\n")
    monkeypatch.setenv("COGMAP_PAPER_TEST", str(modified))
    found = resolve("test")
    assert (found.path, found.sha256, found.source, found.verified) == (
        modified, _sha(b"a deliberately edited test set\n"), "env", False)
    with pytest.raises(PaperDataError) as caught:
        resolve("test", verify=True)
    assert found.sha256 in str(caught.value) and PAPER_FILES["test"].sha256 in str(caught.value)
    assert "$COGMAP_PAPER_TEST" in str(caught.value)
    assert modified.exists()  # a user's file is never deleted


def test_verifying_an_override_of_the_training_set_needs_a_recorded_digest(tmp_path, http_base):
    base, root = http_base
    copy = tmp_path / "train_copy.jsonl"
    copy.write_bytes(FAKE_TRAIN)
    with pytest.raises(PaperDataError, match="no checksum is published"):
        resolve("train", str(copy), verify=True)
    _remote(root, {"train": FAKE_TRAIN})
    resolve("train", base_url=base)  # records the digest
    assert resolve("train", str(copy), verify=True).verified


@pytest.mark.parametrize("where", ["explicit", "env"])
def test_an_override_that_is_not_a_file_names_itself(tmp_path, monkeypatch, where):
    missing = str(tmp_path / "absent.jsonl")
    if where == "env":
        monkeypatch.setenv("COGMAP_PAPER_TRAIN", missing)
    with pytest.raises(PaperDataError, match="COGMAP_PAPER_TRAIN" if where == "env" else "explicit path"):
        resolve("train", missing if where == "explicit" else None)


def test_an_unknown_name_lists_the_known_ones():
    with pytest.raises(PaperDataError, match="allowed: test, train"):
        resolve("validation")


def test_the_command_line_prints_path_digest_and_source(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv(paper_data.BASE_URL_ENV, _remote(tmp_path / "remote", {"train": FAKE_TRAIN}))
    assert paper_data.main(["train"]) == 0
    assert capsys.readouterr().out == (f"train\t{cached_path('train')}\tsha256 {_sha(FAKE_TRAIN)}\tfetch "
                                       f"(not verified)\n")
    monkeypatch.setenv("COGMAP_PAPER_TEST", str(tmp_path / "absent"))
    assert paper_data.main(["test"]) == 1
    assert "COGMAP_PAPER_TEST" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------- real file
def test_the_real_test_file_has_the_pinned_digest(monkeypatch):
    if not REAL_TEST:
        pytest.skip("COGMAP_PAPER_TEST is not set: the paper's test file is not available")
    monkeypatch.setenv("COGMAP_PAPER_TEST", REAL_TEST)
    found = resolve("test", verify=True)
    assert (found.sha256, found.verified) == (PAPER_FILES["test"].sha256, True)
