"""The command-line reference page (docs/reference/cli.md), made from the parsers themselves
so it cannot say what the commands do not: `python scripts/cli_reference.py` writes it, and
a test fails when the page and the parsers disagree."""

from __future__ import annotations

import argparse
import os
from contextlib import contextmanager

#: The width help is laid out at, whatever the terminal that makes the page: what the
#: site's code blocks show without scrolling.
COLUMNS = 74


@contextmanager
def _columns(width: int):
    previous = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(width)
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = previous


def markdown() -> str:
    """The reference: the command list, then each command's --help, in help order."""
    from flowerpose.cli import build_parser

    with _columns(COLUMNS):
        parser = build_parser()
        commands = next(a for a in parser._actions
                        if isinstance(a, argparse._SubParsersAction)).choices
        parts = ["# Command-line reference", "",
                 "Generated from the parsers by `python scripts/cli_reference.py`: every "
                 "command's `--help`, as `flowerpose COMMAND --help` prints it.", "",
                 "```text", parser.format_help().rstrip(), "```"]
        for name, command in commands.items():
            parts += ["", f"## flowerpose {name}", "", "```text",
                      command.format_help().rstrip(), "```"]
    return "\n".join(parts) + "\n"
