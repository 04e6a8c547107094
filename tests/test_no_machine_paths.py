"""No path of the development machine in the project's code, tests or docs.

A clone anywhere else has no such folder: a test that reads one fails (or
silently skips) there, and a documented command does not work. The paths
looked for are computed here, on the machine that runs the test: the absolute
form of ``../shared`` (where the developers keep the method notes and the
original images) and the checkout's parent directory, for this checkout and,
in a git worktree, for the main checkout too. Data the tests need live in
tests/data (tests/datapaths.py)."""

import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: what the tree is checked in: everything a user gets and reads
CHECKED = ["app", "drivers", "processing", "tests", "benchmarks", "resources", "docs", "README.md"]
#: directories every machine has (a clone in /tmp or /home is ordinary): a path under one of
#: them in a doc (e.g. /tmp/.X11-unix, /usr/local/bin) names no particular machine
SYSTEM_DIRS = {"/", "/tmp", "/var/tmp", "/home", "/root", "/usr", "/usr/local", "/opt", "/srv", "/mnt",
               "/media", "/data", "/dev/shm", "/var"}


def _checkouts() -> list[Path]:
    """This checkout, and the main checkout when this one is a git worktree (its .git is a file
    ``gitdir: MAIN/.git/worktrees/NAME``)."""
    found = [ROOT]
    git = ROOT / ".git"
    if git.is_file():
        text = git.read_text(errors="replace").strip()
        if text.startswith("gitdir:"):
            gitdir = Path(text.partition(":")[2].strip())
            if not gitdir.is_absolute():
                gitdir = ROOT / gitdir
            for parent in [gitdir, *gitdir.parents]:
                if parent.name == ".git":
                    found.append(parent.parent)
                    break
    return found


def forbidden_paths() -> set[str]:
    paths = set()
    for checkout in _checkouts():
        for shared in (checkout.parent / "shared", (checkout / ".." / "shared").resolve()):
            paths.add(os.path.normpath(str(shared)))
        for parent in {checkout.parent, checkout.resolve().parent}:
            if str(parent) not in SYSTEM_DIRS:
                paths.add(str(parent))
    return paths


def _pattern(paths) -> re.Pattern:
    # a path, not a piece of a longer word: not after a path character, not followed by one
    # ('/srv/lab' is found in '/srv/lab/x' and '/srv/lab.', not in '/srv/laboratory' nor '/home/a/srv/lab')
    alternatives = "|".join(re.escape(p) for p in sorted(paths, key=len, reverse=True))
    return re.compile(rf"(?<![\w.~/-])(?:{alternatives})(?![\w-]|\.\w)")


def _files():
    for name in CHECKED:
        top = ROOT / name
        if top.is_file():
            yield top
            continue
        for dirpath, dirnames, filenames in os.walk(top):
            dirnames[:] = [d for d in dirnames if d not in {".git", "__pycache__", ".pytest_cache"}]
            for filename in filenames:
                yield Path(dirpath) / filename


def _text(path: Path) -> str | None:
    """The file's text, or None for a binary file (a NUL byte, or not UTF-8)."""
    data = path.read_bytes()
    if b"\0" in data[:8192]:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def machine_path_hits(pattern: re.Pattern) -> list[str]:
    hits = []
    for path in _files():
        text = _text(path)
        if text is None:
            continue
        for number, line in enumerate(text.splitlines(), 1):
            if pattern.search(line):
                hits.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:160]}")
    return hits


def test_the_pattern_finds_a_machine_path_and_nothing_else():
    pattern = _pattern({"/srv/lab", "/srv/lab/shared"})
    assert pattern.search('DATA = Path("/srv/lab/shared/data")')
    assert pattern.search("reads /srv/lab/shared.")
    assert pattern.search("cd /srv/lab && make")
    assert not pattern.search("/srv/laboratory/x")
    assert not pattern.search("/home/me/srv/lab/x")
    assert not pattern.search("tests/data/fsss-needle-waves")


def test_no_path_of_the_development_machine_in_the_tree():
    paths = forbidden_paths()
    assert paths, "no checkout parent found"
    hits = machine_path_hits(_pattern(paths))
    assert not hits, (f"absolute paths of this machine ({', '.join(sorted(paths))}) in the tree; use a path "
                      "inside the repository (data: tests/data, tests/datapaths.py):\n" + "\n".join(hits))
