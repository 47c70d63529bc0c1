"""The wire contract as JSON Schema (2020-12), generated from the message Structs, for peers in other languages.

    python -m semmap.core.messages.schema            # writes docs/interface.schema.json
    python -m semmap.core.messages.schema --check    # exit 1 if the committed file is stale

The schema describes the msgpack maps: where it says `"contentEncoding": "base64"` the value is msgpack `bin`
(raw bytes); base64 is only how JSON would have to carry it. Validation the types cannot express (rigid poses,
x2 > x1 boxes, array sizes that fit their shapes) is in the field descriptions and in docs/INTERFACE.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from . import ALL_MESSAGES

DEFAULT_PATH = Path(__file__).resolve().parents[3] / "docs" / "interface.schema.json"


def _schema_hook(kind: type) -> dict[str, Any]:
    if kind is np.ndarray:  # each array field's own schema comes with its annotation (base.array_map, flat_matrix)
        return {}
    raise NotImplementedError(f"no JSON Schema for {kind}")


def wire_schema() -> dict[str, Any]:
    """One document: `oneOf` every message kind, each Struct under `$defs`, keyed by its `schema` string too."""
    refs, defs = msgspec.json.schema_components(ALL_MESSAGES, schema_hook=_schema_hook,
                                                ref_template="#/$defs/{name}")
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "https://github.com/semmap/semmap/blob/main/docs/interface.schema.json",
        "title": "semmap wire messages",
        "description": (__doc__ or "").split("\n\n")[2].replace("\n", " "),
        "x-semmap-kinds": {kind.SCHEMA: ref["$ref"] for kind, ref in zip(ALL_MESSAGES, refs, strict=True)},
        "oneOf": list(refs),
        "$defs": defs,
    }


def render() -> str:
    return json.dumps(wire_schema(), indent=2, sort_keys=True) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Write (or check) the JSON Schema of semmap's wire messages.")
    parser.add_argument("path", nargs="?", type=Path, default=DEFAULT_PATH)
    parser.add_argument("--check", action="store_true", help="exit 1 if the file differs from a fresh generation")
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        current = args.path.read_text() if args.path.is_file() else ""
        if current != text:
            print(f"{args.path} is stale: run python -m semmap.core.messages.schema", file=sys.stderr)
            return 1
        return 0
    args.path.write_text(text)
    print(f"wrote {args.path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
