"""Where a running semmap can be found: its Zenoh endpoint, robot name and run id, written by the run, read by
the clients that should serve it (the ROS 2 bridge, `SemmapClient.attach`) instead of guessing port 7447.

A run writes `run.json` into its out dir and the same into a per-user runtime directory,
`$XDG_RUNTIME_DIR/semmap/<robot>-<run id>.json` (else `<temp dir>/semmap-<uid>/`), and removes the latter when it
ends. `find_run(run_dir=...)` reads the out dir's; `find_run(robot=...)` looks in the runtime directory for
live runs (their process still there) of that robot, and fails with a clear message when there is none or more
than one.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

from semmap.core import environment
from semmap.core.outputs import atomic_write_text

RUN_FILE = "run.json"
SCHEMA = "semmap.run/1"


class RunNotFound(LookupError):
    """No run, or more than one, where a client looked (the message says which and what to do)."""


@dataclass(frozen=True)
class RunInfo:
    robot: str
    run_id: str
    endpoint: str  # Zenoh endpoint a client connects to, e.g. tcp/127.0.0.1:7447
    out_dir: str
    pid: int
    schema: str = SCHEMA
    check_slam: bool = False  # the run checks the SLAM's poses: publish them on the `slam` key (--check-slam)
    front_end: str = ""  # the run poses the frames with semmap's own front end (--odometry orbslam3): send none

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2)

    @classmethod
    def from_file(cls, path: Path) -> RunInfo:
        d = json.loads(path.read_text())
        if d.get("schema") != SCHEMA:
            raise ValueError(f"{path}: not a semmap run file (schema {d.get('schema')!r})")
        return cls(str(d["robot"]), str(d["run_id"]), str(d["endpoint"]), str(d["out_dir"]), int(d["pid"]),
                   check_slam=bool(d.get("check_slam", False)), front_end=str(d.get("front_end", "")))


def runtime_dir() -> Path:
    base = environment.read(environment.XDG_RUNTIME_DIR)
    return Path(base) / "semmap" if base else Path(tempfile.gettempdir()) / f"semmap-{os.getuid()}"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def register(info: RunInfo) -> list[Path]:
    """Write the run's files (its out dir's run.json and the runtime directory's); return them."""
    out = Path(info.out_dir) / RUN_FILE
    atomic_write_text(out, info.to_json())
    runtime = runtime_dir()
    runtime.mkdir(parents=True, exist_ok=True, mode=0o700)
    mine = runtime / f"{info.robot}-{info.run_id}.json"
    atomic_write_text(mine, info.to_json())
    return [out, mine]


def unregister(info: RunInfo) -> None:
    """The run ended: its runtime file goes (run.json stays in the out dir as a record)."""
    (runtime_dir() / f"{info.robot}-{info.run_id}.json").unlink(missing_ok=True)


def live_runs(robot: str | None = None) -> list[RunInfo]:
    """The runs in the runtime directory whose process is alive (stale files of crashed runs are skipped)."""
    found = []
    for path in sorted(runtime_dir().glob("*.json")):
        try:
            info = RunInfo.from_file(path)
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if (robot is None or info.robot == robot) and _alive(info.pid):
            found.append(info)
    return found


def find_run(run_dir: str | os.PathLike | None = None, robot: str | None = None) -> RunInfo:
    """The run a client should serve: the one whose out dir is `run_dir`, else the only live run of `robot`
    (of any robot when None). Raises RunNotFound with what was looked at and what to do."""
    if run_dir is not None:
        path = Path(run_dir) / RUN_FILE
        if not path.is_file():
            raise RunNotFound(f"no {RUN_FILE} in {run_dir}: is it the --out of a running `semmap run external`?")
        info = RunInfo.from_file(path)
        if not _alive(info.pid):
            raise RunNotFound(f"the run in {run_dir} (run {info.run_id}, pid {info.pid}) has ended")
        return info
    runs = live_runs(robot)
    who = f"robot {robot!r}" if robot else "any robot"
    if not runs:
        raise RunNotFound(
            f"no running semmap for {who} in {runtime_dir()}: start `semmap run external --robot NAME`, or "
            "name the run (--run OUT_DIR) or its endpoint (--connect tcp/HOST:PORT)"
        )
    if len(runs) > 1:
        listing = "; ".join(f"run {r.run_id} (robot {r.robot}, {r.endpoint}, out {r.out_dir})" for r in runs)
        raise RunNotFound(f"{len(runs)} semmap runs for {who}: {listing}. Choose one with --run OUT_DIR or --robot")
    return runs[0]
