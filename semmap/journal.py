"""An append-only SQLite journal of the messages a service has handled, per frame, to rebuild after a crash."""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from pathlib import Path


class FrameJournal:
    """(frame_id, blob, blob) rows; each append is its own transaction (a SIGKILL loses at most that frame)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.db = sqlite3.connect(self.path, timeout=10, isolation_level=None)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute("PRAGMA synchronous=NORMAL")
        self.db.execute("CREATE TABLE IF NOT EXISTS frames (frame_id INTEGER PRIMARY KEY, a BLOB, b BLOB)")

    def append(self, frame_id: int, a: bytes, b: bytes) -> None:
        self.db.execute("INSERT OR REPLACE INTO frames VALUES (?, ?, ?)", (frame_id, a, b))

    def frames(self) -> Iterator[tuple[int, bytes, bytes]]:
        yield from self.db.execute("SELECT frame_id, a, b FROM frames ORDER BY frame_id")

    def clear(self) -> None:
        self.db.execute("DELETE FROM frames")
