"""`semmap query` (a live run or a saved map.json) and `semmap export` (map.json -> PLY)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # (imported when a command runs, not for `semmap --help`)
    from semmap.core.messages import Landmark
    from semmap.runtime.maps.map_query import MapQuery

from semmap.core import environment


def _map_path(arg: str) -> Path:
    path = Path(arg)
    return path / "map.json" if path.is_dir() else path


def _query_live(query: MapQuery, robot: str, connect: str | None, timeout: float) -> list[Landmark]:
    from semmap.runtime.maps.map_query import QueryError, ask_live_map
    from semmap.runtime.orchestrator import DEFAULT_PORT
    from semmap.runtime.transport.bus import Bus, BusConfig

    connect = connect or environment.read(environment.ZENOH_CONNECT) or f"tcp/127.0.0.1:{DEFAULT_PORT}"
    bus = Bus(BusConfig.from_env(connect), robot)
    try:
        selector = bus.keys.map_query + (f"?{query.to_parameters()}" if query.to_parameters() else "")
        found = ask_live_map(bus.session, selector, timeout)
    finally:
        bus.close()
    if found is None:
        raise QueryError(f"no map service answered on {robot!r} within {timeout:g} s (is a run going? --connect?)")
    return found


def _query(args: argparse.Namespace) -> int:
    from semmap.core.messages import MessageError
    from semmap.runtime.maps.map_query import MapQuery, QueryError, class_counts, run_query
    from semmap.runtime.maps.map_store import MAP_SCHEMA, landmark_json, read_map_json

    try:
        query = MapQuery.from_parameters({k: v for k, v in {
            "class": args.class_name, "near": args.near, "radius": None if args.radius is None else str(args.radius),
            "id": args.id}.items() if v is not None})
        if args.map:
            everything = read_map_json(_map_path(args.map))
            found = run_query(query, everything)
        else:
            found = _query_live(query, args.robot, args.connect, args.timeout)
            everything = None
        if not found and query.class_name is not None:  # say what the map does hold
            if everything is None:
                everything = _query_live(MapQuery(), args.robot, args.connect, args.timeout)
            known = ", ".join(f"{name} ({n})" for name, n in class_counts(everything).items()) or "none"
            print(f"no landmark of class {query.class_name!r}; classes in this map: {known}", file=sys.stderr)
    except (QueryError, MessageError) as exc:
        text = str(exc)
        for name in ("near", "radius", "id"):  # a parameter's error names the flag that gave it
            if text.startswith(f"{name}: "):
                text = f"--{text}"
        print(f"error: {text}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"schema": MAP_SCHEMA, "landmarks": [landmark_json(lm) for lm in found]}, indent=1))
        return 0
    near = query.near
    print(f"{'id':>5}  {'class':<14} {'x':>7} {'y':>7} {'z':>7}  {'radius':>6}  {'obs':>4}"
          + ("  distance" if near is not None else ""))
    for lm in found:
        x, y, z = lm.centroid
        line = f"{lm.id:>5}  {lm.class_name:<14} {x:7.3f} {y:7.3f} {z:7.3f}  {lm.radius:6.3f}  {lm.observations:>4}"
        if near is not None:
            line += f"  {math.dist(lm.centroid, near):8.3f}"
        print(line)
    print(f"{len(found)} landmark(s); world frame, metres" + (", nearest first" if near is not None else ""),
          file=sys.stderr)
    return 0


def class_legend(landmarks: list[Landmark]) -> dict[str, int]:
    """{class name: class id} for the export: ids in order of the sorted class names (stable for one map)."""
    return {name: i for i, name in enumerate(sorted({lm.class_name for lm in landmarks}))}


def export_ply(landmarks: list[Landmark], path: Path, spheres: bool) -> Path:
    """Centroids as coloured points, or each landmark as a sphere of its radius, in one ASCII PLY file whose
    vertices carry `class_id` and `landmark_id` (extra vertex properties that MeshLab, CloudCompare and Open3D
    read or skip); the legend (class id -> name) goes to `<path>.classes.json`. Returns the legend's path."""
    import numpy as np
    import open3d as o3d

    from semmap.services.viz.service import landmark_color

    legend = class_legend(landmarks)
    verts, faces = [], []  # (x, y, z, r, g, b, class_id, landmark_id), (i, j, k)
    for lm in landmarks:
        r, g, b = landmark_color(lm.id)
        if spheres:
            sphere = o3d.geometry.TriangleMesh.create_sphere(radius=max(lm.radius, 0.01), resolution=12)
            sphere.translate(np.asarray(lm.centroid, float))
            base = len(verts)
            verts += [(*p, r, g, b, legend[lm.class_name], lm.id) for p in np.asarray(sphere.vertices)]
            faces += [tuple(int(i) + base for i in t) for t in np.asarray(sphere.triangles)]
        else:
            verts.append((*lm.centroid, r, g, b, legend[lm.class_name], lm.id))
    header = ["ply", "format ascii 1.0", "comment semmap map export: class_id names in the .classes.json beside it",
              f"element vertex {len(verts)}", "property double x", "property double y", "property double z",
              "property uchar red", "property uchar green", "property uchar blue", "property int class_id",
              "property int landmark_id"]
    if spheres:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    lines = [*header, "end_header"]
    lines += [f"{x:.6f} {y:.6f} {z:.6f} {r} {g} {b} {c} {i}" for x, y, z, r, g, b, c, i in verts]
    lines += [f"3 {i} {j} {k}" for i, j, k in faces]
    Path(path).write_text("\n".join(lines) + "\n")
    legend_path = Path(f"{path}.classes.json")
    legend_path.write_text(json.dumps({"schema": "semmap.classes/1", "classes": {str(i): name for name, i in
                                                                                 legend.items()}}, indent=1))
    return legend_path


def read_ply_classes(path: Path) -> list[tuple[int, str]]:
    """(landmark id, class name) of every vertex of an exported PLY, through its legend: the round trip."""
    legend = json.loads(Path(f"{path}.classes.json").read_text())["classes"]
    lines = Path(path).read_text().splitlines()
    header_end = lines.index("end_header")
    names = [ln.split()[-1] for ln in lines[:header_end] if ln.startswith("property") and "list" not in ln]
    count = next(int(ln.split()[-1]) for ln in lines if ln.startswith("element vertex"))
    c_col, l_col = names.index("class_id"), names.index("landmark_id")
    rows = [ln.split() for ln in lines[header_end + 1 : header_end + 1 + count]]
    return [(int(r[l_col]), legend[r[c_col]]) for r in rows]


def _export(args: argparse.Namespace) -> int:
    from semmap.core.messages import MessageError
    from semmap.runtime.maps.map_store import read_map_json

    try:
        landmarks = read_map_json(_map_path(args.map))
    except MessageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    if out.is_dir() or not out.parent.is_dir():
        why = "is a folder: name the .ply file" if out.is_dir() else f"its folder {out.parent} does not exist"
        print(f"error: --out {out}: {why}", file=sys.stderr)
        return 2
    try:
        legend = export_ply(landmarks, out, spheres=args.spheres)
    except OSError as exc:
        print(f"error: cannot write --out {out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(landmarks)} landmark(s) to {out} (vertex property class_id; names in {legend})",
          file=sys.stderr)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    q = sub.add_parser("query", help="query the map of a live run, or a saved map.json",
                       description="Landmarks by class, near a point, by id, or all. Without MAP, asks the live run "
                                   "over Zenoh (key semmap/v1/<robot>/map/query).")
    q.add_argument("map", nargs="?", help="a run directory or map.json (default: ask the live run)")
    q.add_argument("--class", dest="class_name", help="only this class, e.g. cup (case-insensitive)")
    q.add_argument("--near", help="x,y,z in the world frame (m): results nearest first, with their distance")
    q.add_argument("--radius", type=float, help="with --near: only landmarks within this many metres")
    q.add_argument("--id", help="landmark id(s), comma-separated")
    q.add_argument("--json", action="store_true", help="print a semmap.map/2 JSON document")
    q.add_argument("--robot", default="robot1")
    q.add_argument("--connect", default=None,
                   help="Zenoh endpoint of the run (env SEMMAP_ZENOH_CONNECT; default tcp/127.0.0.1:7447, "
                        "where `semmap run` listens when that port is free)")
    q.add_argument("--timeout", type=float, default=3.0)
    q.set_defaults(func=_query)
    e = sub.add_parser("export", help="export a map.json as PLY (centroids, or spheres with --spheres)")
    e.add_argument("map", help="a run directory or map.json")
    e.add_argument("--out", required=True, help="output .ply file")
    e.add_argument("--spheres", action="store_true", help="one sphere mesh per landmark instead of points")
    e.set_defaults(func=_export)
