"""A Zenoh router from semmap's own image: `python -m semmap.router [--listen tcp/0.0.0.0:7447]`.

Compose deployments use the `eclipse/zenoh` router image. Where that image cannot be pulled (an air-gapped site, the
container test in CI), a Python Zenoh session in router mode routes the same traffic between client services
(tests/deploy/compose.podman.yaml selects it). It has no plugins (no REST, no storage), and like every semmap service
it touches `$SEMMAP_HEALTH_FILE` once a second so the container health check works.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading

from semmap.bus import ENV_LISTEN, BusConfig, BusError, open_session
from semmap.service import HEALTH_FILE, configure_logging, touch_health

DEFAULT_LISTEN = "tcp/0.0.0.0:7447"  # what zenohd listens on: every interface of its container
HEARTBEAT_S = 1.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="semmap.router", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--listen",
        default=os.environ.get(ENV_LISTEN) or DEFAULT_LISTEN,
        help=f"endpoints to listen on, comma-separated (env {ENV_LISTEN}; default {DEFAULT_LISTEN})",
    )
    parser.add_argument(
        "--health-file",
        default=HEALTH_FILE,
        help="file touched once a second while routing (env SEMMAP_HEALTH_FILE; default: none)",
    )
    args = parser.parse_args(argv)
    configure_logging(False, "router")
    log = logging.getLogger("router")
    listen = [e.strip() for e in args.listen.split(",") if e.strip()]
    if not listen:
        log.error("--listen names no endpoint")
        return 2
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        session = open_session(BusConfig(mode="router", listen=listen), retries=5)
    except BusError as exc:  # e.g. the port is taken
        log.error("%s", exc)
        return 2
    log.info("routing on %s (zid %s)", ", ".join(listen), session.zid())
    try:
        while True:
            if args.health_file:
                touch_health(args.health_file)
            if stop.wait(HEARTBEAT_S):
                break
    finally:
        session.close()
        log.info("stopped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
