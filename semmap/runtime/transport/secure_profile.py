"""The secure profile: Zenoh configuration files for mutual TLS and an access-control list (docs/SECURITY.md).

Every process is a Zenoh *client* of one router over TLS, and proves who it is with its own certificate (mutual
TLS; `scripts/make-dev-certs.sh` makes a development CA and one certificate per identity). The router admits
only certificates from the CA and applies the access-control list below by the certificate's common name:
default deny; each identity may put on the keys it owns (`semmap.core.keys.PUBLISHERS`: only the player puts
`frames`, only the orchestrator and the player `control`, only the backend `poses/corrected`, each service its
own `status/<service>/**` and `progress/<service>`) and receive what it listens to: all of it as the dataflow
declares it (semmap/core/dataflow.py), so the list cannot grant a key no node uses nor miss one a node needs. A
peer without a certificate cannot connect; one with an unknown name can neither read nor put anything.

    python -m semmap.runtime.transport.secure_profile CERT_DIR OUT_DIR [--router tls/HOST:7447] [--listen
    tls/0.0.0.0:7447]

writes `router.json5` and one `<identity>.json5` per identity into OUT_DIR; `semmap run --connect
tls/HOST:7447 --zenoh-mode client --zenoh-config OUT_DIR` gives each child its own file.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from semmap.core import dataflow
from semmap.core.keys import KEYSPACE

ROBOTS = f"{KEYSPACE}/*"  # every robot of the deployment
# the identities: one per node of the dataflow (semmap/core/dataflow.py), each with a certificate of its name
SERVICES = dataflow.SERVICES
CLIENTS = dataflow.CLIENTS  # `semmap run` itself, an external SLAM, a read-only map user
IDENTITIES = (*SERVICES, *CLIENTS)

# what each identity listens to (topics under semmap/v1/<robot>/), besides `control` for every service
SUBSCRIBES: dict[str, tuple[str, ...]] = {n.name: n.inputs for n in dataflow.NODES if n.inputs}


def puts_of(identity: str) -> list[str]:
    """The topics `identity` may put on: its node's outputs, and a service its own status and progress."""
    topics = list(dataflow.node(identity).outputs)
    if identity in SERVICES:
        topics += list(dataflow.service_reports(identity))
    return topics


def _keys(topics: list[str] | tuple[str, ...]) -> list[str]:
    return [f"{ROBOTS}/{t}" for t in topics]


def access_control() -> dict:
    """The router's access-control list: default deny, one policy per identity (certificate common name)."""
    rules: list[dict] = []
    policies: list[dict] = []
    subjects = [{"id": identity, "cert_common_names": [identity]} for identity in IDENTITIES]

    def rule(rule_id: str, messages: list[str], flows: list[str], topics: list[str]) -> str:
        rules.append(
            {"id": rule_id, "messages": messages, "flows": flows, "permission": "allow", "key_exprs": _keys(topics)}
        )
        return rule_id

    for identity in IDENTITIES:
        mine = []
        puts = puts_of(identity)
        if puts:
            mine.append(rule(f"{identity}-put", ["put"], ["ingress"], puts))
            # the router tells a publisher which subscribers match (a client puts only where one does, and
            # semmap waits for one before the first put); listeners of every status / progress use wildcards
            wildcards = ["status/**", "progress/*"] if identity in SERVICES else []
            mine.append(rule(f"{identity}-matching", ["declare_subscriber"], ["egress"], puts + wildcards))
        listens = list(dataflow.node(identity).reads())
        if listens:
            mine.append(rule(f"{identity}-sub", ["declare_subscriber"], ["ingress"], listens))
            mine.append(rule(f"{identity}-receive", ["put"], ["egress"], listens))
        node = dataflow.node(identity)
        if node.liveliness:  # detector replicas share the frames by their liveliness tokens
            mine.append(
                rule(
                    f"{identity}-replicas",
                    ["liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                    ["ingress", "egress"],
                    list(node.liveliness),
                )
            )
        if node.answers:  # the associator answers map queries
            answers = list(node.answers)
            mine.append(rule(f"{identity}-queryable", ["declare_queryable", "reply"], ["ingress"], answers))
            mine.append(rule(f"{identity}-queries", ["query"], ["egress"], answers))
        if node.asks:  # they may ask the map
            mine.append(rule(f"{identity}-query", ["query"], ["ingress"], list(node.asks)))
            mine.append(rule(f"{identity}-replies", ["reply"], ["egress"], list(node.asks)))
        policies.append({"id": f"{identity}-policy", "rules": mine, "subjects": [identity]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def router_config(cert_dir: Path, listen: list[str]) -> dict:
    """The router: TLS only, client certificates required (mutual TLS), the access-control list."""
    return {
        "mode": "router",
        "listen": {"endpoints": listen},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate": str(cert_dir / "ca.pem"),
                    "listen_private_key": str(cert_dir / "router.key"),
                    "listen_certificate": str(cert_dir / "router.pem"),
                    "enable_mtls": True,
                },
            }
        },
        "access_control": access_control(),
    }


def client_config(cert_dir: Path, identity: str, router: list[str]) -> dict:
    """A client of the router with `identity`'s certificate (semmap's flags may still set mode and endpoints)."""
    return {
        "mode": "client",
        "connect": {"endpoints": router},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {
                "protocols": ["tls"],
                "tls": {
                    "root_ca_certificate": str(cert_dir / "ca.pem"),
                    "connect_private_key": str(cert_dir / f"{identity}.key"),
                    "connect_certificate": str(cert_dir / f"{identity}.pem"),
                    "enable_mtls": True,
                },
            }
        },
    }


HEADER = (
    "// semmap secure profile (docs/SECURITY.md), written by\n"
    "// `python -m semmap.runtime.transport.secure_profile`: mutual TLS\n"
    "// and the router's access-control list. Regenerate rather than edit.\n"
)


def write_profile(cert_dir: Path, out_dir: Path, router: list[str], listen: list[str]) -> list[Path]:
    """router.json5 and one <identity>.json5 per identity; returns the files written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    files = {
        "router": router_config(cert_dir, listen),
        **{identity: client_config(cert_dir, identity, router) for identity in IDENTITIES},
    }
    for name, body in files.items():
        path = out_dir / f"{name}.json5"
        path.write_text(HEADER + json.dumps(body, indent=2) + "\n")
        written.append(path)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m semmap.runtime.transport.secure_profile",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "cert_dir",
        type=Path,
        help="certificates from scripts/make-dev-certs.sh (paths are written "
        "as given: use the path the processes will see, e.g. /certs in containers)",
    )
    parser.add_argument("out_dir", type=Path)
    parser.add_argument(
        "--router", action="append", default=None, help="where clients connect (default tls/localhost:7447; repeatable)"
    )
    parser.add_argument(
        "--listen",
        action="append",
        default=None,
        help="where the router listens (default tls/127.0.0.1:7447: this host only; repeatable)",
    )
    args = parser.parse_args(argv)
    files = write_profile(
        args.cert_dir, args.out_dir, args.router or ["tls/localhost:7447"], args.listen or ["tls/127.0.0.1:7447"]
    )
    print(f"wrote {len(files)} files to {args.out_dir}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
