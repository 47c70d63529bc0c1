"""The secure profile (docs/SECURITY.md): a router in TLS mode with client certificates required and the
access-control list; every process a client with its own certificate. Services work; a client without a
certificate cannot connect; one with an unknown identity, or a known identity on keys it does not own, can
neither read frames nor put on any key."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from semmap.core.keys import Keys
from semmap.runtime.orchestrator import free_loopback_port
from semmap.runtime.transport.bus import BusConfig
from semmap.runtime.transport.secure_profile import IDENTITIES, write_profile

PROJECT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed (dev.sh installs it)")


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("certs")
    subprocess.run(
        ["bash", str(PROJECT / "scripts" / "make-dev-certs.sh"), str(out)],
        check=True,
        env={**os.environ, "SEMMAP_CERT_EXTRA": "intruder"},
        capture_output=True,
        timeout=120,
    )
    return out


def _with_identity(profile: Path, base: str, name: str, key: str | None, cert: str | None) -> Path:
    """A client file like `base`'s with another certificate (None: no client certificate at all)."""
    body = json.loads(
        "\n".join(line for line in (profile / f"{base}.json5").read_text().splitlines() if not line.startswith("//"))
    )
    tls = body["transport"]["link"]["tls"]
    tls.pop("connect_private_key"), tls.pop("connect_certificate")
    if key and cert:
        tls["connect_private_key"], tls["connect_certificate"] = key, cert
    path = profile / f"{name}.json5"
    path.write_text(json.dumps(body))
    return path


@pytest.fixture
def secure_router(certs: Path, tmp_path: Path):  # noqa: ANN201
    port = free_loopback_port()
    profile = tmp_path / "profile"
    write_profile(certs, profile, [f"tls/localhost:{port}"], [f"tls/127.0.0.1:{port}"])
    router = subprocess.Popen(
        [sys.executable, "-m", "semmap.runtime.transport.router", "--zenoh-config", str(profile / "router.json5")],
        cwd=PROJECT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert router.stdout is not None and router.stdout.readline().startswith("router up"), router.stderr.read()
    yield f"tls/localhost:{port}", profile
    router.terminate()
    router.wait(timeout=10)


def _session(config_file: Path) -> zenoh.Session:
    return zenoh.open(BusConfig.from_env(config_file=str(config_file)).to_zenoh())


def test_profile_files_cover_every_identity(certs: Path, tmp_path: Path) -> None:
    files = write_profile(certs, tmp_path, ["tls/localhost:7447"], ["tls/127.0.0.1:7447"])
    assert {p.stem for p in files} == {"router", *IDENTITIES}
    for path in files:
        zenoh.Config.from_file(str(path))  # each one a valid Zenoh configuration


def test_services_work_and_strangers_can_neither_read_nor_put(
    secure_router,
    certs: Path,
    tmp_path: Path,  # noqa: ANN001
    semmap_run,
    read_stats,
) -> None:  # noqa: ANN001
    endpoint, profile = secure_router
    keys = Keys("robot1")
    # no certificate: the TLS handshake fails, there is no session at all
    no_cert = _with_identity(profile, "player", "nocert", None, None)
    with pytest.raises(zenoh.ZError):
        zenoh.open(BusConfig.from_env(config_file=str(no_cert)).to_zenoh())

    # a certificate of the CA with an identity the list does not know, and a known one (viz) off its keys
    intruder = _with_identity(profile, "player", "intruder", str(certs / "intruder.key"), str(certs / "intruder.pem"))
    heard: dict[str, list[str]] = {"intruder": [], "viz-frames-put": []}
    listener = _session(intruder)
    listener.declare_subscriber("semmap/**", lambda s: heard["intruder"].append(str(s.key_expr)))
    liveliness_seen: list[str] = []
    listener.liveliness().declare_subscriber("semmap/**", lambda s: liveliness_seen.append(str(s.key_expr)))
    putters = [_session(intruder), _session(profile / "viz.json5")]
    stop = threading.Event()
    attempts = {"n": 0}

    def forge() -> None:
        topics = [
            keys.frames,
            keys.control,
            keys.corrected_poses,
            keys.tracks,
            keys.observations,
            keys.status("associator", "associator"),
            keys.progress("backend"),
            keys.odometry,
        ]
        started = time.monotonic()
        while not stop.is_set() and time.monotonic() - started < 25:
            for session in putters:
                for key in topics:
                    session.put(key, b"\x80")  # would be a rejected message if it ever arrived
                    attempts["n"] += 1
            time.sleep(0.05)

        replies.extend(listener.get(keys.map_query, timeout=2.0))  # (the associator is up by now, or soon)

    replies: list = []
    forger = threading.Thread(target=forge, daemon=True)
    forger.start()
    out = tmp_path / "run"
    try:
        result = semmap_run(
            [
                "synthetic:frames=60",
                "--out",
                str(out),
                "--connect",
                endpoint,
                "--zenoh-mode",
                "client",
                "--zenoh-config",
                str(profile),
            ],
            timeout=400,
        )
    finally:
        stop.set()
        forger.join(timeout=10)
        for session in [listener, *putters]:
            session.close()
    assert result.returncode == 0, result.stderr[-3000:]
    stats = read_stats(out)
    assert stats["frames"]["processed"] == 60 and stats["outcome"] == "completed"
    assert (out / "map.json").is_file() and json.loads((out / "map.json").read_text())["landmarks"]
    assert attempts["n"] > 100
    # nothing the strangers put arrived anywhere (a rejected message would be counted), nothing reached them
    assert stats["rejected"] == {}, stats["rejected"]
    assert heard["intruder"] == [], heard["intruder"][:5]
    assert liveliness_seen == []
    assert all(r.ok is None for r in replies)
