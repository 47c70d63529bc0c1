"""One log format for every process (services, router, the `semmap` command): here, free of heavy imports, so
that the command configures it before knowing whether it will need Zenoh or numpy at all."""

from __future__ import annotations

import logging
import sys


def configure_logging(verbose: bool, name: str) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format=f"%(asctime)s {name:>10} %(levelname)-7s %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
        force=True,
    )
    for noisy in ("zenoh", "numexpr"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
