"""`semmap run`: start every service as its own process on one Zenoh bus, watch them, stop them cleanly.

The orchestrator is itself a Zenoh peer listening on a loopback port (or a client of a router given with
`--connect`); services connect to it. It shows progress from the services' status messages, fails the run with
the failing service's log tail when one dies, and writes `stats.json` from their final statuses.

It also keeps the run honest (docs/SECURITY.md): a run id and a secret key for the run's signed messages go to
its children only (environment); a watchdog fails the run when a child stops unasked (even "exit 0, stopped"),
when nothing moves for too long, or past the run's deadline; a run that processed fewer frames than its player
sent, or none, fails with the reason.
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
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from statistics import fmean, median

from semmap.core.dataflow import OWN_FRONT_ENDS
from semmap.core.messages import Control, Progress, ServiceStatus
from semmap.core.outputs import atomic_write_text, describe_disk_error, read_skipped
from semmap.runtime.transport.bus import ENV_RUN_ID, ENV_RUN_KEY, ENV_RUN_OPEN_KEYS, Bus, BusConfig, BusError, RunTrust
from semmap.runtime.transport.run_registry import RunInfo, register, unregister
from semmap.runtime.transport.service import ENV_PARENT_PID, exit_backstop

log = logging.getLogger("semmap.run")

STOP_GRACE_S = 15.0
INTERRUPT_GRACE_S = 8.0  # after Ctrl-C / SIGTERM: children get SIGTERM at once, and SIGKILL after this
MAX_RESTARTS = 5
RESTART_BACKOFF_S = 0.5
HUB_BIND_TRIES = 5  # ports tried for the bus this run hosts
EXTERNAL = "external"  # `semmap run external`: no player, no odometry; a SLAM feeds the bus (semmap.runtime.client)


@dataclass
class ServiceSpec:
    """One service to start: `python -m services.<module>` with extra flags, `replicas` times."""

    name: str
    extra_args: list[str] = field(default_factory=list)
    replicas: int = 1
    lockstep: bool = True  # whether lockstep playback waits for its progress


def front_end_posed(services: dict[str, dict]) -> int | None:
    """Frames the odometry service posed, from stats.json's `services` (None without one): a frame the front end
    lost is published with a stand-in pose, marked bridged, and is not posed."""
    odometry = [s.get("counters", {}) for s in services.values() if s.get("service") == "odometry"]
    if not odometry:
        return None
    return sum(int(c.get("poses_published", 0)) - int(c.get("poses_bridged", 0)) for c in odometry)


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
    zenoh_config: str | None = None  # a Zenoh config file, or a folder of `<service>.json5` (one identity each)
    verbose: bool = False
    quiet: bool = False
    deadline_s: float = 0.0  # the whole run (0: none)
    stall_s: float = 0.0  # nothing moved for this long: the run fails (0: never)
    resume: bool = False  # continue the run in out_dir (services from their journals, the player after it)
    lock_fd: int | None = None  # the open lock file of out_dir: children inherit it (the lock lives while they do)
    odometry: str = ""  # odometry.mode, for stats.json and the summary
    simulated_odometry: bool = False  # gt / gt+drift: poses made from the ground truth, not a real front end
    camera: str = ""  # where the calibration came from and what it is (the start banner's camera line)
    budget: dict | None = None  # real time: the detector's planned cadence (semmap/cli/run.py detector_budget)


SETTINGS_FILE = "config.yaml"  # the run's effective configuration, in the run folder (what every child reads)


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


def zenoh_config_for(spec: str | None, identity: str) -> str | None:
    """`--zenoh-config`: one file for every process, or a folder holding one file per identity
    (`<service>.json5`, `orchestrator.json5`: each its own certificate in the secure profile)."""
    if not spec or not Path(spec).is_dir():
        return spec
    path = Path(spec) / f"{identity}.json5"
    if not path.is_file():
        raise RunFailed(f"--zenoh-config {spec} has no {path.name} for {identity}")
    return str(path)


class _Child:
    """One service process; restarted in place (same instance name, same log) when it crashes."""

    def __init__(self, name: str, instance: str, argv: list[str], log_path: Path, env: dict[str, str],
                 keep_fds: tuple[int, ...] = ()) -> None:
        self.name, self.instance, self.argv, self.log_path, self.env = name, instance, argv, log_path, env
        self.keep_fds = keep_fds
        self.log_file = open(log_path, "ab")  # noqa: SIM115 - lives as long as the process
        self.restarts = 0
        self.restart_at: float | None = None  # when a crashed process is due to come back
        self.proc = self._spawn(argv)

    def _spawn(self, argv: list[str]) -> subprocess.Popen:
        # keep_fds: the run's lock file, so its flock stays held while any child lives (an orphan outliving a
        # killed run keeps the folder locked until it has stopped)
        return subprocess.Popen(argv, stdout=self.log_file, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True, env=self.env, pass_fds=self.keep_fds)

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
        self.cpu_at_first_frame: dict[str, float] = {}  # per instance: its CPU seconds when frames began
        # the run's identity and secret: every message of the run is signed with it
        # (semmap.runtime.transport.bus.RunTrust);
        # children get it through their environment only (not on a command line others can read)
        self.run_id = uuid.uuid4().hex[:16]
        self.open_keys = ("frames", "odometry", "slam", "control") if plan.data == EXTERNAL else ()
        self.trust = RunTrust(self.run_id, bytes.fromhex(RunTrust.new_secret()), "orchestrator",
                              frozenset(self.open_keys))
        self.failure = ""  # why the run failed, for stats.json
        self._moved_at = time.monotonic()
        self._last_motion: tuple = ()
        self._bus_rejected: dict[str, int] = {}
        self.source: dict = {}  # external runs: the source's end_of_stream report (frames sent, its counters)

    # -- bus --------------------------------------------------------------------------------------------------
    def _open_bus(self) -> tuple[Bus, list[str]]:
        """The orchestrator's bus and the flags its children get. Hosting the bus: the port found free can be taken
        before Zenoh binds it (another run starting at the same moment on this machine); then any other free
        port is tried."""
        preferred = DEFAULT_PORT
        for attempt in range(HUB_BIND_TRIES):
            bus_cfg, child_args = self._bus_config(preferred)
            try:
                return Bus(bus_cfg, self.plan.robot, self.trust), child_args
            except BusError as exc:
                if self.plan.connect or attempt == HUB_BIND_TRIES - 1:
                    raise
                log.warning("bus: %s; trying another port", exc)
                preferred = 0
        raise AssertionError("unreachable")

    def _bus_config(self, preferred: int = DEFAULT_PORT) -> tuple[BusConfig, list[str]]:
        """The orchestrator's own bus config and the flags its children get (`--zenoh-config` is per child)."""
        own_file = zenoh_config_for(self.plan.zenoh_config, "orchestrator")
        if self.plan.connect:
            cfg = BusConfig.from_env(self.plan.connect, self.plan.zenoh_mode or "client", config_file=own_file)
            child = ["--connect", self.plan.connect]
            if self.plan.zenoh_mode:
                child += ["--zenoh-mode", self.plan.zenoh_mode]
            return cfg, child
        port = free_loopback_port(preferred)
        hub = f"tcp/127.0.0.1:{port}"
        self.endpoint = hub
        cfg = BusConfig(mode="peer", listen=[hub], config_file=own_file)
        return cfg, ["--zenoh-mode", "peer", "--connect", hub, "--listen", "tcp/127.0.0.1:0"]

    def _child_env(self) -> dict[str, str]:
        env = {**os.environ, ENV_RUN_ID: self.run_id, ENV_RUN_KEY: self.trust.key.hex(),
               ENV_RUN_OPEN_KEYS: ",".join(self.open_keys),
               ENV_PARENT_PID: str(os.getpid())}  # children stop when this process goes (die_with_parent)
        env.pop("SEMMAP_ZENOH_CONFIG", None)  # each child gets its own file by flag
        env.pop("SEMMAP_ROBOT", None)  # the robot is the settings file's (run.robot)
        return env

    def _on_status(self, s: ServiceStatus) -> None:
        with self.lock:
            self.statuses[s.instance] = s
            self.rss.setdefault(s.instance, []).append(s.rss_mb)
            # CPU spent before the first frame (imports, model load): not a per-frame cost of the frame budget
            if s.instance not in self.cpu_at_first_frame and any(
                    st.counters.get("frames_published", 0) > 0 for st in self.statuses.values()):
                self.cpu_at_first_frame[s.instance] = s.cpu_s

    def _on_control(self, c: Control) -> None:
        if c.command == "end_of_stream":
            with self.lock:
                self.source = {"frames_sent": int(c.frames), "last_frame_id": int(c.last_frame_id),
                               "counters": dict(c.counters)}

    def _on_progress(self, p: Progress) -> None:
        with self.lock:
            self.progress[p.service] = max(self.progress.get(p.service, -1), p.frame_id)

    # -- processes --------------------------------------------------------------------------------------------
    def _start(self, child_bus_args: list[str]) -> None:
        plan = self.plan
        logs = plan.out_dir / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        # one way in for settings: every child reads the run's effective configuration from the run folder
        common = ["--out", str(plan.out_dir), "--config", str(self.write_settings()), *child_bus_args]
        if plan.verbose:
            common.append("--verbose")
        wait_for = ",".join(f"{s.name}:{s.replicas}" for s in plan.services if s.lockstep)
        start_after = ",".join(f"{s.name}:{s.replicas}" for s in plan.services if not s.lockstep)
        specs = list(plan.services)
        if plan.data != EXTERNAL:  # an external SLAM publishes the frames and poses itself
            player_args = ["--data", plan.data, "--wait-for", wait_for, "--start-after", start_after]
            if plan.resume:
                player_args += ["--start-at", str(self._resume_frame())]
            specs.append(ServiceSpec("player", player_args, 1, False))
        env = self._child_env()
        for spec in specs:
            own_config = zenoh_config_for(plan.zenoh_config, spec.name)
            extra = ["--zenoh-config", own_config] if own_config else []
            if plan.resume and spec.name != "player":
                extra += ["--resume", "--frame-base", str(self._resume_frame())]
            for r in range(spec.replicas):
                instance = spec.name if spec.replicas == 1 else f"{spec.name}-{r + 1}"
                argv = [sys.executable, "-m", f"semmap.services.{spec.name}", *common, "--instance", instance, *extra,
                        *spec.extra_args]
                keep = (plan.lock_fd,) if plan.lock_fd is not None else ()
                self.children.append(_Child(spec.name, instance, argv, logs / f"{instance}.log", env, keep))
                log.info("started %s (pid %d)", instance, self.children[-1].proc.pid)

    def write_settings(self) -> Path:
        """The run's effective configuration (the validated tree, with the run's mode and robot) as `config.yaml`
        in the run folder, the one file every child reads (`--config`, no `--set`s): each process starts with
        exactly the settings `semmap run` checked, and the folder keeps what the run used."""
        from semmap.core.config import load_config, render_yaml, run_overrides

        plan = self.plan
        config = load_config(plan.config_path, [*plan.overrides, *run_overrides(plan.mode, plan.robot)])
        path = plan.out_dir / SETTINGS_FILE
        atomic_write_text(path, render_yaml(config))
        return path

    def _resume_frame(self) -> int:
        """`--resume`: the player starts after the frames the interrupted run processed (its stats.json)."""
        try:
            return int(json.loads((self.plan.out_dir / "stats.json").read_text())["frames"]["processed"])
        except (OSError, ValueError, KeyError, TypeError):
            return 0

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
            if code is None:
                continue
            if code == 0:
                # only the orchestrator stops a run: a child that left on its own (even saying "stopped"), or
                # one that finished and then left, took part of the run with it
                state = status.state if status is not None else "no status"
                raise RunFailed(f"{child.instance} stopped unasked (exit 0, {state})\n--- {child.log_path} ---\n"
                                f"{child.tail()}")
            if code == 2 or child.restarts >= MAX_RESTARTS:  # 2: a usage / set-up error, it would fail again
                why = f"exited with code {code}"
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
            return ["--resume", "--frame-base", str(self._frames_done())]
        return ["--start-at", str(self._frames_done())]

    def _frames_done(self, default: int = 0) -> int:
        """How many frames every lockstep service has finished (`default` when none gates the stream)."""
        with self.lock:
            return self._frames_done_locked(default)

    def _frames_done_locked(self, default: int = 0) -> int:
        done = [self.progress.get(s.name, -1) for s in self.plan.services if s.lockstep]
        return min(done) + 1 if done else default

    def _all_finished(self) -> bool:
        if any(c.restart_at is not None for c in self.children):
            return False
        with self.lock:
            return all(
                (s := self.statuses.get(c.instance)) is not None and s.state == "finished" for c in self.children
            )

    def _check_time(self, started: float) -> None:
        """The run's deadline, and a backstop for a run in which nothing moves (no frame, no status change)."""
        now = time.monotonic()
        if self.plan.deadline_s > 0 and now - started > self.plan.deadline_s:
            raise RunFailed(f"the run passed its deadline of {self.plan.deadline_s:.0f} s (--deadline / "
                            f"run.deadline_s) at {self._frames_done()} frames processed")
        with self.lock:
            motion = (self._frames_done_locked(), tuple(sorted((i, s.state, s.last_frame_id)
                                                               for i, s in self.statuses.items())))
        if motion != self._last_motion:
            self._last_motion, self._moved_at = motion, now
        elif self.plan.stall_s > 0 and now - self._moved_at > self.plan.stall_s:
            raise RunFailed(f"nothing moved for {self.plan.stall_s:.0f} s (no frame processed, no service "
                            f"changed state) at {self._frames_done()} frames processed; {self._waiting_on()}")

    def _waiting_on(self) -> str:
        """Which services hold the run back (the fewest frames done) and where they are: a stall names them."""
        with self.lock:
            done = {s.name: self.progress.get(s.name, -1) for s in self.plan.services if s.lockstep}
            statuses = sorted(self.statuses.items())
        if not done:
            return "no service gates the stream"
        low = min(done.values())
        behind = [f"{i} ({s.state}, last frame {s.last_frame_id})" for i, s in statuses
                  if s.service in done and done[s.service] == low]
        return "waiting on " + (", ".join(behind) or ", ".join(n for n, f in done.items() if f == low))

    def _check_frames(self) -> None:
        """Every service finished: did they process every frame the player sent? (None, or fewer: a failure.)"""
        with self.lock:
            player = next((s for s in self.statuses.values() if s.service == "player"), None)
        if player is None:  # an external SLAM fed the run
            return
        unreadable = player.counters.get("frames_unreadable", 0)
        total = player.counters.get("frames_total", 0)
        if player.last_frame_id < 0:
            why = (f"all {unreadable} frames of {self.plan.data} were unreadable" if unreadable
                   else f"no frame was published from {self.plan.data}")
            raise RunFailed(f"no frame was processed: {why} (see logs/player.log)")
        expected, processed = player.last_frame_id + 1, self._frames_done()
        if processed < expected:
            raise RunFailed(f"only {processed} of the {expected} frames the player sent were processed")
        if unreadable and unreadable >= total:
            raise RunFailed(f"no frame was processed: all {unreadable} frames were unreadable")

    def _stop_children(self, control_pub: object | None, urgent: bool = False) -> None:
        """Stop every child: a `stop` message, then SIGTERM, then SIGKILL. `urgent` (interrupted, failed):
        SIGTERM at once and a short grace, so the whole run is gone within seconds."""
        if control_pub is not None:
            with contextlib.suppress(Exception):  # the bus may be gone; signals follow anyway
                control_pub.put(Control(self.plan.robot, "stop"))  # type: ignore[attr-defined]
        deadline = time.monotonic() + (INTERRUPT_GRACE_S if urgent else STOP_GRACE_S)
        for child in self.children:
            if child.proc.poll() is None and (control_pub is None or urgent):
                with contextlib.suppress(ProcessLookupError):
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
        detected = self._counter_sum("frames_detected")
        # real time: how much video passes between two detected frames (lockstep waits for every frame, so there
        # the detected count says it all)
        cadence = self._detection_cadence() if self.plan.mode == "realtime" else None
        every = f" (one every {cadence['p50']:.0f} ms of video)" if cadence else ""
        return (f"[{bar}] {processed}/{total or '?'} frames processed, {published} published, "
                f"{fps:5.1f} fps, {detected} detected{every}, {dropped} dropped, {elapsed:5.1f} s")

    def _detection_cadence(self) -> dict[str, float] | None:
        """Video time between detected frames (p50 / p95 / max ms), as the tracker saw them in frame order: with
        replicas, the run's cadence and how evenly their detections interleave (each replica's own figure covers
        only its share). The detector's own figure where the tracker has none yet; None before two detections."""
        with self.lock:
            tracker = [s for s in self.statuses.values() if s.service == "tracker"]
            detectors = [s for s in self.statuses.values() if s.service == "detector"]
        for source in (tracker, detectors):
            if len(source) == 1 and "detect_interval_ms" in source[0].timings:
                t = source[0].timings["detect_interval_ms"]
                return {k: float(t[k]) for k in ("p50", "p95", "max") if k in t}
        return None

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
        with self.lock:
            source = dict(self.source)
        if self.plan.data == EXTERNAL:  # no player: the frames the client / bridge says it sent (at least those
            # processed, when the source never said: a client that stopped without end of stream)
            published = max(published, int(source.get("frames_sent", 0)), self._frames_done(default=0))
        detected = sum(s.counters.get("frames_detected", 0) for s in statuses.values())
        # frames the detectors could not keep up with (real time); queue drops elsewhere stay per service
        dropped = sum(s.counters.get("frames_dropped", 0) for s in statuses.values())
        unreadable = sum(s.counters.get("frames_unreadable", 0) for s in statuses.values())  # (the player's)
        processed = self._frames_done(default=published)
        with self.lock:
            restarts = dict(self.restarts)
        for instance, n in restarts.items():
            services.setdefault(instance, {})["restarts"] = n
        # every message refused by a trust check, summed over the services (per service in their counters)
        rejected: dict[str, int] = {}
        counters_by_source = [s.counters for s in statuses.values()] + [self._bus_rejected]
        for counters in counters_by_source:
            for name, n in counters.items():
                if name.startswith("rejected") or name == "wrong_robot":
                    rejected[name] = rejected.get(name, 0) + n
        stats = {"schema": "semmap.stats/1", "outcome": outcome, "data": self.plan.data, "mode": self.plan.mode,
                 "odometry": {"mode": self.plan.odometry, "simulated": self.plan.simulated_odometry},
                 "camera": self.plan.camera,
                 "robot": self.plan.robot, "run_id": self.run_id, "wall_s": round(wall_s, 2),
                 "failure": self.failure, "rejected": dict(sorted(rejected.items())),
                 "frames": {"published": published, "processed": processed, "detected": detected,
                            "dropped": dropped, "unreadable": unreadable,
                            # which frames the player skipped (unreadable file, no ground-truth pose) and why
                            "skipped": [{"frame": i, "reason": why}
                                        for i, why in sorted(read_skipped(self.plan.out_dir).items())]},
                 "fps": round(processed / wall_s, 2) if wall_s > 0 else 0.0, "restarts": sum(restarts.values()),
                 "detection_interval_ms": self._detection_cadence(),
                 "services": services}
        if self.plan.budget is not None:
            stats["detector_budget"] = self._budget_achieved(services, processed, detected, wall_s)
        if source:
            stats["source"] = source
        path = self.plan.out_dir / "stats.json"
        atomic_write_text(path, json.dumps(stats, indent=2))
        return path

    def _budget_achieved(self, services: dict[str, dict], processed: int, detected: int, wall_s: float) -> dict:
        """The planned cadence next to what the run achieved; keeps the other services' CPU per frame for the
        next plan on this machine (semmap/runtime/models/detector_choice.py)."""
        budget = dict(self.plan.budget or {})
        fps = float(budget.get("planned", {}).get("fps", 30.0))
        video_s = processed / fps if fps > 0 else 0.0
        det = [s for s in services.values() if s.get("service") == "detector"]
        with self.lock:
            start = dict(self.cpu_at_first_frame)
        others_by_service = {name: s.get("cpu_s", 0.0) - start.get(name, 0.0) for name, s in services.items()
                             if s.get("service") not in ("detector", None)}
        others_cpu = sum(others_by_service.values())
        posed = front_end_posed(services)
        per_replica = [s.get("timings_ms", {}).get("detect_ms", {}) for s in det]
        detect = {k: round(median(t[k] for t in per_replica if k in t), 1)  # (replicas: their median)
                  for k in ("p50", "p95") if any(k in t for t in per_replica)}
        budget["achieved"] = {
            "detected_frames": detected, "video_s": round(video_s, 2),
            "detections_per_s": round(detected / video_s, 2) if video_s > 0 else 0.0,
            "detect_ms_p50": detect.get("p50"), "detect_ms_p95": detect.get("p95"),
            "detector_cpu_s": round(sum(s.get("cpu_s", 0.0) for s in det), 2),
            "others_cpu_ms_per_frame": round(1e3 * others_cpu / processed, 1) if processed else None,
            "cpu_ms_per_frame_by_service": {name: round(1e3 * cpu / processed, 1) for name, cpu
                                            in sorted(others_by_service.items())} if processed else {},
            "wall_s": round(wall_s, 2),
            # the share of the frames the odometry posed: a front end that cannot keep up skips frames
            "front_end_posed_share": round(posed / processed, 3) if processed and posed is not None else None,
        }
        per_frame = budget["achieved"]["others_cpu_ms_per_frame"]
        if per_frame and processed >= 300 and self.plan.mode == "realtime":
            try:
                from semmap.runtime.models.detector_choice import record_pipeline_cost

                record_pipeline_cost(str(budget.get("odometry", "gt")), per_frame,
                                     detector=str(budget.get("detector", "")),
                                     detections_per_s=float(budget["achieved"]["detections_per_s"]),
                                     speed=float(budget.get("speed", 1.0)),
                                     front_end_share=budget["achieved"]["front_end_posed_share"])
            except (OSError, ValueError):
                pass
        return budget

    # -- the run --------------------------------------------------------------------------------------------
    def _on_signal(self, *_: object) -> None:
        self.interrupted.set()
        # children get SIGTERM and, after INTERRUPT_GRACE_S, SIGKILL; whatever hangs, this process ends then
        exit_backstop(int(INTERRUPT_GRACE_S + 15))

    def run(self) -> int:
        plan = self.plan
        started = time.monotonic()
        outcome, code = "completed", 0
        tty = sys.stderr.isatty() and not plan.quiet
        last_line = 0.0
        bus: Bus | None = None
        control_pub = None
        run_info: RunInfo | None = None
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)
        try:
            plan.out_dir.mkdir(parents=True, exist_ok=True)
            bus, child_args = self._open_bus()
            endpoint = self.endpoint or plan.connect
            if endpoint:  # clients (the ROS 2 bridge) find this run here instead of guessing a port
                run_info = RunInfo(plan.robot, self.run_id, endpoint, str(plan.out_dir.resolve()), os.getpid(),
                                   check_slam=plan.data == EXTERNAL and plan.odometry == "external",
                                   front_end=plan.odometry if plan.data == EXTERNAL and plan.odometry in
                                   OWN_FRONT_ENDS else "")
                register(run_info)
            if self.endpoint:
                log.info("bus: %s (robot %s, run %s); e.g. semmap query --connect %s", self.endpoint, plan.robot,
                         self.run_id, self.endpoint)
            bus.subscribe(bus.keys.status_all, ServiceStatus, self._on_status)
            bus.subscribe(bus.keys.progress_all, Progress, self._on_progress)
            if plan.data == EXTERNAL:  # what the external source says it sent (and lost) at its end of stream
                bus.subscribe(bus.keys.control, Control, self._on_control)
            control_pub = bus.publisher(bus.keys.control)
            self._start(child_args)
            while True:
                if self.interrupted.is_set():
                    outcome, code = "interrupted", 130
                    print("\ninterrupted: stopping services (they write what they have)", file=sys.stderr)
                    break
                self._check_children()
                if self._all_finished():
                    self._check_frames()
                    break
                self._check_time(started)
                now = time.monotonic()
                if not plan.quiet and (tty and now - last_line > 0.2 or not tty and now - last_line > 5.0):
                    line = self._progress_line(started)
                    print(("\r" + line) if tty else line, end="" if tty else "\n", file=sys.stderr, flush=True)
                    last_line = now
                time.sleep(0.05)
            if not plan.quiet:
                print(("\r" if tty else "") + self._progress_line(started), file=sys.stderr, flush=True)
        except (RunFailed, BusError, OSError) as exc:
            outcome, code = "failed", 1
            self.failure = str(exc).split("\n", 1)[0]
            if isinstance(exc, OSError):
                self.failure = f"the orchestrator could not go on: {describe_disk_error(exc)}"
            print(f"\nerror: {exc if not isinstance(exc, OSError) else self.failure}", file=sys.stderr)
        finally:
            self._stop_children(control_pub, urgent=code != 0)
            time.sleep(0.2)  # last statuses
            wall = time.monotonic() - started
            if bus is not None:
                with bus._lock:
                    self._bus_rejected = dict(bus.rejected)
            try:
                stats: Path | None = self.write_stats(wall, outcome)
            except OSError as exc:
                stats = None
                print(f"error: stats.json not written: {describe_disk_error(exc)}", file=sys.stderr)
                code = code or 1
            if bus is not None:
                bus.close()
            if run_info is not None:
                unregister(run_info)
            for sig in (signal.SIGINT, signal.SIGTERM):  # from here on a signal just ends the process
                signal.signal(sig, signal.SIG_DFL)
        if code in (0, 130) and stats is not None:  # what was mapped and where it is, also after Ctrl-C
            from semmap.runtime.summary import run_summary

            print(run_summary(plan.out_dir, json.loads(stats.read_text())), flush=True)
        return code
