"""FrameReorderBuffer: frames out in order, each once; gaps given up when bounded; known-missing frames skipped."""

from __future__ import annotations

from semmap.core.reorder import FrameReorderBuffer


def test_out_of_order_and_duplicate_frames_come_out_once_in_order() -> None:
    buf: FrameReorderBuffer[str] = FrameReorderBuffer()
    assert buf.push(3, "c") and buf.pop_ready() == ["c"]
    assert buf.push(5, "e") and buf.pop_ready() == []
    assert buf.push(4, "d") and not buf.push(4, "d again") and not buf.push(3, "c again")
    assert buf.pop_ready() == ["d", "e"]


def test_a_bounded_buffer_gives_up_on_a_missing_frame() -> None:
    buf: FrameReorderBuffer[int] = FrameReorderBuffer(max_pending=2)
    buf.push(0, 0)
    buf.pop_ready()
    buf.push(2, 2)
    assert buf.pop_ready() == []
    buf.push(3, 3)
    assert buf.pop_ready() == [2, 3] and buf.gaps == 1


def test_a_skipped_frame_is_not_waited_for_whether_it_is_announced_before_or_after_later_ones() -> None:
    buf: FrameReorderBuffer[int] = FrameReorderBuffer(max_pending=100_000)
    buf.push(0, 0)
    assert buf.pop_ready() == [0]
    buf.skip(1)  # announced before frame 2 arrives
    buf.push(2, 2)
    assert buf.pop_ready() == [2]
    buf.push(4, 4)
    assert buf.pop_ready() == []
    buf.skip(3)  # announced after
    assert buf.pop_ready() == [4]
    assert not buf.push(3, 3), "a skipped frame that comes anyway is dropped"
    buf.push(6, 6)
    buf.skip(5)
    buf.skip(5)
    assert buf.pop_ready() == [6] and not buf.skipped and buf.gaps == 0


def test_mark_done_moves_past_replayed_frames() -> None:
    buf: FrameReorderBuffer[int] = FrameReorderBuffer()
    buf.push(0, 0)
    buf.push(2, 2)
    buf.mark_done(1)
    assert buf.pop_ready() == [2]


def test_give_up_before_releases_past_every_missing_frame_and_counts_them() -> None:
    buf: FrameReorderBuffer[int] = FrameReorderBuffer(max_pending=8)
    buf.push(0, 0)
    assert buf.pop_ready() == [0]
    buf.skip(2)  # announced: not a gap
    for f in (4, 7, 9):  # 1, 3, 5, 6 and 8 never come; fewer than max_pending wait
        buf.push(f, f)
    assert buf.pop_ready() == [] and buf.gaps == 0
    assert buf.give_up_before(9) == [4, 7, 9]
    assert buf.gaps == 5 and buf.next_id == 10 and not buf.skipped
    assert not buf.push(8, 8), "a frame given up that comes anyway is dropped"
    assert buf.give_up_before(5) == [] and buf.gaps == 5, "nothing before the next frame to give up"


def test_a_bounded_buffer_counts_every_frame_it_gives_up() -> None:
    buf: FrameReorderBuffer[int] = FrameReorderBuffer(max_pending=2)
    buf.push(0, 0)
    buf.pop_ready()
    buf.push(4, 4)
    buf.push(5, 5)
    assert buf.pop_ready() == [4, 5] and buf.gaps == 3


def test_frames_before_the_first_one_heard_are_gaps_once_the_stream_says_where_it_began() -> None:
    """A stream whose first frames were dropped upstream (real time: the odometry keeps only its newest frames)
    starts the buffer late; those frames are counted when the end of the stream says where it began."""
    buf: FrameReorderBuffer[int] = FrameReorderBuffer(max_pending=8)
    buf.skip(1)  # announced unreadable before anything came: not a gap
    buf.push(3, 3)
    buf.skip(2)  # announced after the first frame came: not a gap either
    assert buf.pop_ready() == [3] and buf.gaps == 0
    assert buf.stream_began_at(0) == 1 and buf.gaps == 1, "frame 0 never came"
    assert buf.stream_began_at(0) == 0 and buf.gaps == 1, "counted once"


def test_a_stream_heard_from_its_first_frame_or_resumed_has_no_gap_before_it() -> None:
    buf: FrameReorderBuffer[int] = FrameReorderBuffer()
    buf.push(0, 0)
    assert buf.stream_began_at(0) == 0
    resumed: FrameReorderBuffer[int] = FrameReorderBuffer()
    resumed.mark_done(41)  # frames up to 41 were handled before a restart
    resumed.push(43, 43)
    assert resumed.stream_began_at(0) == 0 and resumed.gaps == 0
