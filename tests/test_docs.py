"""The documentation: the command-line reference is the parsers' own help, and the site
builds with no warning (links, anchors, included files)."""

import importlib.util
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
