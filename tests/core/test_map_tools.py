"""map.json tools without a bus: queries, the CLI on a saved map, PLY export."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import open3d as o3d
import pytest

from semmap.core.messages import Landmark, MessageError
from semmap.runtime.maps.map_query import MapQuery, QueryError, run_query
from semmap.runtime.maps.map_store import MapStore, read_map_json, write_map_json

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
    # near alone: every landmark, nearest first (docs/INTERFACE.md: every parameter optional)
    assert [lm.id for lm in run_query(MapQuery.from_parameters({"near": "0,1,0.5"}), LANDMARKS)] == [2, 0, 1]
    assert [lm.id for lm in run_query(MapQuery.from_parameters({"class": "Cup"}), LANDMARKS)] == [0, 1]
    for bad in ({"near": "1,2"}, {"radius": "1"}, {"radius": "-1", "near": "0,0,0"}, {"colour": "red"},
                {"id": "x"}):
        with pytest.raises(QueryError):
            MapQuery.from_parameters(bad)


def test_query_cli_on_a_saved_map(saved: Path) -> None:
    out = subprocess.run([sys.executable, "-m", "semmap.cli", "query", str(saved), "--class", "chair", "--json"],
                         cwd=PROJECT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert [lm["id"] for lm in json.loads(out.stdout)["landmarks"]] == [2]
    bad = subprocess.run([sys.executable, "-m", "semmap.cli", "query", str(saved), "--radius", "1"],
                         cwd=PROJECT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--radius: needs near" in bad.stderr


def test_cli_errors_are_one_line_naming_the_flag(saved: Path, tmp_path: Path) -> None:
    """No traceback, no bare Python message: the flag and what it expects."""
    near = _query(str(saved), "--near", "a,b,c")
    assert near.returncode == 2 and near.stderr.strip() == (
        "error: --near: expected three numbers x,y,z (metres), got 'a,b,c'"), near.stderr
    ids = _query(str(saved), "--id", "x")
    assert ids.returncode == 2 and ids.stderr.strip().startswith("error: --id: expected landmark ids"), ids.stderr
    export = subprocess.run([sys.executable, "-m", "semmap.cli", "export", str(saved), "--out",
                             str(tmp_path / "missing" / "map.ply")], cwd=PROJECT, capture_output=True, text=True,
                            timeout=60)
    assert export.returncode == 2 and len(export.stderr.strip().splitlines()) == 1, export.stderr
    assert "does not exist" in export.stderr and "Traceback" not in export.stderr
    version = subprocess.run([sys.executable, "-m", "semmap.cli", "--version"], cwd=PROJECT, capture_output=True,
                             text=True, timeout=60)
    assert version.returncode == 0 and version.stdout.startswith("semmap "), version
    for command, words in (("diff", "objects added, missing and moved"), ("merge", "fuse them into one map")):
        helped = subprocess.run([sys.executable, "-m", "semmap.cli", command, "--help"], cwd=PROJECT,
                                capture_output=True, text=True, timeout=60)
        assert words in helped.stdout and f"`semmap {command} A B" in helped.stdout, helped.stdout


def _query(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "semmap.cli", "query", *args], cwd=PROJECT, capture_output=True,
                          text=True, timeout=60)


def test_query_near_without_radius_lists_nearest_first_with_distances(saved: Path) -> None:
    out = _query(str(saved), "--near", "1.25,0.2,0.8")
    assert out.returncode == 0, out.stderr
    header, *rows = out.stdout.splitlines()
    assert header.split()[-1] == "distance"
    assert [int(r.split()[0]) for r in rows] == [1, 0, 2]
    distances = [float(r.split()[-1]) for r in rows]
    assert distances == sorted(distances) and distances[0] == pytest.approx(0.05, abs=1e-3)
    assert "nearest first" in out.stderr


def test_query_class_is_case_insensitive_and_a_miss_lists_the_classes(saved: Path) -> None:
    out = _query(str(saved), "--class", "Cup")
    assert out.returncode == 0 and [int(r.split()[0]) for r in out.stdout.splitlines()[1:]] == [0, 1]
    miss = _query(str(saved), "--class", "sofa")
    assert miss.returncode == 0 and miss.stdout.splitlines()[1:] == []
    assert "no landmark of class 'sofa'; classes in this map: cup (2), chair (1)" in miss.stderr


def test_query_piped_to_head_ends_quietly(tmp_path: Path) -> None:
    many = [Landmark(i, "cup", (0.01 * i, 0.0, 0.0), 0.05, (0.1, 0.1, 0.1), 5, 0.0, 1.0) for i in range(20000)]
    write_map_json(tmp_path / "map.json", many)  # ~1.5 MB of rows: far more than a pipe holds
    out = subprocess.run(f"{sys.executable} -m semmap.cli query {tmp_path} | head -n 2", shell=True, cwd=PROJECT,
                         capture_output=True, text=True, timeout=120)
    assert len(out.stdout.splitlines()) == 2
    assert "Traceback" not in out.stderr and "BrokenPipe" not in out.stderr, out.stderr


@pytest.mark.parametrize("spheres", [False, True])
def test_ply_export(saved: Path, spheres: bool) -> None:
    ply = saved / "map.ply"
    args = ["export", str(saved), "--out", str(ply)] + (["--spheres"] if spheres else [])
    out = subprocess.run([sys.executable, "-m", "semmap.cli", *args], cwd=PROJECT, capture_output=True, text=True,
                         timeout=300)  # imports Open3D: slow on a loaded machine
    assert out.returncode == 0, out.stderr
    if spheres:
        mesh = o3d.io.read_triangle_mesh(str(ply))
        assert len(mesh.triangles) > 3 * 100 and mesh.has_vertex_colors()
        assert abs(mesh.get_max_bound()[2] - (0.45 + 0.45)) < 0.02  # the chair's sphere top
    else:
        cloud = o3d.io.read_point_cloud(str(ply))
        assert len(cloud.points) == 3 and cloud.has_colors()
    # the classes round-trip: every vertex names its landmark's class through the legend beside the file
    from semmap.cli.query_export import read_ply_classes

    classes = {lm.id: lm.class_name for lm in LANDMARKS}
    pairs = read_ply_classes(ply)
    assert len(pairs) >= 3 and all(classes[i] == name for i, name in pairs)
    assert {i for i, _ in pairs} == set(classes)


def test_map_store_survives_reopening(tmp_path: Path) -> None:
    store = MapStore(tmp_path / "map.sqlite")
    assert store.load() is None
    store.save({"version": 1, "blob": b"\x00\x01", "ids": [1, 2]})
    assert MapStore(tmp_path / "map.sqlite").load() == {"version": 1, "blob": b"\x00\x01", "ids": [1, 2]}
