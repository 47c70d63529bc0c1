"""`semmap query` (a live run or a saved map.json) and `semmap export` (map.json -> PLY)."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from semmap.map_query import MapQuery, QueryError, class_counts, run_query
from semmap.map_store import MAP_SCHEMA, landmark_json, read_map_json
from semmap.messages import Landmark, MessageError


def _map_path(arg: str) -> Path:
    path = Path(arg)
    return path / "map.json" if path.is_dir() else path


def _query_live(query: MapQuery, robot: str, connect: str | None, timeout: float) -> list[Landmark]:
    from semmap.bus import Bus, BusConfig
    from semmap.orchestrator import DEFAULT_PORT

    connect = connect or os.environ.get("SEMMAP_ZENOH_CONNECT") or f"tcp/127.0.0.1:{DEFAULT_PORT}"
    bus = Bus(BusConfig.from_env(connect), robot)
    try:
        selector = bus.keys.map_query + (f"?{query.to_parameters()}" if query.to_parameters() else "")
        for reply in bus.session.get(selector, timeout=timeout):
            if reply.ok is None:
                raise QueryError(f"the map service answered: {reply.err.payload.to_bytes().decode(errors='replace')}")
            body = json.loads(reply.ok.payload.to_bytes())
            if body.get("schema") != MAP_SCHEMA:
                raise QueryError(f"unexpected reply schema {body.get('schema')!r}")
            return [Landmark.from_dict(item) for item in body["landmarks"]]
    finally:
        bus.close()
    raise QueryError(f"no map service answered on {robot!r} within {timeout:g} s (is a run going? --connect?)")


def _query(args: argparse.Namespace) -> int:
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
        print(f"error: {exc}", file=sys.stderr)
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


def export_ply(landmarks: list[Landmark], path: Path, spheres: bool) -> None:
    """Centroids as coloured points, or each landmark as a sphere of its radius, in one PLY file."""
    import numpy as np
    import open3d as o3d

    from services.viz.service import landmark_color

    if spheres:
        mesh = o3d.geometry.TriangleMesh()
        for lm in landmarks:
            sphere = o3d.geometry.TriangleMesh.create_sphere(radius=max(lm.radius, 0.01), resolution=12)
            sphere.translate(np.asarray(lm.centroid, float))
            sphere.paint_uniform_color(np.asarray(landmark_color(lm.id)) / 255.0)
            mesh += sphere
        ok = o3d.io.write_triangle_mesh(str(path), mesh, write_ascii=True)
    else:
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array([lm.centroid for lm in landmarks])
                                                                 .reshape(-1, 3)))
        cloud.colors = o3d.utility.Vector3dVector(np.array([landmark_color(lm.id) for lm in landmarks],
                                                           float).reshape(-1, 3) / 255.0)
        ok = o3d.io.write_point_cloud(str(path), cloud, write_ascii=True)
    if not ok:
        raise OSError(f"could not write {path}")


def _export(args: argparse.Namespace) -> int:
    try:
        landmarks = read_map_json(_map_path(args.map))
    except MessageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    export_ply(landmarks, out, spheres=args.spheres)
    print(f"wrote {len(landmarks)} landmark(s) to {out}", file=sys.stderr)
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
    q.add_argument("--json", action="store_true", help="print a semmap.map/1 JSON document")
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
