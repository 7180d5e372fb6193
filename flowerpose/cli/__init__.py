"""The `flowerpose` command line: one console script, one subcommand per stage or job. This
package's modules each hold a group of commands (`jobs`: eval, fidelity, bench, results,
cache; `study`: sweep, stress, tune, guard; `stages`; `field`: the bot's; `data`), what
they share (`options`, `flags`) and the generated reference (`reference`); this module
builds the parser from them and turns what goes wrong into one line."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

from flowerpose.cli import data, field, jobs, stages, study
from flowerpose.cli.flags import SettingHelp, flag_for, say_flags
from flowerpose.errors import InputError, JobsFailed, missing_extra
from flowerpose.hardware.bot_errors import BotError
from flowerpose.stopwatch import process_age

#: The subcommands in the order `flowerpose --help` lists them: each module adds its own.
COMMANDS = (
    jobs.add_eval,
    stages.add_plant,
    field.add_scan,
    field.add_pollinate,
    field.add_field,
    field.add_farmduino,
    stages.add_marker,
    stages.add_frames,
    stages.add_reconstruct,
    stages.add_dataset,
    stages.add_detect,
    stages.add_pose,
    stages.add_score,
    stages.add_label,
    stages.add_agree,
    study.add_sweep,
    study.add_stress,
    study.add_tune,
    study.add_guard,
    jobs.add_results,
    jobs.add_fidelity,
    jobs.add_cache,
    jobs.add_bench,
    data.add_data,
)


class _HelpFormatter(argparse.HelpFormatter):
    """argparse's help, with the description's and epilog's paragraphs filled to the
    terminal's width, a paragraph with indented lines (the examples) kept as written, and a
    setting's flag explained by the setting's own docstring."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if isinstance(action.help, SettingHelp):
            return action.help.expanded()
        return super()._get_help_string(action)

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        import textwrap

        paragraphs = []
        for paragraph in text.split("\n\n"):
            lines = paragraph.splitlines()
            if any(line.startswith(" ") for line in lines):
                paragraphs.append("\n".join(indent + wrapped for line in lines
                                            for wrapped in _shell_lines(line, width)))
            else:
                paragraphs.append(textwrap.fill(" ".join(paragraph.split()), width,
                                                initial_indent=indent,
                                                subsequent_indent=indent))
        return "\n\n".join(paragraphs)


def _shell_lines(line: str, width: int) -> list[str]:
    """An example command as lines of at most `width` characters (where its words allow),
    continued with a backslash as a shell reads them; a line with a comment stays whole."""
    if len(line) <= width or "#" in line:
        return [line]
    import textwrap

    margin = line[:len(line) - len(line.lstrip())]
    parts = textwrap.wrap(line.strip(), width - len(margin) - 2, break_long_words=False,
                          break_on_hyphens=False, subsequent_indent="    ")
    return [margin + part + (" \\" if k < len(parts) - 1 else "")
            for k, part in enumerate(parts)]


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (`flowerpose: error: ...`, exit status 2) and help
    whose examples keep their lines."""

    def __init__(self, *args: Any, **kwargs: Any):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> None:  # type: ignore[override]
        command = self.prog.removeprefix("flowerpose").strip()
        where = f"{command}: " if command else ""
        self.exit(2, f"flowerpose: error: {where}{message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="flowerpose",
        description="Estimate the 3D poses of strawberry flowers in point clouds, and score "
        "them against exact synthetic truth or hand labels. Each command is a stage of the "
        "method or a job made of them; `flowerpose COMMAND --help` says more.",
        epilog="examples:\n"
        "  flowerpose eval --source oracle --plants 2  # the pipeline alone\n"
        "  flowerpose eval                             # the full loop, 10 min")
    from flowerpose import __version__

    parser.add_argument("--version", action="version", version=f"flowerpose {__version__}")
    _add_verbosity(parser, default=0)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=_Parser)

    for add in COMMANDS:
        add(sub)
    for command in sub.choices.values():
        _add_verbosity(command, default=argparse.SUPPRESS)
    return parser


def _add_verbosity(parser: argparse.ArgumentParser, default: Any) -> None:
    """-q / -v, before or after the command (`flowerpose -q eval`, `flowerpose eval -q`)."""
    parser.add_argument("-q", "--quiet", action="count", default=default,
                        help="say only warnings and errors (no progress)")
    parser.add_argument("-v", "--verbose", action="count", default=default,
                        help="say more: debugging detail")


def _standard_streams() -> None:
    """A closed standard output or error (`flowerpose ... >&-`) becomes /dev/null: what the
    command says there goes nowhere, and the command still runs and ends cleanly."""
    for name in ("stdout", "stderr"):
        if getattr(sys, name) is None:
            stream = open(os.devnull, "w")  # noqa: SIM115 - for the rest of the process
            setattr(sys, name, stream)
            setattr(sys, f"__{name}__", stream)


def main(argv: list[str] | None = None) -> int:
    from flowerpose.log import configure as configure_log
    from flowerpose.log import third_party
    from flowerpose.processes import Terminated, terminate_cleanly

    _standard_streams()
    parser = build_parser()
    if not (sys.argv[1:] if argv is None else argv):
        parser.print_help()  # a bare `flowerpose`: what it can do, not an error
        return 0
    # Launched as a program, the clock starts with the process (imports included).
    started = time.monotonic() - (process_age() if argv is None else 0.0)
    import flowerpose

    flowerpose.invocation = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    args.started = started
    configure_log(args.verbose - args.quiet)
    terminate_cleanly()
    try:
        out = getattr(args, "out", None)
        if isinstance(out, Path):  # every command's output folder, tried before any work
            from flowerpose.outputs import check_folder_writable

            check_folder_writable(out)
        with third_party():  # other libraries' warnings: debug lines (-v), not the user's
            return args.func(args)
    except InputError as err:
        # Library code names the setting or argument; say the flag the user typed for it.
        flag = flag_for(parser, args, err.source)
        problem = say_flags(parser, args, err.problem)
        print(f"flowerpose: error: {flag or err.source}: {problem}", file=sys.stderr)
        return 2
    except BotError as err:
        # A fault of the bot or its link, said in one line that names the device.
        print(f"flowerpose: error: {say_flags(parser, args, str(err))}", file=sys.stderr)
        return 2
    except JobsFailed as err:
        # Plants whose jobs failed (on Ray, on every try); the others' results are kept.
        print(f"flowerpose: error: {err}", file=sys.stderr)
        return 1
    except ModuleNotFoundError as err:
        # An optional package of an extra the install left out: say which extra.
        missing = missing_extra(err.name or "", f"flowerpose {args.command}")
        if missing is None:
            raise
        print(f"flowerpose: error: {missing}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader went away (`flowerpose ... | head`): nothing left to tell anyone.
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115
        return 0
    except OSError as err:
        # A path the user gave that cannot be written or read (an --out that is a file, a
        # read-only folder, a full disk): their problem to fix, not a bug.
        where = err.filename or "file system"
        print(f"flowerpose: error: {where}: {err.strerror or err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("flowerpose: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        print("flowerpose: terminated", file=sys.stderr)
        return 143
