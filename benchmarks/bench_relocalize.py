"""Cost of one relocalisation attempt against prior maps of growing size.

    python benchmarks/bench_relocalize.py [--sizes 10,100,300,1000,3000] [--query 8] [--repeats 5] [--clouds]

A prior map of N landmarks (20 classes, a building of 1 landmark per ~2 m^2 of floor, 0-2 m high; the floor
grows with N so the local density stays that of a furnished room), and a new session that has validated
`--query` landmarks of one room of it (5 cm centroid noise, a random rigid transform of a few metres and tens
of degrees) plus 2 distractors that the prior map does not have. Prints, per N: the time to index the prior
map (once per map), ms per attempt (p50 / max), hypotheses tried, how many answers
were within 10 cm (at the session's landmarks) and 3 degrees, and how many paired a landmark with the wrong
prior one. `--clouds` gives every landmark a 300-point cloud and includes the ICP refinement.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semmap.algorithms.relocalize import MapObject, PriorIndex, apply, relocalize, rotation_angle_deg  # noqa: E402

CLASSES = [f"class{i}" for i in range(20)]


def _cloud(rng: np.random.Generator, centre: np.ndarray, size: float, n: int = 300) -> np.ndarray:
    half = np.array([size, 0.7 * size, 1.2 * size]) / 2
    pts = rng.uniform(-1, 1, (n, 3)) * half
    face = rng.integers(0, 3, n)
    pts[np.arange(n), face] = np.sign(pts[np.arange(n), face]) * half[face]
    return centre + pts


def prior_map(rng: np.random.Generator, n: int, clouds: bool) -> list[MapObject]:
    side = math.sqrt(2.0 * n)
    out = []
    for i in range(n):
        c = rng.uniform([0, 0, 0], [side, side, 2.0])
        out.append(
            MapObject(
                i,
                CLASSES[int(rng.integers(len(CLASSES)))],
                c,
                _cloud(rng, c, rng.uniform(0.1, 0.6)) if clouds else None,
            )
        )
    return out


def session(
    rng: np.random.Generator, prior: list[MapObject], k: int
) -> tuple[list[MapObject], np.ndarray, dict[int, int]]:
    """k landmarks nearest a random prior landmark (one room), seen in another frame, plus 2 distractors."""
    centroids = np.array([o.centroid for o in prior])
    centre = centroids[int(rng.integers(len(prior)))]
    near = np.argsort(np.linalg.norm(centroids - centre, axis=1))[:k]
    T = np.eye(4)
    axis = rng.normal(size=3)
    T[:3, :3] = Rotation.from_rotvec(math.radians(rng.uniform(10, 60)) * axis / np.linalg.norm(axis)).as_matrix()
    T[:3, 3] = rng.uniform(-4, 4, 3)
    inv = np.linalg.inv(T)
    query = []
    for j, i in enumerate(near):
        o = prior[int(i)]
        query.append(
            MapObject(
                10_000 + j,
                o.class_name,
                apply(inv, o.centroid[None])[0] + rng.normal(0, 0.05, 3),
                None if o.cloud is None else apply(inv, o.cloud),
            )
        )
    for j in range(2):
        query.append(MapObject(20_000 + j, CLASSES[j], apply(inv, (centre + rng.uniform(-2, 2, 3))[None])[0]))
    return query, T, {10_000 + j: int(i) for j, i in enumerate(near)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="10,100,300,1000,3000")
    ap.add_argument("--query", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--clouds", action="store_true")
    args = ap.parse_args()
    print(
        f"query: {args.query} landmarks + 2 distractors; {args.repeats} sessions per size; "
        f"clouds: {'yes' if args.clouds else 'no'}"
    )
    print(
        f"{'prior N':>8} {'index ms':>9} {'attempt p50 ms':>15} {'max ms':>8} {'hypotheses p50':>15} "
        f"{'answered':>9} {'within 10 cm, 3 deg':>20} {'wrong matches':>14}"
    )
    for n in (int(s) for s in args.sizes.split(",")):
        rng = np.random.default_rng(n)
        prior = prior_map(rng, n, args.clouds)
        t0 = time.perf_counter()
        index = PriorIndex(prior)
        index_ms = (time.perf_counter() - t0) * 1e3
        times, hyps, answered, right, wrong = [], [], 0, 0, 0
        for _ in range(args.repeats):
            query, truth, true_ids = session(rng, prior, min(args.query, n))
            t0 = time.perf_counter()
            attempt = relocalize(query, index)
            times.append((time.perf_counter() - t0) * 1e3)
            hyps.append(attempt.hypotheses)
            if attempt.result is not None:
                answered += 1
                # error where the session is (its landmarks), not at its frame's distant origin
                pts = np.array([o.centroid for o in query])
                err = np.linalg.norm(apply(attempt.result.transform, pts) - apply(truth, pts), axis=1).max()
                D = np.linalg.inv(truth) @ attempt.result.transform
                right += err < 0.1 and rotation_angle_deg(D[:3, :3]) < 3.0
                wrong += any(true_ids.get(q) != p for q, p in attempt.result.matches)
        print(
            f"{n:>8} {index_ms:>9.1f} {np.median(times):>15.1f} {max(times):>8.1f} {np.median(hyps):>15.0f} "
            f"{answered:>6}/{args.repeats} {right:>17}/{args.repeats} {wrong:>11}/{args.repeats}"
        )


if __name__ == "__main__":
    main()
