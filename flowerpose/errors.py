"""User-facing errors: the command line turns these into one line and exit status 2."""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad input from the user (a file, a value, a device): reported as one line, exit 2.

    `source` names what was wrong (a file path, a config key, a device) so the message
    can always say where the problem is.
    """

    def __init__(self, source: str | Path, problem: str):
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")
