"""The map on disk: an atomic SQLite store of the mapper's state, and the `map.json` export.

SQLite because a crash (even SIGKILL) mid-write must leave the previous map intact: each save is one
transaction replacing one row. `map.json` is the documented, tool-friendly export (`semmap.map/1`).
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import msgpack

from semmap.messages import Landmark, MessageError
from semmap.outputs import atomic_write_text

MAP_SCHEMA = "semmap.map/1"


class MapStore:
    """One robot's persisted mapper state (msgpack blob in a single-row table)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._connect() as db:
            db.execute("CREATE TABLE IF NOT EXISTS state (id INTEGER PRIMARY KEY CHECK (id = 0), body BLOB)")

    def _connect(self) -> sqlite3.Connection:
        db = sqlite3.connect(self.path, timeout=10)
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=NORMAL")
        return db

    def save(self, state: dict[str, Any]) -> None:
        body = msgpack.packb(state, use_bin_type=True)
        db = self._connect()
        try:
            with db:
                db.execute("INSERT OR REPLACE INTO state (id, body) VALUES (0, ?)", (body,))
        finally:
            db.close()

    def clear(self) -> None:
        """Forget the saved state (a new run writing to the same directory)."""
        db = self._connect()
        try:
            with db:
                db.execute("DELETE FROM state")
        finally:
            db.close()

    def load(self) -> dict[str, Any] | None:
        db = self._connect()
        try:
            row = db.execute("SELECT body FROM state WHERE id = 0").fetchone()
        finally:
            db.close()
        return None if row is None else msgpack.unpackb(row[0], raw=False, strict_map_key=False)


def landmark_json(lm: Landmark) -> dict[str, Any]:
    return {"id": lm.id, "class": lm.class_name, "centroid": [round(float(v), 5) for v in lm.centroid],
            "radius": round(float(lm.radius), 5), "extent": [round(float(v), 5) for v in lm.extent],
            "observations": lm.observations, "first_seen": lm.first_seen, "last_seen": lm.last_seen}


def write_map_json(path: Path, landmarks: Iterable[Landmark]) -> None:
    """Write `map.json` atomically (write a temporary file, then rename)."""
    body = {"schema": MAP_SCHEMA, "landmarks": [landmark_json(lm) for lm in sorted(landmarks, key=lambda x: x.id)]}
    atomic_write_text(path, json.dumps(body, indent=1))


def read_map_json(path: Path) -> list[Landmark]:
    """Landmarks from a `map.json`; MessageError on a file of another schema or with malformed entries."""
    try:
        body = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise MessageError(f"cannot read map {path}: {exc}") from None
    if not isinstance(body, dict) or body.get("schema") != MAP_SCHEMA:
        raise MessageError(f"{path} is not a {MAP_SCHEMA} file")
    return [Landmark.from_dict(item) for item in body.get("landmarks", [])]
