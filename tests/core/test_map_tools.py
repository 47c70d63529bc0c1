"""map.json tools without a bus: queries, the CLI on a saved map, PLY export."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import open3d as o3d
import pytest

from semmap.map_query import MapQuery, QueryError, run_query
from semmap.map_store import MapStore, read_map_json, write_map_json
from semmap.messages import Landmark, MessageError

PROJECT = Path(__file__).resolve().parents[2]
LANDMARKS = [
    Landmark(0, "cup", (1.0, 0.0, 0.8), 0.05, (0.08, 0.08, 0.1), 12, 0.0, 3.0),
    Landmark(1, "cup", (1.3, 0.2, 0.8), 0.05, (0.08, 0.08, 0.1), 9, 1.0, 4.0),
    Landmark(2, "chair", (0.0, 1.0, 0.45), 0.45, (0.5, 0.5, 0.9), 30, 0.5, 9.0),
]


@pytest.fixture
def saved(tmp_path: Path) -> Path:
    write_map_json(tmp_path / "map.json", LANDMARKS)
    return tmp_path


def test_map_json_round_trip_and_schema(saved: Path) -> None:
    assert [lm.id for lm in read_map_json(saved / "map.json")] == [0, 1, 2]
    (saved / "other.json").write_text(json.dumps({"schema": "something/1"}))
    with pytest.raises(MessageError, match="not a semmap.map file"):
        read_map_json(saved / "other.json")


def test_queries() -> None:
    assert [lm.id for lm in run_query(MapQuery(class_name="cup"), LANDMARKS)] == [0, 1]
    near = run_query(MapQuery.from_parameters({"near": "1.25,0.2,0.8", "radius": "0.4"}), LANDMARKS)
    assert [lm.id for lm in near] == [1, 0]  # nearest first
    assert [lm.id for lm in run_query(MapQuery.from_parameters({"id": "2"}), LANDMARKS)] == [2]
    query = MapQuery(class_name="cup", ids=frozenset({1}))
    assert MapQuery.from_parameters(dict(p.split("=") for p in query.to_parameters().split(";"))) == query
    for bad in ({"near": "1,2"}, {"near": "1,2,3"}, {"radius": "-1", "near": "0,0,0"}, {"colour": "red"},
                {"id": "x"}):
        with pytest.raises(QueryError):
            MapQuery.from_parameters(bad)


def test_query_cli_on_a_saved_map(saved: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "semmap.cli", "query", str(saved), "--class", "chair", "--json"],
                         cwd=PROJECT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert [lm["id"] for lm in json.loads(out.stdout)["landmarks"]] == [2]
    bad = subprocess.run([sys.executable, "-m", "semmap.cli", "query", str(saved), "--near", "1,2,3"],
                         cwd=PROJECT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "near and radius go together" in bad.stderr


@pytest.mark.parametrize("spheres", [False, True])
def test_ply_export(saved: Path, spheres: bool) -> None:
    ply = saved / "map.ply"
    args = ["export", str(saved), "--out", str(ply)] + (["--spheres"] if spheres else [])
    out = subprocess.run([sys.executable, "-m", "semmap.cli", *args], cwd=PROJECT, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    if spheres:
        mesh = o3d.io.read_triangle_mesh(str(ply))
        assert len(mesh.triangles) > 3 * 100 and mesh.has_vertex_colors()
        assert abs(mesh.get_max_bound()[2] - (0.45 + 0.45)) < 0.02  # the chair's sphere top
    else:
        cloud = o3d.io.read_point_cloud(str(ply))
        assert len(cloud.points) == 3 and cloud.has_colors()


def test_map_store_survives_reopening(tmp_path: Path) -> None:
    store = MapStore(tmp_path / "map.sqlite")
    assert store.load() is None
    store.save({"version": 1, "blob": b"\x00\x01", "ids": [1, 2]})
    assert MapStore(tmp_path / "map.sqlite").load() == {"version": 1, "blob": b"\x00\x01", "ids": [1, 2]}
