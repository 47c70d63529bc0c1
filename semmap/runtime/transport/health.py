"""Container health check: `python -m semmap.runtime.transport.health [FILE] [--max-age S]` exits 0 while the service
is alive.

A service touches `$SEMMAP_HEALTH_FILE` with every status message (once a second) while it runs; a stale or
missing file means it hangs or never came up.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from semmap.core import environment


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="semmap.runtime.transport.health", description=__doc__)
    parser.add_argument("file", nargs="?", default=environment.read(environment.HEALTH_FILE) or "/tmp/semmap.health")
    parser.add_argument("--max-age", type=float, default=10.0, help="seconds (default 10)")
    args = parser.parse_args(argv)
    try:
        age = time.time() - os.stat(args.file).st_mtime
    except OSError:
        print(f"unhealthy: {args.file} missing", file=sys.stderr)
        return 1
    if age > args.max_age:
        print(f"unhealthy: last heartbeat {age:.0f} s ago", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
