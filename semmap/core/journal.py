"""Append-only SQLite journals of the messages a service has handled, to rebuild its state after a crash."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from pathlib import Path


def _open(path: Path, table: str) -> sqlite3.Connection:
    """An autocommit connection (each statement its own transaction) in WAL mode, with `table` created."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    db = sqlite3.connect(path, timeout=10, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA synchronous=NORMAL")
    db.execute(f"CREATE TABLE IF NOT EXISTS {table}")
    return db


class FrameJournal:
    """(frame_id, blob, blob) rows, plus an optional extra blob per frame (what a frame added after it was
    handled, e.g. the backend's loop closure); each append is its own transaction (a SIGKILL loses at most
    that frame)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.db = _open(self.path, "frames (frame_id INTEGER PRIMARY KEY, a BLOB, b BLOB)")
        self.db.execute("CREATE TABLE IF NOT EXISTS extras (frame_id INTEGER PRIMARY KEY, body BLOB)")

    def append(self, frame_id: int, a: bytes, b: bytes) -> None:
        self.db.execute("INSERT OR REPLACE INTO frames VALUES (?, ?, ?)", (frame_id, a, b))

    def append_extra(self, frame_id: int, body: bytes) -> None:
        self.db.execute("INSERT OR REPLACE INTO extras VALUES (?, ?)", (frame_id, body))

    def frames(self) -> Iterator[tuple[int, bytes, bytes, bytes | None]]:
        """(frame_id, a, b, extra or None) in frame order."""
        yield from self.db.execute("SELECT f.frame_id, f.a, f.b, e.body FROM frames f "
                                   "LEFT JOIN extras e ON e.frame_id = f.frame_id ORDER BY f.frame_id")

    def last(self, n: int) -> list[tuple[int, bytes, bytes, bytes | None]]:
        """The newest `n` rows, in frame order (what a restart needs of a journal that only continues a state)."""
        rows = self.db.execute("SELECT f.frame_id, f.a, f.b, e.body FROM frames f LEFT JOIN extras e "
                               "ON e.frame_id = f.frame_id ORDER BY f.frame_id DESC LIMIT ?", (n,)).fetchall()
        return rows[::-1]

    def trim(self, before_frame_id: int) -> None:
        """Forget the rows of frames before `before_frame_id` (a newer row holds all a restart needs)."""
        self.db.execute("DELETE FROM frames WHERE frame_id < ?", (before_frame_id,))
        self.db.execute("DELETE FROM extras WHERE frame_id < ?", (before_frame_id,))

    def clear(self) -> None:
        self.db.execute("DELETE FROM frames")
        self.db.execute("DELETE FROM extras")


def _read_only(path: Path) -> sqlite3.Connection:
    """Another run's journal, read-only: a saved run may sit on a read-only disk and is never changed by reading
    it (sqlite3.Error when it is not a database)."""
    return sqlite3.connect(f"{Path(path).resolve().as_uri()}?mode=ro", uri=True, timeout=10)


def read_extras(path: Path) -> Iterator[tuple[int, bytes]]:
    """(frame_id, extra) of another run's FrameJournal, in frame order, streamed."""
    db = _read_only(path)
    try:
        yield from db.execute("SELECT frame_id, body FROM extras ORDER BY frame_id")
    finally:
        db.close()


def read_frames(path: Path) -> Iterator[tuple[int, bytes, bytes, bytes | None]]:
    """(frame_id, a, b, extra or None) of another run's FrameJournal, in frame order, streamed."""
    db = _read_only(path)
    try:
        yield from db.execute("SELECT f.frame_id, f.a, f.b, e.body FROM frames f "
                              "LEFT JOIN extras e ON e.frame_id = f.frame_id ORDER BY f.frame_id")
    finally:
        db.close()


class MessageJournal:
    """(seq, stream, blob) rows in arrival order: the inputs a service handled since its last snapshot.

    A service that snapshots its state now and then (the associator's map) journals every input after the
    snapshot; after a crash it loads the snapshot and handles the journalled inputs again, so it goes on from
    the last message it handled rather than from the last snapshot. Each append is its own transaction.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.db = _open(self.path, "inputs (seq INTEGER PRIMARY KEY, stream TEXT, body BLOB)")
        row = self.db.execute("SELECT MAX(seq) FROM inputs").fetchone()
        self.last_seq = int(row[0]) if row and row[0] is not None else 0

    def append(self, stream: str, body: bytes) -> int:
        self.last_seq += 1
        self.db.execute("INSERT INTO inputs VALUES (?, ?, ?)", (self.last_seq, stream, body))
        return self.last_seq

    def entries(self, after_seq: int = 0) -> Iterator[tuple[int, str, bytes]]:
        yield from self.db.execute("SELECT seq, stream, body FROM inputs WHERE seq > ? ORDER BY seq", (after_seq,))

    def truncate(self, upto_seq: int) -> None:
        """Forget the inputs a snapshot now covers."""
        self.db.execute("DELETE FROM inputs WHERE seq <= ?", (upto_seq,))

    def clear(self) -> None:
        self.db.execute("DELETE FROM inputs")
        self.last_seq = 0

    def close(self) -> None:
        self.db.close()
