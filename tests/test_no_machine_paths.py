"""No tracked file names a place on one machine, or reaches outside the repository.

A clone must work wherever it lands, so the repository's files may not hard-code an absolute location that
exists on one machine only (a home folder, a mounted work or scratch disk, a temporary folder, a Windows
drive), nor a relative path that climbs out of the checkout (a sibling folder of the clone, a markdown
link above the root). System paths that are the same on every machine (the null device, proc files, the
env shebang) and URLs are fine, and so are paths under the user's home written with a tilde or a variable.

Each finding is reported as ``file:line: what: text``. The scanners are tested on examples of their own first,
so a finding in the repository can be trusted to be one.
"""

from __future__ import annotations

import posixpath
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# An absolute path starts at a token boundary: not inside a word, a URL host or path, a `~/...` or a
# `$VAR/...` or `{var}/...` expansion. A slash before is allowed, so `file:///x` and `sqlite:////x` are caught.
_START = r"(?<![\w.~$}\-])"
_MACHINE_ROOTS = (
    r"(?:work|scratch|mnt|media|data|srv|gpfs|lustre|nfs|root|var/folders|var/tmp|private/var|private/tmp)/"
    r"|(?:home|Users)/[^/\s\"'`)]+"
    r"|tmp(?=[/\"'`)\],:;\s]|$)"
)
ABSOLUTE = re.compile(_START + r"/(?:" + _MACHINE_ROOTS + r")")
# A drive letter and a backslash (`\\` in a Python literal); a single backslash only when it does not start a
# common escape, so a label such as `X:` before a newline escape is not a Windows path.
WINDOWS = re.compile(r"(?<![\w\\])[A-Z]:(?:\\\\|\\(?![nrt\\])|/(?=Users|Windows|Program))(?=[\w .$~-])")
# A relative path that climbs: `../` at a token boundary.
CLIMB = re.compile(r"(?<![\w.~$}/\\-])(\.\./[^\s\"'`)\]}>,;]*)")
# Markdown links: inline `[text](target)`, images, reference definitions, and HTML src/href.
LINKS = (
    re.compile(r"\]\(\s*<?([^)\s>]+)"),
    re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)"),
    re.compile(r"""(?:src|href)\s*=\s*["']([^"']+)["']"""),
)
_URL = re.compile(r"^(?:[A-Za-z][\w+.-]*:|//|#)")
# `Path(__file__)` climbed with `.parents[k]` or `.parent` chains.
FILE_PARENTS = re.compile(r"Path\(__file__\)(?:\.resolve\(\)|\.absolute\(\))?((?:\.parent\b)+|\.parents\[(\d+)\])")

MARKUP = {".md", ".markdown", ".rst", ".html"}
# The folder beside the checkout where the development machines keep shared files: never the repository's.
_SIBLING_SHARED = ".." + "/shared"


@dataclass(frozen=True)
class Finding:
    path: str
    line: int
    what: str
    text: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.what}: {self.text}"


def _leaves(base: str, target: str) -> bool:
    """Whether `target`, relative to the repository folder `base` ('' for the root), resolves above the root."""
    resolved = posixpath.normpath(posixpath.join(base, target)) if base else posixpath.normpath(target)
    return resolved == ".." or resolved.startswith("../")


def _relative_base(path: str) -> str:
    """What a relative path in this file is relative to: its own folder for code and markup (imports, Hydra's
    config_path, links), the repository root for configs and scripts (run from the root)."""
    return posixpath.dirname(path) if Path(path).suffix in MARKUP | {".py"} else ""


def _file_depth(path: str) -> int:
    return path.count("/")


def scan_line(path: str, number: int, line: str) -> list[Finding]:
    """The machine paths and climbing paths on one line of the tracked file `path` (repository-relative)."""
    found: list[Finding] = []
    for match in ABSOLUTE.finditer(line):
        found.append(Finding(path, number, "absolute machine path", _around(line, match)))
    for match in WINDOWS.finditer(line):
        found.append(Finding(path, number, "Windows drive path", _around(line, match)))
    base = _relative_base(path)
    if Path(path).suffix in MARKUP:
        for pattern in LINKS:
            for match in pattern.finditer(line):
                target = match.group(1).split("#")[0].split("?")[0]
                if target and not _URL.match(target) and not target.startswith("/") and _leaves(base, target):
                    found.append(Finding(path, number, "link outside the repository", target))
    for match in CLIMB.finditer(line):
        if match.group(1).startswith(_SIBLING_SHARED) or _leaves(base, match.group(1)):
            found.append(Finding(path, number, "relative path outside the repository", _around(line, match)))
    if path.endswith(".py"):
        for match in FILE_PARENTS.finditer(line):
            up = int(match.group(2)) if match.group(2) is not None else match.group(1).count(".parent") - 1
            if up > _file_depth(path):
                found.append(Finding(path, number, "path above the repository root", match.group(0)))
    return _unique(found)


def _around(line: str, match: re.Match) -> str:
    start, end = match.span()
    while end < len(line) and not line[end].isspace() and line[end] not in "\"'`)]},":
        end += 1
    return line[start:end]


def _unique(found: list[Finding]) -> list[Finding]:
    seen, kept = set(), []
    for finding in found:
        key = (finding.what == "link outside the repository" or finding.what.startswith("relative"), finding.text)
        if key not in seen:
            seen.add(key)
            kept.append(finding)
    return kept


def scan_file(root: Path, path: str) -> list[Finding]:
    """Every finding in one tracked file (text files only; a symbolic link is judged by its target)."""
    full = root / path
    if full.is_symlink():
        return scan_line(path, 0, str(full.readlink()))
    if not full.is_file():
        return []  # tracked but deleted in this working tree
    data = full.read_bytes()
    if b"\0" in data[:8192]:
        return []
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        return []
    return [finding for number, line in enumerate(text.splitlines(), 1) for finding in scan_line(path, number, line)]


def tracked_files(root: Path) -> list[str]:
    """The repository's tracked files (`git ls-files`); skips where this is not a git checkout."""
    try:
        listed = subprocess.run(["git", "-C", str(root), "ls-files", "-z"], capture_output=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        pytest.skip(f"not a git checkout (or no git): cannot list the tracked files of {root.name}")
    return [name for name in listed.stdout.decode().split("\0") if name]


# --------------------------------------------------------------------------------------- the repository
# Third-party data, not text of ours: a BPE vocabulary holds pieces that read as paths.
NOT_SCANNED = {"tests/fixtures/llama3_tokenizer/tokenizer.json"}


def test_no_tracked_file_names_a_machine_path_or_leaves_the_repository():
    findings = [finding for path in tracked_files(ROOT) if path not in NOT_SCANNED for finding in scan_file(ROOT, path)]
    if findings:
        pytest.fail("machine-specific or out-of-repository paths (use a repository-relative path, a config "
                    "value, an environment variable or pipeline.workflow.paper_data):\n" + "\n".join(map(str, findings)),
                    pytrace=False)


# ------------------------------------------------------------------------- the scanners on their own cases
def _p(*parts: str) -> str:
    """A path assembled from parts, so this file holds no path literal that its own scan would report."""
    return "/" + "/".join(parts)


UP = ".." + "/"  # likewise for a climbing relative path


FLAGGED = [
    ("tests/conftest.py", f'candidates = ["{_p("work", "shared", "data", "x.jsonl")}"]', "absolute machine path"),
    ("bench.py", f'default=Path("{_p("tmp", "gpu_paths")}")', "absolute machine path"),
    ("bench.py", f'scratch = "{_p("tmp")}"', "absolute machine path"),
    ("x.py", f'uri = "sqlite:///{_p("work", "outputs", "mlflow.db")}"', "absolute machine path"),
    ("x.py", f'uri = "file://{_p("home", "alice", "data")}"', "absolute machine path"),
    ("README.md", f"copied from `{_p('Users', 'bob', 'cogmap')}`", "absolute machine path"),
    ("README.md", f"the store in {_p('scratch', 'runs')} holds", "absolute machine path"),
    ("x.py", 'root = "C:' + "\\\\" + 'Users' + "\\\\" + 'me"', "Windows drive path"),
    ("README.md", "open C:" + "\\" + "Users" + "\\" + "me" + "\\" + "file.txt", "Windows drive path"),
    ("conf/data/paper.yaml", f"test_file: ${{oc.env:COGMAP_PAPER_TEST,{UP}shared/data/paper.jsonl}}",
     "relative path outside the repository"),
    ("conf/data/x.yaml", f"test_file: {UP}elsewhere/x.jsonl", "relative path outside the repository"),
    ("README.md", f"[the spec]({UP}shared/SPEC.md).", "link outside the repository"),
    ("docs/a.md", f"[up two]({UP}{UP}other/README.md)", "link outside the repository"),
    ("docs/a.md", f'<img src="{UP}{UP}logo.png">', "link outside the repository"),
    ("docs/a.md", f"[ref]: {UP}{UP}notes.md", "link outside the repository"),
    ("tests/conftest.py", 'Path(__file__).resolve().parents[' + '2] / "shared"', "path above the repository root"),
    ("tests/conftest.py", "Path(__file__).parent" + ".parent.parent / 'x'", "path above the repository root"),
]

NOT_FLAGGED = [
    ("x.py", 'Path("/dev/null"), Path("/proc/cpuinfo").read_text(), "/sys/fs/cgroup"'),
    (".ci/run", "#!/usr/bin/env bash"),
    (".ci/run", 'cd "$(dirname "$0")/.."'),
    ("README.md", "see https://github.com/kaistAI/language_extrapolation/tree/main/envs/gridworld/data/x"),
    ("README.md", "served from http://example.org/home/alice/ and https://host/tmp/x"),
    ("README.md", "mlflow ui --backend-store-uri sqlite:///outputs/mlflow.db"),
    ("README.md", "eval from `outputs/work/<step>/<hash>/` and train/tmp/ and data/tmp"),
    ("README.md", "cached under `~/.cache/cogmap`, `$XDG_CACHE_HOME/cogmap` or `$HOME/work/x`"),
    ("README.md", "[the spec](docs/spec.md) and [a section](#report) and [web](https://example.org/../x)"),
    ("docs/spec.md", "[the README](../README.md) and ![fig](./figs/a.png)"),
    ("pipeline/run.py", '@hydra.main(version_base="1.3", config_path="../conf", config_name="config")'),
    ("tests/test_x.py", 'ROOT = Path(__file__).resolve().parents[1]; f"{tmp_path}/tmp/x"; tmp_path / "tmp"'),
    ("x.py", r'text = "Thought:\nStep 1:\n(0, 1)\nup"; label = "X:\nfoo\nbar"'),
    ("x.py", 'pattern = r"\\d+:\\s*(\\w+)"; ratio = "1:2"; "w/o"; "and/or"; "input/output"'),
    ("x.py", "for a in range(1, 10): x = a/tmp_count"),
    ("x.py", "path.removeprefix('sqlite:///').removeprefix('file:'); '..'.join(xs); x[..., 0]"),
]


@pytest.mark.parametrize(("path", "line", "what"), FLAGGED)
def test_the_scanner_reports_machine_and_outside_paths(path, line, what):
    assert [finding.what for finding in scan_line(path, 1, line)] == [what], line


@pytest.mark.parametrize(("path", "line"), NOT_FLAGGED)
def test_the_scanner_leaves_legitimate_text_alone(path, line):
    assert scan_line(path, 1, line) == []


def test_a_finding_names_file_and_line(tmp_path):
    (tmp_path / "notes.md").write_text("fine\n" + f"copied from {_p('work', 'x')}\n")
    assert [str(f) for f in scan_file(tmp_path, "notes.md")] == [f"notes.md:2: absolute machine path: {_p('work', 'x')}"]
