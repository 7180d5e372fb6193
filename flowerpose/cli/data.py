"""`flowerpose data`: published real data (the authors' plants, a plant's photographs),
listed and fetched."""

from __future__ import annotations

import argparse
from pathlib import Path


def cmd_data(args: argparse.Namespace) -> int:
    from flowerpose.data import PLANTS, default_data_dir, fetch

    if args.action == "list":
        for name, published in PLANTS.items():
            print(f"{name}: {published.description} ({len(published.files)} files, from "
                  f"{published.upstream})")
        print(f"into {default_data_dir()}/NAME by default")
        return 0
    if args.name is None:
        from flowerpose.errors import InputError

        raise InputError("fetch", "which plant? flowerpose data fetch NAME (data list says)")
    folder, files = fetch(args.name, args.to, args.mirror)
    for path, size, digest in files:
        print(f"{path.relative_to(folder)}: {size} bytes, sha256 {digest}")
    print(folder)
    return 0


def add_data(sub: argparse._SubParsersAction) -> None:
    """The `data` subcommand's parser."""
    from flowerpose.data import MIRROR_ENV, PLANTS

    p = sub.add_parser(
        "data", help="real data: the authors' labelled plants, a plant's photographs",
        description="List the published real data, or fetch one set: a real plant's labels "
        "and candidate clouds from the authors' repository, laid out as a real plant folder "
        "with its source.json and the authors' licence; or a plant's photographs with their "
        "logged and calibrated poses (romi-arabidopsis: images/, poses.csv, colmap/). Each "
        "is pinned to one commit, every file checked by SHA-256; the folder is printed "
        "last. A fetch that fails leaves nothing behind.",
        epilog="examples:\n"
        "  flowerpose data list\n"
        "  flowerpose data fetch paper-plant-3\n"
        "  flowerpose data fetch romi-arabidopsis")
    p.add_argument("action", choices=("list", "fetch"), help="list the plants, or fetch one")
    p.add_argument("name", nargs="?", choices=list(PLANTS), metavar="NAME",
                   help=f"fetch: the plant ({', '.join(PLANTS)})")
    p.add_argument("--to", type=Path, metavar="DIR",
                   help="fetch: the plant's folder (default: a data folder under the user's "
                   "cache, printed by data list)")
    p.add_argument("--mirror", metavar="DIR|URL",
                   help=f"fetch: a copy of the authors' repository to fetch from, a folder or "
                   f"a URL prefix (default: ${MIRROR_ENV}, else GitHub)")
    p.set_defaults(func=cmd_data)
