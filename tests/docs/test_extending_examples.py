"""docs/EXTENDING.md's worked examples run as written: each example file registers its new piece through the
registry and checks what it built, and the guide quotes the file as it is."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = sorted((ROOT / "examples" / "extending").glob("*.py"))


@pytest.mark.parametrize("example", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_the_example_runs(example: Path) -> None:
    # (a process of its own: an example registers into the registries, which the other tests must not see)
    result = subprocess.run([sys.executable, str(example)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]


def test_the_guide_quotes_the_examples_as_they_are() -> None:
    guide = (ROOT / "docs" / "EXTENDING.md").read_text()
    quoted = re.findall(r"<!-- example: (\S+) -->\s*```python\n(.*?)```", guide, flags=re.S)
    assert {path for path, _ in quoted} >= {str(p.relative_to(ROOT)) for p in EXAMPLES}
    for path, code in quoted:
        assert code.strip() in (ROOT / path).read_text(), f"docs/EXTENDING.md quotes {path} as it no longer is"
