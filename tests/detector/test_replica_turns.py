"""How a detector replica answers the frames of its turns in real time: which it detects, which it counts as
dropped (a detection real time cost) and which as stride (the cadence would have skipped them anyway)."""

from __future__ import annotations

from semmap.services.detector.service import DetectorService, owner


def test_replicas_take_turns_in_blocks_of_the_cadence() -> None:
    assert [owner(f, 2, 2) for f in range(8)] == [0, 0, 1, 1, 0, 0, 1, 1]  # every 2nd frame: 0, 2, 4, 6 in turn
    assert [owner(f, 1, 2) for f in range(4)] == [0, 1, 0, 1]  # every frame: by frame id, as before
    assert [owner(f, 3, 1) for f in range(4)] == [0, 0, 0, 0]
    for every_n in (1, 2, 3, 5):  # each frame has exactly one owner, and each replica owns due frames
        for replicas in (1, 2, 3):
            due = {owner(f, every_n, replicas) for f in range(0, 60, every_n)}
            assert due == set(range(replicas))


class _Frame:
    def __init__(self, frame_id: int) -> None:
        self.frame_id = frame_id


def _replica(every_n: int, last_detected: int | None) -> tuple[DetectorService, list[tuple[int, str]]]:
    """The service's turn logic alone (no bus): a replica in real time that last detected `last_detected`."""
    replica = object.__new__(DetectorService)
    replica.every_n, replica.lockstep, replica._last_detected_id = every_n, False, last_detected
    replica._dropped_ids = set()
    answered: list[tuple[int, str]] = []
    replica._publish_skip = lambda frame, frame_id, reason: answered.append((frame_id, reason))
    return replica, answered


def test_a_late_replica_counts_a_lost_detection_once_and_a_late_one_not_at_all() -> None:
    # every 2nd frame, one replica, last detected frame 0; busy until frame 7 came
    replica, answered = _replica(2, 0)
    assert not replica._stride_skips(7)  # frame 7 is detected: the first of its block (6, 7) to reach the replica
    replica._answer_missed(_Frame(7), [1, 2, 3, 4, 5, 6], detects_frame=True)
    # 1: frame 0's block; 2 and 4 were due and never detected (3, 5: their blocks' stride); 6: late, 7 detected
    assert answered == [(1, "stride"), (2, "dropped"), (3, "stride"), (4, "dropped"), (5, "stride"), (6, "stride")]
    assert replica._dropped_ids == {2, 4}
    # at every frame, a frame passed over is always a lost detection
    replica, answered = _replica(1, 0)
    replica._answer_missed(_Frame(3), [1, 2], detects_frame=True)
    assert answered == [(1, "dropped"), (2, "dropped")]
