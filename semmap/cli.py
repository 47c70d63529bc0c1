"""The `semmap` command: run the pipeline, fetch models, detect, evaluate, view and query maps."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from semmap.config import ConfigError, load_config, validate_sections
from semmap.service import configure_logging

# services a run starts, in data-flow order; each is `python -m services.<name>`
PIPELINE = ("odometry", "detector", "tracker", "associator", "backend", "viz")


def pipeline_specs(data: str, config: dict, detectors: int, viz: bool, only: list[str] | None = None) -> list:
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
        elif name == "viz" and "associator" in chosen:
            extra = ["--wait-for-map"]
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
    if args.detectors < 1:
        print("error: --detectors must be at least 1", file=sys.stderr)
        return 2
    only = [s.strip() for s in args.only.split(",")] if args.only else None
    unknown = sorted(set(only or []) - set(PIPELINE))
    if unknown:
        print(f"error: unknown service(s) {', '.join(unknown)}; known: {', '.join(PIPELINE)}", file=sys.stderr)
        return 2
    specs = pipeline_specs(args.data, config, args.detectors, not args.no_viz, only)
    plan = RunPlan(data=args.data, out_dir=Path(args.out), robot=args.robot or config["run"]["robot"],
                   mode=args.mode or config["run"]["mode"], services=specs, config_path=args.config,
                   overrides=overrides, connect=args.connect, zenoh_mode=args.zenoh_mode, verbose=args.verbose,
                   quiet=args.quiet)
    return Orchestrator(plan).run()


def _add_view(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="open a run's Rerun recording (DIR/run.rrd) in the viewer")
    p.add_argument("dir", help="run output directory (or an .rrd file)")
    p.add_argument("--web", action="store_true", help="serve the web viewer instead of the native one")
    p.set_defaults(func=_view)


def _view(args: argparse.Namespace) -> int:
    import os
    import shutil
    import subprocess

    path = Path(args.dir)
    rrd = path / "run.rrd" if path.is_dir() else path
    if not rrd.is_file():
        print(f"error: no Rerun recording at {rrd} (runs record one unless --no-viz)", file=sys.stderr)
        return 2
    viewer = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if viewer is None:
        print("error: the rerun viewer is not installed (pip install rerun-sdk)", file=sys.stderr)
        return 2
    cmd = [viewer, *(["--web-viewer"] if args.web else []), str(rrd)]
    return subprocess.call(cmd, env={**os.environ, "RERUN_ANALYTICS": os.environ.get("RERUN_ANALYTICS", "0")})


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
