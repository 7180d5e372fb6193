"""The README's commands work as written: each one parses, each synopsis names real
options, and each one that is quick and needs no bot runs, in the README's order, in a
scratch folder; those of the authors' real plant fetch it from a mirror made of the shared
copy (`../shared/real/`, beside the repository, or the folder FLOWERPOSE_SHARED names). A
command the README marks ⏱ (a long job) or "needs the bot" has its arguments checked only."""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from flowerpose.cli import build_parser

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
SHARED = Path(os.environ.get("FLOWERPOSE_SHARED", REPO.parent / "shared"))
LONG, BOT = "⏱", "needs the bot"
#: A word of a synopsis that stands for a value: DIR, N, CLOUD.ply, SYNTH_DIR..., key=v1,...
PLACEHOLDER = re.compile(r"\.\.\.|[\[\]|]|^[A-Z][A-Z0-9_]*(\.[a-z]+)?$|^--[a-z-]+=[A-Z]")


@dataclass(frozen=True)
class Command:
    text: str
    """The command as written (continuation lines joined, comment removed)."""
    line: int
    """Its line in the README."""
    long: bool
    bot: bool
    synopsis: bool
    """A usage line with placeholders, not a command to run."""

    @property
    def argv(self) -> list[str]:
        """The arguments after `flowerpose` (a `time`, an environment variable or a
        `.venv/bin/` before it left out)."""
        words = self.text.split() if self.synopsis else shlex.split(self.text)
        while words and (words[0] == "time" or re.match(r"^[A-Z_]+=", words[0])):
            words.pop(0)
        return words[1:]

    @property
    def is_name(self) -> bool:
        """A command's name in the prose (`flowerpose detect`), not a command that runs as
        it stands."""
        return not self.synopsis and len(self.argv) == 1 and not _parses(self.argv)

    @property
    def runs(self) -> bool:
        return not (self.long or self.bot or self.synopsis or self.is_name)

    def __str__(self) -> str:
        return f"README.md:{self.line}: {self.text}"


def _parses(argv: list[str]) -> bool:
    """Whether the command line takes these arguments (--version and --help exit 0 once
    they have said it)."""
    import contextlib
    import io

    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            build_parser().parse_args(argv)
    except SystemExit as exit_:
        return exit_.code == 0
    return True


def _is_flowerpose(text: str) -> bool:
    """A flowerpose command with something after the program's name."""
    return bool(re.match(r"^(time |[A-Z_]+=\S+ )*(\.venv/bin/)?flowerpose \S", text))


def _synopsis(text: str) -> bool:
    return any(PLACEHOLDER.search(word) for word in text.split()[1:])


def readme_commands() -> list[Command]:
    """Every flowerpose command of the README: the lines of its sh blocks, its text blocks'
    usage lines, its CI job's, and the commands quoted in its prose."""
    text = README.read_text(encoding="utf-8")
    commands = []
    for fence in re.finditer(r"^```(\w*)\n(.*?)^```", text, re.S | re.M):
        kind, body = fence.group(1), fence.group(2)
        first = text[:fence.start(2)].count("\n") + 1
        if kind == "yaml":  # a CI job: its folded `run: >` commands
            for job in re.finditer(r"- run: >(.*)\n((?:    .*\n?)+)", body):
                text_ = " ".join(job.group(2).split())
                if _is_flowerpose(text_):
                    commands.append(Command(text_, first + body[:job.start()].count("\n"),
                                            LONG in job.group(1), False, False))
            continue
        lines = body.splitlines()
        k = 0
        while k < len(lines):
            start, joined = k, lines[k]
            while joined.rstrip().endswith("\\") or (kind == "text" and k + 1 < len(lines)
                                                      and lines[k + 1].startswith(" ")):
                k += 1
                joined = joined.rstrip().removesuffix("\\") + " " + lines[k].strip()
            k += 1
            command, _, comment = joined.partition(" #")
            command = " ".join(command.split())
            if _is_flowerpose(command):
                commands.append(Command(command, first + start, LONG in comment,
                                        BOT in comment, kind == "text" or _synopsis(command)))
    prose = re.sub(r"^```.*?^```", lambda m: "\n" * m.group(0).count("\n"), text,
                   flags=re.S | re.M)
    for span in re.finditer(r"`([^`]+)`( ⏱)?", prose):
        quoted = " ".join(span.group(1).split())
        if _is_flowerpose(quoted):
            commands.append(Command(quoted, prose[:span.start()].count("\n") + 1,
                                    bool(span.group(2)), False, _synopsis(quoted)))
    return commands


COMMANDS = readme_commands()


def _subcommands() -> dict:
    import argparse

    return next(a for a in build_parser()._actions
                if isinstance(a, argparse._SubParsersAction)).choices


def test_the_readme_has_commands_of_every_kind():
    assert len(COMMANDS) > 25
    assert sum(c.runs for c in COMMANDS) >= 8
    assert any(c.long for c in COMMANDS) and any(c.bot for c in COMMANDS)
    assert any(c.synopsis for c in COMMANDS)


@pytest.mark.parametrize("command", COMMANDS, ids=[f"line{c.line}" for c in COMMANDS])
def test_each_readme_command_parses_as_written(command):
    argv = command.argv
    commands = _subcommands()
    if command.synopsis:
        # A usage line: its command exists and names its real options; a placeholder for the
        # command (`flowerpose COMMAND --help`) names options every command has.
        name = argv[0]
        assert PLACEHOLDER.search(name) or name in commands, command
        named = list(commands.values()) if PLACEHOLDER.search(name) else [commands[name]]
        options = [option for word in argv[1:]
                   for option in re.findall(r"(?<![\w-])(--[a-z][a-z-]*)", word)]
        for parser in named:
            known = {o for a in parser._actions for o in a.option_strings}
            missing = [option for option in options if option not in known]
            assert not missing, f"{command}: {parser.prog} has no option {missing}"
        return
    if command.is_name:
        assert argv[0] in commands, f"{command}: no such command"
        return
    assert _parses(argv), f"{command}: does not parse"


def _environment(extra: dict | None = None) -> dict:
    return {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}"
            f"{os.environ.get('PATH', '')}", "MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl",
            **(extra or {})}


def _interruptible() -> None:
    """Ctrl-C as a terminal gives it: a job started in the background (a CI runner's, a
    shell's `&`) has SIGINT ignored, its children too, and the signal would never arrive."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _serve(command: Command, cwd: Path) -> str | None:
    """A command that serves until stopped (the virtual Farmduino): it must print its
    device path, then stop cleanly at Ctrl-C; the problem, or None."""
    process = subprocess.Popen(["bash", "-c", f"exec {command.text}"], cwd=cwd,
                               env=_environment(), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, preexec_fn=_interruptible)
    try:
        path = process.stdout.readline().strip()
        if not path or not Path(path).exists():
            return f"printed {path!r}, not a device path"
    finally:
        process.send_signal(signal.SIGINT)
        try:
            _, err = process.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            return "did not stop at Ctrl-C"
    return None if process.returncode == 0 else f"exit status {process.returncode}: {err}"


def _run_all(commands: list[Command], cwd: Path, extra: dict | None = None) -> None:
    """Run the commands in order in `cwd` (a later one may read what an earlier one
    wrote), each distinct command once, with `extra` in their environment; fail naming
    every one that did not succeed."""
    failures = []
    distinct = {command.text: command for command in reversed(commands)}
    for command in sorted(distinct.values(), key=commands.index):
        if command.argv[0] == "farmduino":
            problem = _serve(command, cwd)
        else:
            done = subprocess.run(["bash", "-c", command.text], cwd=cwd,
                                  env=_environment(extra), capture_output=True, text=True,
                                  timeout=300)
            # A CI gate that does not hold exits 1 by design; anything else must succeed.
            allowed = (0, 1) if "--require" in command.argv else (0,)
            problem = None if done.returncode in allowed and "Traceback" not in done.stderr \
                else f"exit status {done.returncode}: {done.stderr.strip()[-2000:]}"
        if problem:
            failures.append(f"{command}\n  {problem}")
    assert not failures, "\n".join(failures)


def _needs_shared(command: Command) -> bool:
    """A command of the authors' real plant, which `data fetch` downloads (the test
    fetches it from a mirror made of the shared copy, never the network)."""
    return "paper-plant-3" in command.text


def _mirror_of_the_shared_plant(mirror: Path) -> Path:
    """A local copy of the published plant laid out as its repository is, made from the
    shared copy, so that `data fetch` reads it instead of the network."""
    from flowerpose.data import PLANTS

    for item in PLANTS["paper-plant-3"].files:
        source = (SHARED / "real" / item.local if item.local.startswith("LICENSE")
                  else SHARED / "real" / "paper-plant-3" / item.local)
        (mirror / item.upstream).parent.mkdir(parents=True, exist_ok=True)
        (mirror / item.upstream).write_bytes(source.read_bytes())
    return mirror


@pytest.mark.slow
def test_the_readme_examples_run_as_written(tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    _run_all([c for c in COMMANDS if c.runs and not _needs_shared(c)], work)
    if not (SHARED / "real").is_dir():
        pytest.skip(f"no shared real plants at {SHARED / 'real'} (FLOWERPOSE_SHARED): "
                    "the real plant's commands were not run")
    mirror = _mirror_of_the_shared_plant(tmp_path / "mirror")
    _run_all([c for c in COMMANDS if c.runs and _needs_shared(c)], work,
             {"FLOWERPOSE_DATA_MIRROR": str(mirror)})
