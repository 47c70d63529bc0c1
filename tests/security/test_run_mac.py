"""The run's message MAC: either version verifies, the receiver follows the sender's version, and nothing forged,
replayed on another key or downgraded passes (semmap.runtime.transport.bus.RunTrust)."""

from __future__ import annotations

import msgpack
import pytest

from semmap.runtime.transport import bus
from semmap.runtime.transport.bus import MAC_BLAKE2B, MAC_HMAC_SHA256, Refused, RunTrust

KEY = "semmap/v1/robot1/frames"
PAYLOAD = bytes(range(256)) * 2000  # ~500 KB, a camera frame's size


@pytest.fixture(params=[MAC_BLAKE2B, MAC_HMAC_SHA256])
def version(request, monkeypatch):
    monkeypatch.setattr(bus, "_faster_mac", request.param)
    return request.param


def test_each_version_signs_and_verifies(version):
    trust = RunTrust("run1", bytes(range(32)), "player")
    attachment = trust.sign(KEY, PAYLOAD)
    assert msgpack.unpackb(attachment)[0] == version
    assert RunTrust("run1", bytes(range(32)), "tracker").verify(KEY, "frames", PAYLOAD, attachment) == "player"


def test_forgeries_refused_in_each_version(version):
    trust = RunTrust("run1", bytes(range(32)), "player")
    attachment = trust.sign(KEY, PAYLOAD)
    with pytest.raises(Refused, match="bad_signature"):  # one byte changed
        trust.verify(KEY, "frames", PAYLOAD[:-1] + b"\x00", attachment)
    with pytest.raises(Refused, match="bad_signature"):  # the same message replayed on another key
        trust.verify("semmap/v1/robot1/control", "control", PAYLOAD, attachment)
    with pytest.raises(Refused, match="bad_signature"):  # signed by someone without the key
        trust.verify(KEY, "frames", PAYLOAD, RunTrust("run1", bytes(32), "player").sign(KEY, PAYLOAD))
    _, run, sender, mac = msgpack.unpackb(attachment)
    other = MAC_HMAC_SHA256 if version == MAC_BLAKE2B else MAC_BLAKE2B
    with pytest.raises(Refused, match="bad_signature"):  # a valid MAC relabelled as the other version
        trust.verify(KEY, "frames", PAYLOAD, msgpack.packb([other, run, sender, mac]))
    with pytest.raises(Refused, match="bad_signature"):  # an unknown version
        trust.verify(KEY, "frames", PAYLOAD, msgpack.packb([7, run, sender, mac]))


def test_sender_takes_the_faster_mac_measured_here(monkeypatch):
    monkeypatch.setattr(bus, "_faster_mac", None)
    chosen = bus.faster_mac(sample_bytes=64 * 1024, rounds=5)
    assert chosen in (MAC_BLAKE2B, MAC_HMAC_SHA256)
    assert bus.faster_mac() == chosen  # measured once per process
