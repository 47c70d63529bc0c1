"""`semmap diff A B` and `semmap merge A B --out C`: compare and fuse saved maps (see semmap/algorithms/map_merge.py).

A map argument is a run directory (its map.json, with the landmark clouds of its map.sqlite when present), a
map.json, or a map.sqlite. Unless `--same-frame`, B is registered to A by its objects first; a registration
that is not certain (too few agreeing objects, an ambiguous layout) is an error (exit 2), not a guess. `merge`
then re-optimises B's trajectory in A's frame where B is a run directory (its backend journal replayed with A's
objects and A's run's keyframes: semmap/runtime/maps/map_refit.py), so B's own drift does not go into the merged map;
`--rigid` moves B by the fit alone.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # (the algorithms import scipy: only when a command runs, not for `semmap --help`)
    import numpy as np

    from semmap.algorithms.map_merge import MatchParams
    from semmap.algorithms.relocalize import RelocResult
    from semmap.core.messages import Landmark


def load_map(arg: str | Path) -> tuple[list[Landmark], dict[int, np.ndarray]]:
    """Landmarks (with their status) and, where the map.sqlite is there, each landmark's world cloud."""
    from semmap.core.messages import MessageError
    from semmap.runtime.maps.map_store import MapStore, read_map_json
    path = Path(arg)
    json_path = path / "map.json" if path.is_dir() else (path if path.suffix == ".json" else None)
    db_path = path / "map.sqlite" if path.is_dir() else (path if path.suffix == ".sqlite" else None)
    if json_path is None and db_path is None:
        raise MessageError(f"{path}: expected a run directory, a map.json or a map.sqlite")
    clouds: dict[int, np.ndarray] = {}
    from_db: list[Landmark] = []
    if db_path is not None and db_path.is_file():
        from semmap.algorithms.associator.mapper import LandmarkMapper

        state = MapStore.open_existing(db_path).load()
        if state is not None:
            try:
                mapper = LandmarkMapper.from_state(state)
            except (KeyError, TypeError, ValueError) as exc:
                raise MessageError(f"{db_path}: unreadable map state: {exc}") from None
            from_db = mapper.landmarks()
            clouds = {lm.id: lm.cloud for lm in mapper.map.all() if len(lm.cloud)}
    if json_path is not None and json_path.is_file():
        return read_map_json(json_path), clouds
    if from_db or (db_path is not None and db_path.is_file()):
        return from_db, clouds
    raise MessageError(f"no map at {path} (no map.json or map.sqlite)")


def prior_map_path(arg: str | Path, out_dir: Path) -> Path:
    """The map.sqlite of `semmap run --map ARG`, checked now (exists, this version, holds a map) rather than in
    the associator; ValueError (MessageError) with the reason otherwise."""
    from semmap.core.messages import MessageError
    from semmap.runtime.maps.map_store import MapStore
    path = Path(arg)
    db = path / "map.sqlite" if path.is_dir() else path
    if db.suffix != ".sqlite":
        raise MessageError(f"--map {arg}: expected a run directory or its map.sqlite")
    if db.resolve() == (out_dir / "map.sqlite").resolve():
        raise MessageError(
            f"--map {arg} is the output directory's own map, which a new run replaces: use another --out"
        )
    if MapStore.open_existing(db).load() is None:
        raise MessageError(f"--map {arg}: {db} holds no map")
    return db.resolve()


def _map_db(arg: str | Path) -> Path | None:
    """The map.sqlite of a map argument (a run directory, its map.json or map.sqlite), where there is one."""
    path = Path(arg)
    db = path / "map.sqlite" if path.is_dir() else (path if path.suffix == ".sqlite" else path.parent / "map.sqlite")
    return db if db.is_file() else None


def _registered(
    args: argparse.Namespace, refit: bool = False,
) -> tuple[list[Landmark], list[Landmark], RelocResult | None, dict[int, np.ndarray], dict[int, np.ndarray]]:
    """A, B in A's frame, the fit, and both maps' clouds (B's in A's frame). `refit`: B's trajectory re-optimised
    in A's frame where B's run holds its backend journal (semmap/runtime/maps/map_refit.py), else B moved rigidly."""
    from semmap.algorithms.map_merge import register as register_maps
    from semmap.algorithms.map_merge import transform_landmark
    from semmap.algorithms.relocalize import RelocParams, apply
    from semmap.core.messages import MessageError

    a, clouds_a = load_map(args.a)
    b, clouds_b = load_map(args.b)
    if args.same_frame:
        return a, b, None, clouds_a, clouds_b
    b_db = _map_db(args.b) if refit else None
    attempt = register_maps(a, b, clouds_a, clouds_b, refit=b_db is not None)
    if attempt.result is None:
        raise MessageError(
            f"cannot register {args.b} to {args.a} by their objects: {attempt.reason} "
            "(--same-frame if they share a frame)"
        )
    T = attempt.result.transform
    moved = {i: apply(T, c) for i, c in clouds_b.items()}
    rigid = [transform_landmark(lm, T) for lm in b]
    if b_db is None:
        return a, rigid, attempt.result, clouds_a, moved
    from msgspec.structs import replace

    from semmap.runtime.maps.map_refit import refit_run

    result = refit_run(b_db, _map_db(args.a), attempt.result, a)
    if isinstance(result, str):
        limit = RelocParams().max_rotation_sigma_deg
        if attempt.result.rotation_sigma_deg > limit:  # what the re-optimisation would have settled: not certain
            raise MessageError(
                f"cannot register {args.b} to {args.a} by their objects alone: the fit's rotation is uncertain by "
                f"{attempt.result.rotation_sigma_deg:.1f} deg (> {limit} deg) and B's trajectory could not be "
                f"re-optimised in A's frame ({result}); (--same-frame if they share a frame)"
            )
        print(f"B moved by the objects' fit alone (its trajectory not re-optimised: {result})", file=sys.stderr)
        return a, rigid, attempt.result, clouds_a, moved
    print(f"B's trajectory re-optimised in A's frame: {result.frames} frames, {result.closures_to_a} of its "
          f"keyframes registered to A's {result.prior_keyframes}"
          + (f", {result.skipped} journal rows unreadable (skipped)" if result.skipped else ""), file=sys.stderr)
    # B's landmarks as its map lists them (ids, status, counts), each where the re-optimised views put it
    refitted = {lm.id: lm for lm in result.landmarks}
    placed = [replace(lm, centroid=refitted[lm.id].centroid, extent=refitted[lm.id].extent,
                      radius=refitted[lm.id].radius) if lm.id in refitted else moved_lm
              for lm, moved_lm in zip(b, rigid, strict=True)]
    clouds = {i: result.clouds.get(i, c) for i, c in moved.items()}
    return a, placed, attempt.result, clouds_a, clouds


def _fit_line(fit: RelocResult | None) -> str:
    if fit is None:
        return "frames: taken as the same (--same-frame)"
    t = fit.translation
    return (
        f"registered B to A by {fit.inliers} objects: translation ({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) m, "
        f"rotation {fit.rotation_deg:.2f} deg, residual {fit.rms_m * 100:.1f} cm"
        f"{', refined on clouds' if fit.refined else ''}; best alternative {fit.runner_up} objects"
    )


def _fit_json(fit: RelocResult | None) -> dict | None:
    if fit is None:
        return None
    return {
        "transform": [round(float(v), 6) for v in fit.transform.reshape(16)],
        "inliers": fit.inliers,
        "rms_m": round(fit.rms_m, 4),
        "runner_up": fit.runner_up,
        "refined": fit.refined,
        "matches": [list(m) for m in fit.matches],
    }


def _at(lm: Landmark) -> str:
    return "(" + ", ".join(f"{v:.2f}" for v in lm.centroid) + ")"


def _params(args: argparse.Namespace) -> MatchParams:
    from semmap.algorithms.map_merge import MatchParams

    defaults = MatchParams()
    return MatchParams(gate_m=defaults.gate_m if args.gate is None else args.gate,
                       moved_m=defaults.moved_m if args.moved is None else args.moved)


def _diff(args: argparse.Namespace) -> int:
    from semmap.core.messages import MessageError
    try:
        a, b, fit, _, _ = _registered(args)
    except MessageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from semmap.algorithms.map_merge import diff_maps

    d = diff_maps(a, b, _params(args))
    if args.json:
        print(json.dumps({"registration": _fit_json(fit), **d.to_json()}, indent=1))
        return 0
    print(_fit_line(fit))
    for x, y in d.moved:
        print(f"moved    {x.class_name:<14} #{x.id} -> #{y.id}  {math.dist(x.centroid, y.centroid):.2f} m  to {_at(y)}")
    for lm in d.missing:
        print(f"missing  {lm.class_name:<14} #{lm.id}  at {_at(lm)}")
    for lm in d.added:
        print(f"added    {lm.class_name:<14} #{lm.id}  at {_at(lm)}")
    print(
        f"{len(d.kept)} kept, {len(d.moved)} moved, {len(d.missing)} missing, {len(d.added)} added, "
        f"{len(d.unseen)} not looked at again"
    )
    return 0


def _merge(args: argparse.Namespace) -> int:
    from semmap.core.messages import MessageError
    try:
        a, b, fit, clouds_a, clouds_b = _registered(args, refit=not args.rigid)
    except MessageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from semmap.algorithms.map_merge import merge_maps
    from semmap.runtime.maps.map_store import write_map_json

    merged = merge_maps(a, b, _params(args), clouds_a, clouds_b)
    out = Path(args.out)
    target = out / "map.json" if out.suffix != ".json" else out
    target.parent.mkdir(parents=True, exist_ok=True)
    write_map_json(target, merged)
    print(_fit_line(fit), file=sys.stderr)
    print(f"wrote {len(merged)} landmarks ({len(a)} from A, {len(b)} from B) to {target}", file=sys.stderr)
    return 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("a", help="map A: a run directory, map.json or map.sqlite (the reference frame)")
    p.add_argument("b", help="map B: a run directory, map.json or map.sqlite")
    p.add_argument("--same-frame", action="store_true", help="the maps share a frame: do not register B to A")
    p.add_argument(
        "--gate",
        type=float,
        default=None,
        help="same object if same class and centres this close, metres (default: MatchParams.gate_m of "
        "semmap/algorithms/map_merge.py; half the larger radius if that is more)",
    )
    p.add_argument(
        "--moved",
        type=float,
        default=None,
        help="report a paired object as moved beyond this, metres (default: MatchParams.moved_m)",
    )


MAP_ARGUMENTS = ("A map argument is a run directory (its map.json, with the landmark clouds of its map.sqlite when "
                 "present), a map.json, or a map.sqlite.")
DIFF_TEXT = f"""`semmap diff A B`: the objects added, missing and moved from map A to map B (e.g. two days of one room).

{MAP_ARGUMENTS} Unless `--same-frame`, B is registered to A by its objects first; a registration that is not
certain (too few agreeing objects, an ambiguous layout) is an error (exit 2), not a guess.
"""
MERGE_TEXT = f"""`semmap merge A B --out C`: register map B to map A by their objects and fuse them into one map
in A's frame.

{MAP_ARGUMENTS} Unless `--same-frame`, B is registered to A by its objects first; a registration that is not
certain is an error (exit 2), not a guess. Where B is a run directory, its trajectory is then re-optimised in A's
frame (its backend journal replayed with A's objects and A's run's keyframes: semmap/runtime/maps/map_refit.py), so B's
own drift does not go into the merged map; `--rigid` moves B by the fit alone.
"""


def register(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser(
        "diff",
        help="objects added, missing and moved between two saved maps",
        description=DIFF_TEXT,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _common(d)
    d.add_argument("--json", action="store_true", help="print the differences as JSON")
    d.set_defaults(func=_diff)
    m = sub.add_parser(
        "merge",
        help="register two maps by their objects and fuse them into one (A's frame)",
        description=MERGE_TEXT,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _common(m)
    m.add_argument("--out", required=True, help="output directory (writes OUT/map.json) or .json file")
    m.add_argument("--rigid", action="store_true",
                   help="move B by the objects' fit alone; by default, where B is a run directory, its trajectory "
                   "is re-optimised in A's frame first (its keyframes registered to A's run's), which removes B's "
                   "own drift")
    m.set_defaults(func=_merge)
