"""The `semmap` command: run the pipeline, fetch models, detect, evaluate, view and query maps."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from semmap.config import ConfigError, load_config, validate_sections
from semmap.service import configure_logging

# services a run starts, in data-flow order; each is `python -m services.<name>`
PIPELINE = ("odometry", "detector", "tracker", "associator", "backend", "viz")


def pipeline_specs(data: str, config: dict, detectors: int, viz: bool, only: list[str] | None = None,
                   serve: bool = False) -> list:
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
        elif name == "associator" and "backend" in chosen:
            extra = ["--await-backend"]
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
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", dest="mode", action="store_const", const="lockstep",
                      help="wait for the pipeline after every frame: deterministic (default)")
    mode.add_argument("--realtime", dest="mode", action="store_const", const="realtime",
                      help="play at the dataset rate; services drop what they cannot keep up with")
    p.add_argument("--config", default=None, help="YAML config (same layout as semmap/config/default.yaml)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    p.add_argument("--robot", default=None, help="robot name used in the key expressions")
    p.add_argument("--max-frames", type=int, default=None, help="play at most N frames")
    p.add_argument("--detectors", type=int, default=1, help="detector replicas")
    p.add_argument("--connect", default=None, help="join a Zenoh router (e.g. tcp/127.0.0.1:7447) instead of "
                   "hosting the bus; env SEMMAP_ZENOH_CONNECT")
    p.add_argument("--zenoh-mode", default=None, choices=("peer", "client"))
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
    if not special and config["odometry"]["mode"] in ("gt", "gt+drift"):
        problem = _groundtruth_problem(args.data, config)
        if problem:
            print(f"error: --odometry {config['odometry']['mode']}: {problem}", file=sys.stderr)
            return 2
    if args.detectors < 1:
        print("error: --detectors must be at least 1", file=sys.stderr)
        return 2
    only = [s.strip() for s in args.only.split(",")] if args.only else None
    unknown = sorted(set(only or []) - set(PIPELINE))
    if unknown:
        print(f"error: unknown service(s) {', '.join(unknown)}; known: {', '.join(PIPELINE)}", file=sys.stderr)
        return 2
    specs = pipeline_specs(args.data, config, args.detectors, not args.no_viz, only, args.serve)
    plan = RunPlan(data=args.data, out_dir=Path(args.out), robot=args.robot or config["run"]["robot"],
                   mode=args.mode or config["run"]["mode"], services=specs, config_path=args.config,
                   overrides=overrides, connect=args.connect, zenoh_mode=args.zenoh_mode, verbose=args.verbose,
                   quiet=args.quiet)
    return Orchestrator(plan).run()


def _groundtruth_problem(data: str, config: dict) -> str:
    """Why a ground-truth front end cannot run on `data` ('' when it can): checked before any process starts
    (opening a dataset reads its file lists, not its images)."""
    from semmap.datasets import DatasetError, open_dataset
    from services.player.service import dataset_options

    try:
        dataset = open_dataset(data, **dataset_options(data, config["run"]))
    except DatasetError as exc:
        return str(exc)
    if not dataset.has_groundtruth:
        return f"{data} has no ground-truth poses; use --odometry rgbd or file:PATH"
    return ""


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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="semmap", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_run(sub)
    _add_view(sub)
    from semmap.eval_cli import register as register_eval
    from semmap.map_cli import register as register_map

    register_eval(sub)
    register_map(sub)
    try:
        from services.detector.commands import register as register_detector
    except ImportError:  # pragma: no cover - the detector commands are part of the package
        register_detector = None
    if register_detector:
        register_detector(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(getattr(args, "verbose", False), "semmap")
    logging.getLogger("semmap.run").setLevel(logging.INFO)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
