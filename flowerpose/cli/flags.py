"""Command-line flags made from settings: a flag is a short name for `--set KEY=VALUE`, its
help the setting's own docstring and its default the setting's value in the command's
starting configuration, so neither is written twice. Library code names the setting when a
value is wrong, and names settings and arguments in backticks in its advice; the command line
says the flag the user types for each (`flag_for`, `say_flags`)."""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable
from typing import Any

#: The argparse attribute that holds a command's {flag dest: setting key}.
FLAGS_ATTRIBUTE = "setting_flags"
#: The argparse attribute that holds a command's {library name: how its flags say it}, for
#: a name no flag sets by itself (the USB camera's `choose` is --keep-all left out).
PHRASES_ATTRIBUTE = "flag_phrases"
#: A setting's or argument's name as library messages quote it.
QUOTED_NAME = re.compile(r"`([A-Za-z_][\w.]*)`")


class SettingHelp(str):
    """A flag's help, written out from the setting when help is shown (the configuration's
    module is imported then, not every time the command line starts)."""

    def __new__(cls, key: str, base: Callable[[], Any], extra: str = "") -> SettingHelp:
        help_text = super().__new__(cls, f"the setting {key}")
        help_text.key, help_text.base, help_text.extra = key, base, extra
        return help_text

    def expanded(self) -> str:
        from flowerpose.config import setting_doc, value_at

        config = self.base()
        doc = setting_doc(config, self.key) or f"the setting {self.key}"
        default = value_at(config, self.key)
        shown = "" if default is None else f"default: {default}; "
        return (f"{self.extra}{doc.rstrip('.')} ({shown}the same as --set "
                f"{self.key}=...)").replace("%", "%%")


def add_setting_flags(parser: argparse.ArgumentParser, base: Callable[[], Any],
                      flags: dict[str, str], metavars: dict[str, str] | None = None,
                      switches: tuple[str, ...] = (), extra: dict[str, str] | None = None) -> None:
    """Flags for settings of the configuration `base()` returns: {"--count": "count"}. A
    flag in `switches` takes no value and sets a true/false setting to true. `extra`: words
    before a flag's help (where it applies: "--sim: ")."""
    metavars, extra = metavars or {}, extra or {}
    known = dict(parser.get_default(FLAGS_ATTRIBUTE) or {})
    for flag, key in flags.items():
        dest = flag.lstrip("-").replace("-", "_")
        help_text = SettingHelp(key, base, extra.get(flag, ""))
        if flag in switches:
            parser.add_argument(flag, dest=dest, action="store_const", const="true",
                                default=None, help=help_text)
        else:
            parser.add_argument(flag, dest=dest, default=None, help=help_text,
                                metavar=metavars.get(flag, "VALUE"))
        known[dest] = key
    parser.set_defaults(**{FLAGS_ATTRIBUTE: known})


def given_settings(args: argparse.Namespace) -> list[str]:
    """The settings the command's flags were given, as --set items."""
    flags = getattr(args, FLAGS_ATTRIBUTE, None) or {}
    return [f"{key}={getattr(args, dest)}" for dest, key in flags.items()
            if getattr(args, dest, None) is not None]


def flag_for(parser: argparse.ArgumentParser, args: argparse.Namespace, name: str) -> str | None:
    """The flag of the command that sets `name`: a setting key one of its flags sets, or an
    argument's name (`plants` for --plants); None when no flag does."""
    flags = getattr(args, FLAGS_ATTRIBUTE, None) or {}
    dests = {key: dest for dest, key in flags.items()}
    dest = dests.get(name, name)
    command = _subparser(parser, args)
    for action in command._actions:
        if action.dest == dest and action.option_strings:
            return max(action.option_strings, key=len)
    return None


def _subparser(parser: argparse.ArgumentParser,
               args: argparse.Namespace) -> argparse.ArgumentParser:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices.get(getattr(args, "command", ""), parser)
    return parser


def say_flags(parser: argparse.ArgumentParser, args: argparse.Namespace, text: str) -> str:
    """`text` (a library's message) with each name it quotes in backticks said as the
    command's flag for it, or its phrase; a name the command has no flag for keeps its
    quotes (it is a setting for --set or a config file)."""
    phrases = getattr(args, PHRASES_ATTRIBUTE, None) or {}

    def said(match: re.Match) -> str:
        name = match.group(1)
        return phrases.get(name) or flag_for(parser, args, name) or match.group(0)
    return QUOTED_NAME.sub(said, text)
