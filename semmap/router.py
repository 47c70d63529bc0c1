"""A Zenoh router in a Python process, for hosts without `zenohd` (it is not on PyPI or Debian):

    python -m semmap.router --zenoh-config deploy/secure/router.json5     # the secure profile's router
    python -m semmap.router --listen tcp/127.0.0.1:7447                    # a plain one, this host only

It routes, applies the configuration's TLS and access control, and exits on SIGTERM / SIGINT.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading

import zenoh

from semmap.bus import BusConfig, BusError, open_session


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m semmap.router", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--zenoh-config", default=None, help="Zenoh configuration file (mode is forced to router)")
    parser.add_argument(
        "--listen",
        default=None,
        help="endpoints to listen on, comma-separated (default: the file's, else tcp/127.0.0.1:7447)",
    )
    args = parser.parse_args(argv)
    listen = args.listen if args.listen is not None else (None if args.zenoh_config else "tcp/127.0.0.1:7447")
    try:
        config = BusConfig.from_env(mode="router", listen=listen, config_file=args.zenoh_config)
        session = open_session(config, retries=1)
    except (BusError, zenoh.ZError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    print(f"router up ({session.zid()})", flush=True)
    while not stop.wait(0.5):
        pass
    session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
