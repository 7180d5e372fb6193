"""CI gates on an eval's scores: `--require 'recall_visible>=0.95'`, a JUnit file and a
Markdown summary for a CI job's page.

A requirement is a key of report.json's `summary` (dotted for nested ones, e.g.
`error_deg.plane.mean`), a comparison (>=, <=, >, <, ==) and a number. It is checked on
the whole run and on each plant (the plant's own summary), so a JUnit file has one test
case per plant and requirement. A requirement whose value is not there (no flowers found:
no mean error) fails. A key that is not a summary number is bad input (exit status 2),
said before anything runs; a requirement that does not hold makes the command's exit
status 1.
"""

from __future__ import annotations

import math
import operator
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from flowerpose.atomic import write_file, write_text
from flowerpose.errors import InputError
from flowerpose.eval.reports.report import markdown_table, run_summary, summary_template

_OPERATORS = {">=": operator.ge, "<=": operator.le, "==": operator.eq, ">": operator.gt,
              "<": operator.lt}
_PATTERN = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*(>=|<=|==|>|<)\s*(\S+)\s*$")


@dataclass(frozen=True)
class Requirement:
    """`key` `op` `value`, as given on the command line (`text`)."""

    key: str
    op: str
    value: float
    text: str

    def holds(self, measured: float | None) -> bool:
        return measured is not None and bool(_OPERATORS[self.op](measured, self.value))


@dataclass(frozen=True)
class Outcome:
    """A requirement checked on one scope ("all" plants or one plant's name)."""

    scope: str
    requirement: Requirement
    measured: float | None

    @property
    def passed(self) -> bool:
        return self.requirement.holds(self.measured)


def parse_requirements(texts: list[str], task: str = "pose") -> list[Requirement]:
    """--require values, checked against the summary's keys of a run of `task`: InputError
    for a malformed one or a key that is not a number of the summary."""
    requirements = []
    for text in texts:
        match = _PATTERN.match(text)
        if match is None:
            raise InputError("require", f"'{text}': expected KEY>=NUMBER (or <=, >, <, ==),"
                             " e.g. 'error_deg.plane.mean<=3'")
        key, op, number = match.groups()
        try:
            value = float(number)
        except ValueError:
            raise InputError("require", f"'{text}': {number!r} is not a number") from None
        if not math.isfinite(value):
            raise InputError("require", f"'{text}': the bound must be finite")
        check_key(key, "require", f"'{text}': ", task)
        requirements.append(Requirement(key, op, value, text))
    return requirements


def check_key(key: str, where: str, said: str = "", task: str = "pose") -> None:
    """InputError unless `key` names a number of report.json's summary (dotted) in a run
    of `task` (the pollination task's adds `pollination.*`)."""
    template = summary_template(task)
    try:
        leaf = _lookup(template, key)
    except KeyError:
        leaf = {}
    if isinstance(leaf, dict):
        if task != "pollinate" and key in _leaves(summary_template("pollinate")):
            raise InputError(where, f"{said}{key} is a number of the pollination task's "
                             "summary only: run with --task pollinate")
        raise InputError(where, f"{said}{key} is not a number of the report's summary (its "
                         f"numbers: {', '.join(_leaves(template))})")


def summary_value(summary: dict, key: str) -> float | None:
    """The number a summary holds under a dotted key (None where there is none)."""
    return _number(summary, key)


def check(report: dict, requirements: list[Requirement]) -> list[Outcome]:
    """Every requirement on the whole run ("all"), then on each plant."""
    outcomes = [Outcome("all", r, _number(report["summary"], r.key)) for r in requirements]
    for plant in report["plants"]:
        summary = run_summary([plant])
        outcomes += [Outcome(plant["plant"], r, _number(summary, r.key)) for r in requirements]
    return outcomes


def outcome_table(outcomes: list[Outcome], failed_only: bool = False) -> str:
    """The requirements as a table: scope, requirement, measured, verdict."""
    rows = [[o.scope, o.requirement.text, _format(o.measured), "pass" if o.passed else "FAIL"]
            for o in outcomes if not (failed_only and o.passed)]
    return markdown_table(["Scope", "Requirement", "Measured", "Verdict"], rows)


def write_summary(path: Path, outcomes: list[Outcome], title: str) -> Path:
    """A Markdown page for a CI job's summary: the verdict, then every requirement."""
    failed = [o for o in outcomes if not o.passed]
    verdict = (f"**{len(failed)} of {len(outcomes)} requirements failed**" if failed
               else f"All {len(outcomes)} requirements hold")
    return write_text(path, f"## {title}\n\n{verdict}\n\n{outcome_table(outcomes)}\n")


def write_junit(path: Path, outcomes: list[Outcome], title: str) -> Path:
    """JUnit XML: a test suite of one test case per scope and requirement."""
    failures = sum(not o.passed for o in outcomes)
    suite = ET.Element("testsuite", name=title, tests=str(len(outcomes)),
                       failures=str(failures), errors="0")
    for o in outcomes:
        case = ET.SubElement(suite, "testcase", classname=f"flowerpose.{o.scope}",
                             name=o.requirement.text)
        if not o.passed:
            ET.SubElement(case, "failure", message=f"measured {_format(o.measured)}").text = (
                f"{o.scope}: {o.requirement.text} does not hold: measured "
                f"{_format(o.measured)}")
    tree = ET.ElementTree(ET.Element("testsuites"))
    tree.getroot().append(suite)
    ET.indent(tree)
    return write_file(path, lambda tmp: tree.write(tmp, encoding="utf-8",
                                                   xml_declaration=True))


def _lookup(tree: Any, key: str) -> Any:
    for part in key.split("."):
        if not isinstance(tree, dict) or part not in tree:
            raise KeyError(key)
        tree = tree[part]
    return tree


def _number(summary: dict, key: str) -> float | None:
    """The number under a dotted key; None where there is none (no flower found, or a
    section this run has not: the close look's `pollination_scan_pose` without a look)."""
    try:
        value = _lookup(summary, key)
    except KeyError:
        return None
    return None if value is None else float(value)


def _leaves(tree: dict, prefix: str = "") -> list[str]:
    names = []
    for key, value in tree.items():
        names += (_leaves(value, f"{prefix}{key}.") if isinstance(value, dict)
                  else [f"{prefix}{key}"])
    return names


def _format(value: float | None) -> str:
    return "-" if value is None else f"{value:.4g}"
