"""How detector replicas share frames at a cadence in real time (semmap/algorithms/detector/turns.py): which frames
they detect, which they count as dropped (a detection real time cost) and which as stride (the cadence would have
skipped them anyway), and the same logic played against a clock (`simulate`)."""

from __future__ import annotations

import numpy as np

from semmap.algorithms.detector.turns import ReplicaTurns, owner, simulate


def test_replicas_take_turns_in_blocks_of_the_cadence() -> None:
    assert [owner(f, 2, 2) for f in range(8)] == [0, 0, 1, 1, 0, 0, 1, 1]  # every 2nd frame: 0, 2, 4, 6 in turn
    assert [owner(f, 1, 2) for f in range(4)] == [0, 1, 0, 1]  # every frame: by frame id, as before
    assert [owner(f, 3, 1) for f in range(4)] == [0, 0, 0, 0]
    for every_n in (1, 2, 3, 5):  # each frame has exactly one owner, and each replica owns due frames
        for replicas in (1, 2, 3):
            due = {owner(f, every_n, replicas) for f in range(0, 60, every_n)}
            assert due == set(range(replicas))


def test_a_late_replica_counts_a_lost_detection_once_and_a_late_one_not_at_all() -> None:
    # every 2nd frame, one replica, last detected frame 0; busy until frame 7 came
    turns = ReplicaTurns(2, last_detected=0)
    assert not turns.skips(7)  # frame 7 is detected: the first of its block (6, 7) to reach the replica
    # 1: frame 0's block; 2 and 4 were due and never detected (3, 5: their blocks' stride); 6: late, 7 detected
    assert turns.passed_over(7, [1, 2, 3, 4, 5, 6], detects_frame=True) == [
        (1, "stride"), (2, "dropped"), (3, "stride"), (4, "dropped"), (5, "stride"), (6, "stride")]
    # at every frame, a frame passed over is always a lost detection
    assert ReplicaTurns(1, last_detected=0).passed_over(3, [1, 2], detects_frame=True) == [
        (1, "dropped"), (2, "dropped")]
    # lockstep: every n-th frame by id, whatever came before
    assert [ReplicaTurns(3, lockstep=True, last_detected=2).skips(f) for f in range(4)] == [False, True, True, False]


def test_a_simulated_run_that_keeps_up_detects_exactly_the_planned_frames() -> None:
    # 2 replicas, every 2nd frame at 30 Hz: each has 133 ms a turn; 100 ms detections keep up
    got = simulate(60, 2, 2, lambda f: 0.100, 1 / 30)
    assert got == list(range(0, 60, 2))
    # every frame, one replica that needs less than a frame
    assert simulate(10, 1, 1, lambda f: 0.02, 1 / 30) == list(range(10))


def test_a_simulated_overrun_takes_the_late_frame_of_its_turn_or_loses_the_turn() -> None:
    # one replica, every 2nd frame; frame 0 takes 50 ms (past frame 1, before frame 2): frame 2 is detected on time
    assert simulate(6, 2, 1, lambda f: 0.050 if f == 0 else 0.01, 1 / 30)[:3] == [0, 2, 4]
    # frame 0 takes 80 ms: frame 2 came at 67 ms while it was busy, so it is detected late (at 80 ms), still in turn
    assert simulate(6, 2, 1, lambda f: 0.080 if f == 0 else 0.01, 1 / 30)[:3] == [0, 2, 4]
    # frame 0 takes 110 ms: frame 3 (100 ms) is the newest queued, the late frame of the same turn
    assert simulate(8, 2, 1, lambda f: 0.110 if f == 0 else 0.01, 1 / 30)[:2] == [0, 3]
    # frame 0 takes 140 ms: the block (2, 3) came and went while it was busy (a lost detection); frame 4 (133 ms),
    # queued, is detected next
    assert simulate(8, 2, 1, lambda f: 0.140 if f == 0 else 0.01, 1 / 30)[:2] == [0, 4]


def test_another_replicas_frame_never_takes_the_queue_place_of_a_late_frame_of_ones_own_turn() -> None:
    # 2 replicas, every 2nd frame: replica 0 owns frames 0-1, 4-5, 8-9; frame 0 takes 210 ms, past frame 4 (133 ms),
    # frame 5 (167 ms) and replica 1's frame 6 (200 ms). Its queue held frame 5, the late frame of its turn, because
    # frame 6 is passed over on arrival (the service's `wanted`): a queue of any frame would have lost the turn.
    got = simulate(12, 2, 2, lambda f: 0.210 if f == 0 else 0.01, 1 / 30)
    assert got == [0, 2, 5, 6, 8, 10]


def test_slow_replicas_detect_less_often_and_never_a_frame_twice() -> None:
    rng = np.random.default_rng(0)
    times = rng.lognormal(np.log(0.150), 0.25, size=1000)
    got = simulate(1000, 2, 2, lambda f: float(times[f]), 1 / 30)
    assert len(got) == len(set(got))
    assert 300 < len(got) < 500  # 2 replicas of ~150 ms (each turn 133 ms): fewer than the planned 500
    fast = simulate(1000, 2, 2, lambda f: 0.050, 1 / 30)
    assert len(fast) == 500
