"""The paper's released data files: where they come from, where they are cached, and their checksums.

`resolve("test")` or `resolve("train")` finds one of the two files the paper's repository published and
returns its path and sha256. The first answer in this order wins:

1. an explicit path (a config value; the word ``paper`` means "no explicit path, resolve the paper's file"),
2. the file's environment variable (``COGMAP_PAPER_TEST`` / ``COGMAP_PAPER_TRAIN``),
3. the cache folder (``$COGMAP_CACHE``, else ``$XDG_CACHE_HOME/cogmap``, else ``~/.cache/cogmap``),
4. a download into the cache, from ``raw.githubusercontent.com`` at the pinned commit (another base URL
   through ``COGMAP_PAPER_BASE_URL`` or ``base_url=``: a mirror, or a ``file://`` folder).

Checksums: the test set has a pinned sha256, checked whenever the file comes from the cache or a download.
The training set has none published: the digest of its first download is written beside the cached file
(``<file>.sha256``, in ``sha256sum`` format) and later uses are checked against it. A file named by an explicit
path or the environment variable is taken as it is (a user may point at a modified file on purpose); its
digest is always computed and returned, and compared with the known one only when ``verify=True``.

A download goes to a temporary file in the cache folder, is checked, and is then renamed into place, so an
interrupted or corrupt download never sits under the final name, and parallel jobs can fetch at once.

Standard library only, so it runs wherever the domain core does (a cluster's login node, to prefetch:
``python -m pipeline.workflow.paper_data test train``).
"""

from __future__ import annotations

import hashlib
import http.client
import os
import sys
import tempfile
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

PAPER_REPO = "kaistAI/language_extrapolation"
PAPER_COMMIT = "51fcec3d9c475aca4bbafdea7b6a3ec5dbfddf10"
DEFAULT_BASE_URL = "https://raw.githubusercontent.com"
BASE_URL_ENV = "COGMAP_PAPER_BASE_URL"
CACHE_ENV = "COGMAP_CACHE"
# The config value that asks for the paper's file rather than naming one.
PAPER_WORD = "paper"

Source = Literal["explicit", "env", "cache", "fetch"]


class PaperDataError(ValueError):
    """A paper file that cannot be found, fetched or trusted (the message says where it was looked for)."""


@dataclass(frozen=True)
class PaperFile:
    """One file released with the paper: where it lives in the paper's repository and how it is checked."""

    name: str
    repo_path: str
    env: str
    sha256: str | None
    description: str

    @property
    def filename(self) -> str:
        return self.repo_path.rsplit("/", 1)[-1]

    def url(self, base_url: str | None = None) -> str:
        """Its download address under `base_url` (default: $COGMAP_PAPER_BASE_URL, else GitHub's raw host)."""
        base = (base_url or os.environ.get(BASE_URL_ENV) or DEFAULT_BASE_URL).rstrip("/")
        return f"{base}/{PAPER_REPO}/{PAPER_COMMIT}/{self.repo_path}"


PAPER_FILES: dict[str, PaperFile] = {
    "test": PaperFile(
        name="test",
        repo_path="envs/gridworld/data/inference_3000_hard_20x20.jsonl",
        env="COGMAP_PAPER_TEST",
        sha256="612695a702eac493cf6ff6df078e32bc7e6a9883e37d7566342ea9bd4999ba04",
        description="the paper's test set (3,000 worlds, sides 2..20)",
    ),
    "train": PaperFile(
        name="train",
        repo_path="envs/gridworld/data/train_50000_hard_10x10.jsonl",
        env="COGMAP_PAPER_TRAIN",
        sha256=None,  # not published: recorded at the first download
        description="the paper's training set (50,000 worlds, sides 2..10)",
    ),
}


@dataclass(frozen=True)
class ResolvedFile:
    """A paper file found on disk: its path, its sha256 as computed now, where it came from, and whether that
    digest was checked against a known one (pinned, or recorded at the first download)."""

    path: Path
    sha256: str
    source: Source
    verified: bool


def cache_root() -> Path:
    """The cache folder: $COGMAP_CACHE, else $XDG_CACHE_HOME/cogmap, else ~/.cache/cogmap."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV]).expanduser()
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]).expanduser() / "cogmap"
    return Path.home() / ".cache" / "cogmap"


def cached_path(name: str, cache: Path | str | None = None) -> Path:
    """Where the paper file `name` is kept in the cache (a folder per pinned commit)."""
    spec = paper_file(name)
    root = Path(cache).expanduser() if cache is not None else cache_root()
    return root / "paper" / PAPER_COMMIT / spec.filename


def file_sha256(path: Path | str) -> str:
    """The sha256 of a file's bytes, as hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def paper_file(name: str) -> PaperFile:
    """The description of paper file `name` ("test" or "train")."""
    try:
        return PAPER_FILES[name]
    except KeyError:
        raise PaperDataError(f"unknown paper file {name!r}; allowed: {', '.join(PAPER_FILES)}") from None


def resolve(
    name: str,
    explicit: str | os.PathLike | None = None,
    *,
    verify: bool = False,
    cache: Path | str | None = None,
    base_url: str | None = None,
    timeout: float = 60.0,
) -> ResolvedFile:
    """Find the paper file `name` ("test" or "train"): `explicit` path (unless None, empty or ``paper``) >
    its environment variable > the cache > a download into the cache. Files from the cache or a download are
    always checked; an explicit or environment path only with `verify=True`. Raises PaperDataError."""
    spec = paper_file(name)
    if explicit is not None and str(explicit) not in ("", PAPER_WORD):
        return _given(spec, Path(explicit).expanduser(), "explicit", f"the explicit path {str(explicit)!r}", verify,
                      cache)
    if os.environ.get(spec.env):
        return _given(spec, Path(os.environ[spec.env]).expanduser(), "env", f"${spec.env}={os.environ[spec.env]!r}",
                      verify, cache)
    target = cached_path(name, cache)
    if target.is_file():
        return _from_cache(spec, target)
    return _fetch(spec, target, spec.url(base_url), timeout)


def _given(spec: PaperFile, path: Path, source: Source, named: str, verify: bool, cache) -> ResolvedFile:
    """A file the user pointed at: used as it is, checked only when asked."""
    if not path.is_file():
        raise PaperDataError(f"{spec.description}: {named} is not a file")
    digest = file_sha256(path)
    if not verify:
        return ResolvedFile(path, digest, source, verified=False)
    expected = spec.sha256 or _recorded_digest(cached_path(spec.name, cache))
    if expected is None:
        raise PaperDataError(f"{spec.description}: cannot verify {named} (sha256 {digest}): no checksum is "
                             f"published for it and none is recorded in the cache yet; fetch it once or "
                             f"pass verify=False")
    if digest != expected:
        raise PaperDataError(f"{spec.description}: {named} has sha256 {digest}, expected {expected}")
    return ResolvedFile(path, digest, source, verified=True)


def _from_cache(spec: PaperFile, target: Path) -> ResolvedFile:
    """The cached copy, checked against the pinned digest or the one recorded at its download. A copy put there
    by hand without a record gets its digest recorded now. A bad copy is removed so the next call fetches."""
    digest = file_sha256(target)
    expected = spec.sha256 or _recorded_digest(target)
    if expected is None:
        try:
            _record_digest(target, digest)
        except OSError:  # a read-only cache, filled by someone else: use it, unverified
            pass
        return ResolvedFile(target, digest, "cache", verified=False)
    if digest != expected:
        try:
            _remove(target)
            _remove(_digest_path(target))
            done = "removed it, the next use fetches it again"
        except OSError as error:
            done = f"could not remove it ({error})"
        raise PaperDataError(f"{spec.description}: the cached {target} has sha256 {digest}, expected {expected}; "
                             f"{done} (or set ${spec.env} to a local copy)")
    return ResolvedFile(target, digest, "cache", verified=True)


def _fetch(spec: PaperFile, target: Path, url: str, timeout: float) -> ResolvedFile:
    """Download `url` beside `target`, check it, then rename it into place (never a partial file there)."""
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        handle = tempfile.NamedTemporaryFile(dir=target.parent, prefix=f".{target.name}.", suffix=".part",
                                             delete=False)
    except OSError as error:
        raise PaperDataError(f"cannot fetch {spec.description} from {url}: the cache folder {target.parent} is not "
                             f"writable ({error}). Set ${CACHE_ENV} to a writable folder, or ${spec.env} to a local "
                             f"copy") from error
    part = Path(handle.name)
    try:
        with handle:
            digest = _download(url, handle, timeout)
            handle.flush()
            os.fsync(handle.fileno())
    except (OSError, ValueError, http.client.HTTPException) as error:
        _remove(part)
        raise PaperDataError(
            f"could not fetch {spec.description} from {url}: {_reason(error)}. Set ${spec.env} to a local copy, "
            f"or put the file at {target} (the cache), or pass an explicit path"
        ) from error
    if spec.sha256 is not None and digest != spec.sha256:
        _remove(part)
        raise PaperDataError(f"{spec.description} downloaded from {url} has sha256 {digest}, expected "
                             f"{spec.sha256}; the download was deleted")
    try:
        _record_digest(target, digest)
        os.chmod(part, 0o644)  # a temporary file is private; the cache may be shared
        os.replace(part, target)
    finally:
        _remove(part)
    return ResolvedFile(target, digest, "fetch", verified=spec.sha256 is not None)


def _download(url: str, handle, timeout: float) -> str:
    """Stream `url` into `handle`; the sha256 of what was written."""
    digest = hashlib.sha256()
    with urllib.request.urlopen(url, timeout=timeout) as response:
        for block in iter(lambda: response.read(1 << 20), b""):
            digest.update(block)
            handle.write(block)
    return digest.hexdigest()


def _reason(error: BaseException) -> str:
    if isinstance(error, urllib.error.HTTPError):
        return f"HTTP {error.code} {error.reason}"
    if isinstance(error, urllib.error.URLError):
        return str(error.reason)
    return str(error) or type(error).__name__


def _digest_path(target: Path) -> Path:
    return target.with_name(target.name + ".sha256")


def _recorded_digest(target: Path) -> str | None:
    """The digest recorded beside a cached file at its download, if any."""
    try:
        return _digest_path(target).read_text().split()[0]
    except (OSError, IndexError):
        return None


def _record_digest(target: Path, digest: str) -> None:
    """Write `<target>.sha256` (``sha256sum -c`` reads it), atomically."""
    target.parent.mkdir(parents=True, exist_ok=True)
    record = _digest_path(target)
    with tempfile.NamedTemporaryFile("w", dir=target.parent, prefix=f".{record.name}.", suffix=".part",
                                     delete=False) as handle:
        handle.write(f"{digest}  {target.name}\n")
    os.chmod(handle.name, 0o644)
    os.replace(handle.name, record)


def _remove(path: Path) -> None:
    try:
        path.unlink()
    except FileNotFoundError:
        pass


def main(argv: list[str] | None = None) -> int:
    """Resolve (and so fetch and cache) the named paper files; print each one's path, sha256 and source."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m pipeline.workflow.paper_data",
                                     description="Fetch the paper's released files into the cache (or find them "
                                                 "through their overrides) and print where they are.")
    parser.add_argument("names", nargs="*", metavar="NAME", help=f"{' or '.join(PAPER_FILES)} (default: both)")
    names = parser.parse_args(argv).names or list(PAPER_FILES)
    unknown = [name for name in names if name not in PAPER_FILES]
    if unknown:
        parser.error(f"unknown file {unknown[0]!r}; allowed: {', '.join(PAPER_FILES)}")
    try:
        for name in names:
            found = resolve(name)
            print(f"{name}\t{found.path}\tsha256 {found.sha256}\t{found.source}"
                  f"{'' if found.verified else ' (not verified)'}")
    except PaperDataError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
