"""Write docs/reference/cli.md from the command line's parsers (flowerpose/cli_reference.py)."""

from pathlib import Path

from flowerpose.atomic import write_text
from flowerpose.cli.reference import markdown

if __name__ == "__main__":
    page = Path(__file__).resolve().parents[1] / "docs" / "reference" / "cli.md"
    write_text(page, markdown())
    print(page)
