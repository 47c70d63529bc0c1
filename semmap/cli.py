"""The `semmap` command: run the pipeline, fetch models, detect, evaluate, view and query maps."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from semmap.config import ConfigError, load_config, validate_sections
from semmap.outputs import OutputError, OutputLock, check_writable, prepare_output_dir
from semmap.service import configure_logging

if TYPE_CHECKING:
    from semmap.datasets.base import Dataset

# services a run starts, in data-flow order; each is `python -m services.<name>`
PIPELINE = ("odometry", "detector", "tracker", "associator", "backend", "viz")


def pipeline_specs(data: str, config: dict, detectors: int, viz: bool, only: list[str] | None = None,
                   serve: bool = False, prior_map: Path | None = None) -> list:
    """What `semmap run` starts: every stage (or `only` these), the detector `detectors` times, the Rerun sink
    unless disabled."""
    from semmap.orchestrator import ServiceSpec

    synthetic = data == "synthetic" or data.startswith("synthetic:")
    chosen = [n for n in PIPELINE if (only is None or n in only) and not (data == "external" and n == "odometry")]
    specs = []
    for name in chosen:
        if name == "viz" and not (viz and config["viz"]["enabled"]):
            continue
        extra: list[str] = []
        if name == "detector" and config["detector"]["kind"] == "auto":
            extra = ["--set", f"detector.kind={'oracle' if synthetic else 'onnx'}"]
        elif name == "associator":
            extra = (["--await-backend"] if "backend" in chosen else []) + (
                ["--prior-map", str(prior_map)] if prior_map is not None else [])
        elif name == "backend" and data == "external":  # no odometry service: record the SLAM's input poses
            extra = ["--write-odometry"]
        elif name == "odometry" and "tracker" in chosen and "detector" in chosen:
            extra = ["--await-dynamic"]  # (only a front end that uses dynamic objects waits for them)
        elif name == "viz":
            extra = (["--wait-for-map"] if "associator" in chosen else []) + (["--serve"] if serve else [])
        specs.append(ServiceSpec(name, extra, replicas=detectors if name == "detector" else 1,
                                 lockstep=name != "viz"))
    return specs


def _add_run(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the whole pipeline on a dataset (or 'synthetic')",
                       description="Start every service as its own process over Zenoh and play DATA through them.")
    p.add_argument("data", help="dataset path (7-Scenes, TUM RGB-D, KITTI odometry), 'synthetic[:frames=N,seed=S]', "
                   "or 'external' (no player or odometry: a SLAM publishes frames and poses, see semmap.client)")
    p.add_argument("--out", default="out", help="output directory (default: out)")
    p.add_argument("--odometry", default=None, help="gt | gt+drift | rgbd | file:PATH (default from config)")
    p.add_argument("--seed", type=int, default=None, help="seed of the drifting odometry")
    p.add_argument("--time-offset", type=float, default=None, metavar="SECONDS",
                   help="with --odometry file:PATH: added to the trajectory's stamps before matching them to frames")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", dest="mode", action="store_const", const="lockstep",
                      help="wait for the pipeline after every frame: deterministic (default)")
    mode.add_argument("--realtime", dest="mode", action="store_const", const="realtime",
                      help="play at the dataset rate; services drop what they cannot keep up with")
    p.add_argument("--config", default=None, help="YAML config (same layout as semmap/config/default.yaml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    p.add_argument("--robot", default=None, help="robot name used in the key expressions")
    p.add_argument("--max-frames", type=int, default=None, help="play at most N frames")
    p.add_argument("--topics", default=None, metavar="ROLE=TOPIC,...",
                   help="ROS bags: topics to use (color, depth, camera_info, pose, groundtruth; default: found by "
                   "message type), e.g. color=/camera/color/image_raw,pose=/odom")
    p.add_argument("--start-frame", type=int, default=None,
                   help="begin at this frame of the dataset (a later session of the same recording)")
    p.add_argument("--map", default=None, metavar="PRIOR",
                   help="start from a saved map (a run directory or its map.sqlite): relocalise against its objects, "
                        "then map in its frame (docs/MAPS.md)")
    p.add_argument("--detectors", type=int, default=1, help="detector replicas")
    p.add_argument("--connect", default=None, help="join a Zenoh router (e.g. tcp/127.0.0.1:7447) instead of "
                   "hosting the bus; env SEMMAP_ZENOH_CONNECT")
    p.add_argument("--zenoh-mode", default=None, choices=("peer", "client"))
    p.add_argument("--zenoh-config", default=os.environ.get("SEMMAP_ZENOH_CONFIG"), metavar="FILE_OR_DIR",
                   help="Zenoh configuration (TLS, access control; env SEMMAP_ZENOH_CONFIG): one file for every "
                   "process, or a folder with one <service>.json5 per identity (docs/SECURITY.md)")
    p.add_argument("--deadline", type=float, default=None, metavar="S",
                   help="fail the run if it takes longer than S seconds (default: run.deadline_s, 0 = none)")
    existing = p.add_mutually_exclusive_group()
    existing.add_argument("--resume", action="store_true",
                          help="continue the interrupted run in a non-empty --out (services from their journals)")
    existing.add_argument("--overwrite", action="store_true",
                          help="replace the previous run in a non-empty --out")
    p.add_argument("--no-viz", action="store_true", help="do not record run.rrd")
    p.add_argument("--serve", action="store_true",
                   help="serve the Rerun web viewer for the live run (http://localhost:9090)")
    p.add_argument("--only", default=None, metavar="SERVICES",
                   help=f"start only these services (comma-separated; the player always runs): {','.join(PIPELINE)}")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from semmap.orchestrator import Orchestrator, RunPlan

    overrides = list(args.overrides)
    if args.odometry:
        overrides.append(f"odometry.mode={args.odometry}")
    if args.seed is not None:
        overrides.append(f"odometry.seed={args.seed}")
    if args.max_frames is not None:
        overrides.append(f"run.max_frames={args.max_frames}")
    if args.topics is not None:
        overrides.append(f"rosbag.topics={args.topics}")
    if args.start_frame is not None:
        overrides.append(f"run.start_frame={args.start_frame}")
    prior_map = None
    if args.map is not None:
        from semmap.maps_cli import prior_map_path

        try:
            prior_map = prior_map_path(args.map, Path(args.out))
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    if args.time_offset is not None:
        overrides.append(f"odometry.file_time_offset_s={args.time_offset}")
    try:
        config = load_config(args.config, overrides)
        validate_sections(config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    special = args.data in ("synthetic", "external") or args.data.startswith("synthetic:")
    if not special and not Path(args.data).exists():
        print(f"error: dataset path {args.data} does not exist", file=sys.stderr)
        return 2
    dataset = None
    if not special:  # opened once for every check before the run (a bag's missing topic fails here, listing them)
        from semmap.datasets import DatasetError, open_dataset, reader_options

        try:
            dataset = open_dataset(args.data, **reader_options(args.data, config))
        except DatasetError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    if args.detectors < 1:
        print("error: --detectors must be at least 1", file=sys.stderr)
        return 2
    mode = str(config["odometry"]["mode"])
    if mode.startswith("file:") and args.data != "external":
        message = _check_file_odometry(dataset, args.data, mode[5:], config)
        if message.startswith("error:"):
            print(message, file=sys.stderr)
            return 2
        print(f"semmap: {message}", file=sys.stderr)
    only = [s.strip() for s in args.only.split(",")] if args.only else None
    unknown = sorted(set(only or []) - set(PIPELINE))
    if unknown:
        print(f"error: unknown service(s) {', '.join(unknown)}; known: {', '.join(PIPELINE)}", file=sys.stderr)
        return 2
    if args.zenoh_config and not Path(args.zenoh_config).exists():
        print(f"error: --zenoh-config {args.zenoh_config} does not exist", file=sys.stderr)
        return 2
    specs = pipeline_specs(args.data, config, args.detectors, not args.no_viz, only, args.serve, prior_map)
    run = config["run"]
    deadline = args.deadline if args.deadline is not None else float(run["deadline_s"])
    plan = RunPlan(data=args.data, out_dir=Path(args.out), robot=args.robot or run["robot"],
                   mode=args.mode or run["mode"], services=specs, config_path=args.config,
                   overrides=overrides, connect=args.connect, zenoh_mode=args.zenoh_mode,
                   zenoh_config=args.zenoh_config, verbose=args.verbose, quiet=args.quiet, deadline_s=deadline,
                   # (an external SLAM may connect whenever it likes: no stall limit without a player)
                   stall_s=0.0 if args.data == "external" else
                   float(run["start_timeout_s"]) + 2 * float(run["frame_timeout_s"]) + 30.0,
                   resume=args.resume)
    lock = OutputLock(plan.out_dir)
    try:  # before any process starts: the output directory is ours, empty (or meant to be reused), writable
        try:
            plan.out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot create --out {plan.out_dir}: {exc.strerror or exc}") from None
        lock.acquire()
        prepare_output_dir(plan.out_dir, args.resume, args.overwrite)
        check_writable(plan.out_dir, float(run["min_free_mb"]))
        if dataset is not None:
            preflight_dataset(dataset, args.data, config)
    except OutputError as exc:
        lock.release(refused=True)
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finally:
        if dataset is not None and hasattr(dataset, "close"):  # (bags hold their file open)
            dataset.close()
    try:
        return Orchestrator(plan).run()
    finally:
        lock.release()


def preflight_dataset(dataset: Dataset, data: str, config: dict) -> None:
    """The dataset's first frame reads, and it has ground truth where the odometry needs it (else a run would
    wait for a frame that never comes and blame 'no progress')."""
    from semmap.datasets import DatasetError

    try:
        if len(dataset) == 0:
            raise OutputError(f"dataset {data} has no frames")
        dataset[0]
    except DatasetError as exc:
        raise OutputError(f"dataset {data}: its first frame cannot be read: {exc}") from None
    mode = str(config["odometry"]["mode"])
    if mode in ("gt", "gt+drift") and not dataset.has_groundtruth:
        raise OutputError(f"--odometry {mode} needs ground-truth poses, and dataset {data} has no ground-truth "
                          "poses: use --odometry rgbd or file:PATH")


def _check_file_odometry(dataset: Dataset | None, data: str, path: str, config: dict) -> str:
    """Match a `file:` trajectory's stamps against the frames' before starting anything: a report, or 'error: ...'
    when too few frames find a pose (two clocks that do not overlap)."""
    from semmap.datasets import DatasetError, open_dataset
    from services.odometry.frontends import OdometryError, check_trajectory_overlap

    if not Path(path).is_file():
        return f"error: trajectory file {path} does not exist"
    try:
        stamps = (dataset if dataset is not None else open_dataset(data)).stamps()  # (synthetic: opened here)
        limit = config["run"].get("max_frames")
        if limit:
            stamps = stamps[: int(limit)]
        return check_trajectory_overlap(path, stamps, float(config["odometry"]["file_time_offset_s"]))
    except (DatasetError, OdometryError) as exc:
        return f"error: {exc}"


def _add_view(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="open a run's Rerun recording (DIR/run.rrd) in the viewer",
                       description="Open DIR/run.rrd in the native Rerun viewer, or with --web serve it to a browser "
                       "on this machine only: the web viewer (shipped in rerun-sdk, nothing is downloaded) over HTTP "
                       "and the recording over gRPC, both bound to 127.0.0.1. Prints the page's URL; Ctrl-C stops.")
    p.add_argument("dir", help="run output directory (or an .rrd file)")
    p.add_argument("--web", action="store_true", help="serve the web viewer on 127.0.0.1 instead of opening the "
                   "native one")
    p.add_argument("--port", type=int, default=9090, help="with --web: HTTP port of the web viewer (default 9090; "
                   "0 = any free port)")
    p.add_argument("--grpc-port", type=int, default=0, help="with --web: port of the gRPC server the page reads the "
                   "recording from (default: any free port)")
    p.set_defaults(func=_view)


def _listening(port: int) -> bool:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _rerun_executable() -> str | None:
    """The Rerun binary itself (not the `rerun` Python launcher, which does not pass SIGTERM on), else the launcher."""
    import shutil

    try:
        import rerun_cli
    except ImportError:
        rerun_cli = None
    if rerun_cli is not None:
        exe = Path(rerun_cli.__file__).with_name("rerun")
        if exe.is_file() and os.access(exe, os.X_OK):
            return str(exe)
    return shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")


def web_viewer_url(web_port: int, grpc_port: int) -> str:
    """The page that opens the web viewer on the recording streamed from `grpc_port` (all on 127.0.0.1)."""
    from urllib.parse import quote

    return f"http://127.0.0.1:{web_port}/?url=" + quote(f"rerun+http://127.0.0.1:{grpc_port}/proxy", safe="")


def _view(args: argparse.Namespace) -> int:
    import subprocess

    path = Path(args.dir)
    rrd = path / "run.rrd" if path.is_dir() else path
    if not rrd.is_file():
        print(f"error: no Rerun recording at {rrd} (runs record one unless --no-viz)", file=sys.stderr)
        return 2
    viewer = _rerun_executable()
    if viewer is None:
        print("error: the rerun viewer is not installed (pip install rerun-sdk)", file=sys.stderr)
        return 2
    # no usage analytics from the Rerun CLI (it turns them on in ~/.config/rerun otherwise)
    env = {**os.environ, "RERUN_ANALYTICS": "0", "CI": "true"}
    if not args.web:
        return subprocess.call([viewer, str(rrd)], env=env)
    return _serve_web(viewer, rrd, args, env)


def _serve_web(viewer: str, rrd: Path, args: argparse.Namespace, env: dict) -> int:
    """`rerun --serve-web` bound to 127.0.0.1 (it opens no browser); prints the URL once both ports answer."""
    import signal
    import subprocess
    import threading
    import time

    from semmap.orchestrator import free_loopback_port

    ports = {}
    for name, wanted, flag in (("web", args.port, "--port"), ("grpc", args.grpc_port, "--grpc-port")):
        try:
            port = free_loopback_port(wanted)
        except OSError:
            port = None
        if port is None or (wanted and port != wanted) or port in ports.values():
            print(f"error: cannot listen on 127.0.0.1:{wanted} (in use, or not a port): choose another with {flag}",
                  file=sys.stderr)
            return 2
        ports[name] = port
    cmd = [viewer, "--serve-web", "--bind", "127.0.0.1", "--port", str(ports["grpc"]),
           "--web-viewer-port", str(ports["web"]), str(rrd)]

    def _terminate(signum, frame):  # noqa: ANN001 - signal handler
        raise SystemExit(128 + signum)

    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if main_thread else None
    proc = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 30
        while not (_listening(ports["web"]) and _listening(ports["grpc"])):
            if proc.poll() is not None:
                print(f"error: the Rerun server exited ({proc.returncode})", file=sys.stderr)
                return proc.returncode or 1
            if time.monotonic() > deadline:
                print("error: the Rerun server did not start listening within 30 s", file=sys.stderr)
                return 1
            time.sleep(0.1)
        print(f"semmap: serving {rrd} in the Rerun web viewer on 127.0.0.1 only; open this URL "
              "(Ctrl-C stops):", file=sys.stderr)
        print(web_viewer_url(ports["web"], ports["grpc"]), flush=True)
        return proc.wait()
    except KeyboardInterrupt:
        return 130
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


def _add_ros2(sub: argparse._SubParsersAction) -> None:
    from semmap.ros2.bridge import add_arguments

    p = sub.add_parser("ros2", help="ROS 2 bridge: camera + SLAM topics in, landmarks and trajectory out "
                       "(needs the ros2 extra; see docs/ROS2.md)",
                       description="Feed a running `semmap run external` from ROS 2 topics and publish the map "
                       "back. ROS arguments follow --ros-args (remap topics with -r FROM:=TO, parameters with "
                       "-p NAME:=VALUE).")
    add_arguments(p)
    p.set_defaults(func=_ros2)


def _ros2(args: argparse.Namespace) -> int:
    from semmap.ros2.bridge import run

    return run(args, args.ros_args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="semmap", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_run(sub)
    _add_view(sub)
    _add_ros2(sub)
    from semmap.eval_cli import register as register_eval
    from semmap.map_cli import register as register_map
    from semmap.maps_cli import register_commands as register_maps

    register_eval(sub)
    register_map(sub)
    register_maps(sub)
    try:
        from services.detector.commands import register as register_detector
    except ImportError:  # pragma: no cover - the detector commands are part of the package
        register_detector = None
    if register_detector:
        register_detector(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    ros_args = argv[argv.index("--ros-args"):] if argv[:1] == ["ros2"] and "--ros-args" in argv else []
    args = parser.parse_args(argv[: len(argv) - len(ros_args)])
    args.ros_args = ros_args
    configure_logging(getattr(args, "verbose", False), "semmap")
    logging.getLogger("semmap.run").setLevel(logging.INFO)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `semmap query ... | head`: the reader left; say nothing more
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # Python flushes stdout at exit: into /dev/null, not a traceback
        return 141
    finally:
        if argv is None:  # a process of its own: Zenoh's threads must not keep it alive past its end
            from semmap.service import exit_backstop

            exit_backstop()


if __name__ == "__main__":
    sys.exit(main())
