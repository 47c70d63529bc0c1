"""What every semmap service process shares: flags, the bus, a single-threaded message loop, health and stats.

A service subclass declares what it listens to in `setup()` and handles one message at a time in the main
thread; algorithms live in plain modules beside it and know nothing of this. A bad message or a failing
handler is logged and counted, never fatal: a long-running service must not lose what it has mapped.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import logging
import os
import resource
import signal
import sqlite3
import sys
import threading
import time
import traceback
import uuid
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from semmap.core import dataflow, environment
from semmap.core.config import Config, ConfigError, load_config, run_overrides
from semmap.core.keys import EXTERNAL_SENDER, InvalidNameError
from semmap.core.logs import configure_logging
from semmap.core.messages import Control, Message, MessageError, Progress, ServiceStatus
from semmap.core.outputs import describe_disk_error, is_disk_error
from semmap.runtime.transport.bus import Bus, BusConfig, BusError, Inbox, Publisher, RunTrust

M = TypeVar("M", bound=Message)
STATUS_PERIOD_S = 1.0
QUEUE_CAPACITY = 100_000  # messages a stream may queue (real time: unless it asks for fewer)
REPLAY_FRAMES = 8  # how many recent frames' outputs a service can send again
MAX_ERRORS_IN_A_ROW = 10  # handler failures in a row that make a service give up (a bug, not bad luck)
HEALTH_FILE = environment.read(environment.HEALTH_FILE) or ""  # containers: touched on each status (runtime.health)
# real time: a service reports its progress at most this often (the newest frame it finished). Nothing waits on
# each frame there, and a progress message per frame per service was ~40 % of the messages of a run (two readers,
# ~0.1-0.3 ms of CPU at each end of each, taken from the detector on 2 cores); lockstep sends every one
PROGRESS_PERIOD_S = 0.1
EXIT_BACKSTOP_S = 10  # after SIGTERM / SIGINT, or once run() returned: the kernel ends a process still alive then
# (Zenoh's native threads can keep a finishing interpreter alive; SIGALRM's default action terminates)
CONTROL_SENDERS = {"stop": ("orchestrator",), "end_of_stream": ("player", EXTERNAL_SENDER),
                   "frame_unreadable": ("player", EXTERNAL_SENDER)}


# set by `semmap run` for its children: the pid of the run; a child whose parent is gone stops (see die_with_parent)
ENV_PARENT_PID = environment.PARENT_PID
ORPHAN_BACKSTOP_S = 5  # an orphaned service writes what it has, then ends within this many seconds
PR_SET_PDEATHSIG = 1


def parent_gone() -> bool:
    """Started by a `semmap run` that is no longer this process's parent (killed, even with SIGKILL)."""
    want = environment.read(ENV_PARENT_PID) or ""
    return want.isdigit() and os.getppid() != int(want)


def die_with_parent(poll_s: float = 0.5) -> None:
    """A service started by `semmap run` ends when the run does, however the run ended (SIGKILL included): the
    kernel sends SIGTERM when the parent goes (Linux `PR_SET_PDEATHSIG`; it fires when the parent *thread* that
    forked ends, so it is not trusted alone), and a daemon thread polls `os.getppid()` every `poll_s` seconds
    (re-parented to init or a subreaper: the run is gone) and sends SIGTERM itself. SIGTERM is the service's
    ordinary stop: it writes its outputs and exits; ORPHAN_BACKSTOP_S after the SIGTERM the watch thread
    SIGKILLs its process if it is still there. Nothing happens for a service
    started by hand or by compose (no SEMMAP_PARENT_PID)."""
    if not (environment.read(ENV_PARENT_PID) or "").isdigit():
        return
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)

    def watch() -> None:
        while not parent_gone():
            time.sleep(poll_s)
        logging.getLogger("semmap").warning("the semmap run that started this service is gone: stopping")
        os.kill(os.getpid(), signal.SIGTERM)
        # the main thread may be blocked where no Python signal handler runs (a send to a bus that is gone):
        # then this thread ends the process itself
        time.sleep(ORPHAN_BACKSTOP_S)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def exit_backstop(seconds: int = EXIT_BACKSTOP_S) -> None:
    """Make sure this process ends within `seconds` whatever hangs (SIGALRM with its default action: terminate)."""
    signal.signal(signal.SIGALRM, signal.SIG_DFL)
    signal.alarm(seconds)


def touch_health(path: str) -> None:
    with contextlib.suppress(OSError):  # a read-only disk must not stop the service
        Path(path).touch()


def rss_mb() -> float:
    """Current resident set size (Linux), or the peak where /proc is unavailable."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


class Metrics:
    """Counters and latency samples (last 10,000 per name) with percentiles for status and stats.json."""

    def __init__(self) -> None:
        self.counters: dict[str, int] = {}
        self._samples: dict[str, deque[float]] = {}
        self.peak_rss_mb = 0.0

    def count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    def time_ms(self, name: str, value_ms: float) -> None:
        self._samples.setdefault(name, deque(maxlen=10_000)).append(value_ms)

    def timer(self, name: str) -> _Timer:
        return _Timer(self, name)

    def summary(self) -> dict[str, dict[str, float]]:
        out = {}
        for name, samples in self._samples.items():
            if samples:
                a = np.fromiter(samples, float)
                out[name] = {"n": float(len(a)), "mean": float(a.mean()), "p50": float(np.percentile(a, 50)),
                             "p95": float(np.percentile(a, 95)), "p99": float(np.percentile(a, 99)),
                             "max": float(a.max())}
        return out


class _Timer:
    def __init__(self, metrics: Metrics, name: str) -> None:
        self.metrics, self.name, self.ms = metrics, name, 0.0

    def __enter__(self) -> _Timer:
        self._t0 = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        self.ms = (time.perf_counter() - self._t0) * 1e3
        self.metrics.time_ms(self.name, self.ms)


def common_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags every service takes (the CLI passes them on to each child process)."""
    parser.add_argument("--robot", default=environment.read(environment.ROBOT),
                        help="robot name in the key expressions (env SEMMAP_ROBOT; default from config)")
    parser.add_argument("--config", default=None,
                        help="YAML config file (the layout `semmap config show` prints; any subset)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override one setting; repeatable")
    parser.add_argument("--out", default=None, help="output directory for this service's files")
    parser.add_argument("--instance", default=None, help="instance name (default: random)")
    parser.add_argument("--connect", default=None, help="Zenoh endpoints to connect to, comma-separated")
    parser.add_argument("--listen", default=None, help="Zenoh endpoints to listen on, comma-separated")
    parser.add_argument("--zenoh-mode", default=None, choices=("peer", "client", "router"))
    parser.add_argument("--zenoh-config", default=None, metavar="FILE",
                        help="Zenoh configuration file (TLS, access control...; env SEMMAP_ZENOH_CONFIG): see "
                        "docs/SECURITY.md")
    parser.add_argument("--mode", default=None, choices=("lockstep", "realtime"), help="playback mode")
    parser.add_argument("--resume", action="store_true",
                        help="continue from the state this service saved in --out (after a crash or restart)")
    parser.add_argument("--frame-base", type=int, default=0, metavar="N",
                        help="in a run: the frame the stream is at (a restarted service); frame ids further than "
                        "security.max_frame_gap from it are refused")
    parser.add_argument("-v", "--verbose", action="store_true")


REANCHOR_AFTER = 3  # frame ids refused in a row on a signed stream before the service follows it (see above)


class Service:
    """Base class of a service process. Subclasses set `name`, implement `setup()` and message handlers."""

    name = "service"
    lockstep = True  # (the run's mode, set per instance: lockstep, or real time)

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        # --mode and --robot are settings like any other: validated with the tree, never changed after
        self.config: Config = load_config(args.config, [*args.overrides, *run_overrides(args.mode, args.robot)])
        self.robot: str = self.config.run.robot
        self.instance: str = args.instance or f"{self.name}-{uuid.uuid4().hex[:6]}"
        self.out_dir: Path | None = Path(args.out) if args.out else None
        self.lockstep = self.config.run.mode == "lockstep"
        self.log = logging.getLogger(self.name)
        self.metrics = Metrics()
        self.inbox = Inbox()
        self.stop_event = threading.Event()
        self.state = "starting"
        self.last_frame_id = -1
        self.end_of_stream: Control | None = None
        self.finished = False
        self._handlers: dict[str, Callable[[Any], None]] = {}
        self._error_count = 0
        self._errors_in_a_row = 0
        self.idle_timeout_s = 0.05
        self.resume = bool(getattr(args, "resume", False))
        self._sent: dict[int, list[tuple[Publisher, Message]]] = {}  # recent outputs by frame, for replays
        # handling journalled inputs again after a crash: outputs are remembered but not sent (they were sent)
        self.muted = False
        # frame ids more than this away from the newest one seen on a stream are refused (a forged or broken
        # publisher must not make a service loop over an absurd gap or skip the frames in between)
        self.max_frame_gap = self.config.security.max_frame_gap
        self._newest: dict[str, int] = {}  # per stream, the newest frame id accepted
        self._refused_ids: dict[str, list[int]] = {}  # per stream, the frame ids refused in a row
        self._gap_rejected: dict[str, int] = {}
        self._gap_lock = threading.Lock()
        self.newest_frame_id = -1  # over every stream: an end of stream before it is not believed
        self.bus: Bus
        self._status_pub: Publisher
        self._progress_pub: Publisher
        self._progress_sent_at = 0.0  # (real time) when progress last went out
        self._progress_owed: int | None = None  # (real time) the newest frame finished and not reported yet

    # -- to be provided by subclasses ------------------------------------------------------------------------
    def setup(self) -> None:
        """Declare subscriptions (`self.listen`) and publishers; load models."""

    def on_end_of_stream(self, control: Control) -> None:
        """The player sent its last frame. Default: finish once this service has handled that frame."""
        if self.last_frame_id >= control.last_frame_id:
            self.finish()

    def write_outputs(self) -> None:
        """Write this service's files to `self.out_dir` (called on finish and on shutdown)."""

    def teardown(self) -> None:
        """Release resources."""

    def on_frame_unreadable(self, frame_id: int) -> None:
        """The player could not read frame `frame_id`: it never comes. Services that handle frames in order
        skip it here (lockstep would otherwise wait for it until the run times out)."""

    def tick(self) -> None:
        """Called on every loop turn (at least every `idle_timeout_s`): for services that produce on a clock."""

    # -- helpers for subclasses -------------------------------------------------------------------------------
    def subscribe(self) -> None:
        """Listen to what semmap/core/dataflow.py declares for this node: each port's topic, with the message class
        the table gives the topic, to the handler the port names (the table is what runs: a subscription no table
        declares cannot exist). A port whose `when` names an attribute that is false here is left out (an input
        only some configurations need); `listen_options` adds what a port needs beyond that (real-time queues)."""
        for port in dataflow.node(self.name).ports:
            if port.when and not getattr(self, port.when):
                continue
            self.listen(self.bus.keys.key(port.topic), dataflow.message_class(port.topic),
                        getattr(self, port.handler), **self.listen_options(port.topic))

    def listen_options(self, topic: str) -> dict[str, Any]:
        """More for one port's `listen` (`realtime_capacity`, `wanted`, `prepare`); none by default."""
        return {}

    def open_outputs(self) -> dict[str, Publisher]:
        """A publisher for every topic the dataflow table lets this node write, by topic (`self.out`)."""
        self.out = {topic: self.publisher(self.bus.keys.key(topic)) for topic in dataflow.node(self.name).outputs}
        return self.out

    def listen(self, key: str, kind: type[M], handler: Callable[[M], None],
               realtime_capacity: int | None = None, wanted: Callable[[int], bool] | None = None,
               prepare: Callable[[M], object] | None = None) -> None:
        """Handle `kind` messages from `key`. Lockstep queues everything (the player paces the run); in real time
        a stream with `realtime_capacity` keeps only that many waiting, dropping the oldest (frames: stay live).
        `wanted`: the frame ids the handler takes; the rest are passed over as they arrive (`Bus.subscribe`).
        `prepare`: work on a message in the bus's thread as it arrives, before it queues (decoding a frame's
        images while the handler is still busy with the previous one: on a second core, not on its path)."""
        stream = f"{key}#{kind.SCHEMA}"
        capacity = realtime_capacity if realtime_capacity is not None and not self.lockstep else QUEUE_CAPACITY

        topic = self.bus.keys.topic(key)
        dataflow.check_input(self.name, topic)  # the wiring is declared once: semmap/core/dataflow.py

        def checked(message: M) -> None:
            robot = getattr(message, "robot", self.robot)
            if robot != self.robot:  # on our key but naming another robot: a misconfigured publisher
                self.metrics.count("wrong_robot")
                if self.metrics.counters["wrong_robot"] <= 5:
                    self.log.warning("skipped a %s for robot %r on %s (this is %r)", kind.SCHEMA, robot, key,
                                     self.robot)
                return
            handler(message)

        def arrived(message: M) -> None:  # (a Zenoh thread) checked on arrival, before it takes queue space
            if self._frame_id_plausible(stream, topic, message):
                if prepare is not None:
                    with contextlib.suppress(Exception):  # (the handler meets the same error and says so, counted)
                        prepare(message)
                self.inbox.put(stream, message)

        self._handlers[stream] = checked
        self.inbox.add_stream(stream, capacity)
        # real time: as many again may wait undecoded in the bus (the newest; older ones are dropped unread)
        self.bus.subscribe(key, kind, arrived, latest=capacity if capacity < QUEUE_CAPACITY else None, wanted=wanted)

    def _frame_id_plausible(self, stream: str, topic: str, message: Message) -> bool:
        """Frame ids move forward within a window: one more than `max_frame_gap` from the newest accepted on
        this stream (either way) is refused and counted, so no absurd id drives a skip loop or a memory grab.

        Except where the stream really moved on while this service was behind (stopped, starved, started late):
        `REANCHOR_AFTER` refusals in a row on a signed stream (a peer of this run, not an open key), agreeing
        within the window, make the stream's newest id theirs, or the service would refuse it forever."""
        frame_id = getattr(message, "frame_id", None)
        if not isinstance(frame_id, int) or isinstance(message, Progress) or self.max_frame_gap <= 0:
            return True
        with self._gap_lock:
            newest = self._newest.get(stream)
            if newest is None and self.bus.trust.key:  # in a run the stream starts where the run is
                newest = max(self.last_frame_id, int(getattr(self.args, "frame_base", 0) or 0) - 1)
            refused = self._refused_ids.setdefault(stream, [])
            if newest is not None and abs(frame_id - newest) > self.max_frame_gap:
                refused.append(frame_id)
                del refused[:-REANCHOR_AFTER]
                signed = bool(self.bus.trust.key) and topic not in self.bus.trust.open_keys
                if signed and len(refused) == REANCHOR_AFTER and max(refused) - min(refused) <= self.max_frame_gap:
                    self.log.warning("%s moved on to frame %d while this service stood at %d: following it", topic,
                                     frame_id, newest)
                    counter = f"frame_gap_followed[{topic}]"
                    self._gap_rejected[counter] = self._gap_rejected.get(counter, 0) + 1
                    refused.clear()
                    self._newest[stream] = frame_id
                    self.newest_frame_id = max(self.newest_frame_id, frame_id)
                    return True
                counter = f"rejected_frame_gap[{topic}]"
                n = self._gap_rejected[counter] = self._gap_rejected.get(counter, 0) + 1
                if n <= 5:
                    self.log.warning("refused frame id %d on %s: the newest is %d (max gap %d)", frame_id, topic,
                                     newest, self.max_frame_gap)
                return False
            refused.clear()
            if newest is None or frame_id > newest:
                self._newest[stream] = frame_id
                self.newest_frame_id = max(self.newest_frame_id, frame_id)
        return True

    def publisher(self, key: str) -> Publisher:
        """A publisher on `key`, which this service's node must declare among its outputs (semmap/core/dataflow.py;
        UndeclaredKeyError otherwise: the access-control list and the signature checks follow that table)."""
        dataflow.check_output(self.name, self.bus.keys.topic(key))
        return self.bus.publisher(key)

    def emit(self, publisher: Publisher, message: Message, frame_id: int) -> None:
        """Publish an output of frame `frame_id`, remembered for a while so a repeated input can be answered."""
        if not self.muted:
            publisher.put(message)
        self._sent.setdefault(frame_id, []).append((publisher, message))
        for old in [f for f in self._sent if f < frame_id - REPLAY_FRAMES]:
            del self._sent[old]

    def remember(self, publisher: Publisher, message: Message, frame_id: int) -> None:
        """An output of frame `frame_id` that went out before a crash (read back from a journal): a restarted
        service answers that frame again with it when the frame comes again (the old process may have died
        before its output or its progress left), instead of staying silent and stalling a lockstep run."""
        self._sent.setdefault(frame_id, []).append((publisher, message))

    def replay(self, frame_id: int) -> bool:
        """A frame's input came again (the player resends a frame that got lost, e.g. in a crashed service):
        send what it produced again, and the progress. False if it is too old to remember."""
        outputs = self._sent.get(frame_id)
        if outputs is None:
            return False
        if self.muted:
            return True
        for publisher, message in outputs:
            publisher.put(message)
        self._put_progress(frame_id)
        self.metrics.count("replays")
        return True

    def report_progress(self, frame_id: int) -> None:
        """Everything frame `frame_id` caused is done here (lockstep playback waits for it). In real time the
        report goes out at most every PROGRESS_PERIOD_S, with the newest frame done (`_send_owed_progress`); the
        stream's last frame at once."""
        self.last_frame_id = max(self.last_frame_id, frame_id)
        if self.muted:
            return
        last = self.end_of_stream.last_frame_id if self.end_of_stream is not None else None
        if self.lockstep or frame_id == last:
            self._put_progress(frame_id)
            if self._progress_owed is not None and self._progress_owed <= frame_id:
                self._progress_owed = None
        else:
            self._progress_owed = frame_id if self._progress_owed is None else max(self._progress_owed, frame_id)
            self._send_owed_progress()
        if self.end_of_stream is not None and not self.finished:
            self.on_end_of_stream(self.end_of_stream)

    def _send_owed_progress(self, force: bool = False) -> None:
        """(Real time) report the newest frame done, if one is owed and PROGRESS_PERIOD_S has passed."""
        if self._progress_owed is None or self.muted:
            return
        now = time.monotonic()
        if force or now - self._progress_sent_at >= PROGRESS_PERIOD_S:
            self._put_progress(self._progress_owed)
            self._progress_owed, self._progress_sent_at = None, now

    def _put_progress(self, frame_id: int) -> None:
        self._progress_pub.put(Progress(self.robot, self.name, frame_id))

    def finish(self) -> None:
        """All input handled: write outputs and tell the run so. The service stays up until told to stop."""
        if self.finished:
            return
        self.finished = True
        self._send_owed_progress(force=True)
        if not self._write_outputs_safely():
            return
        self.state = "finished"
        self.publish_status()
        self.log.info("finished (last frame %d)", self.last_frame_id)

    def fail(self, reason: str) -> None:
        """A fatal condition: tell the run why, then stop."""
        self.log.error("%s", reason)
        self.state = "failed"
        self.publish_status(reason)
        self.stop_event.set()

    def publish_status(self, message: str = "") -> None:
        rss = rss_mb()
        self.metrics.peak_rss_mb = max(self.metrics.peak_rss_mb, rss)
        counters = dict(self.metrics.counters)
        for stream, n in self.inbox.dropped.items():
            if n:
                counters[f"dropped[{stream.split('#')[0].rsplit('/', 1)[-1]}]"] = n
        for topic, n in self.bus.dropped.items():  # dropped unread, before the inbox (real time)
            if n:
                name = f"dropped[{topic.rsplit('/', 1)[-1]}]"
                counters[name] = counters.get(name, 0) + n
        with self.bus._lock:
            counters.update(self.bus.rejected)
        with self._gap_lock:
            counters.update(self._gap_rejected)
        usage = resource.getrusage(resource.RUSAGE_SELF)
        status = ServiceStatus(self.robot, self.name, self.instance, self.state, self.last_frame_id, counters,
                               self.metrics.summary(), rss, usage.ru_utime + usage.ru_stime, message)
        status.timings["peak_rss_mb"] = {"max": self.metrics.peak_rss_mb}
        try:
            self._status_pub.put(status)
        except Exception as exc:  # the bus may already be closing
            self.log.debug("status not sent: %s", exc)
        if HEALTH_FILE and self.state in ("running", "finished"):
            touch_health(HEALTH_FILE)

    # -- the loop --------------------------------------------------------------------------------------------
    def _on_control(self, control: Control) -> None:
        # in a run, each command has its owner: `stop` the orchestrator, the stream's end and gaps the player
        # (or an external SLAM where the run leaves control open); the bus has checked who signed it
        if self.bus.trust.key and control.sender not in CONTROL_SENDERS[control.command]:
            self._refuse_control(control, f"{control.command} from {control.sender!r}")
            return
        if control.command == "stop":
            self.stop_event.set()
        elif control.command == "frame_unreadable":
            self.metrics.count("unreadable_skipped")
            self.on_frame_unreadable(control.last_frame_id)
        elif control.command == "end_of_stream":
            if control.last_frame_id < self.newest_frame_id or (
                    self.end_of_stream is not None and control.last_frame_id != self.end_of_stream.last_frame_id):
                # the stream cannot end before a frame this service already has, nor end twice differently
                self._refuse_control(control, f"end of stream at frame {control.last_frame_id}, but frame "
                                     f"{self.newest_frame_id} was seen")
                return
            self.end_of_stream = control
            self.on_end_of_stream(control)

    def _refuse_control(self, control: Control, why: str) -> None:
        self.metrics.count(f"rejected_control[{control.command}]")
        if self.metrics.counters[f"rejected_control[{control.command}]"] <= 5:
            self.log.warning("refused control: %s", why)

    def _write_outputs_safely(self) -> bool:
        """Write the outputs; a failure fails the service with its cause (a full disk is named as such)."""
        if self.out_dir is None:
            return True
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            self.write_outputs()
        except (OSError, sqlite3.OperationalError) as exc:
            self.log.error("writing outputs failed:\n%s", traceback.format_exc())
            why = describe_disk_error(exc) if is_disk_error(exc) else f"{type(exc).__name__}: {exc}"
            self.fail(f"writing outputs failed: {why}")
            return False
        except Exception as exc:
            self.log.error("writing outputs failed:\n%s", traceback.format_exc())
            self.fail(f"writing outputs failed: {type(exc).__name__}: {exc}")
            return False
        return True

    def _guarded(self, fn: Callable[..., None], message: Any = None, what: str = "tick") -> None:
        """Run one handler; bad input is a counted skip, any other failure a counted, logged error."""
        try:
            fn() if message is None else fn(message)
        except (MessageError, ValueError) as exc:
            self.metrics.count("bad_input")
            self.log.warning("skipped a bad %s message: %s", what, exc)
        except (OSError, sqlite3.OperationalError) as exc:
            if is_disk_error(exc):
                # a full or read-only disk: no retry helps; say so at once rather than as "no progress" later
                self.metrics.count("errors")
                self.log.error("%s handler failed:\n%s", what, traceback.format_exc())
                self.fail(describe_disk_error(exc))
            else:
                self._handler_failed(what)
        except Exception:
            self._handler_failed(what)
        else:
            self._errors_in_a_row = 0

    def _handler_failed(self, what: str) -> None:
        """(In an `except` block.) Count and log; give up after MAX_ERRORS_IN_A_ROW."""
        self._error_count += 1
        self._errors_in_a_row += 1
        self.metrics.count("errors")
        self.log.error("%s handler failed (error %d):\n%s", what, self._error_count, traceback.format_exc())
        if self._errors_in_a_row >= MAX_ERRORS_IN_A_ROW:  # not bad luck but a bug or a broken set-up
            self.fail(f"{self._errors_in_a_row} {what} handler failures in a row; last: "
                      f"{traceback.format_exc(limit=1).strip().splitlines()[-1]}")

    def _on_signal(self, *_: object) -> None:
        self.stop_event.set()
        # outputs are written within seconds; a wedged process must not outlive its stop (nor an orphan its run)
        exit_backstop(ORPHAN_BACKSTOP_S if parent_gone() else EXIT_BACKSTOP_S)

    def run(self) -> int:
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self._on_signal)
        bus_config = BusConfig.from_env(self.args.connect, self.args.zenoh_mode, self.args.listen,
                                        getattr(self.args, "zenoh_config", None))
        self.bus = Bus(bus_config, self.robot, RunTrust.from_env(self.name),
                       self.config.security.max_rate_hz)
        self._status_pub = self.bus.publisher(self.bus.keys.status(self.name, self.instance))
        self._progress_pub = self.bus.publisher(self.bus.keys.progress(self.name))
        try:
            self.listen(self.bus.keys.control, Control, self._on_control)
            self.setup()
        except Exception as exc:
            self.state = "failed"
            self.publish_status(f"setup failed: {exc}")
            self.log.error("setup failed: %s", exc)
            self.bus.close()
            return 2
        self.state = "running"
        mode = "lockstep" if self.lockstep else "realtime"
        self.log.info("started as %s (robot %s, %s)", self.instance, self.robot, mode)
        self.publish_status()
        next_status = time.monotonic() + STATUS_PERIOD_S
        try:
            while not self.stop_event.is_set():
                item = self.inbox.get(timeout=self.idle_timeout_s)
                if item is not None:
                    stream, message = item
                    self._guarded(self._handlers[stream], message, stream.split("#")[0].rsplit("/", 1)[-1])
                self._guarded(self.tick)
                self._send_owed_progress()
                if time.monotonic() >= next_status:
                    self.publish_status()
                    next_status = time.monotonic() + STATUS_PERIOD_S
        finally:
            if not self.finished:
                self._write_outputs_safely()
            if self.state != "failed":
                self.state = "finished" if self.finished else "stopped"
                self.publish_status()
            self.log.info("stopped (%s)", ", ".join(f"{k}={v}" for k, v in sorted(self.metrics.counters.items())))
            try:
                self.teardown()
            finally:
                self.bus.close()
        return 2 if self.state == "failed" else 0  # failed: its status says why; a restart would not help


def service_main(service_cls: type[Service], argv: list[str] | None = None,
                 extra_arguments: Callable[[argparse.ArgumentParser], None] | None = None) -> int:
    """Entry point of `python -m services.<name>`."""
    parser = argparse.ArgumentParser(prog=f"semmap-{service_cls.name}", description=service_cls.__doc__)
    common_arguments(parser)
    if extra_arguments:
        extra_arguments(parser)
    args = parser.parse_args(argv)
    configure_logging(args.verbose, service_cls.name)
    if argv is None:  # a process of its own (not a test calling main in-process)
        die_with_parent()
    try:
        service = service_cls(args)
        return service.run()
    except (ConfigError, InvalidNameError, ValueError, BusError) as exc:
        logging.getLogger(service_cls.name).error("%s", exc)
        return 2
    finally:
        # from here on a signal ends the process (no handler needs the main thread), and the interpreter's
        # shutdown may not hang on Zenoh's threads for longer than the backstop (a process of its own only)
        if argv is None:
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, signal.SIG_DFL)
            exit_backstop(ORPHAN_BACKSTOP_S if parent_gone() else EXIT_BACKSTOP_S)
