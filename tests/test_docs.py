"""The documentation: the command-line reference is the parsers' own help, the site builds
with no warning (links, anchors, included files), and every result it quotes lives in a
block `make results` writes."""

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

from flowerpose.cli.reference import markdown

ROOT = Path(__file__).resolve().parents[1]


def test_the_command_line_reference_is_the_parsers_help():
    page = ROOT / "docs" / "reference" / "cli.md"
    assert page.read_text() == markdown(), (
        "docs/reference/cli.md is stale: run python scripts/cli_reference.py")


@pytest.mark.skipif(importlib.util.find_spec("mkdocs") is None,
                    reason="MkDocs is not installed here (the [docs] extra; make test has it)")
@pytest.mark.slow
def test_the_site_builds_strictly(tmp_path):
    built = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                            str(tmp_path / "site")], cwd=ROOT, capture_output=True, text=True,
                           env={"NO_MKDOCS_2_WARNING": "1", "PATH": "/usr/bin:/bin"},
                           timeout=300)
    assert built.returncode == 0, built.stderr[-2000:]
    site = tmp_path / "site"
    assert (site / "reference" / "cli.html").is_file()
    assert "Operating envelope".lower() in (site / "design.html").read_text().lower()
    # It opens from disk: every internal link of every page names a file that is there.
    import re

    broken = []
    for page in site.rglob("*.html"):
        if page.name == "404.html":  # a server's page, with links from the site's root
            continue
        for target in re.findall(r'(?:href|src)="([^"#?]+)', page.read_text()):
            if "://" in target or target.startswith(("mailto:", "data:", "javascript:")):
                continue
            if not (page.parent / target).resolve().is_file():
                broken.append(f"{page.relative_to(site)} -> {target}")
    assert not broken, broken[:10]
    # and it loads nothing from the network (fonts, scripts, styles)
    loads = [f"{page.name}: {url}" for page in site.rglob("*.html")
             for url in re.findall(r'<(?:link|script)[^>]+(?:href|src)="(https?://[^"]+)',
                                   page.read_text())]
    assert not loads, loads[:5]


def test_the_citation_file_is_valid_citation_file_format():
    """CITATION.cff against the Citation File Format 1.2.0 schema (tests/data), offline."""
    import json

    jsonschema = pytest.importorskip("jsonschema")
    yaml = pytest.importorskip("yaml")
    schema = json.loads((ROOT / "tests" / "data" / "cff-1.2.0.schema.json").read_text())
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    jsonschema.validate(citation, schema)
    assert citation["date-released"] and citation["version"]
    assert citation["preferred-citation"]["year"]


def test_the_example_files_the_guides_use_are_read_as_the_commands_read_them():
    from flowerpose.config import load_suite
    from flowerpose.eval.jobs.config import EvalConfig
    from flowerpose.eval.studies.tune_space import read_space

    examples = ROOT / "examples"
    keys = [p.key for p in read_space(examples / "tuning" / "space.toml", EvalConfig())]
    assert "cluster.eps" in keys and "grid.pixel_size_m" in keys
    for suite in ("hard-train.toml", "field-validate.toml"):
        assert load_suite(str(examples / "tuning" / suite))["eval"]["source"] == "oracle"
    guides = "".join(p.read_text() for p in (ROOT / "docs" / "guides").glob("*.md"))
    for path in examples.rglob("*.toml"):  # every example a guide names
        assert str(path.relative_to(ROOT)) in guides, path


def test_the_command_line_reference_fits_the_page():
    """Every line of the reference's help is at most the width it is laid out at (the
    site's code blocks show that many characters): long examples are continued."""
    from flowerpose.cli.reference import COLUMNS

    wide = [line for line in markdown().splitlines()
            if len(line) > COLUMNS and not line.startswith("Generated from")]
    assert not wide, wide[:3]


def _result_blocks():
    spec = importlib.util.spec_from_file_location("result_blocks",
                                                  ROOT / "scripts" / "result_blocks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


#: What a result number looks like in prose: degrees to a decimal, an interval of decimals,
#: a count of flowers found, a recall or precision to decimals.
RESULT_NUMBERS = re.compile(
    r"\d+\.\d+°|\[-?\d+\.\d+, -?\d+\.\d+\]|\d+ of \d+ (?:labelled |visible )?flowers"
    r"|(?:recall|precision) (?:of \w+ flowers )?[01]\.\d+")
#: Decimal degrees that are settings or specifications, not results.
STATED = {"0.5°": "the paired ties' margin (stats.TIE_DEG)",
          "62.2°": "the IMX219 camera's field of view"}
#: Pages made whole by `make results` or `make gallery`, and pages that include another.
GENERATED = {"docs/results.md", "docs/gallery.md", "docs/what-you-get.md",
             "docs/changelog.md", "docs/design.md", "docs/reference/cli.md"}


def test_result_numbers_in_the_docs_live_only_in_generated_blocks():
    blocks = _result_blocks()
    pages = [ROOT / "README.md", ROOT / "DESIGN.md",
             *sorted((ROOT / "docs").rglob("*.md"))]
    found = []
    for page in pages:
        name = page.relative_to(ROOT).as_posix()
        if name in GENERATED or name.startswith("docs/samples/"):
            continue
        text = page.read_text(encoding="utf-8")
        prose = blocks.outside_blocks(text)
        for number in RESULT_NUMBERS.findall(prose):
            if number not in STATED:
                found.append(f"{name}: {number}")
        if page.relative_to(ROOT).as_posix() not in blocks.PAGES:
            assert not blocks.blocks(text), f"{name} has result blocks but is not in PAGES"
    assert not found, "result numbers outside a results block: " + ", ".join(found)


def test_every_result_block_is_one_make_results_fills():
    blocks = _result_blocks()
    for page in blocks.PAGES:
        text = (ROOT / page).read_text(encoding="utf-8")
        names = blocks.blocks(text)
        assert names, page
        assert set(names) <= set(blocks.BLOCKS), page
        opened = re.findall(r"<!-- results:([a-z0-9-]+) -->", text)
        assert opened == names, f"{page}: a block opened and not closed"
    # A result number written into prose is found; the same inside its block is not.
    probe = "It was 7.35° [6.1, 8.6].\n<!-- results:x -->\n7.35°\n<!-- /results:x -->\n"
    assert RESULT_NUMBERS.findall(blocks.outside_blocks(probe)) == ["7.35°", "[6.1, 8.6]"]
