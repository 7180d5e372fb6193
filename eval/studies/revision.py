"""Another revision's flowerpose, run beside this one (`flowerpose guard --base REV`).

The revision's files are taken from the git repository this flowerpose runs from (`git
archive`, so nothing in the repository changes: no worktree is registered, no branch
moved) and laid out as the installed namespace (`flowerpose`, `flowerpose.pipeline`, ...)
by that revision's own `pyproject.toml` (its `[tool.setuptools] package-dir`), so a
revision with another layout runs too. A command then runs as `python -P -m flowerpose`
with the laid-out tree first on the path: the same interpreter and libraries, that
revision's code. The working tree's side runs the same way without the tree, so both sides
go through the same command line.
"""

from __future__ import annotations

import io
import os
import shutil
import subprocess
import sys
import tarfile
import tomllib
import uuid
from dataclasses import dataclass
from pathlib import Path

from flowerpose.errors import InputError
from flowerpose.log import LOG

#: The file a laid-out tree is marked whole by.
_WHOLE = ".flowerpose-revision"


def repository() -> Path:
    """The git checkout this flowerpose runs from; InputError where it runs from an
    installed copy (a revision needs the repository's history)."""
    source = Path(__file__).resolve().parent.parent
    found = _git(source, "rev-parse", "--show-toplevel", check=False)
    if found.returncode != 0:
        raise InputError("--base", f"flowerpose runs from {source}, not a git checkout: the "
                         "guard compares with a revision of the repository, so run it from a "
                         "clone (git clone ...; make setup)")
    return Path(found.stdout.strip())


def resolve(repo: Path, revision: str) -> str:
    """The full commit `revision` names in `repo`; InputError naming it where there is
    none (a shallow clone lacks the history: `git fetch --unshallow`)."""
    found = _git(repo, "rev-parse", "--verify", "--quiet", f"{revision}^{{commit}}",
                 check=False)
    if found.returncode != 0 or not found.stdout.strip():
        shallow = _git(repo, "rev-parse", "--is-shallow-repository", check=False)
        hint = (" (this clone is shallow: git fetch --unshallow)"
                if shallow.stdout.strip() == "true" else "")
        raise InputError("--base", f"{revision!r} names no commit of {repo}{hint}")
    return found.stdout.strip()


def head(repo: Path) -> str:
    """The commit checked out in `repo`."""
    return _git(repo, "rev-parse", "HEAD").stdout.strip()


def dirty(repo: Path, ignore: tuple[Path, ...] = ()) -> list[str]:
    """The tracked files with uncommitted changes (but `ignore`), as git names them."""
    status = _git(repo, "status", "--porcelain", "--untracked-files=no").stdout
    ignored = {Path(p).resolve() for p in ignore}
    return [line[3:] for line in status.splitlines()
            if (repo / line[3:]).resolve() not in ignored]


@dataclass(frozen=True)
class Revision:
    """A flowerpose to run commands with: a laid-out revision (`tree`), or, without one,
    the flowerpose this process runs."""

    name: str
    """What reports call it: a commit, or "working tree"."""
    commit: str | None = None
    tree: Path | None = None

    def run(self, arguments: list[str], log: Path) -> None:
        """`flowerpose ARGUMENTS` with this revision's code, its output into `log`;
        InputError naming the revision, the command and the log's last line where it
        fails."""
        environment = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        if self.tree is not None:
            environment["PYTHONPATH"] = str(self.tree)
        log.parent.mkdir(parents=True, exist_ok=True)
        command = [sys.executable, "-P", "-m", "flowerpose", *arguments]
        with open(log, "w", encoding="utf-8") as output:
            # From the caller's folder, so that relative paths in `arguments` mean what
            # they meant to the caller; PYTHONPATH (not the folder, -P) picks the code.
            finished = subprocess.run(command, stdout=output, stderr=subprocess.STDOUT,
                                      env=environment)
        if finished.returncode != 0:
            lines = [line for line in log.read_text(encoding="utf-8").splitlines() if line]
            raise InputError(self.name, f"`flowerpose {' '.join(arguments)}` failed (exit "
                             f"{finished.returncode}): {lines[-1] if lines else 'no output'}"
                             f" (all of it in {log})")


def materialise(repo: Path, commit: str, into: Path) -> Revision:
    """The revision `commit` of `repo` laid out under `into`/COMMIT as the installed
    namespace (module docstring), reused where a whole one is there."""
    tree = into / commit
    if (tree / _WHOLE).is_file():
        return Revision(commit[:12], commit, tree)
    layout = _package_folders(repo, commit)
    roots = sorted({folder.split("/")[0] for folder in layout.values()})
    archive = _git(repo, "archive", "--format=tar", commit, "--", *roots, text=False).stdout
    private = into / f".{commit}.partial-{uuid.uuid4().hex[:8]}"
    private.mkdir(parents=True)
    try:
        unpacked = private / "archive"
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(unpacked, filter="data")
        laid = private / "tree"
        for package, folder in sorted(layout.items(), key=lambda item: item[0].count(".")):
            target = laid.joinpath(*package.split("."))
            if not target.exists() and (unpacked / folder).is_dir():
                shutil.copytree(unpacked / folder, target)
        (laid / _WHOLE).write_text(commit + "\n", encoding="utf-8")
        if tree.exists():
            shutil.rmtree(tree)
        os.rename(laid, tree)
    finally:
        shutil.rmtree(private, ignore_errors=True)
    LOG.info(f"guard: revision {commit[:12]} laid out in {tree}")
    return Revision(commit[:12], commit, tree)


def _package_folders(repo: Path, commit: str) -> dict[str, str]:
    """The revision's packages and their folders, from its pyproject.toml."""
    text = _git(repo, "show", f"{commit}:pyproject.toml").stdout
    settings = tomllib.loads(text).get("tool", {}).get("setuptools", {})
    folders = dict(settings.get("package-dir", {}))
    for package in settings.get("packages", []):
        folders.setdefault(package, package.replace(".", "/"))
    if "flowerpose" not in folders:
        raise InputError("--base", f"{commit[:12]}: its pyproject.toml installs no flowerpose "
                         "package")
    return folders


def _git(repo: Path, *arguments: str, check: bool = True, text: bool = True
         ) -> subprocess.CompletedProcess:
    try:
        done = subprocess.run(["git", "-C", str(repo), *arguments], capture_output=True,
                              text=text, timeout=600)
    except OSError as err:
        raise InputError("git", f"cannot run git: {err.strerror or err}") from None
    if check and done.returncode != 0:
        error = done.stderr if text else done.stderr.decode(errors="replace")
        raise InputError("git", f"git {' '.join(arguments)}: {error.strip().splitlines()[-1]}")
    return done
