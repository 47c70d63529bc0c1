"""The Zenoh bus, configured in one place.

Default (embedded): every process is a Zenoh *peer* on loopback with explicit endpoints and multicast scouting
off; `semmap run` listens on one port and services connect to it, then find each other through gossip.
Deployed: services connect to a Zenoh router (`--connect tcp/router:7447` or `SEMMAP_ZENOH_CONNECT`), usually
in client mode (`SEMMAP_ZENOH_MODE=client`). A Zenoh configuration file (`--zenoh-config FILE` or
`SEMMAP_ZENOH_CONFIG`) adds what semmap does not set itself (TLS, authentication, access control, ...; see
docs/SECURITY.md); semmap's own settings given by flags or environment win over the file's.

Trust on the bus (docs/SECURITY.md): inside a `semmap run` every message is signed with the run's secret key
(`SEMMAP_RUN_KEY`, made by the orchestrator and handed to its children only) and the sender's role, and carries
the run id (`SEMMAP_RUN_ID`). A receiver rejects, and counts, unsigned or badly signed messages, messages of
another run, messages from a sender that does not own the key (`semmap.core.keys.PUBLISHERS`), oversized payloads
and floods beyond a per-key rate.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import json
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import msgpack
import zenoh

from semmap.core import environment
from semmap.core.keys import EXTERNAL_SENDER, Keys
from semmap.core.messages import Control, Message, MessageError, Progress, ServiceStatus, peek_frame_id

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)

# the environment variables of the bus (semmap/core/environment.py says what each means)
ENV_CONNECT = environment.ZENOH_CONNECT
ENV_LISTEN = environment.ZENOH_LISTEN
ENV_MODE = environment.ZENOH_MODE
ENV_ZENOH_CONFIG = environment.ZENOH_CONFIG
ENV_RUN_ID = environment.RUN_ID
ENV_RUN_KEY = environment.RUN_KEY
ENV_RUN_OPEN_KEYS = environment.RUN_OPEN_KEYS  # topics a run takes unsigned messages on (`semmap run external`)
MODES = ("peer", "client", "router")
SMALL_KINDS = (Control, Progress, ServiceStatus)
SMALL_MESSAGE_BYTES = 64 * 1024  # control, progress, status: anything bigger is not ours
DEFAULT_RATE_HZ = 5000.0  # per subscription; a lockstep run stays far below (progress: ~6 messages a frame)


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
    config_file: str | None = None  # a Zenoh configuration file (TLS, authentication, access control...)
    # which of mode / connect / listen were given (flags, environment): those override the file's
    explicit: frozenset[str] = frozenset({"mode", "connect", "listen"})

    @classmethod
    def from_env(cls, connect: str | None = None, mode: str | None = None, listen: str | None = None,
                 config_file: str | None = None, env_connect: bool = True) -> BusConfig:
        """Flags win over environment variables, which win over the Zenoh config file, which wins over the
        embedded default. env_connect=False: ignore SEMMAP_ZENOH_CONNECT (a router is what others dial)."""
        config_file = config_file or environment.read(ENV_ZENOH_CONFIG) or None
        if config_file and not os.path.isfile(config_file):
            raise BusError(f"Zenoh config file {config_file} does not exist (--zenoh-config / {ENV_ZENOH_CONFIG})")
        explicit = set()
        mode_given = mode or environment.read(ENV_MODE)
        if mode_given:
            explicit.add("mode")
        mode = mode_given or "peer"
        if mode not in MODES:
            raise BusError(f"unknown Zenoh mode {mode!r}; use one of {', '.join(MODES)}")
        connect_spec = connect or (environment.read(ENV_CONNECT) if env_connect else None)
        if connect_spec:
            explicit.add("connect")
        connect_list = _split(connect_spec)
        listen_spec = listen if listen is not None else environment.read(ENV_LISTEN)
        if listen_spec is not None:
            explicit.add("listen")
            listen_list = _split(listen_spec)
        else:
            listen_list = [] if mode == "client" else ["tcp/127.0.0.1:0"]
        if not config_file:  # no file: semmap's defaults are the whole configuration
            explicit = {"mode", "connect", "listen"}
        return cls(mode=mode, connect=connect_list, listen=listen_list, config_file=config_file,
                   explicit=frozenset(explicit))

    def to_zenoh(self) -> zenoh.Config:
        """The session configuration: the file (if any) with semmap's settings merged in. A setting the file
        leaves unset gets semmap's default; one given by flag or environment replaces the file's."""
        if self.config_file:
            try:
                cfg = zenoh.Config.from_file(self.config_file)
            except (zenoh.ZError, OSError) as exc:
                raise BusError(f"cannot read Zenoh config file {self.config_file}: {exc}") from None
        else:
            cfg = zenoh.Config()

        def unset(path: str) -> bool:
            value = json.loads(cfg.get_json(path))
            return value is None or value == [] or isinstance(value, dict)  # (listen's per-mode default)

        mode = self.mode if "mode" in self.explicit or unset("mode") else json.loads(cfg.get_json("mode"))
        cfg.insert_json5("mode", json.dumps(mode))
        if unset("scouting/multicast/enabled"):
            cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        if "connect" in self.explicit or unset("connect/endpoints"):
            cfg.insert_json5("connect/endpoints", json.dumps(self.connect))
        if mode != "client" and ("listen" in self.explicit or unset("listen/endpoints")):
            cfg.insert_json5("listen/endpoints", json.dumps(self.listen))
        return cfg

    def as_args(self) -> list[str]:
        """The command-line flags that give a child process this configuration."""
        args = ["--zenoh-mode", self.mode, "--listen", ",".join(self.listen)]
        if self.connect:
            args += ["--connect", ",".join(self.connect)]
        if self.config_file:
            args += ["--zenoh-config", self.config_file]
        return args


# The MAC of a signed message, named by the version in its attachment (the receiver follows the sender): both are
# keyed 128-bit MACs; they differ only in speed, which depends on the CPU. A 700 KB camera frame is signed once and
# checked by every subscriber (four in a run), so on 2 cores the MAC's cost is felt in real time: BLAKE2b takes
# 1.6 ms per frame in software, HMAC-SHA256 0.5 ms where the CPU has SHA extensions (AMD Zen, Intel since Ice
# Lake) and ~3 ms where it has not. Each sender measures both once and signs with the faster.
MAC_BLAKE2B = 1
MAC_HMAC_SHA256 = 2
MAC_VERSIONS = (MAC_BLAKE2B, MAC_HMAC_SHA256)
_faster_mac: int | None = None


def faster_mac(sample_bytes: int = 256 * 1024, rounds: int = 3) -> int:
    """The MAC version this process signs with: the faster of the two on this CPU (measured once, ~5 ms)."""
    global _faster_mac
    if _faster_mac is None:
        data, key = bytes(sample_bytes), b"k" * 32

        def best(mac: Callable[[], object]) -> float:
            times = []
            for _ in range(rounds):
                t0 = time.perf_counter()
                mac()
                times.append(time.perf_counter() - t0)
            return min(times)

        blake = best(lambda: hashlib.blake2b(data, key=key, digest_size=16).digest())
        sha = best(lambda: hmac.digest(key, data, "sha256"))
        _faster_mac = MAC_HMAC_SHA256 if sha < blake else MAC_BLAKE2B
    return _faster_mac


class Refused(Exception):  # noqa: N818 - a verdict, not a failure
    """A message refused by the run's trust checks; `reason` names the counter."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass
class RunTrust:
    """A run's identity and secret: messages are signed with the sender's role and checked on receipt.

    `key` empty: no signing, no checks (a deployment without `semmap run`; the secure profile's access control
    protects it). `open_keys`: topics whose unsigned messages are taken (an external SLAM's frames, poses and
    end of stream in `semmap run external`); they may still not name another run.
    """

    run_id: str = ""
    key: bytes = b""
    sender: str = ""
    open_keys: frozenset[str] = frozenset()

    @classmethod
    def from_env(cls, sender: str) -> RunTrust:
        run_id = environment.read(ENV_RUN_ID) or ""
        open_keys = _split(environment.read(ENV_RUN_OPEN_KEYS))
        key_hex = environment.read(ENV_RUN_KEY) or ""
        try:
            key = bytes.fromhex(key_hex)
        except ValueError:
            raise BusError(f"{ENV_RUN_KEY} must be hex") from None
        if key and not run_id:
            raise BusError(f"{ENV_RUN_KEY} is set but {ENV_RUN_ID} is not")
        return cls(run_id, key, sender, frozenset(open_keys))

    @staticmethod
    def new_secret() -> str:
        return os.urandom(32).hex()

    def _mac(self, key_expr: str, sender: str, payload: bytes, version: int = 1) -> bytes:
        header = b"\0".join((key_expr.encode(), self.run_id.encode(), sender.encode(), b""))
        if version == MAC_HMAC_SHA256:
            h = hmac.new(self.key, b"semmap-run-v2\0" + header, "sha256")
            h.update(payload)
            return h.digest()[:16]
        h = hashlib.blake2b(key=self.key, digest_size=16, person=b"semmap-run-v1")
        h.update(header)
        h.update(payload)
        return h.digest()

    def sign(self, key_expr: str, payload: bytes) -> bytes | None:
        if not self.key:
            return None
        version = faster_mac()
        return msgpack.packb([version, self.run_id, self.sender, self._mac(key_expr, self.sender, payload, version)])

    def verify(self, key_expr: str, topic: str, payload: bytes, attachment: bytes | None) -> str:
        """The sender's role, or `Refused`."""
        if attachment is None:
            if topic in self.open_keys:
                return EXTERNAL_SENDER
            raise Refused("unsigned")
        try:
            version, run_id, sender, mac = msgpack.unpackb(attachment, raw=False)
            if version not in MAC_VERSIONS or not isinstance(sender, str) or not isinstance(mac, bytes):
                raise ValueError
        except Exception:  # noqa: BLE001 - any malformed attachment is one verdict
            raise Refused("bad_signature") from None
        if run_id != self.run_id:
            raise Refused("foreign_run")
        if not hmac.compare_digest(mac, self._mac(key_expr, sender, payload, version)):
            raise Refused("bad_signature")
        return sender


class RateLimit:
    """A token bucket: `rate` messages a second, bursts of as many (bounded work under a flood)."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.tokens = rate
        self.at = time.monotonic()
        self._lock = threading.Lock()

    def take(self) -> bool:
        if self.rate <= 0:
            return True
        with self._lock:
            now = time.monotonic()
            self.tokens = min(self.rate, self.tokens + (now - self.at) * self.rate)
            self.at = now
            if self.tokens < 1.0:
                return False
            self.tokens -= 1.0
            return True


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

    def waiting(self, name: str) -> int:
        """How many items of stream `name` wait to be handled (a service that falls behind sees it grow)."""
        with self._cv:
            return self._count.get(name, 0)

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


def passes_over(sample: zenoh.Sample, wanted: Callable[[int], bool]) -> bool:
    """Whether a reader passes `sample` over: its frame id (read unchecked) is one `wanted` refuses. A sample
    without a readable id, or a `wanted` that fails, is taken (and checked in full)."""
    frame_id = peek_frame_id(sample.payload.to_bytes())
    if frame_id is None:
        return False
    try:
        return not wanted(frame_id)
    except Exception:  # noqa: BLE001 - the check in full decides such a sample
        return False


class LatestSamples:
    """The newest `capacity` raw samples of a subscription, for a reader thread that checks and decodes them.

    Why: a Python callback subscription runs its callback on a thread of its own, fed by a channel of 256
    samples; a reader slower than the stream (a detector on a loaded machine takes 1.5 s a frame, the frames
    come at 90 Hz) filled it: 256 frames, 384 MB (the detector's RSS grew 346 -> 581 MB over a real-time soak)
    and every frame taken was ~3 s old. Here Zenoh's receiving thread only appends the sample and the oldest
    waiting one is dropped (and counted) when full, before anything is copied or decoded: memory is bounded by
    `capacity` samples and a reader always gets the newest.
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError("LatestSamples needs a capacity of at least 1")
        self._items: deque[Any] = deque()
        self.capacity = capacity
        self.dropped = 0
        self._closed = False
        self._cv = threading.Condition()

    def put(self, sample: Any) -> None:
        with self._cv:
            if len(self._items) >= self.capacity:
                self._items.popleft()
                self.dropped += 1
            self._items.append(sample)
            self._cv.notify()

    def take(self, timeout: float | None = None) -> Any | None:
        """The oldest waiting sample, or None once closed (or after `timeout` seconds without one)."""
        with self._cv:
            if not self._cv.wait_for(lambda: self._items or self._closed, timeout) or not self._items:
                return None
            return self._items.popleft()

    def drain(self, handle: Callable[[Any], None]) -> None:
        """Hand every sample to `handle` until closed (the reader thread's loop)."""
        while (sample := self.take()) is not None:
            try:
                handle(sample)
            except Exception:  # noqa: BLE001 - a reader thread must outlive one bad sample
                log.exception("handling a sample failed")
            del sample  # (its buffers go now, not when the next one comes)

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._items.clear()
            self._cv.notify_all()

    def __len__(self) -> int:
        with self._cv:
            return len(self._items)


class Bus:
    """A Zenoh session for one robot with typed publishers and validated subscriptions."""

    def __init__(self, config: BusConfig, robot: str, trust: RunTrust | None = None,
                 rate_hz: float = DEFAULT_RATE_HZ) -> None:
        self.keys = Keys(robot)
        self.config = config
        self.trust = trust or RunTrust()
        self.rate_hz = rate_hz
        self.session = open_session(config)
        self.rejected: dict[str, int] = {}  # by counter name: `rejected[<topic>]` (malformed),
        # `rejected_<reason>[<topic>]` (unsigned, bad_signature, foreign_run, wrong_sender, size, rate)
        self._lock = threading.Lock()
        self._undeclare: list[Any] = []
        self._boxes: dict[str, LatestSamples] = {}  # per topic, the subscriptions that keep the latest samples

    def publisher(self, key: str, express: bool = False) -> Publisher:
        pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK, express=express)
        self._undeclare.append(pub)
        return Publisher(pub, self.trust, key)

    def subscribe(self, key: str, kind: type[M], on_message: Callable[[M], None], latest: int | None = None,
                  wanted: Callable[[int], bool] | None = None) -> None:
        """Check and decode every sample on `key`; a refused or bad one is logged and counted, never raised.

        In a run (`trust.key`): the signature, the run id, the sender's right to the key; always: the size and
        the rate. The decoded message gets `.sender` (the signed role, "" outside a run).

        `latest`: at most this many samples wait to be checked and decoded, the oldest are dropped (counted in
        `dropped[<topic>]`); for real-time streams a reader cannot always keep up with (frames). Without it a
        slow reader's samples queue in Zenoh's Python callback channel, 256 of them (384 MB of 7-Scenes frames,
        seconds late), before Zenoh slows the publisher down (see `LatestSamples`).

        `wanted`: which frame ids this reader takes; the others are passed over on arrival, before the signature
        check, the decode and the queue (`passes_over`). Why: a detector replica takes only its share of the frames
        and the backend only keyframes; checking and decoding a 140 KB frame costs ~0.6 ms of CPU, and in real time
        a frame it passes over anyway would take the queue's place from the newest one it wants. The id is read
        unchecked (`peek_frame_id`): a forged message can make a reader pass over only itself (a forged frame it
        does not want is not counted here as rejected; the readers that take it count it)."""
        max_bytes = SMALL_MESSAGE_BYTES if issubclass(kind, SMALL_KINDS) else None
        limit = RateLimit(self.rate_hz)
        trust = self.trust

        def callback(sample: zenoh.Sample) -> None:
            key_expr = str(sample.key_expr)
            topic = self.keys.topic(key_expr)
            payload = sample.payload.to_bytes()
            sender = ""
            try:
                if max_bytes is not None and len(payload) > max_bytes:
                    raise Refused("size")
                if trust.key:
                    attachment = sample.attachment
                    sender = trust.verify(key_expr, topic, payload,
                                          None if attachment is None else attachment.to_bytes())
                    allowed = self.keys.publishers(key_expr)
                    if allowed is not None and sender not in allowed:
                        raise Refused("wrong_sender")
                if not limit.take():
                    raise Refused("rate")
            except Refused as refused:
                self._reject(f"rejected_{refused.reason}[{topic}]", f"{refused.reason} on {key_expr}")
                return
            try:
                message = kind.decode(payload)
            except MessageError as exc:
                self._reject(f"rejected[{topic}]", f"{key}: {exc}")
                return
            run = getattr(message, "run", "")
            if trust.run_id and (run != trust.run_id if sender != EXTERNAL_SENDER else run not in ("", trust.run_id)):
                self._reject(f"rejected_foreign_run[{topic}]", f"run {run!r} on {key_expr}")
                return
            if sender and sender != EXTERNAL_SENDER and getattr(message, "service", sender) != sender:
                self._reject(f"rejected_wrong_sender[{topic}]", f"{sender} speaking for {message.service}")
                return
            message.sender = sender
            on_message(message)

        def taken(deliver: Callable[[zenoh.Sample], None]) -> Callable[[zenoh.Sample], None]:
            """`deliver`, for the samples this reader wants."""
            if wanted is None:
                return deliver
            return lambda sample: None if passes_over(sample, wanted) else deliver(sample)

        if latest is None:
            self._undeclare.append(self.session.declare_subscriber(key, taken(callback)))
            return
        box = LatestSamples(latest)
        # (not indirect: the put runs on Zenoh's receiving thread, so no channel of its own queues samples first)
        self._undeclare.append(self.session.declare_subscriber(
            key, zenoh.handlers.Callback(taken(box.put), indirect=False)))
        self._boxes[self.keys.topic(key)] = box
        threading.Thread(target=box.drain, args=(callback,), name=f"latest {key}", daemon=True).start()

    @property
    def dropped(self) -> dict[str, int]:
        """Samples dropped unread per topic by `subscribe(..., latest=N)` (the reader was behind)."""
        return {topic: box.dropped for topic, box in self._boxes.items()}

    def subscribe_to_inbox(self, key: str, kind: type[M], inbox: Inbox, stream: str, capacity: int = 10_000) -> None:
        inbox.add_stream(stream, capacity)
        self.subscribe(key, kind, lambda message: inbox.put(stream, message))

    def _reject(self, counter: str, reason: str) -> None:
        with self._lock:
            n = self.rejected[counter] = self.rejected.get(counter, 0) + 1
        if n <= 5 or n % 100 == 0:
            log.warning("rejected message #%d (%s): %s", n, counter, reason)

    def close(self) -> None:
        for box in self._boxes.values():
            box.close()
        for entity in reversed(self._undeclare):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        self._undeclare.clear()
        self.session.close()


class Publisher:
    """Puts `Message`s; stamps `sent_at` and can wait until a subscriber matches (early puts would vanish)."""

    def __init__(self, publisher: zenoh.Publisher, trust: RunTrust | None = None, key: str = "") -> None:
        self._pub = publisher
        self._trust = trust or RunTrust()
        self._key = key

    def put(self, message: Message) -> int:
        if hasattr(message, "sent_at"):
            message.sent_at = time.time()
        if self._trust.run_id:
            message.run = self._trust.run_id
        payload = message.encode()
        self.put_bytes(payload)
        return len(payload)

    def put_bytes(self, payload: bytes) -> None:
        signature = self._trust.sign(self._key, payload)
        if signature is None:
            self._pub.put(payload)
        else:
            self._pub.put(payload, attachment=signature)

    def matching(self) -> bool:
        return bool(self._pub.matching_status.matching)

    def wait_matching(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.matching():
                return True
            time.sleep(0.01)
        return self.matching()
