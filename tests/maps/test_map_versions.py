"""Versioned map files: this version's files round-trip; older, newer and foreign ones are refused clearly."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import msgpack
import pytest

from semmap.core.messages import Landmark, MessageError
from semmap.runtime.maps.map_store import (
    MAP_SCHEMA,
    STORE_SCHEMA,
    MapStore,
    MapVersionError,
    read_map_json,
    write_map_json,
)

LANDMARKS = [
    Landmark(0, "cup", (1.0, 0.0, 0.8), 0.05, (0.08, 0.08, 0.1), 12, 0.0, 3.0, "present"),
    Landmark(1, "chair", (0.0, 1.0, 0.45), 0.45, (0.5, 0.5, 0.9), 30, 0.5, 9.0, "missing"),
    Landmark(2, "tv", (2.0, 1.0, 1.2), 0.4, (0.8, 0.1, 0.5), 5, 0.5, 1.0, "prior"),
]


def test_map_json_keeps_times_and_status(tmp_path: Path) -> None:
    write_map_json(tmp_path / "map.json", LANDMARKS)
    body = json.loads((tmp_path / "map.json").read_text())
    assert body["schema"] == MAP_SCHEMA == "semmap.map/2"
    assert [(d["first_seen"], d["last_seen"], d["status"]) for d in body["landmarks"]] == [
        (0.0, 3.0, "present"),
        (0.5, 9.0, "missing"),
        (0.5, 1.0, "prior"),
    ]
    assert read_map_json(tmp_path / "map.json") == LANDMARKS
    assert not list(tmp_path.glob("*.tmp"))  # written atomically through a temporary file


@pytest.mark.parametrize(
    ("schema", "says"),
    [
        ("semmap.map/1", "older semmap (schema semmap.map/1); this version reads only semmap.map/2"),
        ("semmap.map/3", "newer semmap (schema semmap.map/3); this version reads only semmap.map/2: update semmap"),
        ("other/2", "not a semmap.map file"),
        (None, "not a semmap.map file"),
    ],
)
def test_map_json_of_another_version_is_refused(tmp_path: Path, schema: str | None, says: str) -> None:
    write_map_json(tmp_path / "map.json", LANDMARKS)
    body = json.loads((tmp_path / "map.json").read_text())
    body["schema"] = schema
    (tmp_path / "map.json").write_text(json.dumps(body))
    with pytest.raises(MapVersionError, match=says.replace("(", r"\(").replace(")", r"\)")):
        read_map_json(tmp_path / "map.json")


def test_bad_status_is_refused(tmp_path: Path) -> None:
    write_map_json(tmp_path / "map.json", LANDMARKS)
    body = json.loads((tmp_path / "map.json").read_text())
    body["landmarks"][0]["status"] = "gone"
    (tmp_path / "map.json").write_text(json.dumps(body))
    with pytest.raises(MessageError, match="status must be one of present, prior, missing"):
        read_map_json(tmp_path / "map.json")


def test_map_store_states_its_version(tmp_path: Path) -> None:
    store = MapStore(tmp_path / "map.sqlite")
    store.save({"version": 1, "x": [1, 2]})
    db = sqlite3.connect(tmp_path / "map.sqlite")
    assert db.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone() == (STORE_SCHEMA,)
    db.close()
    assert MapStore(tmp_path / "map.sqlite").load() == {"version": 1, "x": [1, 2]}


def _rewrite_meta(path: Path, value: str | None) -> None:
    db = sqlite3.connect(path)
    with db:
        if value is None:
            db.execute("DROP TABLE meta")
        else:
            db.execute("UPDATE meta SET value = ? WHERE key = 'schema'", (value,))
    db.close()


@pytest.mark.parametrize(
    ("value", "says"),
    [
        ("semmap.mapstore/2", "newer semmap"),
        ("semmap.mapstore/0", "older semmap"),
        (None, "older semmap \\(no schema version\\)"),
    ],
)
def test_map_store_of_another_version_is_refused(tmp_path: Path, value: str | None, says: str) -> None:
    MapStore(tmp_path / "map.sqlite").save({"version": 1})
    _rewrite_meta(tmp_path / "map.sqlite", value)
    with pytest.raises(MapVersionError, match=says):
        MapStore(tmp_path / "map.sqlite")


def test_map_store_refuses_a_file_that_is_no_database(tmp_path: Path) -> None:
    (tmp_path / "map.sqlite").write_bytes(msgpack.packb({"not": "sqlite"}) * 100)
    with pytest.raises(MapVersionError, match="not a semmap map database"):
        MapStore(tmp_path / "map.sqlite")
    with pytest.raises(MessageError, match="no map database"):
        MapStore.open_existing(tmp_path / "absent.sqlite")
