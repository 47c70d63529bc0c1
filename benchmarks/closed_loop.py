"""Closed-loop harness: the services' per-frame loop in one process, without a bus, on cached detections.

    python benchmarks/closed_loop.py DATA [--odometry gt+drift] [--seed N] [--frames N] [--set sec.key=val]...
        [--refresh-cache] [--cache-dir DIR] [--json-out FILE] [-v]

DATA is a dataset folder (e.g. ../shared/data/7scenes-redkitchen) or `synthetic[:frames=N,seed=S]`.

What it reproduces, frame by frame, in the order of a lockstep `semmap run`:
  odometry(i) (the real front end from services/odometry/frontends.py)
  -> tracker(i) (the real IouTracker; skipped frames only age tracklets)
  -> mapper.process(i) against the associator's `PoseBook` (corrected poses where known, odometry moved by
     the newest correction otherwise)
  -> backend: odometry(i), then the merges held back from the previous frame's refine plus this frame's
     merges and observations, one iSAM2 update (the real `PoseGraph`)
  -> `PoseBook.set_corrected` with the backend's whole corrected trajectory
  -> every `refine_every_n_frames` frames `mapper.refine(poses, stamp)`; its merges go to the backend with the
     next frame's observations.
Configuration comes from semmap/config/default.yaml with the same `--set` overrides as `semmap run`.

Detections are what the detector service would publish: the player's frame message (RGB through JPEG q90,
as on the bus), the ONNX detector (or the oracle on synthetic data), `depth_gate` and the strided depth
patches. They are computed once per (data, frames, detector settings) and cached as msgpack under
`.cache/closed_loop/` (never committed); `rgbd` odometry poses are cached the same way.

Reports ATE (evo, `semmap.evaluation.ate_rmse`) of the odometry and of the optimised trajectory, landmarks,
observations sent and used, merges, and run times. Seconds instead of the pipeline's minutes.
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semmap.config import load_config, validate_sections  # noqa: E402
from semmap.datasets import open_dataset  # noqa: E402
from semmap.datasets.base import ObjectTruth  # noqa: E402
from semmap.evaluation import ate_rmse  # noqa: E402
from semmap.messages import (  # noqa: E402
    CorrectedPoses,
    Detections,
    Observations,
    OdometryPose,
)
from services.associator.mapper import LandmarkMapper, MapperParams  # noqa: E402
from services.associator.service import SERVICE_DEFAULTS, PoseBook  # noqa: E402
from services.backend.corrections import CorrectionPublisher, CorrectionsParams  # noqa: E402
from services.backend.loop_closure import LoopCloser, LoopClosureParams  # noqa: E402
from services.backend.pose_graph import BackendParams, PoseGraph  # noqa: E402
from services.odometry.frontends import OdometryInput, make_frontend  # noqa: E402
from services.tracker.iou_tracker import IouTracker, TrackerParams  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CACHE_DIR = ROOT / ".cache" / "closed_loop"
CACHE_VERSION = 1
ROBOT = "robot1"


# ------------------------------------------------------------------------------------------------ inputs


@dataclass
class Recording:
    """What the loop needs from a dataset: each frame's detector answer and ground truth."""

    name: str
    detections: list[Detections]
    gt: list[np.ndarray | None]
    objects: list[ObjectTruth] = field(default_factory=list)

    @property
    def stamps(self) -> list[float]:
        return [d.stamp for d in self.detections]


def _is_synthetic(data: str) -> bool:
    return data == "synthetic" or data.startswith("synthetic:")


def _cache_key(*parts: object) -> str:
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


@functools.lru_cache(maxsize=2)
def _open(data: str):  # noqa: ANN202 - a semmap Dataset
    """Opened once per run (the synthetic scene builds its meshes on opening)."""
    return open_dataset(data)


def _frame_count(ds, frames: int) -> int:  # noqa: ANN001
    return min(len(ds), frames) if frames > 0 else len(ds)


def detect_recording(data: str, frames: int, config: dict, cache_dir: Path = CACHE_DIR, refresh: bool = False,
                     verbose: bool = True) -> Recording:
    """Every frame's `Detections` as the detector service makes them (cached; see module docstring)."""
    from services.associator.offline import make_detections
    from services.player.service import frame_message

    det_cfg = dict(config["detector"])
    synthetic = _is_synthetic(data)
    kind = det_cfg["kind"] if det_cfg["kind"] != "auto" else ("oracle" if synthetic else "onnx")
    ds = _open(data)
    n = _frame_count(ds, frames)
    model = None
    if kind == "onnx":
        from services.detector.model_store import packaged_model

        model = Path(det_cfg["model"] or packaged_model(det_cfg["precision"]))
    model_id = None if model is None else (str(model), model.stat().st_size, int(model.stat().st_mtime))
    # the model file stands for `precision`; threads and queueing do not change detections
    key = _cache_key(CACHE_VERSION, str(Path(data).resolve()) if not synthetic else data, n, kind, model_id,
                     {k: det_cfg[k] for k in sorted(det_cfg) if k not in ("threads", "queue", "precision")})
    path = cache_dir / f"detections-{key}.msgpack"
    objects = ds.objects()
    if path.is_file() and not refresh:
        raw = msgpack.unpackb(path.read_bytes(), raw=False)
        dets = [Detections.decode(b) for b in raw["detections"]]
        gt = [None if g is None else np.array(g, dtype=np.float64).reshape(4, 4) for g in raw["gt"]]
        return Recording(raw["name"], dets, gt, objects)

    if kind == "oracle":
        from services.detector.oracle import OracleDetector

        oracle = OracleDetector(seed=int(det_cfg["oracle_seed"]), miss_rate=det_cfg["oracle_miss_rate"],
                                false_positive_rate=det_cfg["oracle_false_positive_rate"],
                                confusion_rate=det_cfg["oracle_confusion_rate"])
        onnx = None
    else:
        from services.detector.onnx_detector import OnnxDetector

        onnx = OnnxDetector(model, conf=det_cfg["confidence"], iou=det_cfg["iou"], threads=int(det_cfg["threads"]),
                            allow=set(det_cfg["classes"]) or None, deny=set(det_cfg["exclude"]) or None,
                            names=det_cfg["names"] or None)
    allow, deny = set(det_cfg["classes"]), set(det_cfg["exclude"])
    every = max(1, int(det_cfg["every_n_frames"]))
    stride = max(1, int(det_cfg["depth_patch_stride"]))
    dets, gt = [], []
    t0 = time.perf_counter()
    for i in range(n):
        data_i = ds[i]
        frame = on_the_wire(frame_message(ROBOT, data_i))
        gt.append(frame.gt_pose)
        if i % every:
            dets.append(Detections(ROBOT, i, frame.stamp, frame.intrinsics, frame.depth_scale, [], "stride"))
            continue
        if onnx is None:
            boxes = oracle.detect(frame.frame_id, frame.instances, frame.intrinsics.width, frame.intrinsics.height)
            boxes = [b for b in boxes if (not allow or b.class_name in allow) and b.class_name not in deny]
        else:
            boxes = onnx.detect(frame.rgb())
        # depth travels raw: the dataset's array is what the subscriber decodes
        detections = make_detections(data_i, boxes, stride, det_cfg["depth_min_m"], det_cfg["depth_max_m"])
        dets.append(Detections(ROBOT, i, frame.stamp, frame.intrinsics, frame.depth_scale, detections))
        if verbose and (i + 1) % 100 == 0:
            print(f"  detected {i + 1}/{n} frames ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    encoded = [d.encode() for d in dets]
    dets = [Detections.decode(b) for b in encoded]  # exactly what a subscriber decodes
    cache_dir.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(msgpack.packb({"name": ds.name, "detections": encoded,
                                   "gt": [None if g is None else np.asarray(g).reshape(16).tolist() for g in gt]},
                                  use_bin_type=True))
    tmp.replace(path)
    return Recording(ds.name, dets, gt, objects)


def on_the_wire(frame):  # noqa: ANN001, ANN201 - the frame as a subscriber decodes it
    from semmap.messages import Frame

    return Frame.decode(frame.encode())


def rgbd_poses(data: str, frames: int, config: dict, cache_dir: Path = CACHE_DIR, refresh: bool = False,
               verbose: bool = True) -> list[np.ndarray]:
    """The `rgbd` front end's poses for every frame (Open3D, slow: cached)."""
    from services.player.service import frame_message

    ds = _open(data)
    n = _frame_count(ds, frames)
    cfg = config["odometry"]
    code = hashlib.sha1(Path(make_frontend.__code__.co_filename).read_bytes()).hexdigest()  # the front end's code
    key = _cache_key(CACHE_VERSION, "rgbd", str(Path(data).resolve()), n, code,
                     {k: v for k, v in cfg.items() if k.startswith("rgbd_")})
    path = cache_dir / f"rgbd-{key}.npy"
    if path.is_file() and not refresh:
        return list(np.load(path))
    front = make_frontend("rgbd", cfg)
    poses = []
    t0 = time.perf_counter()
    for i in range(n):
        frame = on_the_wire(frame_message(ROBOT, ds[i]))
        poses.append(front.estimate(OdometryInput(i, frame.stamp, frame.gt_pose, frame.rgb(), frame.depth(),
                                                  frame.depth_scale, frame.intrinsics.matrix)))
        if verbose and (i + 1) % 100 == 0:
            print(f"  rgbd odometry {i + 1}/{n} frames ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    cache_dir.mkdir(parents=True, exist_ok=True)
    np.save(path, np.stack(poses))
    return poses


# ------------------------------------------------------------------------------------------------ the loop


@dataclass
class LoopResult:
    ate_odometry: float
    ate_optimized: float
    landmarks: int
    observations: int  # sent by the mapper
    observation_factors: int  # that became factors in the graph
    graph_landmarks: int
    merges: int
    frames: int
    wall_s: float
    classes: dict[str, int]
    mapper_ms_p50: float = 0.0  # mapper.process (+ refine) per frame
    loop_closures: dict[str, int] = field(default_factory=dict)  # the backend's loop closer's counters
    backend_ms_p50: float = 0.0  # odometry + observations + iSAM2 update per frame
    mapper: LandmarkMapper | None = None
    optimized: list[tuple[float, np.ndarray]] = field(default_factory=list)

    @property
    def improvement_pct(self) -> float:
        return 100.0 * (self.ate_odometry - self.ate_optimized) / max(self.ate_odometry, 1e-12)

    def summary(self) -> dict:
        return {"ate_odometry_m": self.ate_odometry, "ate_optimized_m": self.ate_optimized,
                "improvement_pct": self.improvement_pct, "landmarks": self.landmarks,
                "observations": self.observations, "observation_factors": self.observation_factors,
                "graph_landmarks": self.graph_landmarks, "merges": self.merges, "frames": self.frames,
                "wall_s": self.wall_s, "mapper_ms_p50": self.mapper_ms_p50, "backend_ms_p50": self.backend_ms_p50,
                "classes": self.classes, "loop_closures": self.loop_closures}


def run_loop(rec: Recording, config: dict, odometry: str, odometry_poses: list[np.ndarray] | None = None,
             verbose: bool = False, depth_frames=None) -> LoopResult:  # noqa: ANN001 - a semmap Dataset
    """The services' lockstep loop (see module docstring) over a recording. `depth_frames` (the dataset)
    feeds the backend's loop closer with keyframe depth, as the frames key does in the services."""
    t_start = time.perf_counter()
    odo_cfg = dict(config["odometry"])
    front = make_frontend(odometry, odo_cfg)  # with cached poses only for what it declares
    sigma_t, sigma_r = front.sigmas
    keyframe_every = max(1, int(odo_cfg["keyframe_every"]))
    section = dict(config.get("associator") or {})
    service_cfg = {k: section.pop(k, v) for k, v in SERVICE_DEFAULTS.items()}
    refine_every = max(1, int(service_cfg["refine_every_n_frames"]))
    mapper = LandmarkMapper(MapperParams.from_dict(section))
    tracker = IouTracker(TrackerParams(**config["tracker"]))
    graph = PoseGraph(BackendParams.from_config(config.get("backend")))
    closer = LoopCloser(LoopClosureParams.from_config(config.get("loop_closure")))
    corrections = CorrectionPublisher(CorrectionsParams.from_config(config.get("corrections")))
    poses = PoseBook()
    pending_merges: list[tuple[int, int]] = []
    n_obs = n_merges = 0
    odo_traj = []
    mapper_ms, backend_ms = [], []
    for seq, det in enumerate(rec.detections, start=1):
        i, stamp = det.frame_id, det.stamp
        # odometry
        if odometry_poses is not None:
            pose = np.asarray(odometry_poses[i], dtype=np.float64)
        else:
            pose = front.estimate(OdometryInput(i, stamp, rec.gt[i], depth_scale=det.depth_scale,
                                                intrinsics=det.intrinsics.matrix))
        odo = OdometryPose(ROBOT, i, stamp, pose, keyframe=i % keyframe_every == 0, sigma_translation=sigma_t,
                           sigma_rotation=sigma_r, source=odometry)
        odo_traj.append((stamp, pose.copy()))
        poses.odometry[i] = odo.pose
        # tracker (as services/tracker/service.py: a skipped frame only ages tracklets, which may end them)
        if det.skipped:
            ended = tracker.skip(i, stamp).ended if det.stamp >= 0 else []
            candidates, boxes = [], []
        else:
            out = tracker.update(i, stamp, det.detections, det.intrinsics, det.depth_scale)
            candidates, ended, boxes = out.candidates, out.ended, out.boxes
        # associator
        t0 = time.perf_counter()
        step = mapper.process(i, stamp, candidates, ended, poses, boxes=boxes)
        mapper_ms.append((time.perf_counter() - t0) * 1e3)
        merges = pending_merges + list(step.merges)
        pending_merges = []
        n_obs += len(step.observations)
        n_merges += len(merges)
        obs_msg = Observations(ROBOT, i, stamp, step.observations, merges)
        # backend
        t0 = time.perf_counter()
        graph.add_odometry_message(odo)
        graph.add_observations_message(obs_msg)
        graph.update()
        if depth_frames is not None and closer.wants(i):
            frame = depth_frames[i]
            k = frame.intrinsics
            closer.close(graph, closer.cloud_from_depth(i, stamp, frame.depth, frame.depth_scale, k.fx, k.fy, k.cx,
                                                        k.cy))
        backend_ms.append((time.perf_counter() - t0) * 1e3)
        delta = corrections.next(graph)  # the deltas the backend service sends
        poses.set_corrected(CorrectedPoses(ROBOT, seq, i, *delta.arrays(), full=delta.full,
                                           num_frames=delta.num_frames))
        # associator, after the backend's answer
        if i % refine_every == 0 and len(mapper.landmarks()) > 0:
            t0 = time.perf_counter()
            refined = mapper.refine(poses, stamp)
            mapper_ms[-1] += (time.perf_counter() - t0) * 1e3
            pending_merges += list(refined.merges)
        if verbose and (i + 1) % 100 == 0:
            print(f"  frame {i + 1}: {len(mapper.landmarks())} landmarks, {n_obs} observations "
                  f"({time.perf_counter() - t_start:.0f} s)", file=sys.stderr)
    ids, stamps, corrected = graph.corrected_poses()
    optimized = [(float(t), p) for t, p in zip(stamps, corrected, strict=True)]
    gt = [(s, g) for s, g in zip(rec.stamps, rec.gt, strict=True) if g is not None]
    landmarks = mapper.landmarks()
    return LoopResult(
        ate_odometry=ate_rmse(gt, odo_traj), ate_optimized=ate_rmse(gt, optimized), landmarks=len(landmarks),
        observations=n_obs, observation_factors=graph.counters["observation_factors"],
        graph_landmarks=graph.num_landmarks, merges=n_merges, frames=len(rec.detections),
        wall_s=time.perf_counter() - t_start, classes=dict(Counter(lm.class_name for lm in landmarks)),
        mapper=mapper, optimized=optimized, mapper_ms_p50=float(np.median(mapper_ms)) if mapper_ms else 0.0,
        loop_closures=dict(closer.counters), backend_ms_p50=float(np.median(backend_ms)) if backend_ms else 0.0)


def closed_loop(data: str, odometry: str = "gt+drift", seed: int = 0, frames: int = 0,
                overrides: list[str] | None = None, cache_dir: Path = CACHE_DIR, refresh: bool = False,
                verbose: bool = False) -> tuple[LoopResult, Recording]:
    """Load config (defaults + overrides, as `semmap run`), detections (cached) and run the loop."""
    over = [*(overrides or []), f"odometry.mode={odometry}", f"odometry.seed={seed}"]
    config = load_config(None, over)
    validate_sections(config)
    rec = detect_recording(data, frames, config, cache_dir, refresh, verbose)
    odo_poses = rgbd_poses(data, frames, config, cache_dir, refresh, verbose) if odometry == "rgbd" else None
    return run_loop(rec, config, odometry, odo_poses, verbose, depth_frames=_open(data)), rec


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data")
    ap.add_argument("--odometry", default="gt+drift")
    ap.add_argument("--seed", type=int, default=0, help="seed of the drifting odometry")
    ap.add_argument("--seeds", default=None, help="several seeds, comma-separated (overrides --seed)")
    ap.add_argument("--frames", type=int, default=0, help="0 = all")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--cache-dir", type=Path, default=CACHE_DIR)
    ap.add_argument("--refresh-cache", action="store_true")
    ap.add_argument("--json-out", type=Path, default=None)
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args(argv)

    seeds = [int(s) for s in args.seeds.split(",")] if args.seeds else [args.seed]
    rows = []
    for seed in seeds:
        res, rec = closed_loop(args.data, args.odometry, seed, args.frames, args.overrides, args.cache_dir,
                               args.refresh_cache, args.verbose)
        row = {"data": args.data, "odometry": args.odometry, "seed": seed, **res.summary()}
        if rec.objects:
            from services.associator.offline import score_map

            score = score_map(res.mapper.landmarks(), rec.objects)
            row.update(recall=score.recall, duplicates=score.duplicates, false_landmarks=score.false_landmarks,
                       on_moving=score.on_moving, median_centroid_error_m=score.median_error)
        rows.append(row)
        extra = ""
        if "on_moving" in row:
            extra = (f"  recall {row['recall']:.2f} dup {row['duplicates']} false {row['false_landmarks']} "
                     f"on_moving {row['on_moving']}")
        print(f"{args.odometry:9s} seed {seed}: ATE odometry {res.ate_odometry:.4f} m, optimised "
              f"{res.ate_optimized:.4f} m ({res.improvement_pct:+.1f} %), landmarks {res.landmarks}, observations "
              f"{res.observations} ({res.observation_factors} factors, {res.graph_landmarks} in graph), merges "
              f"{res.merges}, loop closures {res.loop_closures.get('accepted', 0)}/"
              f"{res.loop_closures.get('registered', 0)}, {res.wall_s:.0f} s{extra}", flush=True)
    if args.json_out is not None:
        args.json_out.parent.mkdir(parents=True, exist_ok=True)
        args.json_out.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
