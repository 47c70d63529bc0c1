"""What `semmap run` prints when it ends: what was mapped, how good the trajectory is, where the files are, and
what to type next. Built from the run's own output files, so it says exactly what the folder holds."""

from __future__ import annotations

import json
import shlex
from collections import Counter
from pathlib import Path

from semmap.runtime.models.detector_choice import describe_fidelity

SUMMARY_TITLE = "semmap run summary"


def _landmarks(out_dir: Path) -> list[dict] | None:
    try:
        body = json.loads((out_dir / "map.json").read_text())
    except (OSError, json.JSONDecodeError):
        return None
    landmarks = body.get("landmarks") if isinstance(body, dict) else None
    return landmarks if isinstance(landmarks, list) else None


def _ate(out_dir: Path) -> tuple[float, float] | None:
    """(odometry, optimised) ATE RMSE in metres where ground truth and both trajectories exist."""
    if not all(
        (out_dir / f).is_file() for f in ("groundtruth.tum", "trajectory_odometry.tum", "trajectory_optimized.tum")
    ):
        return None
    from semmap.algorithms.evaluation import EvaluationError, evaluate_run  # evo: only when there is something to score

    try:
        result = evaluate_run(out_dir)
    except (EvaluationError, ValueError):
        return None
    return float(result["ate_odometry_m"]), float(result["ate_optimized_m"])


def run_summary(out_dir: Path, stats: dict) -> str:
    """The end-of-run table (plain text, one fact a line) for a finished run folder and its stats.json."""
    out_dir = Path(out_dir)
    lines = [f"{SUMMARY_TITLE} ({stats.get('outcome', '?')}, {stats.get('wall_s', 0):.1f} s)"]
    frames = stats.get("frames", {})
    lines.append(
        f"  frames      {frames.get('processed', 0)} processed of {frames.get('published', 0)} published, "
        f"{frames.get('detected', 0)} detected, {frames.get('dropped', 0)} dropped, "
        f"{frames.get('unreadable', 0)} unreadable; {stats.get('fps', 0):.1f} fps"
    )
    odometry = stats.get("odometry") if isinstance(stats.get("odometry"), dict) else {}
    if odometry.get("simulated"):
        lines.append(f"  odometry    {odometry.get('mode')}: simulated odometry (from ground truth), not a real front "
                     "end: the ATE below measures a drift semmap made itself")
    elif odometry.get("mode"):
        lines.append(f"  odometry    {odometry.get('mode')}")
    skipped = frames.get("skipped") or []
    if skipped:
        lines.append(f"  skipped     {len(skipped)} frame(s), named in {out_dir / 'skipped_frames.json'}:")
        for item in skipped[:10]:
            lines.append(f"    frame {item.get('frame')}: {item.get('reason')}")
        if len(skipped) > 10:
            lines.append(f"    ... and {len(skipped) - 10} more")
    budget = stats.get("detector_budget") or {}
    if budget.get("planned") and budget.get("achieved"):
        p, a = budget["planned"], budget["achieved"]
        lines.append(
            f"  detection   planned: {budget.get('detector')}, every {p['every_n_frames']} frame(s), "
            f"{p['expected_detections_per_s']:.1f}/s; achieved {a['detections_per_s']:.1f}/s of video"
            + (f", detector {a['detect_ms_p50']:.0f} ms p50 in the run" if a.get("detect_ms_p50") else "")
        )
    told = describe_fidelity(budget["fidelity"]) if budget.get("fidelity") else None
    if told:
        lines.append(f"  fidelity    the detector {told}")
    lost = stats.get("source", {}).get("counters", {})
    if lost:  # an external source's own count of frames it lost before semmap (the ROS 2 bridge: by reason)
        reasons = ", ".join(f"{k} {v}" for k, v in sorted(lost.items()) if k != "total" and v)
        total = lost.get("total", 0)
        lines.append(f"  source      {total} frames lost before semmap" + (f": {reasons}" if reasons else ""))
    landmarks = _landmarks(out_dir)
    if landmarks is None:
        lines.append("  landmarks   none (no map.json: the associator did not run)")
    else:
        counts = Counter(str(lm.get("class", "?")) for lm in landmarks)
        lines.append(f"  landmarks   {len(landmarks)}")
        for name, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])):
            lines.append(f"    {name:<16}{n:>4}")
    ate = _ate(out_dir)
    if ate is not None:
        odo, opt = ate
        notes = [f"{100 * (odo - opt) / odo:+.1f} %"] if odo >= 1e-3 else []
        backend = stats.get("services", {}).get("backend", {}).get("counters")
        if isinstance(backend, dict):  # what the backend had to work with: a 0 % gain says why
            observations, loops = int(backend.get("observations", 0)), int(backend.get("loop_registered", 0))
            notes.append("the backend received no landmark observations" if observations == 0
                         else f"from {observations} landmark observations")
            if loops:
                notes.append(f"{loops} loop closure{'s' * (loops != 1)}")
        gain = f" ({', '.join(notes)})" if notes else ""
        lines.append(f"  ATE         odometry {odo:.3f} m -> optimised {opt:.3f} m{gain} (RMSE vs ground truth)")
    repair = repair_line(out_dir, refinement_note(stats))
    if repair:
        lines.append(repair)
    lines.append("  outputs")
    for name, what in (
        ("map.json", "landmarks: class, centroid, extent (world frame, m)"),
        ("run.rrd", "Rerun recording"),
        ("trajectory_optimized.tum", "camera-to-world poses, TUM format"),
    ):
        path = out_dir / name
        if path.is_file():
            lines.append(f"    {path}  ({what})")
    lines.append(f"    {out_dir / 'stats.json'}  (counters, timings), logs in {out_dir / 'logs'}/")
    folder = shlex.quote(str(out_dir))
    commands = []
    if (out_dir / "run.rrd").is_file():
        commands.append((f"semmap view {folder} --web", "look at the map in a browser"))
    if landmarks is not None:
        commands.append((f"semmap query {folder} --near 0,0,0", "landmarks nearest first (also --class, --radius)"))
    if (out_dir / "groundtruth.tum").is_file():
        commands.append((f"semmap eval {folder}", "ATE of both trajectories, written to eval.json"))
    if commands:
        lines.append("  next")
        width = max(len(c) for c, _ in commands)
        lines.extend(f"    {c:<{width}}  # {why}" for c, why in commands)
    return "\n".join(lines)


def refinement_note(stats: dict) -> str:
    """Whether the backend took the SLAM's refinement at its end into semmap's result (its counters; the odometry
    service's where the backend never heard of one: it was not set to wait for a refining front end)."""
    counters, sent = _counters(stats, "backend"), _counters(stats, "odometry").get("refinement_frames")
    if counters.get("odometry_refined_frames"):
        passed_over = counters.get("odometry_refinement_passed_over")
        return (f"taken into semmap's result ({counters['odometry_refined_frames']} frames"
                + (f"; {passed_over} passed over: not in the graph as measured)" if passed_over else ")"))
    if counters.get("odometry_refinement_withheld"):
        return "not taken into semmap's result (why: logs/backend.log)"
    if counters.get("odometry_refinement_timeouts"):
        return "not taken: it did not come in time"
    if sent:
        return (f"not taken: sent ({sent} frames), but the backend was not waiting for it (its odometry.mode is "
                "not the front end's)")
    return ""


def _counters(stats: dict, service: str) -> dict:
    """One service's counters from a run's stats.json ({} where it has none)."""
    services = stats.get("services") if isinstance(stats.get("services"), dict) else {}
    found = next((s for s in services.values() if isinstance(s, dict) and s.get("service") == service), {})
    return found.get("counters") if isinstance(found.get("counters"), dict) else {}


def repair_line(out_dir: Path, refinement: str = "") -> str | None:
    """How often and where semmap overruled the SLAM's steps (odometry_repair.json), one line; `refinement`:
    what became of the SLAM's refinement at its end (`refinement_note`)."""
    import json

    from semmap.core.outputs import REPAIR_REPORT

    try:
        report = json.loads((Path(out_dir) / REPAIR_REPORT).read_text())
        c = report["counters"]
        steps = int(c.get("repair_steps", 0))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    if not steps:
        return None
    replaced = int(c.get("repair_overruled", 0)) + int(c.get("repair_implausible", 0))
    kept = int(c.get("repair_kept", 0))
    spans = report.get("overruled_spans", [])
    where = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in spans[:6]) + (" ..." if len(spans) > 6 else "")
    lines = [f"  repair      {report.get('mode', '?')}: semmap overruled {replaced} of {steps} SLAM steps "
             f"({100 * replaced / steps:.0f} %) where the static scene favoured its own measurement, kept the SLAM's "
             f"step in {kept} other disagreements (weak or contrary evidence), the SLAM had no pose for "
             f"{int(c.get('repair_slam_missing', 0))} (frames it lost are left out of the trajectories, as from its "
             "own)" + (f"; frames {where}" if where else "") + f" ({REPAIR_REPORT})"]
    changed = trajectory_change(Path(out_dir))
    if changed is not None:
        lines.append(f"  changed     semmap moved the SLAM's trajectory by {changed:.3f} m RMS (trajectory_slam.tum -> "
                     "trajectory_optimized.tum, aligned as ATE is)")
    try:
        from semmap.algorithms.evaluation import evaluate_run

        result = evaluate_run(Path(out_dir)) if (Path(out_dir) / "groundtruth.tum").is_file() else {}
        if result.get("ate_slam_m") is not None:
            lines.append(f"  SLAM alone  ATE {result['ate_slam_m']:.3f} m (its own poses, trajectory_slam.tum) -> "
                         f"repaired {result['ate_odometry_m']:.3f} m -> optimised {result['ate_optimized_m']:.3f} m")
        if result.get("ate_slam_refined_m") is not None:
            lines.append(f"              {result['ate_slam_refined_m']:.3f} m as the SLAM refined its own poses at its "
                         "end (trajectory_slam_refined.tum: what it alone would save)"
                         + (f"; {refinement}" if refinement else ""))
    except (ValueError, OSError):
        pass
    return "\n".join(lines)


def trajectory_change(out_dir: Path) -> float | None:
    """How far semmap moved the SLAM's own trajectory: the RMS of the optimised poses against the SLAM's, after the
    same SE(3) alignment ATE uses (so a different world frame is no change), or None without both files."""
    from semmap.algorithms.evaluation import ate_rmse
    from semmap.core.outputs import SLAM_TRAJECTORY
    from semmap.datasets.trajectory_io import read_tum

    try:
        slam, optimized = read_tum(out_dir / SLAM_TRAJECTORY), read_tum(out_dir / "trajectory_optimized.tum")
        return ate_rmse(slam, optimized) if len(slam) >= 3 and len(optimized) >= 3 else None
    except (OSError, ValueError):
        return None
