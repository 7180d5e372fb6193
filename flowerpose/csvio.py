"""User CSV tables with a header row (a bed's plants, a photo set's rough poses)."""

from __future__ import annotations

import csv
from pathlib import Path

from flowerpose.errors import InputError


def read_csv_table(path: str | Path, required: tuple[str, ...], what: str,
                   optional: str = "") -> list[dict[str, str]]:
    """The rows of a UTF-8 CSV file as {column: text}, empty cells left out (so an
    optional column's default applies, as an absent TOML key's does). Errors name the file:
    not found, not UTF-8 text, not CSV, or a `required` column missing from the header.
    what: the file's role for the messages ("bed file"); optional: the optional columns, as
    the message about a missing column lists them."""
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            rows = list(reader)
            header = reader.fieldnames or []
    except FileNotFoundError:
        raise InputError(path, f"{what} not found") from None
    except UnicodeDecodeError:
        raise InputError(path, "not a UTF-8 text file") from None
    except (OSError, csv.Error) as err:
        raise InputError(path, f"cannot read it as CSV ({err})") from None
    missing = [key for key in required if key not in header]
    if missing:
        extra = f" (optional {optional})" if optional else ""
        raise InputError(path, f"the header needs the columns {', '.join(required)}{extra}; "
                         f"{missing[0]!r} is missing")
    return [{key: value for key, value in row.items() if value not in ("", None)}
            for row in rows]
