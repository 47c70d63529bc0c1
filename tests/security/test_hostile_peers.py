"""Hostile peers on an open bus: every kind of forged message, replayed against a live run.

A run joins a router-mode Zenoh process as clients; a hostile peer (tests/security/hostile_peer.py, its own
process) joins the same router and forges controls, statuses, progress, frames with absurd ids, detector
liveliness tokens, tracks, observations with merges, corrected poses and map updates for the whole run. The run
must end as the clean run did (same map, same trajectories), its memory within 20 % of the clean run's, and
every refusal must be counted in stats.json.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

from semmap.core.messages import GroundTruthInstance, Intrinsics
from semmap.datasets import open_dataset
from semmap.runtime.client import SemmapClient

PROJECT = Path(__file__).resolve().parents[2]
DATA = "synthetic:frames=60"


def _run(out: Path, endpoint: str, semmap_run, *extra: str):  # noqa: ANN001, ANN202
    return semmap_run(
        [
            DATA,
            "--out",
            str(out),
            "--no-viz",
            "--odometry",
            "gt+drift",
            "--connect",
            endpoint,
            "--zenoh-mode",
            "client",
            *extra,
        ],
        timeout=400,
    )


def _start_hostile(endpoint: str, *extra: str) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.security.hostile_peer", endpoint, "--seconds", "600", *extra],
        cwd=PROJECT,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "up"
    return proc


def _stop_hostile(proc: subprocess.Popen) -> dict:
    proc.terminate()
    out, _ = proc.communicate(timeout=30)
    return json.loads(out.strip().splitlines()[-1])


def _peak_rss(stats: dict) -> dict[str, float]:
    return {name: s["peak_rss_mb"] for name, s in stats["services"].items() if "peak_rss_mb" in s}


def test_forged_messages_from_every_disguise_change_nothing(
    tmp_path: Path,
    router,
    semmap_run,  # noqa: ANN001
    read_stats,
) -> None:  # noqa: ANN001
    clean = tmp_path / "clean"
    result = _run(clean, router.endpoint, semmap_run)
    assert result.returncode == 0, result.stderr[-3000:]

    hostile = _start_hostile(router.endpoint)
    try:
        attacked = tmp_path / "attacked"
        result = _run(attacked, router.endpoint, semmap_run)
    finally:
        sent = _stop_hostile(hostile)
    assert result.returncode == 0, result.stderr[-3000:]
    assert sent["live_run"], "the hostile peer sniffed the run id (an open bus hides nothing)"
    assert all(sent["sent"].get(k, 0) > 50 for k in ("unsigned", "foreign_run", "bad_signature", "oversize")), sent

    # the same map and trajectories as the clean run
    assert json.loads((attacked / "map.json").read_text()) == json.loads((clean / "map.json").read_text())
    for name in ("trajectory_optimized.tum", "trajectory_odometry.tum"):
        assert (attacked / name).read_text() == (clean / name).read_text(), name
    stats, clean_stats = read_stats(attacked), read_stats(clean)
    assert stats["outcome"] == "completed" and stats["frames"] == clean_stats["frames"]
    assert stats["run_id"] == sent["live_run"]

    # every refusal counted, by reason and key
    rejected = stats["rejected"]
    assert clean_stats["rejected"] == {}, clean_stats["rejected"]
    for counter in (
        "rejected_unsigned[control]",
        "rejected_foreign_run[control]",
        "rejected_bad_signature[control]",
        "rejected_size[control]",
        "rejected_unsigned[frames]",
        "rejected_foreign_run[frames]",
        "rejected_bad_signature[frames]",
        "rejected_unsigned[status/associator/associator]",
        "rejected_bad_signature[status/associator/associator]",
        "rejected_unsigned[progress/backend]",
        "rejected_foreign_run[progress/associator]",
        "rejected_unsigned[tracks]",
        "rejected_foreign_run[tracks]",
        "rejected_bad_signature[tracks]",
        "rejected_unsigned[observations]",
        "rejected_bad_signature[observations]",
        "rejected_unsigned[poses/corrected]",
        "rejected_foreign_run[poses/corrected]",
        "rejected_bad_signature[poses/corrected]",
        "rejected_unsigned[odometry]",
        "rejected_unsigned[detections]",
        "rejected_foreign_replica",
    ):
        assert rejected.get(counter, 0) > 0, (counter, rejected)
    detector = next(s for s in stats["services"].values() if s["service"] == "detector")
    assert detector["counters"]["frames_detected"] == 60  # one replica, not "1 of 2" or "1 of 3"

    # memory within 20 % of the clean run, service by service
    clean_rss, attacked_rss = _peak_rss(clean_stats), _peak_rss(stats)
    for name, mb in attacked_rss.items():
        assert mb <= 1.2 * clean_rss[name], (name, mb, clean_rss[name])


def _feed_external(endpoint: str, frames: int) -> None:
    """An external SLAM: the synthetic frames (with their instances, for the oracle detector) and their poses."""
    dataset = open_dataset(DATA)
    with SemmapClient("robot1", endpoint) as client:
        client.wait_ready(timeout=120)
        for i in range(frames):
            f = dataset[i]
            k = f.intrinsics
            instances = [
                GroundTruthInstance(x.instance_id, x.class_name, tuple(x.box), x.visible_pixels, x.moving)
                for x in f.instances
            ]
            client.publish_frame(
                i,
                f.stamp,
                f.rgb,
                f.depth,
                f.depth_scale,
                Intrinsics(k.fx, k.fy, k.cx, k.cy, k.width, k.height),
                instances,
            )
            client.publish_pose(i, f.stamp, f.gt_pose)
            client.wait_frame_done(i, timeout=120)
        client.end_of_stream(frames - 1)


def _external_run(out: Path, endpoint: str, semmap_run):  # noqa: ANN001, ANN202
    outcome: dict = {}
    runner = threading.Thread(
        target=lambda: outcome.setdefault(
            "run",
            semmap_run(
                [
                    "external",
                    "--out",
                    str(out),
                    "--no-viz",
                    "--connect",
                    endpoint,
                    "--zenoh-mode",
                    "client",
                    "--set",
                    "detector.kind=oracle",
                ],
                timeout=400,
            ),
        )
    )
    runner.start()
    _feed_external(endpoint, 60)
    runner.join(timeout=400)
    return outcome["run"]


def test_an_open_input_run_refuses_absurd_frame_ids_a_foreign_stop_and_a_false_end(
    tmp_path: Path,
    router,  # noqa: ANN001
    semmap_run,
    read_stats,
) -> None:  # noqa: ANN001
    """`semmap run external` takes unsigned frames, poses and end of stream (an external SLAM has no run key):
    the checks behind the signature still hold there."""
    clean = tmp_path / "clean"
    result = _external_run(clean, router.endpoint, semmap_run)
    assert result.returncode == 0, result.stderr[-3000:]

    hostile = _start_hostile(router.endpoint, "--external")
    try:
        attacked = tmp_path / "attacked"
        result = _external_run(attacked, router.endpoint, semmap_run)
    finally:
        sent = _stop_hostile(hostile)
    assert result.returncode == 0, result.stderr[-3000:]
    assert sent["sent"].get("early_eos", 0) > 5 and sent["sent"].get("frame_2^40", 0) > 50, sent
    assert json.loads((attacked / "map.json").read_text()) == json.loads((clean / "map.json").read_text())
    assert (attacked / "trajectory_optimized.tum").read_text() == (clean / "trajectory_optimized.tum").read_text()
    stats, clean_stats = read_stats(attacked), read_stats(clean)
    rejected = stats["rejected"]
    for counter in ("rejected_frame_gap[frames]", "rejected_control[stop]", "rejected_control[end_of_stream]"):
        assert rejected.get(counter, 0) > 0, (counter, rejected)
    for name, mb in _peak_rss(stats).items():
        assert mb <= 1.2 * _peak_rss(clean_stats)[name], name
