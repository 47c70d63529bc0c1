"""The Fast DDS profile `semmap ros2` ships (semmap.services.ros2.transport): well-formed, shared memory first and
loopback-only UDP, loaded for the bridge's own process unless the user set one. Its effect on 30 Hz images between
processes is measured by tests/ros2/test_bridge_live.py and benchmarks/bench_ros2.py."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from semmap.services.ros2.transport import PROFILE_ENV, PROFILE_XML, use_profile, write_profile

NS = {"d": "http://www.eprosima.com"}


def test_the_profile_is_shared_memory_and_loopback_udp_only(tmp_path: Path) -> None:
    root = ET.fromstring(write_profile(tmp_path / "p.xml").read_text())
    kinds = {
        t.findtext("d:transport_id", namespaces=NS): t.findtext("d:type", namespaces=NS)
        for t in root.iterfind(".//d:transport_descriptor", NS)
    }
    assert kinds == {"semmap_shm": "SHM", "semmap_udp_loopback": "UDPv4"}
    addresses = [a.text for a in root.iterfind(".//d:interfaceWhiteList/d:address", NS)]
    assert addresses == ["127.0.0.1"]
    participant = root.find(".//d:participant", NS)
    assert participant is not None and participant.get("is_default_profile") == "true"
    assert participant.findtext("d:rtps/d:useBuiltinTransports", namespaces=NS) == "false"


def test_the_users_profile_wins_and_ours_is_written_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    assert use_profile({PROFILE_ENV: "/theirs.xml"}) == "/theirs.xml"
    env: dict = {}
    path = Path(use_profile(env))
    assert env[PROFILE_ENV] == str(path) and path.read_text() == PROFILE_XML
    assert path.parent == tmp_path / "semmap"
