"""The map on disk: an atomic SQLite store of the mapper's state, and the `map.json` export.

SQLite because a crash (even SIGKILL) mid-write must leave the previous map intact: each save is one
transaction replacing one row. `map.json` is the documented, tool-friendly export (`semmap.map/2`).

Both state their schema version (`map.json`: its "schema" field; `map.sqlite`: a `meta` table) and a file of
another version is refused with a `MapVersionError` that says which version it is and which this semmap reads,
rather than misread: a map is kept for days, and the code that reads it moves on. `semmap.map/1` (before
`status`) and a `map.sqlite` without `meta` (before versioning) count as older versions.
"""

from __future__ import annotations

import json
import re
import sqlite3
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import msgpack

from semmap.core.messages import Landmark, MessageError
from semmap.core.outputs import atomic_write_text

MAP_SCHEMA = "semmap.map/2"
STORE_SCHEMA = "semmap.mapstore/1"


class MapVersionError(MessageError):
    """A map file of another schema version than this semmap reads (older or newer), or of no known schema."""


def _check_version(path: Path, found: object, expected: str) -> None:
    """Refuse `found` unless it is `expected`, saying whether the file is older or newer."""
    if found == expected:
        return
    name, _, want = expected.rpartition("/")
    m = re.fullmatch(re.escape(name) + r"/(\d+)", found) if isinstance(found, str) else None
    if m is None:
        raise MapVersionError(f"{path} is not a {name} file (schema {found!r}); this semmap reads {expected}")
    age = "an older" if int(m.group(1)) < int(want) else "a newer"
    raise MapVersionError(f"{path} was written by {age} semmap (schema {found}); this version reads only {expected}"
                          f"{': map it again or convert it' if age == 'an older' else ': update semmap'}")


class MapStore:
    """One robot's persisted mapper state (msgpack blob in a single-row table) and its schema version."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        db = None
        try:
            db = self._connect()
            with db:
                db.execute("CREATE TABLE IF NOT EXISTS state (id INTEGER PRIMARY KEY CHECK (id = 0), body BLOB)")
                db.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT)")
                row = db.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone()
                if row is None:
                    if db.execute("SELECT COUNT(*) FROM state").fetchone()[0]:  # saved before versioning
                        raise MapVersionError(f"{self.path} was written by an older semmap (no schema version); "
                                              f"this version reads only {STORE_SCHEMA}: map it again")
                    db.execute("INSERT INTO meta (key, value) VALUES ('schema', ?)", (STORE_SCHEMA,))
                else:
                    _check_version(self.path, row[0], STORE_SCHEMA)
        except sqlite3.DatabaseError as exc:
            raise MapVersionError(f"{self.path} is not a semmap map database: {exc}") from None
        finally:
            if db is not None:
                db.close()

    @classmethod
    def open_existing(cls, path: Path) -> MapStore:
        """An existing store, for reading (a missing file is an error, not a new empty map)."""
        if not Path(path).is_file():
            raise MessageError(f"no map database at {path}")
        return cls(path)

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
            "observations": lm.observations, "first_seen": lm.first_seen, "last_seen": lm.last_seen,
            "status": lm.status}


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
    if not isinstance(body, dict):
        raise MapVersionError(f"{path} is not a {MAP_SCHEMA} file")
    _check_version(Path(path), body.get("schema"), MAP_SCHEMA)
    if not isinstance(body.get("landmarks", []), list):
        raise MessageError(f"{path}: 'landmarks' must be a list")
    return [Landmark.from_dict(item) for item in body.get("landmarks", [])]
