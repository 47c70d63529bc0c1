"""Re-ordering per-frame messages that may arrive out of order or twice (e.g. from several detector replicas)."""

from __future__ import annotations

from typing import Generic, TypeVar

T = TypeVar("T")


class FrameReorderBuffer(Generic[T]):
    """Releases items strictly in frame-id order, each frame once.

    Frame ids start wherever the first item starts (a consumer may join a running stream, and a stream's first
    frames may have been dropped upstream): `stream_began_at` counts, once the stream says where it began, the
    frames before the first one heard that never came. `max_pending` bounds memory: when that many later frames
    are waiting, the missing ones are given up; `gaps` counts the frames given up (there, in `give_up_before` or
    before the first one heard), not frames announced as skipped.
    """

    def __init__(self, max_pending: int = 256) -> None:
        self.next_id: int | None = None
        self.pending: dict[int, T] = {}
        self.max_pending = max_pending
        self.gaps = 0
        self.skipped: set[int] = set()  # frames that will never come (e.g. unreadable in the dataset)
        # the first frame heard, until the frames before it are counted (None: none yet, counted, or resumed by
        # `mark_done`)
        self.joined_at: int | None = None
        self.skipped_before_join: set[int] = set()  # announced frames before `joined_at`: not gaps

    def push(self, frame_id: int, item: T) -> bool:
        """Queue an item; False for a duplicate or an already released frame."""
        if self.next_id is None:
            self.next_id = self.joined_at = frame_id
        if frame_id < self.next_id or frame_id in self.pending or frame_id in self.skipped:
            return False
        self.pending[frame_id] = item
        return True

    def mark_done(self, frame_id: int) -> None:
        """Frames up to `frame_id` were handled elsewhere (e.g. replayed from a journal): expect the next one."""
        self.next_id = max(self.next_id or 0, frame_id + 1)
        self.joined_at = None  # (the frames before were handled before a restart, not lost)
        for old in [f for f in self.pending if f <= frame_id]:
            del self.pending[old]

    def skip(self, frame_id: int) -> None:
        """Frame `frame_id` will never come: release the later ones without waiting for it (an item of it that
        comes anyway is dropped)."""
        self.pending.pop(frame_id, None)
        if self.next_id is None or frame_id >= self.next_id:
            self.skipped.add(frame_id)
        elif self.joined_at is not None and frame_id < self.joined_at:
            self.skipped_before_join.add(frame_id)

    def stream_began_at(self, first_id: int) -> int:
        """The stream began at frame `first_id` (its end says so): the frames before the first one heard that
        never came, and were not announced as skipped, are gaps (counted once); returns how many."""
        joined, self.joined_at = self.joined_at, None  # (counted once)
        if joined is None or first_id >= joined:
            return 0
        announced = {f for f in self.skipped | self.skipped_before_join if first_id <= f < joined}
        self.skipped_before_join.clear()
        lost = joined - first_id - len(announced)
        self.gaps += lost
        return lost

    def pop_ready(self) -> list[T]:
        ready: list[T] = []
        while self.next_id is not None:
            if self.next_id in self.skipped:
                self.skipped.discard(self.next_id)
                self.next_id += 1
            elif self.next_id in self.pending:
                ready.append(self.pending.pop(self.next_id))
                self.next_id += 1
            elif len(self.pending) >= self.max_pending:
                self._give_up(min(self.pending))
            else:
                break
        return ready

    def give_up_before(self, frame_id: int) -> list[T]:
        """Frames before `frame_id` that have not come never will (an in-order stream whose frame `frame_id` is
        here, or is known to be the last): stop waiting for them and release what follows, like `pop_ready`."""
        ready = self.pop_ready()
        while self.next_id is not None and self.next_id < frame_id:  # (the next frame is missing: pop_ready stopped)
            self._give_up(min([f for f in self.pending if f < frame_id] + [frame_id]))
            ready += self.pop_ready()
        return ready

    def _give_up(self, upto: int) -> None:
        """Move past every missing frame before `upto`: each one not announced as skipped counts as a gap."""
        assert self.next_id is not None
        announced = {f for f in self.skipped if self.next_id <= f < upto}
        self.gaps += upto - self.next_id - len(announced)
        self.skipped -= announced
        self.next_id = upto
