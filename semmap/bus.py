"""The Zenoh bus, configured in one place.

Default (embedded): every process is a Zenoh *peer* on loopback with explicit endpoints and multicast scouting
off; `semmap run` listens on one port and services connect to it, then find each other through gossip.
Deployed: services connect to a Zenoh router (`--connect tcp/router:7447` or `SEMMAP_ZENOH_CONNECT`), usually
in client mode (`SEMMAP_ZENOH_MODE=client`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import zenoh

from semmap.keys import Keys
from semmap.messages import Message, MessageError

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)

ENV_CONNECT = "SEMMAP_ZENOH_CONNECT"
ENV_LISTEN = "SEMMAP_ZENOH_LISTEN"
ENV_MODE = "SEMMAP_ZENOH_MODE"
MODES = ("peer", "client", "router")


class BusError(RuntimeError):
    """The bus could not be opened or configured."""


def _split(value: str | None) -> list[str]:
    return [v.strip() for v in (value or "").split(",") if v.strip()]


@dataclass
class BusConfig:
    """Where this process sits on the Zenoh network."""

    mode: str = "peer"
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    multicast_scouting: bool = False

    @classmethod
    def from_env(cls, connect: str | None = None, mode: str | None = None, listen: str | None = None) -> BusConfig:
        """Flags win over environment variables, which win over the embedded default."""
        mode = mode or os.environ.get(ENV_MODE) or "peer"
        if mode not in MODES:
            raise BusError(f"unknown Zenoh mode {mode!r}; use one of {', '.join(MODES)}")
        connect_list = _split(connect or os.environ.get(ENV_CONNECT))
        listen_spec = listen if listen is not None else os.environ.get(ENV_LISTEN)
        if listen_spec is not None:
            listen_list = _split(listen_spec)
        else:
            listen_list = [] if mode == "client" else ["tcp/127.0.0.1:0"]
        return cls(mode=mode, connect=connect_list, listen=listen_list)

    def to_zenoh(self) -> zenoh.Config:
        body: dict[str, Any] = {
            "mode": self.mode,
            "scouting": {"multicast": {"enabled": self.multicast_scouting}},
            "connect": {"endpoints": self.connect},
            "listen": {"endpoints": self.listen},
        }
        if self.mode == "client":
            body.pop("listen")
        return zenoh.Config.from_json5(json.dumps(body))

    def as_args(self) -> list[str]:
        """The command-line flags that give a child process this configuration."""
        args = ["--zenoh-mode", self.mode, "--listen", ",".join(self.listen)]
        if self.connect:
            args += ["--connect", ",".join(self.connect)]
        return args


def open_session(config: BusConfig, retries: int = 50, delay_s: float = 0.2) -> zenoh.Session:
    """Open a session; retried because a router or the first peer may still be starting."""
    last: Exception | None = None
    for _ in range(max(1, retries)):
        try:
            return zenoh.open(config.to_zenoh())
        except zenoh.ZError as exc:  # e.g. an endpoint not up yet
            last = exc
            time.sleep(delay_s)
    raise BusError(f"could not open a Zenoh session ({config}): {last}")


class Inbox:
    """One ordered queue for everything a service receives, so its main thread handles messages one at a time.

    Each stream has a capacity; when full, its oldest entry is dropped and counted (bounded memory under
    overload). Lockstep playback never fills it; real-time playback relies on it.
    """

    def __init__(self) -> None:
        self._items: deque[tuple[str, Any]] = deque()
        self._count: dict[str, int] = {}
        self._capacity: dict[str, int] = {}
        self.dropped: dict[str, int] = {}
        self._cv = threading.Condition()

    def add_stream(self, name: str, capacity: int) -> None:
        with self._cv:
            self._capacity[name] = capacity
            self._count.setdefault(name, 0)
            self.dropped.setdefault(name, 0)

    def put(self, name: str, item: Any) -> None:
        with self._cv:
            if self._count[name] >= self._capacity[name]:
                for i, (n, _) in enumerate(self._items):
                    if n == name:
                        del self._items[i]
                        break
                self._count[name] -= 1
                self.dropped[name] += 1
            self._items.append((name, item))
            self._count[name] += 1
            self._cv.notify()

    def get(self, timeout: float) -> tuple[str, Any] | None:
        with self._cv:
            if not self._items and not self._cv.wait_for(lambda: bool(self._items), timeout):
                return None
            name, item = self._items.popleft()
            self._count[name] -= 1
            return name, item

    def __len__(self) -> int:
        with self._cv:
            return len(self._items)


class Bus:
    """A Zenoh session for one robot with typed publishers and validated subscriptions."""

    def __init__(self, config: BusConfig, robot: str) -> None:
        self.keys = Keys(robot)
        self.config = config
        self.session = open_session(config)
        self.rejected: dict[str, int] = {}
        self._lock = threading.Lock()
        self._undeclare: list[Any] = []

    def publisher(self, key: str, express: bool = False) -> Publisher:
        pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK, express=express)
        self._undeclare.append(pub)
        return Publisher(pub)

    def subscribe(self, key: str, kind: type[M], on_message: Callable[[M], None]) -> None:
        """Decode and validate every sample on `key`; a bad one is logged and counted, never raised."""

        def callback(sample: zenoh.Sample) -> None:
            try:
                message = kind.decode(sample.payload.to_bytes())
            except MessageError as exc:
                self._reject(key, str(exc))
                return
            on_message(message)

        self._undeclare.append(self.session.declare_subscriber(key, callback))

    def subscribe_to_inbox(self, key: str, kind: type[M], inbox: Inbox, stream: str, capacity: int = 10_000) -> None:
        inbox.add_stream(stream, capacity)
        self.subscribe(key, kind, lambda message: inbox.put(stream, message))

    def _reject(self, key: str, reason: str) -> None:
        with self._lock:
            n = self.rejected[key] = self.rejected.get(key, 0) + 1
        if n <= 5 or n % 100 == 0:
            log.warning("rejected message #%d on %s: %s", n, key, reason)

    def close(self) -> None:
        for entity in reversed(self._undeclare):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        self._undeclare.clear()
        self.session.close()


class Publisher:
    """Puts `Message`s; stamps `sent_at` and can wait until a subscriber matches (early puts would vanish)."""

    def __init__(self, publisher: zenoh.Publisher) -> None:
        self._pub = publisher

    def put(self, message: Message) -> int:
        if hasattr(message, "sent_at"):
            message.sent_at = time.time()
        payload = message.encode()
        self._pub.put(payload)
        return len(payload)

    def put_bytes(self, payload: bytes) -> None:
        self._pub.put(payload)

    def matching(self) -> bool:
        return bool(self._pub.matching_status.matching)

    def wait_matching(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.matching():
                return True
            time.sleep(0.01)
        return self.matching()
