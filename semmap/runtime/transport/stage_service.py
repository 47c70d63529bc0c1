"""One base for the services that run a per-frame stage: tracker, odometry, associator and backend.

Each of them gets one input per frame from the bus, runs its stage (semmap/runtime/pipeline/stages.py or a front end)
on it, publishes what the stage made and must survive a crash without changing the run's result. What that takes
is the same for all four and lives here, once:

- **Order**: frame inputs are released in frame-id order, each frame once (`receive`). Several detector replicas
  send out of order; the player resends a frame that made no progress. A stream that must not wait for a frame
  that never comes (the odometry's frames, dropped in real time) is not re-ordered: a frame newer than the last
  handled one goes through, an older one is a resent frame.
- **Resent frames**: a frame that comes again is answered with what it produced before (`on_resent`, by default
  `Service.replay`), because the first answer may have died with a crashed consumer or producer.
- **Journal**: every completed frame is written to a `FrameJournal` before its outputs go out
  (`complete_frame`), so a frame whose outputs left is always in the journal; a service that snapshots its
  state now and then journals its inputs instead (`journal_input`, a `MessageJournal`) and handles them again
  after a restart (`replay_inputs`).
- **Restart**: with `--resume` the service continues from its journal (`restore`, with `remember_newest` to
  answer a resent frame of before the crash and `resume_after` to expect the next frame); without it the
  journal of an earlier run is cleared (`start_afresh`).

A subclass is a thin adapter: `setup_stage` builds the stage and its publishers, `restore` reads its journal,
`subscribe` declares its inputs (one of them calling `receive`), and `handle` runs the stage on one frame's
input and ends with `complete_frame`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from typing import Any, ClassVar

from semmap.core.journal import FrameJournal, MessageJournal
from semmap.core.messages import Control, Message
from semmap.core.reorder import FrameReorderBuffer
from semmap.runtime.transport.bus import Publisher
from semmap.runtime.transport.service import REPLAY_FRAMES, Service

LOCKSTEP_MAX_PENDING = 100_000  # lockstep: the player paces the run, nothing is ever given up
JOURNAL_TRIM_EVERY = 10  # frames: a trimmed journal keeps at most this many rows more than a restart reads

Output = tuple[Publisher, Message]


class StageService(Service):
    """A per-frame stage behind the bus: in order, journalled, answering resent frames, restartable (see the
    module docstring)."""

    # a FrameJournal of completed frames in --out ("" for none, or a journal of another kind: `open_journal`)
    journal_file: ClassVar[str] = ""
    # the newest rows a restart reads of the frame journal; older ones are trimmed (0: every row is kept)
    journal_keeps: ClassVar[int] = 0
    # re-order the frame inputs by frame id (False: a frame older than the last handled one is a resent frame)
    reorders: ClassVar[bool] = True
    # frames that may wait for a missing one before it is given up (real time: a dropped frame never comes)
    lockstep_max_pending: ClassVar[int] = LOCKSTEP_MAX_PENDING
    realtime_max_pending: ClassVar[int] = 256
    duplicates_counter: ClassVar[str] = "duplicates_dropped"  # counts the frames that came again
    gaps_counter: ClassVar[str] = ""  # counts the frames given up ("" not counted)
    # real time: a map stage (tracker, associator, backend) yields the CPU to the front end (`yield_to_front_end`)
    yields_to_front_end: ClassVar[bool] = False

    journal: FrameJournal | None

    # -- set up: the order is the same for every stage service --------------------------------------------------
    def setup(self) -> None:
        if self.yields_to_front_end and not self.lockstep:
            self.yield_to_front_end()
        pending = self.lockstep_max_pending if self.lockstep else self.realtime_max_pending
        self.inputs: FrameReorderBuffer[Any] = FrameReorderBuffer(max_pending=pending)
        self.setup_stage()
        self.journal = self.open_journal()
        # (before the subscriptions: a restored service judges the first frames it hears by where it stands)
        if self.resuming():
            self.restore()
        else:
            self.start_afresh()
        self.subscribe()
        self.restored()

    def yield_to_front_end(self) -> None:
        """Real time: lower this stage's CPU priority by `run.realtime_map_niceness`. The front end must pose every
        frame as it comes (a SLAM that misses frames loses track); a map stage that falls behind only answers later,
        its frames queued in order. Bonn crowd on 2 cores: 58 frames dropped by the front end with equal shares, 5
        with the map stages at niceness 5."""
        niceness = int(self.config.run.realtime_map_niceness)
        if niceness <= 0:
            return
        try:
            os.nice(niceness)
        except OSError as exc:  # (a container may refuse it: then the shares stay as they are)
            self.log.warning("real time: could not lower the %s's priority: %s", self.name, exc)

    def setup_stage(self) -> None:
        """Build the stage, its publishers and this service's own state (no subscriptions yet)."""

    def open_journal(self) -> FrameJournal | None:
        """The journal of completed frames (none without --out or `journal_file`)."""
        if self.out_dir is None or not self.journal_file:
            return None
        return FrameJournal(self.out_dir / self.journal_file)

    def resuming(self) -> bool:
        """Continue from the journal (--resume) rather than start afresh."""
        return self.resume and self.journal is not None

    def restore(self) -> None:
        """After a crash (--resume): continue from the journal (see `remember_newest`, `resume_after`)."""

    def start_afresh(self) -> None:
        """A new run: nothing of an earlier one in this folder is continued."""
        if self.journal is not None:
            self.journal.clear()

    def restored(self) -> None:
        """Once subscribed: what a restarted service still has to do (e.g. handle journalled inputs again)."""

    # -- per frame -----------------------------------------------------------------------------------------------
    def handle(self, message: Any) -> None:
        """One frame's input, in frame order, each frame once: run the stage, then `complete_frame`."""
        raise NotImplementedError

    def receive(self, message: Any) -> None:
        """A frame's input from the bus: handled in frame order once; a frame that came before goes to
        `on_resent` (and is counted)."""
        frame_id = message.frame_id
        fresh = self.inputs.push(frame_id, message) if self.reorders else frame_id > self.last_frame_id
        if not fresh:
            if self.duplicates_counter:
                self.metrics.count(self.duplicates_counter)
            self.on_resent(message)
            return
        if self.reorders:
            self.release()
        else:
            self.handle(message)

    def on_resent(self, message: Any) -> None:
        """A frame's input came again: answer it with what it produced before (a consumer may have lost it)."""
        self.replay(message.frame_id)

    def release(self, ready: Iterable[Any] | None = None) -> None:
        """Handle the inputs now in order (`ready`: those a caller released itself, e.g. given up on a gap)."""
        for message in self.inputs.pop_ready() if ready is None else ready:
            self.handle(message)
        if self.gaps_counter and self.inputs.gaps:  # real time: frames whose input never came, given up
            self.metrics.counters[self.gaps_counter] = self.inputs.gaps

    def on_end_of_stream(self, control: Control) -> None:
        self.count_frames_before_the_first(control)
        super().on_end_of_stream(control)

    def count_frames_before_the_first(self, control: Control) -> None:
        """The stream's end says where it began (frames 0..last, all sent): the frames before the first input
        this service heard that never came are counted like any other given up (real time drops a stream's first
        frames too). A subclass with its own `on_end_of_stream` calls this first."""
        if self.reorders and control.frames == control.last_frame_id + 1 and self.inputs.stream_began_at(0):
            self.release([])

    def on_frame_unreadable(self, frame_id: int) -> None:
        """The player could not read this frame: it never comes; the later ones go on without it (a stream
        that is not re-ordered never waits for a frame anyway)."""
        if self.reorders:
            self.inputs.skip(frame_id)
            self.release()

    def complete_frame(self, frame_id: int, outputs: Sequence[Output],
                       journal_row: tuple[bytes, bytes] | None = None) -> None:
        """A frame is done: journal it (first: a frame whose outputs left must be in the journal), publish its
        outputs (remembered, for a resent frame) and report the frame's progress."""
        if self.journal is not None and journal_row is not None:
            with self.metrics.timer("journal_ms"):
                self.journal.append(frame_id, *journal_row)
                if self.journal_keeps and frame_id % JOURNAL_TRIM_EVERY == 0:  # only the newest rows are read back
                    self.journal.trim(frame_id - self.journal_keeps)
        for publisher, message in outputs:
            self.emit(publisher, message, frame_id)
        self.report_progress(frame_id)

    # -- restoring -----------------------------------------------------------------------------------------------
    def resume_after(self, frame_id: int) -> None:
        """Frames up to `frame_id` were handled before the crash: the next input expected is the one after."""
        self.last_frame_id = max(self.last_frame_id, frame_id)
        self.inputs.mark_done(frame_id)

    def remember_newest(self, publisher: Publisher, decode: Callable[[bytes], Message]) -> None:
        """The newest journalled frames' outputs (the journal's first blob), to answer such a frame again if it
        is resent: the old process may have journalled it and died before its output or progress left."""
        assert self.journal is not None
        for frame_id, output, _, _ in self.journal.last(REPLAY_FRAMES):
            self.remember(publisher, decode(output), frame_id)

    def journal_input(self, journal: MessageJournal | None, stream: str, message: Message) -> int | None:
        """Append an input to a service's input journal (not while handling journalled inputs again); returns
        its sequence number (None when nothing was journalled)."""
        if journal is None or self.muted:
            return None
        with self.metrics.timer("journal_ms"):
            return journal.append(stream, message.encode())

    def replay_inputs(self, entries: Iterable[tuple[int, str, bytes]],
                      handlers: dict[str, tuple[type[Message], Callable[[Any], None]]]) -> tuple[int, int | None]:
        """Handle journalled inputs again, muted (their outputs went out before the crash and are only
        remembered), each as it came; returns how many, and the sequence number of the last (None if none)."""
        n, last = 0, None
        self.muted = True
        try:
            for seq, stream, body in entries:
                kind, handler = handlers[stream]
                self._guarded(handler, kind.decode(body), f"journalled {stream}")
                n, last = n + 1, seq
        finally:
            self.muted = False
        return n, last
