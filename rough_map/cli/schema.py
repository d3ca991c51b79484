"""``rough-map schema --out data_schema/``: regenerate the JSON Schemas of the file formats.

Write <name>.schema.json for each file format (traverse, ...), generated from the pydantic
models of rough_map.config. Prints the files written.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from rough_map.cli._common import add_command

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = add_command(
        subparsers, "schema", "write the JSON Schemas of the file formats", __doc__
    )
    parser.add_argument(
        "--out", default="data_schema", metavar="DIR", help="folder (default data_schema)"
    )
    parser.add_argument(
        "--check",
        action="store_true",
        help="write nothing; exit 1 if a file in DIR differs from the generated schema",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from rough_map.config import schema_texts, write_schemas

    out = Path(args.out)
    if not args.check:
        for path in write_schemas(out):
            print(path)
        return 0
    stale = []
    for name, text in schema_texts().items():
        path = out / name
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            stale.append(path)
            print(f"{path}: out of date; run `rough-map schema --out {out}`", file=sys.stderr)
    return 1 if stale else 0
