"""A Zenoh router in a Python process, for hosts and images without `zenohd` (it is not on PyPI or Debian):

    python -m semmap.runtime.transport.router --listen tcp/127.0.0.1:7447                    # a plain one, this host
    only
    python -m semmap.runtime.transport.router --zenoh-config deploy/secure/router.json5  # secure profile's router
    (TLS + ACL)

Compose deployments use the `eclipse/zenoh` router image; where that image cannot be pulled (an air-gapped site, the
container test in CI) this routes the same traffic between client services (tests/deploy/compose.podman.yaml selects
it). It has no plugins (no REST, no storage). Like every semmap service it touches `$SEMMAP_HEALTH_FILE` once a second
so a container health check works, and it exits on SIGTERM / SIGINT.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

import zenoh

from semmap.core import environment
from semmap.runtime.transport.bus import ENV_LISTEN, BusConfig, BusError, open_session
from semmap.runtime.transport.service import HEALTH_FILE, configure_logging, touch_health

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"  # this host only; a container passes tcp/0.0.0.0:7447 explicitly
HEARTBEAT_S = 1.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m semmap.runtime.transport.router",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "-c",
        "--zenoh-config",
        default=None,
        help="Zenoh configuration file (mode is forced to router); -c as for zenohd, so compose.secure.yaml's "
        "router command fits both routers",
    )
    parser.add_argument(
        "--listen",
        default=environment.read(ENV_LISTEN),
        help=f"endpoints to listen on, comma-separated (env {ENV_LISTEN}; default: the configuration file's, "
        f"else {DEFAULT_LISTEN})",
    )
    parser.add_argument(
        "--health-file",
        default=HEALTH_FILE,
        help="file touched once a second while routing (env SEMMAP_HEALTH_FILE; default: none)",
    )
    args = parser.parse_args(argv)
    configure_logging(False, "router")
    log = logging.getLogger("router")
    listen = args.listen if args.listen is not None else (None if args.zenoh_config else DEFAULT_LISTEN)
    if listen is not None and not [e for e in listen.split(",") if e.strip()]:
        log.error("--listen names no endpoint")
        return 2
    # the router is what others connect to: it does not follow SEMMAP_ZENOH_CONNECT (semmap's image sets it for the
    # services, which would make the router dial itself; links to other routers go in its Zenoh config file)
    try:
        config = BusConfig.from_env(mode="router", listen=listen, config_file=args.zenoh_config, env_connect=False)
        session = open_session(config, retries=5)
    except (BusError, zenoh.ZError) as exc:  # e.g. the port is taken, a bad configuration file
        log.error("%s", exc)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    print(f"router up ({session.zid()})", flush=True)
    log.info("routing (zid %s)", session.zid())
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
