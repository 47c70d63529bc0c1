"""The ROS 2 path as a robot uses it: camera process -> Fast DDS -> `semmap ros2` -> Zenoh -> `semmap run external`.

    python benchmarks/bench_ros2.py [--frames 150] [--data ../shared/data/7scenes-redkitchen] [--rate 30]
                                    [--configs profile,default] [--lockstep]

Per configuration, fresh processes: a Zenoh router (in this process), `semmap run external`, `semmap ros2`, a
listener node and a camera node (tests/ros2/ros_nodes.py `camera`) that publishes the recording's frames
(640x480 rgb8 + 16UC1 + CameraInfo + Odometry, prepared in memory first) on a clock at `--rate`, best effort
(`--lockstep`: reliable, bridge `lockstep:=true reliable_input:=true`), never waiting for anyone. Reported:
frames the camera sent, colour images the bridge received, frames it sent to semmap, frames semmap processed
(its stats.json), landmarks mapped (and classes), and the bridge's losses by reason (/semmap/bridge_status).
Configurations:
  profile   semmap's Fast DDS profile (shared memory + 4 MB loopback UDP buffers) in the bridge (its default)
            and in the camera (FASTDDS_DEFAULT_PROFILES_FILE), as docs/ROS2.md tells a user to do
  default   Fast DDS defaults on both sides (`semmap ros2 --no-fastdds-profile`, no profile in the camera)
  bridge    the profile in the bridge only (the camera with Fast DDS defaults)
Discovery: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and a ROS domain of its own.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(PROJECT))
NODES = PROJECT / "tests" / "ros2" / "ros_nodes.py"


def _session(data: Path, frames: int, rate: float, config: str, lockstep: bool, work: Path,
             odometry: list[str]) -> dict:
    import zenoh

    from semmap.runtime.orchestrator import free_loopback_port, front_end_posed
    from semmap.runtime.transport.bus import BusConfig

    work.mkdir(parents=True)
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    router = zenoh.open(BusConfig(mode="router", listen=[endpoint]).to_zenoh())
    env = {
        **os.environ,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_DOMAIN_ID": str(150 + os.getpid() % 50),
        "ROS_LOG_DIR": str(work / "roslog"),
        "PYTHONPATH": str(PROJECT),
        "XDG_RUNTIME_DIR": str(work / "runtime"),
        "CI": "true",
    }
    env.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
    profile = work / "fastdds.xml"
    cli = [sys.executable, "-m", "semmap.cli"]
    subprocess.run([*cli, "ros2", "--write-fastdds-profile", str(profile)], env=env, check=True, capture_output=True)
    procs: dict[str, subprocess.Popen] = {}

    def start(name: str, argv: list[str], extra: dict | None = None) -> None:
        procs[name] = subprocess.Popen(
            argv,
            cwd=PROJECT,
            env={**env, **(extra or {})},
            stdout=open(work / f"{name}.log", "w"),  # noqa: SIM115
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )

    out = work / "run"
    listened, sent = work / "listened.json", work / "camera.json"
    started = time.monotonic()
    try:
        zenoh_args = ["--connect", endpoint, "--zenoh-mode", "client"]
        start("run", [*cli, "run", "external", "--out", str(out), "--no-viz", "--quiet", *odometry, *zenoh_args])
        bridge = [*cli, "ros2", *zenoh_args] + (["--no-fastdds-profile"] if config == "default" else [])
        params = ["end_after_idle_s:=3.0"] + (["lockstep:=true", "reliable_input:=true"] if lockstep else [])
        bridge += ["--ros-args", "-r", "/odom:=/slam/odom", *[x for p in params for x in ("-p", p)]]
        start("bridge", bridge)
        start("listener", [sys.executable, str(NODES), "listen", str(listened), "0"])
        deadline = time.monotonic() + 60
        while not listened.with_suffix(".ready").exists():
            if time.monotonic() > deadline:
                raise RuntimeError((work / "bridge.log").read_text()[-2000:])
            time.sleep(0.1)
        camera_env = {"FASTDDS_DEFAULT_PROFILES_FILE": str(profile)} if config == "profile" else {}
        camera = [sys.executable, str(NODES), "camera", str(data), str(frames), str(sent), "--rate", str(rate)]
        start("camera", camera + (["--reliable"] if lockstep else []), camera_env)
        procs["camera"].wait(timeout=600)
        procs["listener"].wait(timeout=900)
        procs["run"].wait(timeout=900)
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT)
        for proc in procs.values():
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
        router.close()
    status = json.loads(listened.read_text())["status"] or {}
    stats = json.loads((out / "stats.json").read_text())
    landmarks = json.loads((out / "map.json").read_text())["landmarks"] if (out / "map.json").exists() else []
    posed = front_end_posed(stats.get("services", {}))
    return {
        "front_end_posed": posed,
        "config": config,
        "camera": json.loads(sent.read_text()),
        "received": status.get("received", {}),
        "frames_sent_to_semmap": status.get("frames_sent"),
        "processed": stats["frames"]["processed"],
        "published_in_stats": stats["frames"]["published"],
        "landmarks": len(landmarks),
        "classes": sorted({lm["class"] for lm in landmarks}),
        "lost": status.get("lost", {}),
        "source_in_stats": stats.get("source", {}).get("counters", {}),
        "wall_s": round(time.monotonic() - started, 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--rate", type=float, default=30.0)
    parser.add_argument("--data", type=Path, default=PROJECT.parent / "shared" / "data" / "7scenes-redkitchen")
    parser.add_argument("--configs", default="profile,default")
    parser.add_argument("--lockstep", action="store_true")
    parser.add_argument("--odometry", default="", help="orbslam3 or rgbd: semmap poses the camera's frames itself "
                        "(`semmap run external --odometry orbslam3`); default: the camera's own odometry")
    parser.add_argument("--realtime", action="store_true", help="`semmap run external --realtime`: keep up with the "
                        "camera, dropping what it cannot (counted), instead of queueing every frame")
    parser.add_argument("--vocabulary", default="", help="with --odometry orbslam3: the ORB vocabulary (default: "
                        "the model directory's orbvoc.txt)")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    parser.add_argument("--keep", type=Path, default=None, help="keep each configuration's run and logs here")
    args = parser.parse_args()
    with open("/proc/loadavg") as f:
        print(f"load average at the start: {' '.join(f.read().split()[:3])}")
    results = []
    with tempfile.TemporaryDirectory(prefix="bench_ros2_") as tmp:
        for config in args.configs.split(","):
            odometry = (["--odometry", args.odometry] if args.odometry else []) + (
                ["--realtime"] if args.realtime else []) + (
                ["--set", f"odometry.orbslam3_vocabulary={args.vocabulary}"] if args.vocabulary else [])
            r = _session(args.data, args.frames, args.rate, config, args.lockstep, (args.keep or Path(tmp)) / config,
                         odometry)
            results.append(r)
            rec = r["received"]
            print(
                f"{config:8} camera sent {r['camera']['sent']} ({r['camera']['late_frames']} late); bridge received "
                f"colour {rec.get('colour', 0)}, depth {rec.get('depth', 0)}, pose {rec.get('pose', 0)}; "
                f"sent to semmap {r['frames_sent_to_semmap']}; processed {r['processed']}; "
                f"landmarks {r['landmarks']} ({', '.join(r['classes'])}); lost {json.dumps(r['lost'])}; "
                + (f"front end posed {r['front_end_posed']} ({r['front_end_posed'] / max(1, r['processed']):.0%} of "
                   "the frames that arrived); " if r["front_end_posed"] is not None else "")
                + f"{r['wall_s']} s",
                flush=True,
            )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
