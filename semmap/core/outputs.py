"""Run outputs kept the way a database keeps its files.

- One run per output directory: `semmap run` holds an exclusive lock on `--out` for its whole life, so a second
  run with the same `--out` is refused instead of interleaving its journal with the first one's.
- A finished run is not overwritten by accident: a non-empty `--out` needs `--resume` or `--overwrite`.
- Whole files or none: every output is written to a temporary file beside it and renamed over the old one, so a
  full disk or a killed process leaves the previous file (or none), never a truncated one.
- Checked before any process starts (pre-flight): the directory is writable and has room.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shutil
import sqlite3
import tempfile
from pathlib import Path

LOCK_NAME = ".semmap.lock"
# what marks a directory as a semmap run's (only such a directory is wiped by --overwrite)
SLAM_TRAJECTORY = "trajectory_slam.tum"  # an external SLAM's own poses before semmap repaired them
# ...and as the SLAM itself saves them at its end, where it does that (ORB-SLAM3, after its last bundle adjustments):
# what it alone gives a user, held against semmap's result
SLAM_REFINED_TRAJECTORY = "trajectory_slam_refined.tum"
REPAIR_REPORT = "odometry_repair.json"  # where semmap overruled the SLAM (the odometry service writes it)
RUN_MARKERS = ("stats.json", "logs", "map.json")
# errors of the disk itself: no retry or restart helps, the operator must act (named as they are)
SKIPPED_FILE = "skipped_frames.json"  # the frames the player could not send, and why (the summary names them)
DISK_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO})


class OutputError(RuntimeError):
    """The output directory cannot be used for this run (the message says why and what to do)."""


def atomic_write_bytes(path: str | Path, data: bytes, mode: int = 0o644) -> None:
    """Write `data` to `path` through a temporary file in the same directory and a rename: readers see the old
    file or the new one, never a part (a full disk fails here and leaves the old file as it was). `mode`: the
    file's permissions (mkstemp makes 0600; outputs and models are not secret)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.chmod(tmp, mode)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


class OutputLock:
    """An exclusive `flock` on `<out>/.semmap.lock`, held while the run lives (released by the kernel if the
    process dies, so a crashed run never leaves a stale lock)."""

    def __init__(self, out_dir: Path) -> None:
        self.path = Path(out_dir) / LOCK_NAME
        self._fd: int | None = None
        self._created = False

    def acquire(self) -> None:
        self._created = not self.path.exists()
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise OutputError(f"cannot create the lock file {self.path}: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise OutputError(
                f"{self.path.parent} is in use by another semmap run (pid {holder}); wait for it or "
                "choose another --out"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd

    @property
    def fd(self) -> int | None:
        """The locked file's descriptor (None unless held). A child process that inherits it shares the lock:
        the folder stays locked until the last holder exits, even if this process is killed."""
        return self._fd

    def release(self, refused: bool = False) -> None:
        """Unlock; `refused` (the run never started): also remove the lock file if this run created it."""
        if self._fd is not None:
            if refused and self._created:
                with contextlib.suppress(OSError):
                    self.path.unlink()
            with contextlib.suppress(OSError):
                fcntl.flock(self._fd, fcntl.LOCK_UN)
                os.close(self._fd)
            self._fd = None


def _contents(out_dir: Path) -> list[Path]:
    return [p for p in out_dir.iterdir() if p.name != LOCK_NAME] if out_dir.is_dir() else []


def prepare_output_dir(out_dir: Path, resume: bool = False, overwrite: bool = False) -> None:
    """Create `out_dir`, or accept an existing one only as the flags allow. `overwrite` empties it, but only if
    it is a semmap run's directory (never a home folder given by mistake)."""
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"--out {out_dir} exists and is not a directory")
    existing = _contents(out_dir)
    if existing and not (resume or overwrite):
        raise OutputError(
            f"--out {out_dir} is not empty ({len(existing)} entries, e.g. {existing[0].name}): "
            "pass --resume to continue that run, --overwrite to replace it, or choose another --out"
        )
    if existing and overwrite:
        if not any((out_dir / m).exists() for m in RUN_MARKERS):
            raise OutputError(
                f"--out {out_dir} does not look like a semmap output directory (no stats.json, logs/ "
                "or map.json): refusing to empty it; choose an empty or new directory"
            )
        for entry in existing:
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create --out {out_dir}: {exc.strerror or exc}") from None


def check_writable(out_dir: Path, min_free_mb: float) -> None:
    """Pre-flight: a probe file can be written, fsynced and removed, and at least `min_free_mb` are free."""
    probe = out_dir / f".semmap-probe-{os.getpid()}"
    try:
        atomic_write_bytes(probe, b"probe")
        probe.unlink()
    except OSError as exc:
        raise OutputError(f"cannot write to --out {out_dir}: {exc.strerror or exc}") from None
    free_mb = shutil.disk_usage(out_dir).free / 1e6
    if free_mb < min_free_mb:
        raise OutputError(
            f"only {free_mb:.0f} MB free on the disk of --out {out_dir}; a run needs at least "
            f"{min_free_mb:.0f} MB (run.min_free_mb)"
        )


def is_disk_error(exc: BaseException) -> bool:
    """A full, read-only or failing disk (SQLite says so in words, not with an errno)."""
    if isinstance(exc, OSError):
        return exc.errno in DISK_ERRNOS
    text = str(exc).lower()
    return isinstance(exc, sqlite3.OperationalError) and any(
        w in text for w in ("disk is full", "readonly database", "disk i/o error", "unable to open database")
    )


def describe_disk_error(exc: BaseException) -> str:
    """`[Errno 28] No space left on device: 'out/map.sqlite'` -> a line that names the disk as the cause."""
    if isinstance(exc, OSError):
        where = f" ({exc.filename})" if exc.filename else ""
        return f"disk error: {exc.strerror or exc}{where}"
    return f"disk error: {exc} (SQLite)"


def read_skipped(out_dir: str | Path | None) -> dict[int, str]:
    """Frame -> why it was skipped, from the `skipped_frames.json` a run's player wrote ({} where there is none
    or it is unreadable)."""
    if out_dir is None:
        return {}
    try:
        items = json.loads((Path(out_dir) / SKIPPED_FILE).read_text())
        return {int(item["frame"]): str(item["reason"]) for item in items}
    except (OSError, ValueError, TypeError, KeyError):
        return {}
