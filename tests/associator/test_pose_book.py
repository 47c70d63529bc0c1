"""The associator's PoseBook: corrected poses where the backend has them, odometry moved by the newest correction
otherwise, and a saved book that places later frames exactly as the live one did."""

from __future__ import annotations

import msgpack
import numpy as np

from semmap.algorithms.associator.pose_book import PoseBook
from semmap.core.messages import CorrectedPoses
from tests.associator.helpers import orbit_pose


def _shifted(pose: np.ndarray, dx: float) -> np.ndarray:
    out = pose.copy()
    out[:3, 3] += (dx, 0.0, 0.0)
    return out


def _book(frames: int) -> PoseBook:
    """Odometry drifting 1 cm per frame; the backend corrected frames 0..frames-2 back onto the truth."""
    book = PoseBook()
    for f in range(frames):
        book.odometry[f] = _shifted(orbit_pose(f / 30), 0.01 * f)
    ids = np.arange(frames - 1)
    book.set_corrected(CorrectedPoses("r", 1, frames - 2, ids, ids / 30.0, np.stack([orbit_pose(f / 30) for f in ids])))
    return book


def test_lookups_prefer_corrections_and_move_newer_odometry_by_the_newest_one() -> None:
    book = _book(20)
    np.testing.assert_allclose(book(5), orbit_pose(5 / 30))
    # frame 19 has odometry only: moved by frame 18's correction, it lands within the drift of one frame
    assert np.linalg.norm(book(19)[:3, 3] - orbit_pose(19 / 30)[:3, 3]) < 0.011 + 1e-9
    assert book(25) is None


def test_a_saved_book_places_new_frames_as_the_live_one() -> None:
    live = _book(400)
    saved = PoseBook.from_state(msgpack.unpackb(msgpack.packb(live.to_state(recent=50), use_bin_type=True),
                                                strict_map_key=False))
    assert len(saved.odometry) == 50 and max(saved.odometry) == 399  # bounded: the recent frames only
    for f in (400, 401, 450):
        pose = _shifted(orbit_pose(f / 30), 0.01 * f)
        live.odometry[f] = saved.odometry[f] = pose
        np.testing.assert_allclose(saved(f), live(f), atol=1e-12)
    np.testing.assert_allclose(saved(390), live(390), atol=1e-12)
    assert PoseBook.from_state(None)(3) is None


def test_a_saved_book_ignores_an_old_resent_delta_as_the_live_one() -> None:
    """After a restart the backend may answer a resent frame with a correction the book applied before: a delta
    older than the newest applied one changes nothing, in a restored book too."""
    live = _book(20)
    ids = np.arange(5)
    newer = CorrectedPoses("r", 3, 19, ids, ids / 30.0, np.stack([_shifted(orbit_pose(f / 30), 0.002) for f in ids]),
                           full=False)
    live.set_corrected(newer)
    saved = PoseBook.from_state(msgpack.unpackb(msgpack.packb(live.to_state(), use_bin_type=True),
                                                strict_map_key=False))
    older = CorrectedPoses("r", 2, 18, ids, ids / 30.0, np.stack([orbit_pose(f / 30) for f in ids]), full=False)
    for book in (live, saved):
        book.set_corrected(older)
    for f in ids:
        np.testing.assert_array_equal(saved(int(f)), live(int(f)))
        np.testing.assert_array_equal(live(int(f)), _shifted(orbit_pose(f / 30), 0.002))
