"""`semmap view`: a run's Rerun recording in the native viewer, or served to a browser on this machine."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from semmap.core import environment

ORDER = 10

def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="open a run's Rerun recording (DIR/run.rrd) in the viewer",
                       description="Open DIR/run.rrd in the native Rerun viewer, or with --web serve it to a browser "
                       "on this machine only: the web viewer (shipped in rerun-sdk, nothing is downloaded) over HTTP "
                       "and the recording over gRPC, both bound to 127.0.0.1. Prints the page's URL; Ctrl-C stops.")
    p.add_argument("dir", help="run output directory (or an .rrd file)")
    p.add_argument("--web", action="store_true", help="serve the web viewer on 127.0.0.1 instead of opening the "
                   "native one")
    p.add_argument("--port", type=int, default=9090, help="with --web: HTTP port of the web viewer (default 9090; "
                   "0 = any free port)")
    p.add_argument("--images", action="store_true", help="with --web: stream the camera images too (by default the "
                   "page gets the map, trajectories and boxes only, so the landmarks show within seconds)")
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
        display = environment.read(environment.DISPLAY) or environment.read(environment.WAYLAND_DISPLAY)
        if sys.platform.startswith("linux") and not display:
            print(f"error: no display (neither DISPLAY nor WAYLAND_DISPLAY is set): use --web (semmap view {args.dir} "
                  "--web) and open the URL it prints", file=sys.stderr)
            return 2
        # the native viewer's own server (gRPC, 9876 by default) on loopback only, not on every interface
        return _native(viewer, rrd, args.dir, env)
    return _serve_web(viewer, rrd, args, env)


def _native(viewer: str, rrd: Path, where: str, env: dict) -> int:
    """The native viewer, its messages passed on; a window that cannot open (a DISPLAY with no X server behind
    it) ends as one line pointing to --web instead of winit's error."""
    import subprocess

    proc = subprocess.Popen([viewer, "--bind", "127.0.0.1", str(rrd)], env=env, stdin=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, errors="replace")
    no_display = False
    try:
        assert proc.stderr is not None
        for line in proc.stderr:
            if "winit" in line or "EventLoopError" in line:
                no_display = True
                continue
            sys.stderr.write(line)
        code = proc.wait()
    except KeyboardInterrupt:
        proc.terminate()
        proc.wait()
        return 130
    if no_display and code != 0:
        print(f"error: no display (the viewer cannot open a window here): use --web (semmap view {where} --web) "
              "and open the URL it prints", file=sys.stderr)
        return 2
    return code


# what the web page does without unless --images: a recording's bulk (a JPEG per frame, a depth image every few),
# streamed before the map that comes later in the file (75 s without a landmark on a loaded 2-core machine)
IMAGE_ENTITIES = ("/world/camera/image", "/world/camera/image/detections", "/world/camera/image/tracks",
                  "/world/camera/depth")


def map_first_copy(viewer: str, rrd: Path, folder: Path, env: dict) -> Path | None:
    """A copy of `rrd` without the camera images (`rerun rrd filter`) in `folder`; None if the filter fails."""
    import subprocess

    target = folder / "map.rrd"
    drops = [arg for entity in IMAGE_ENTITIES for arg in ("--drop-entity", entity)]
    result = subprocess.run([viewer, "rrd", "filter", *drops, str(rrd), "-o", str(target)], env=env,
                            capture_output=True, text=True)
    return target if result.returncode == 0 and target.is_file() else None


def _serve_web(viewer: str, rrd: Path, args: argparse.Namespace, env: dict) -> int:
    """`rerun --serve-web` bound to 127.0.0.1 (it opens no browser); prints the URL once both ports answer."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="semmap-view-") as tmp:
        served = rrd if args.images else map_first_copy(viewer, rrd, Path(tmp), env)
        if served is None:
            print("semmap: could not leave the images out of the recording; serving all of it", file=sys.stderr)
            served = rrd
        return _serve_file(viewer, rrd, served, args, env)


def _serve_file(viewer: str, rrd: Path, served: Path, args: argparse.Namespace, env: dict) -> int:
    import signal
    import subprocess
    import threading
    import time

    from semmap.runtime.orchestrator import free_loopback_port

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
    cmd = [viewer, "--serve-web", "--newest-first", "--bind", "127.0.0.1", "--port", str(ports["grpc"]),
           "--web-viewer-port", str(ports["web"]), str(served)]

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
        what = "" if served == rrd else " (map, trajectories and boxes; --images for the camera images)"
        print(f"semmap: serving {rrd}{what} in the Rerun web viewer on 127.0.0.1 only; open this URL "
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
