"""The test's side of a lockstep run against one real service process: publish each frame's inputs, wait for the
service's progress, resend after 2 s without it (as the player does: a restarted service may not have
subscribed yet when the router still lists the killed one's subscription), then end the stream."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from semmap.core.messages import Control, Message, Progress
from semmap.runtime.transport.bus import Bus, BusConfig

PROJECT = Path(__file__).resolve().parents[2]


class LockstepFeeder:
    """Publishes on the given keys of `robot` and follows `service`'s progress."""

    def __init__(self, endpoint: str, robot: str, service: str, keys: list[str]) -> None:
        self.bus = Bus(BusConfig(mode="client", connect=[endpoint], listen=[]), robot)
        self.robot = robot
        self.publishers = {key: self.bus.publisher(key) for key in keys}
        self.control = self.bus.publisher(self.bus.keys.control)
        self.done = -1
        self.changed = threading.Condition()
        self.bus.subscribe(self.bus.keys.progress(service), Progress, self._on_progress)

    def _on_progress(self, p: Progress) -> None:
        with self.changed:
            self.done = max(self.done, p.frame_id)
            self.changed.notify_all()

    def feed(self, frames: list[tuple[int, list[tuple[str, Message]]]]) -> None:
        """(frame id, [(key, message), ...]) in order, each frame once the previous one is through."""
        first_key = next(iter(self.publishers))
        assert self.publishers[first_key].wait_matching(30), "the service did not come up"
        for frame_id, messages in frames:
            for _ in range(15):
                for key, message in messages:
                    self.publishers[key].put(message)
                with self.changed:
                    if self.changed.wait_for(lambda f=frame_id: self.done >= f, timeout=2.0):
                        break
            else:
                raise AssertionError(f"no progress for frame {frame_id} in 30 s")

    def restart(self) -> None:
        """A new service process reports progress from scratch."""
        self.done = -1

    def finish(self, proc: subprocess.Popen, log: Path, frames: int) -> None:
        """End the stream, wait until the service has finished, stop it; it must exit cleanly."""
        self.control.put(Control(self.robot, "end_of_stream", frames - 1, frames))
        deadline = time.monotonic() + 30
        while "finished (last frame" not in log.read_text() and time.monotonic() < deadline:
            time.sleep(0.1)
        self.control.put(Control(self.robot, "stop"))
        assert proc.wait(timeout=30) == 0, log.read_text()[-3000:]

    def close(self) -> None:
        self.bus.close()


def start_service(service: str, endpoint: str, robot: str, out: Path, *extra: str) -> subprocess.Popen:
    """`python -m services.<service>` in lockstep mode, logging to `out/<service>.log`."""
    log = open(out / f"{service}.log", "ab")  # noqa: SIM115 - closed with the process
    return subprocess.Popen([sys.executable, "-m", f"semmap.services.{service}", "--connect", endpoint, "--zenoh-mode",
                             "client", "--robot", robot, "--out", str(out), "--mode", "lockstep", *extra],
                            cwd=PROJECT, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "CI": "true"})


def run_killed_and_resumed(feeder: LockstepFeeder, service: str, endpoint: str, robot: str, out: Path,
                           frames: list, kill_after: int, procs: list[subprocess.Popen], *extra: str) -> None:
    """Feed `frames[:kill_after]` to a fresh service, SIGKILL it, start it again with --resume and feed the rest
    (the caller finishes the last process, `procs[-1]`, and kills whatever is left on the way out)."""
    feeder.restart()
    procs.append(start_service(service, endpoint, robot, out, *extra))
    feeder.feed(frames[:kill_after])
    procs[-1].send_signal(signal.SIGKILL)
    procs[-1].wait(timeout=10)
    feeder.restart()
    procs.append(start_service(service, endpoint, robot, out, *extra, "--resume"))
    feeder.feed(frames[kill_after:])
