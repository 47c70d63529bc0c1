"""Dataset player: publishes a dataset's frames on the bus, in real time or in lockstep with the pipeline.

Lockstep: frame i+1 goes out only when every service named in `--wait-for` has reported progress for frame i,
so a run is deterministic and as fast as the machine allows. Real time: frames go out at the dataset rate
(times `run.speed`) whatever happens downstream; services drop what they cannot keep up with and count it.
"""

from __future__ import annotations

import argparse
import json
import time

from semmap.algorithms.odometry import check_mode
from semmap.core.messages import Control, Frame, Progress, ServiceStatus
from semmap.core.outputs import SKIPPED_FILE, atomic_write_text, read_skipped
from semmap.datasets import DatasetError, open_dataset, reader_options
from semmap.datasets.base import Dataset, FrameData, WindowDataset
from semmap.datasets.trajectory_io import write_tum
from semmap.runtime.pipeline.stages import frame_message  # noqa: F401 - the player's message, used here and in tests
from semmap.runtime.transport.service import Service, service_main


def parse_wait_for(spec: str) -> dict[str, int]:
    """'detector:2,tracker' -> {'detector': 2, 'tracker': 1}: services (and replica counts) lockstep waits on."""
    out: dict[str, int] = {}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        name, _, count = item.partition(":")
        out[name] = int(count or 1)
    return out


RETRY_AFTER_S = 5.0
# a waited-for service whose status (sent every second) has not come for this long is down, e.g. being restarted
# after a crash: lockstep's frame timeout does not run while it is (a restart is not a stuck pipeline)
DOWN_AFTER_S = 3.0


class PlayerService(Service):
    """Publishes dataset frames (see module docstring)."""

    name = "player"

    def setup(self) -> None:
        run = self.config.run
        self.dataset: Dataset = open_dataset(self.args.data, **reader_options(self.args.data, self.config))
        if run.start_frame > 0:  # a later session of the recording, renumbered from frame 0
            self.dataset = WindowDataset(self.dataset, int(run.start_frame))
        # ground-truth odometry cannot place a frame without a pose: skip it like an unreadable one
        # (announced, so nobody waits for it) instead of letting the front end fail it and lockstep stall
        self.needs_gt = (check_mode(self.config.odometry.mode)[0].needs_groundtruth
                         and "odometry" in parse_wait_for(f"{self.args.wait_for},{self.args.start_after}"))
        limit = run.max_frames
        self.loops = max(1, int(run.loops))
        self.period_s = len(self.dataset) / self.dataset.rate_hz  # one pass, for the stamps of later loops
        played = len(self.dataset) * self.loops
        self.total = min(played, limit) if limit > 0 else played
        self.metrics.counters["frames_total"] = self.total
        self.wait_for = parse_wait_for(self.args.wait_for or "")
        self.start_after = {**parse_wait_for(self.args.start_after or ""), **self.wait_for}
        self.speed = run.speed
        self.depth_png = run.depth_encoding == "png"
        self.frame_timeout_s = float(run.frame_timeout_s)
        self.start_timeout_s = float(run.start_timeout_s)
        self.progress: dict[str, int] = {}
        self.running: dict[str, set[str]] = {name: set() for name in self.start_after}
        self.last_status: dict[str, float] = {}  # waited-for service -> when its last status came (monotonic)
        self.down_since: float | None = None
        self.next_index = max(0, int(self.args.start_at))
        self.last_sent = 0.0
        self.last_message: Frame | None = None
        # frame -> why it was skipped; a restarted or resumed player keeps the list its predecessor wrote
        self.skipped: dict[int, str] = read_skipped(self.out_dir) if self.next_index else {}
        if self.next_index:  # the run knows every service finished the frames before this one
            self.progress = dict.fromkeys(self.wait_for, self.next_index - 1)
            self.last_frame_id = self.next_index - 1
            self.log.info("resuming at frame %d", self.next_index)
        self.started_at: float | None = None
        self.waiting_since = time.monotonic()
        self.open_outputs()
        # (progress only in lockstep, which paces the frames by the services' progress; real time: the clock)
        self.subscribe()
        self.idle_timeout_s = 0.002
        self.log.info("playing %s: %d frames at %.1f Hz, %s", self.dataset.name, self.total, self.dataset.rate_hz,
                      "lockstep" if self.lockstep else f"real time x{self.speed:g}")

    def _on_progress(self, p: Progress) -> None:
        if p.service in self.wait_for:
            self.progress[p.service] = max(self.progress.get(p.service, -1), p.frame_id)

    def _on_status(self, s: ServiceStatus) -> None:
        if s.service in self.running and s.state == "running":
            self.running[s.service].add(s.instance)
        if s.service in self.wait_for:
            self.last_status[s.service] = time.monotonic()

    def _down(self) -> list[str]:
        """Waited-for services that have gone silent (crashed, being restarted)."""
        now = time.monotonic()
        return [n for n, t in self.last_status.items() if now - t > DOWN_AFTER_S]

    def _frame_clock(self) -> float:
        """Seconds the current frame has waited on a live pipeline: time while a waited-for service was down
        does not count, so a slow restart on a loaded machine does not fail the run; a service down for longer
        than start_timeout_s does."""
        now = time.monotonic()
        down = self._down()
        if down:
            if self.down_since is None:
                self.down_since = now
                self.log.warning("%s silent for %.0f s (restarting?): frame timeout paused", ", ".join(down),
                                 DOWN_AFTER_S)
            elif now - self.down_since > self.start_timeout_s:
                self.fail(f"{', '.join(down)} silent for {now - self.down_since:.0f} s")
            return 0.0
        if self.down_since is not None:  # back: the frame's clock starts again
            self.waiting_since = max(self.waiting_since, now)
            self.down_since = None
        return now - self.waiting_since

    def _pipeline_ready(self) -> bool:
        ready = all(len(self.running[n]) >= count for n, count in self.start_after.items())
        if not ready and time.monotonic() - self.waiting_since > self.start_timeout_s:
            missing = [n for n, c in self.start_after.items() if len(self.running[n]) < c]
            self.fail(f"services not up after {self.start_timeout_s:.0f} s: {', '.join(missing)}")
            return False
        return ready and (not self.start_after or self.out["frames"].matching())

    def _lockstep_done(self) -> int:
        """The newest frame every waited-for service has finished."""
        return min((self.progress.get(n, -1) for n in self.wait_for), default=self.next_index - 1)

    def tick(self) -> None:
        if self.finished or self.state == "failed":
            return
        if self.next_index >= self.total:
            # lockstep: end the stream once the last frame is through (a small control message would overtake
            # the big last frame otherwise); real time: right away, services give late frames a grace period
            if not self.lockstep or self._lockstep_done() >= self.last_frame_id:
                # (the last frame sent: an unreadable last frame never comes)
                self.out["control"].put(Control(self.robot, "end_of_stream", self.last_frame_id, self.total))
                self.log.info("end of stream after %d frames", self.total)
                self.finish()
            elif self._frame_clock() > self.frame_timeout_s:
                self.fail(f"lockstep: the last frame was not processed within {self.frame_timeout_s:.0f} s")
            return
        if self.started_at is None:
            if not self._pipeline_ready():
                return
            self.started_at = time.monotonic()
            self.waiting_since = self.started_at
            self.log.info("pipeline ready: %s", ", ".join(f"{n} x{len(i)}" for n, i in self.running.items()) or "-")
        if self.lockstep:
            if self._lockstep_done() < self.last_frame_id:  # (the newest frame read and sent)
                waited = self._frame_clock()
                if self.state == "failed":
                    return
                if time.monotonic() - self.last_sent > RETRY_AFTER_S:
                    # a frame lost in a crashed service (or between two detector replicas while their membership
                    # changes): resend it; services answer a repeated frame with what it produced before
                    self.metrics.count("frames_republished")
                    self.log.warning("no progress for frame %d after %.0f s: republishing it", self.last_frame_id,
                                     waited)
                    self._resend_last()
                if waited > self.frame_timeout_s:
                    late = [n for n in self.wait_for if self.progress.get(n, -1) < self.last_frame_id]
                    self.fail(f"lockstep: no progress for frame {self.last_frame_id} from {', '.join(late)} "
                              f"within {self.frame_timeout_s:.0f} s")
                return
        else:
            due = self.started_at + self.next_index / (self.dataset.rate_hz * self.speed)
            if time.monotonic() < due:
                return
        self._publish(self.next_index)

    def _publish(self, index: int) -> None:
        self.next_index = index + 1
        self.waiting_since = time.monotonic()
        try:
            with self.metrics.timer("read_ms"):
                data = self._frame(index)
            if self.needs_gt and data.gt_pose is None:
                self.metrics.count("frames_without_gt")
                raise DatasetError(f"no ground-truth pose (none within run.gt_max_gap_s="
                                   f"{self.config.run.gt_max_gap_s} s to interpolate from)")
            with self.metrics.timer("encode_ms"):
                message = frame_message(self.robot, data, self.depth_png)
        except DatasetError as exc:
            self.metrics.count("frames_unreadable")
            self.skipped[index] = str(exc)
            self.log.warning("frame %d skipped: %s", index, exc)
            self.out["control"].put(Control(self.robot, "frame_unreadable", index, self.total))
            return
        self.last_sent = time.monotonic()
        with self.metrics.timer("publish_ms"):
            self.out["frames"].put(message)
        self.last_message = message
        self.metrics.count("frames_published")
        self.last_frame_id = index

    def _resend_last(self) -> None:
        """Publish the newest frame again, as it was (no counters moved but the republish count)."""
        self.last_sent = time.monotonic()
        if self.last_message is not None:
            self.out["frames"].put(self.last_message)

    def _frame(self, index: int) -> FrameData:
        """Frame `index` of the (possibly looped) stream: later loops continue the ids and the clock."""
        data = self.dataset[index % len(self.dataset)]
        if index >= len(self.dataset):
            data.index = index
            data.stamp += (index // len(self.dataset)) * self.period_s
        return data

    def write_outputs(self) -> None:
        if self.out_dir is None:
            return
        if self.skipped or (self.out_dir / SKIPPED_FILE).exists():
            atomic_write_text(self.out_dir / SKIPPED_FILE, json.dumps(
                [{"frame": i, "reason": why} for i, why in sorted(self.skipped.items())], indent=1))
        if self.dataset.has_groundtruth:
            for index, why in getattr(self.dataset, "groundtruth_skipped", []):
                self.log.warning("groundtruth.tum: frame %d left out: %s", index, why)
            if self.loops == 1 and self.total >= len(self.dataset):
                # the dataset's own reference (a TUM folder's mocap samples), so that `semmap eval` scores the run
                # as evo scores it against that file
                write_tum(self.out_dir / "groundtruth.tum", self.dataset.reference_trajectory())
                return
            # a frame whose pose file is unreadable is left out (the reader names it), not the whole file
            gt = self.dataset.groundtruth()
            looped = [(t + k * self.period_s, pose) for k in range(self.loops) for t, pose in gt]
            write_tum(self.out_dir / "groundtruth.tum", looped[: self.total])


def _arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, help="dataset path, or 'synthetic[:k=v,...]'")
    parser.add_argument("--wait-for", default="", help="lockstep: services to wait for, e.g. detector:2,tracker")
    parser.add_argument("--start-at", type=int, default=0, help="first frame to publish (a restarted player)")
    parser.add_argument("--start-after", default="", help="services that must be up before the first frame "
                        "(without gating each frame), e.g. viz")


def main(argv: list[str] | None = None) -> int:
    return service_main(PlayerService, argv, _arguments)
