"""The guard's accepted decisions (`assets/guard/accepted.json`): a history, appended to and
never rewritten, of every guard run someone accepted, one record an entry.

A record names the entry and its battery version, the commit whose code ran (the change),
the commit it was compared with (its base), the date, the command and every setting given
over the entry's preset, the run seed (`flowerpose guard --seed N` draws the same plants),
the decision ("pass": the entry passed; "loss": it did not and was accepted anyway, with
the reason given) and what was measured: each measure's loss with its standard error and
upper bound, the tails, and the entry on the battery's fixed trend seeds where they ran.

The reference a change is compared with is the commit of its entry's newest record of the
battery's version: it moves only by a record. The drift of an entry is the sum of the
losses its records accepted (and, for a run, its own): each within its margin, their sum
is not, so `guard` reports it since the first record and since the last accepted loss,
and fails an entry whose drift since the last loss passes a margin.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from flowerpose.atomic import write_text
from flowerpose.errors import InputError
from flowerpose.jsonio import read_json

#: The format of the file this code writes.
FORMAT = 2
#: What every record holds, with its type.
_RECORD_KEYS: dict[str, type | tuple[type, ...]] = {
    "entry": str, "battery_version": int, "commit": str, "base": (str, type(None)),
    "date": str, "command": str, "settings": list, "run_seed": (int, type(None)),
    "decision": str, "reason": (str, type(None)), "measures": dict}
DECISIONS = ("pass", "loss", "legacy")


def read_history(path: Path) -> list[dict]:
    """The records of the accepted file at `path` (none where there is no file), checked
    whole: InputError naming the file and the record for anything malformed. A file of the
    first format (one set of values, no history) reads as one legacy record an entry."""
    path = Path(path)
    if not path.exists():
        return []
    document = read_json(path)
    if not isinstance(document, dict):
        raise InputError(path, "an accepted file holds a JSON object")
    if "format" not in document and "entries" in document:
        return _legacy(path, document)
    if document.get("format") != FORMAT:
        raise InputError(path, f"format {document.get('format')!r}: this flowerpose reads "
                         f"format {FORMAT} (or the first, without a format)")
    records = document.get("records")
    if not isinstance(records, list):
        raise InputError(path, "\"records\" must be a list")
    for k, record in enumerate(records):
        _check(path, k, record)
    return records


def _check(path: Path, k: int, record: Any) -> None:
    if not isinstance(record, dict):
        raise InputError(path, f"record {k}: must be an object")
    for key, kind in _RECORD_KEYS.items():
        if key not in record:
            raise InputError(path, f"record {k}: lacks {key!r}")
        if not isinstance(record[key], kind) or isinstance(record[key], bool):
            raise InputError(path, f"record {k}: {key!r} has the wrong type "
                             f"({type(record[key]).__name__})")
    if record["decision"] not in DECISIONS:
        raise InputError(path, f"record {k}: decision {record['decision']!r} (one of "
                         f"{', '.join(DECISIONS)})")
    if record["decision"] == "loss" and not record["reason"]:
        raise InputError(path, f"record {k}: an accepted loss needs its reason")


def _legacy(path: Path, document: dict) -> list[dict]:
    """The first format's values as records: one an entry, decision "legacy" (accepted by
    the unguarded `--accept` before the history was kept)."""
    run, entries = document.get("run"), document.get("entries")
    version = document.get("battery_version")
    if not isinstance(run, dict) or not isinstance(entries, dict) or not isinstance(version, int):
        raise InputError(path, "neither format 2 (\"format\", \"records\") nor the first "
                         "(\"battery_version\", \"run\", \"entries\")")
    return [{"entry": name, "battery_version": version, "commit": str(run.get("commit")),
             "base": None, "date": str(run.get("date")), "command": str(run.get("command")),
             "settings": [], "run_seed": None, "decision": "legacy", "reason": None,
             "measures": {}, "values": values} for name, values in entries.items()]


def append(path: Path, history: list[dict], records: list[dict]) -> None:
    """Write the history with `records` after it (the file replaced whole, atomically:
    a killed write leaves the old file)."""
    import json

    document = {"format": FORMAT, "records": [*history, *records]}
    write_text(Path(path), json.dumps(document, indent=1, sort_keys=False) + "\n")


def of_entry(history: list[dict], entry: str, version: int) -> list[dict]:
    """An entry's records of a battery version, oldest first."""
    return [r for r in history if r["entry"] == entry and r["battery_version"] == version]


def base_of(history: list[dict], entry: str, version: int) -> str | None:
    """The commit an entry is compared with: its newest record's."""
    records = of_entry(history, entry, version)
    return records[-1]["commit"] if records else None


def drift(records: list[dict], run: dict[str, dict] | None) -> dict[str, dict]:
    """Per measure, the summed loss of the records (and of `run`'s measures, the run being
    judged) with its standard error: since the first record ("total") and since the last
    accepted loss ("since_loss"), and how many records each sums. None without records: a
    run alone is judged by its own margins."""
    measures: dict[str, dict] = {}
    if not records:
        return measures
    last_loss = max((k for k, r in enumerate(records) if r["decision"] == "loss"), default=-1)
    spans = {"total": records, "since_loss": records[last_loss + 1:]}
    for span, chosen in spans.items():
        series = [r["measures"] for r in chosen] + ([run] if run else [])
        for measures_of in series:
            for name, m in measures_of.items():
                if m.get("loss") is None:
                    continue
                summed = measures.setdefault(name, {}).setdefault(
                    span, {"loss": 0.0, "variance": 0.0, "records": 0})
                summed["loss"] += m["loss"]
                summed["variance"] += (m.get("se") or 0.0) ** 2
                summed["records"] += 1
    for spans_of in measures.values():
        for summed in spans_of.values():
            summed["loss"] = round(summed["loss"], 4)
            summed["se"] = round(math.sqrt(summed.pop("variance")), 4)
    return measures
