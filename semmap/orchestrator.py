"""`semmap run`: start every service as its own process on one Zenoh bus, watch them, stop them cleanly.

The orchestrator is itself a Zenoh peer listening on a loopback port (or a client of a router given with
`--connect`); services connect to it. It shows progress from the services' status messages, fails the run with
the failing service's log tail when one dies, and writes `stats.json` from their final statuses.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from statistics import fmean

from semmap.bus import Bus, BusConfig
from semmap.messages import Control, Progress, ServiceStatus

log = logging.getLogger("semmap.run")

STOP_GRACE_S = 15.0
MAX_RESTARTS = 5
RESTART_BACKOFF_S = 0.5
EXTERNAL = "external"  # `semmap run external`: no player, no odometry; a SLAM feeds the bus (semmap.client)


@dataclass
class ServiceSpec:
    """One service to start: `python -m services.<module>` with extra flags, `replicas` times."""

    name: str
    extra_args: list[str] = field(default_factory=list)
    replicas: int = 1
    lockstep: bool = True  # whether lockstep playback waits for its progress


@dataclass
class RunPlan:
    data: str
    out_dir: Path
    robot: str
    mode: str  # lockstep | realtime
    services: list[ServiceSpec]
    config_path: str | None = None
    overrides: list[str] = field(default_factory=list)
    connect: str | None = None  # a router to join instead of hosting the bus
    zenoh_mode: str | None = None
    verbose: bool = False
    quiet: bool = False


DEFAULT_PORT = 7447  # the Zenoh default: `semmap query` finds a local run there without flags


def free_loopback_port(preferred: int = 0) -> int:
    """`preferred` if it is free on loopback, else any free port."""
    for port in (preferred, 0) if preferred else (0,):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except (OSError, OverflowError):  # in use, or not a port number
                continue
            return int(s.getsockname()[1])
    raise OSError("no free loopback port")


class _Child:
    """One service process; restarted in place (same instance name, same log) when it crashes."""

    def __init__(self, name: str, instance: str, argv: list[str], log_path: Path) -> None:
        self.name, self.instance, self.argv, self.log_path = name, instance, argv, log_path
        self.log_file = open(log_path, "ab")  # noqa: SIM115 - lives as long as the process
        self.restarts = 0
        self.restart_at: float | None = None  # when a crashed process is due to come back
        self.proc = self._spawn(argv)

    def _spawn(self, argv: list[str]) -> subprocess.Popen:
        return subprocess.Popen(argv, stdout=self.log_file, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True)

    def restart(self, extra_args: list[str]) -> None:
        self.restarts += 1
        self.restart_at = None
        self.log_file.write(f"--- restart {self.restarts} ---\n".encode())
        self.log_file.flush()
        self.proc = self._spawn([*self.argv, *extra_args])

    def tail(self, lines: int = 25) -> str:
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(text[-lines:])


class RunFailed(RuntimeError):
    pass


class Orchestrator:
    def __init__(self, plan: RunPlan) -> None:
        self.plan = plan
        self.children: list[_Child] = []
        self.statuses: dict[str, ServiceStatus] = {}
        self.progress: dict[str, int] = {}
        self.lock = threading.Lock()
        self.interrupted = threading.Event()
        self.endpoint = ""
        self.restarts: dict[str, int] = {}
        self.rss: dict[str, list[float]] = {}  # per instance, one sample a second (status period)

    # -- bus --------------------------------------------------------------------------------------------------
    def _bus_config(self) -> tuple[BusConfig, list[str]]:
        """The orchestrator's own bus config and the flags its children get."""
        if self.plan.connect:
            cfg = BusConfig.from_env(self.plan.connect, self.plan.zenoh_mode or "client")
            child = ["--connect", self.plan.connect]
            if self.plan.zenoh_mode:
                child += ["--zenoh-mode", self.plan.zenoh_mode]
            return cfg, child
        port = free_loopback_port(DEFAULT_PORT)
        hub = f"tcp/127.0.0.1:{port}"
        self.endpoint = hub
        return BusConfig(mode="peer", listen=[hub]), ["--zenoh-mode", "peer", "--connect", hub,
                                                      "--listen", "tcp/127.0.0.1:0"]

    def _on_status(self, s: ServiceStatus) -> None:
        with self.lock:
            self.statuses[s.instance] = s
            self.rss.setdefault(s.instance, []).append(s.rss_mb)

    def _on_progress(self, p: Progress) -> None:
        with self.lock:
            self.progress[p.service] = max(self.progress.get(p.service, -1), p.frame_id)

    # -- processes --------------------------------------------------------------------------------------------
    def _start(self, child_bus_args: list[str]) -> None:
        plan = self.plan
        logs = plan.out_dir / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        common = ["--robot", plan.robot, "--mode", plan.mode, "--out", str(plan.out_dir), *child_bus_args]
        if plan.config_path:
            common += ["--config", plan.config_path]
        for item in plan.overrides:
            common += ["--set", item]
        if plan.verbose:
            common.append("--verbose")
        wait_for = ",".join(f"{s.name}:{s.replicas}" for s in plan.services if s.lockstep)
        start_after = ",".join(f"{s.name}:{s.replicas}" for s in plan.services if not s.lockstep)
        specs = list(plan.services)
        if plan.data != EXTERNAL:  # an external SLAM publishes the frames and poses itself
            specs.append(ServiceSpec("player", ["--data", plan.data, "--wait-for", wait_for, "--start-after",
                                                start_after], 1, False))
        for spec in specs:
            for r in range(spec.replicas):
                instance = spec.name if spec.replicas == 1 else f"{spec.name}-{r + 1}"
                argv = [sys.executable, "-m", f"services.{spec.name}", *common, "--instance", instance,
                        *spec.extra_args]
                self.children.append(_Child(spec.name, instance, argv, logs / f"{instance}.log"))
                log.info("started %s (pid %d)", instance, self.children[-1].proc.pid)

    def _check_children(self) -> None:
        """Fail the run on a service that reports failure (bad config, missing model: a restart cannot help);
        restart one that crashed (killed, an uncaught error) with backoff, up to MAX_RESTARTS times."""
        now = time.monotonic()
        for child in self.children:
            if child.restart_at is not None:
                if now >= child.restart_at:
                    child.restart(self._resume_args(child))
                    log.warning("restarted %s (restart %d, pid %d)", child.instance, child.restarts, child.proc.pid)
                continue
            code = child.proc.poll()
            status = self.statuses.get(child.instance)
            if status is not None and status.state == "failed":
                raise RunFailed(f"{child.instance} failed: {status.message}\n--- {child.log_path} ---\n{child.tail()}")
            if code is None or (code == 0 and status is not None and status.state in ("finished", "stopped")):
                continue
            if code == 2 or child.restarts >= MAX_RESTARTS:  # 2: a usage / set-up error, it would fail again
                why = f"exited with code {code}" if code != 0 else "exited early"
                more = f" after {child.restarts} restarts" if child.restarts else ""
                raise RunFailed(f"{child.instance} {why}{more}\n--- {child.log_path} ---\n{child.tail()}")
            delay = min(RESTART_BACKOFF_S * 2**child.restarts, 10.0)
            child.restart_at = now + delay
            with self.lock:
                self.statuses.pop(child.instance, None)
                self.restarts[child.instance] = child.restarts + 1
            log.warning("%s died (exit %s); restarting in %.1f s", child.instance, code, delay)

    def _resume_args(self, child: _Child) -> list[str]:
        """A restarted service picks up its saved state; the player continues after the last finished frame."""
        if child.name != "player":
            return ["--resume"]
        return ["--start-at", str(self._frames_done())]

    def _frames_done(self, default: int = 0) -> int:
        """How many frames every lockstep service has finished (`default` when none gates the stream)."""
        with self.lock:
            done = [self.progress.get(s.name, -1) for s in self.plan.services if s.lockstep]
        return min(done) + 1 if done else default

    def _all_finished(self) -> bool:
        if any(c.restart_at is not None for c in self.children):
            return False
        with self.lock:
            return all(
                (s := self.statuses.get(c.instance)) is not None and s.state == "finished" for c in self.children
            )

    def _stop_children(self, control_pub: object | None) -> None:
        if control_pub is not None:
            with contextlib.suppress(Exception):  # the bus may be gone; signals follow anyway
                control_pub.put(Control(self.plan.robot, "stop"))  # type: ignore[attr-defined]
        deadline = time.monotonic() + STOP_GRACE_S
        for child in self.children:
            if child.proc.poll() is None and control_pub is None:
                child.proc.send_signal(signal.SIGTERM)
        for child in self.children:
            try:
                child.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                child.proc.send_signal(signal.SIGTERM)
                try:
                    child.proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    child.proc.kill()
                    child.proc.wait()
            child.log_file.close()
            log.info("stopped %s (exit %s)", child.instance, child.proc.returncode)

    # -- progress -------------------------------------------------------------------------------------------
    def _counter_sum(self, prefix: str) -> int:
        with self.lock:
            return sum(v for s in self.statuses.values() for k, v in s.counters.items() if k.startswith(prefix))

    def _progress_line(self, started: float) -> str:
        published = self._counter_sum("frames_published")
        total = self._total_frames
        processed = self._frames_done(default=published)
        published = max(published, processed)
        dropped = self._counter_sum("frames_dropped")
        elapsed = max(time.monotonic() - started, 1e-6)
        fps = processed / elapsed
        width = 30
        frac = processed / total if total else 0.0
        bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
        return (f"[{bar}] {processed}/{total or '?'} frames processed, {published} published, "
                f"{fps:5.1f} fps, {dropped} dropped, {elapsed:5.1f} s")

    @property
    def _total_frames(self) -> int:
        with self.lock:
            for s in self.statuses.values():
                if s.service == "player" and s.counters.get("frames_total"):
                    return s.counters["frames_total"]
        return 0

    # -- stats ----------------------------------------------------------------------------------------------
    def write_stats(self, wall_s: float, outcome: str) -> Path:
        with self.lock:
            statuses = dict(self.statuses)
        services: dict[str, dict] = {}
        for instance, s in sorted(statuses.items()):
            timings = {k: v for k, v in s.timings.items() if k != "peak_rss_mb"}
            peak = s.timings.get("peak_rss_mb", {}).get("max", s.rss_mb)
            series = self.rss[instance]  # filled with statuses
            quarter = max(1, len(series) // 4)
            services[instance] = {"service": s.service, "state": s.state, "last_frame_id": s.last_frame_id,
                                  "counters": s.counters, "timings_ms": timings, "rss_mb": round(s.rss_mb, 1),
                                  "peak_rss_mb": round(max(peak, s.rss_mb), 1), "cpu_s": round(s.cpu_s, 2),
                                  # memory over the run: mean of the second quarter vs the last quarter
                                  "rss_early_mb": round(fmean(series[quarter:2 * quarter] or series), 1),
                                  "rss_late_mb": round(fmean(series[-quarter:]), 1)}
        published = sum(s.counters.get("frames_published", 0) for s in statuses.values())
        detected = sum(s.counters.get("frames_detected", 0) for s in statuses.values())
        # frames the detectors could not keep up with (real time); queue drops elsewhere stay per service
        dropped = sum(s.counters.get("frames_dropped", 0) for s in statuses.values())
        unreadable = sum(s.counters.get("frames_unreadable", 0) for s in statuses.values())  # (the player's)
        processed = self._frames_done(default=published)
        with self.lock:
            restarts = dict(self.restarts)
        for instance, n in restarts.items():
            services.setdefault(instance, {})["restarts"] = n
        stats = {"schema": "semmap.stats/1", "outcome": outcome, "data": self.plan.data, "mode": self.plan.mode,
                 "robot": self.plan.robot, "wall_s": round(wall_s, 2),
                 "frames": {"published": published, "processed": processed, "detected": detected,
                            "dropped": dropped, "unreadable": unreadable},
                 "fps": round(processed / wall_s, 2) if wall_s > 0 else 0.0, "restarts": sum(restarts.values()),
                 "services": services}
        path = self.plan.out_dir / "stats.json"
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(stats, indent=2))
        os.replace(tmp, path)
        return path

    # -- the run --------------------------------------------------------------------------------------------
    def run(self) -> int:
        plan = self.plan
        plan.out_dir.mkdir(parents=True, exist_ok=True)
        bus_cfg, child_args = self._bus_config()
        bus = Bus(bus_cfg, plan.robot)
        if self.endpoint:
            log.info("bus: %s (robot %s); e.g. semmap query --connect %s", self.endpoint, plan.robot, self.endpoint)
        bus.subscribe(bus.keys.status_all, ServiceStatus, self._on_status)
        bus.subscribe(bus.keys.progress_all, Progress, self._on_progress)
        control_pub = bus.publisher(bus.keys.control)
        previous = signal.signal(signal.SIGINT, lambda *_: self.interrupted.set())
        signal.signal(signal.SIGTERM, lambda *_: self.interrupted.set())
        started = time.monotonic()
        outcome, code = "completed", 0
        tty = sys.stderr.isatty() and not plan.quiet
        last_line = 0.0
        try:
            self._start(child_args)
            while True:
                if self.interrupted.is_set():
                    outcome, code = "interrupted", 130
                    print("\ninterrupted: stopping services (they write what they have)", file=sys.stderr)
                    break
                self._check_children()
                if self._all_finished():
                    break
                now = time.monotonic()
                if not plan.quiet and (tty and now - last_line > 0.2 or not tty and now - last_line > 5.0):
                    line = self._progress_line(started)
                    print(("\r" + line) if tty else line, end="" if tty else "\n", file=sys.stderr, flush=True)
                    last_line = now
                time.sleep(0.05)
            if not plan.quiet:
                print(("\r" if tty else "") + self._progress_line(started), file=sys.stderr, flush=True)
        except RunFailed as exc:
            outcome, code = "failed", 1
            print(f"\nerror: {exc}", file=sys.stderr)
        finally:
            self._stop_children(control_pub)
            time.sleep(0.2)  # last statuses
            wall = time.monotonic() - started
            stats = self.write_stats(wall, outcome)
            bus.close()
            signal.signal(signal.SIGINT, previous)
        if code in (0, 130):  # what was mapped and where it is, also after Ctrl-C (services wrote what they had)
            from semmap.summary import run_summary

            print(run_summary(plan.out_dir, json.loads(stats.read_text())), flush=True)
        return code
