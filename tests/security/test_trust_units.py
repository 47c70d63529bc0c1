"""The pieces of the run's trust checks, one at a time: signatures, owners, limits, the Zenoh config file hook,
atomic outputs and the output lock."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from semmap.core.keys import Keys
from semmap.core.messages import Control, MessageError, Progress
from semmap.core.outputs import OutputError, OutputLock, atomic_write_text
from semmap.runtime.orchestrator import free_loopback_port
from semmap.runtime.transport.bus import Bus, BusConfig, RateLimit, Refused, RunTrust
from semmap.runtime.transport.secure_profile import write_profile

PROJECT = Path(__file__).resolve().parents[2]
KEY = "semmap/v1/robot1/control"


def _trust(run: str = "r1", sender: str = "player", key: bytes | None = None) -> RunTrust:
    return RunTrust(run, key or bytes(range(32)), sender)


def test_a_signature_names_its_sender_and_binds_key_run_and_payload() -> None:
    signer, checker = _trust(), _trust(sender="detector")
    payload = Control("robot1", "end_of_stream", 5, 6).encode()
    attachment = signer.sign(KEY, payload)
    assert checker.verify(KEY, "control", payload, attachment) == "player"
    with pytest.raises(Refused, match="bad_signature"):
        checker.verify(KEY, "control", payload + b"x", attachment)  # another payload
    with pytest.raises(Refused, match="bad_signature"):
        checker.verify("semmap/v1/robot1/frames", "frames", payload, attachment)  # another key
    with pytest.raises(Refused, match="foreign_run"):
        _trust("r2").verify(KEY, "control", payload, attachment)
    with pytest.raises(Refused, match="bad_signature"):  # the run id is public, the secret is not
        checker.verify(KEY, "control", payload, _trust(key=os.urandom(32)).sign(KEY, payload))
    with pytest.raises(Refused, match="unsigned"):
        checker.verify(KEY, "control", payload, None)
    with pytest.raises(Refused, match="bad_signature"):
        checker.verify(KEY, "control", payload, b"\x93garbage")
    open_checker = RunTrust("r1", bytes(range(32)), "detector", frozenset({"control"}))
    assert open_checker.verify(KEY, "control", payload, None) == "external"


def test_owners_of_each_key() -> None:
    keys = Keys("robot1")
    assert keys.publishers(keys.frames) == ("player", "external")
    assert keys.publishers(keys.corrected_poses) == ("backend",)
    assert keys.publishers(keys.status("associator", "associator-2")) == ("associator",)
    assert keys.publishers(keys.progress("tracker")) == ("tracker",)
    assert keys.publishers(keys.map_query) is None
    assert keys.topic(keys.landmark_tags) == "observations/tags"
    assert keys.detector_replica("d1", "run9") == "semmap/v1/robot1/detector/replicas/run9/d1"


def test_a_rate_limit_bounds_a_flood() -> None:
    limit = RateLimit(100.0)
    taken = sum(limit.take() for _ in range(1000))
    assert 100 <= taken <= 105
    time.sleep(0.1)
    assert limit.take()


def test_the_run_field_is_optional_and_checked() -> None:
    message = Progress("robot1", "tracker", 3)
    assert Progress.decode(message.encode()).run == ""
    message.run = "abc123"
    assert Progress.decode(message.encode()).run == "abc123"
    message.run = "bad run/**"
    with pytest.raises(MessageError, match="run"):
        Progress.decode(message.encode())


def test_signed_buses_refuse_what_they_should(tmp_path: Path) -> None:
    """Two real sessions: a run member receives its run's signed messages, not unsigned or foreign ones, nor a
    status put by someone else than the service it names."""
    port = free_loopback_port()
    hub = f"tcp/127.0.0.1:{port}"
    secret = os.urandom(32)
    receiver = Bus(BusConfig(listen=[hub]), "robot1", RunTrust("run1", secret, "orchestrator"))
    member = Bus(BusConfig(connect=[hub]), "robot1", RunTrust("run1", secret, "tracker"))
    stranger = Bus(BusConfig(connect=[hub]), "robot1", RunTrust("run2", os.urandom(32), "tracker"))
    plain = Bus(BusConfig(connect=[hub]), "robot1")
    got: list[Progress] = []
    try:
        receiver.subscribe(receiver.keys.progress_all, Progress, got.append)
        pubs = [
            (bus, bus.publisher(bus.keys.progress(svc)))
            for bus, svc in ((member, "tracker"), (stranger, "tracker"), (plain, "tracker"), (member, "backend"))
        ]
        for _, pub in pubs:
            assert pub.wait_matching(10)
        for i, (_, pub) in enumerate(pubs):
            pub.put(Progress("robot1", "backend" if i == 3 else "tracker", i))
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and sum(receiver.rejected.values()) + len(got) < 4:
            time.sleep(0.05)
        assert [(p.frame_id, p.sender, p.run) for p in got] == [(0, "tracker", "run1")]
        assert receiver.rejected == {
            "rejected_foreign_run[progress/tracker]": 1,
            "rejected_unsigned[progress/tracker]": 1,
            "rejected_wrong_sender[progress/backend]": 1,
        }
    finally:
        for bus in (plain, stranger, member, receiver):
            bus.close()


def test_a_zenoh_config_file_is_merged_with_semmaps_settings(tmp_path: Path) -> None:
    path = tmp_path / "z.json5"
    path.write_text(
        '// a user file\n{ mode: "client", connect: { endpoints: ["tcp/10.0.0.1:7447"] },'
        " transport: { link: { tx: { lease: 12345 } } } }"
    )
    kept = BusConfig.from_env(config_file=str(path)).to_zenoh()  # nothing given: the file's settings stay
    assert json.loads(kept.get_json("mode")) == "client"
    assert json.loads(kept.get_json("connect/endpoints")) == ["tcp/10.0.0.1:7447"]
    assert json.loads(kept.get_json("transport/link/tx/lease")) == 12345
    assert json.loads(kept.get_json("scouting/multicast/enabled")) is False  # unset in the file: semmap's
    given = BusConfig.from_env("tcp/127.0.0.1:9999", "peer", config_file=str(path)).to_zenoh()  # flags win
    assert json.loads(given.get_json("mode")) == "peer"
    assert json.loads(given.get_json("connect/endpoints")) == ["tcp/127.0.0.1:9999"]
    assert json.loads(given.get_json("transport/link/tx/lease")) == 12345
    os.environ["SEMMAP_ZENOH_CONFIG"] = str(path)
    try:
        assert BusConfig.from_env().config_file == str(path)
    finally:
        del os.environ["SEMMAP_ZENOH_CONFIG"]
    with pytest.raises(Exception, match="does not exist"):
        BusConfig.from_env(config_file=str(tmp_path / "missing.json5"))


def test_deploy_secure_matches_the_generator(tmp_path: Path) -> None:
    """deploy/secure/ is `python -m semmap.runtime.transport.secure_profile /certs deploy/secure --router
    tls/zenoh:7447 --listen
    tls/0.0.0.0:7447`: regenerate it when the access-control table changes."""
    write_profile(Path("/certs"), tmp_path, ["tls/zenoh:7447"], ["tls/0.0.0.0:7447"])
    shipped = PROJECT / "deploy" / "secure"
    assert sorted(p.name for p in shipped.glob("*.json5")) == sorted(p.name for p in tmp_path.glob("*.json5"))
    for path in tmp_path.glob("*.json5"):
        assert (shipped / path.name).read_text() == path.read_text(), path.name
        zenoh.Config.from_file(str(shipped / path.name))


def test_atomic_writes_leave_the_old_file_when_they_fail(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "trajectory.tum"
    atomic_write_text(path, "old\n")

    def full_disk(fd: int) -> None:  # the data went to the temporary file, then the disk filled up
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full_disk)
    with pytest.raises(OSError, match="No space"):
        atomic_write_text(path, "new\n" * 1000)
    assert path.read_text() == "old\n" and list(tmp_path.iterdir()) == [path]


def test_the_output_lock_is_exclusive_across_processes(tmp_path: Path) -> None:
    lock = OutputLock(tmp_path)
    lock.acquire()
    try:
        other = subprocess.run(
            [
                sys.executable,
                "-c",
                "import sys; from pathlib import Path\n"
                "from semmap.core.outputs import OutputLock, OutputError\n"
                f"try: OutputLock(Path({str(tmp_path)!r})).acquire()\n"
                "except OutputError as e: print(e); sys.exit(3)",
            ],
            cwd=PROJECT,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert other.returncode == 3 and f"pid {os.getpid()}" in other.stdout
    finally:
        lock.release()
    OutputLock(tmp_path).acquire()  # free again
    with pytest.raises(OutputError):
        OutputLock(tmp_path / "missing" / "deeper").acquire()
