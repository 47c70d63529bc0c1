"""Where the benchmarks write their tables: between `<!-- results:NAME begin ... -->` and `<!-- results:NAME end -->`
in docs/RESULTS.md (or another page), so that the page holds the current figures and each names its command."""

from __future__ import annotations

import re
from pathlib import Path


def write_between_markers(page: Path, name: str, body: str) -> None:
    """Replace what lies between the `results:NAME` markers of `page` with `body` (SystemExit without them)."""
    text = page.read_text()
    begin = re.search(rf"<!-- results:{re.escape(name)} begin[^>]*-->\n", text)
    end = re.search(rf"<!-- results:{re.escape(name)} end -->", text)
    if begin is None or end is None or end.start() < begin.end():
        raise SystemExit(f"{page} has no results:{name} markers")
    page.write_text(text[: begin.end()] + "\n" + body + "\n\n" + text[end.start():])
