"""compose.yaml for real: build the image, bring the stack up in containers with podman-compose, map a 7-Scenes window
with two detector replicas, and get the embedded run's map. Then `down` leaves nothing behind.

What runs is compose.yaml plus tests/deploy/compose.podman.yaml (router from semmap's own image, a local Debian base,
deploy.replicas for the detector scale), with the settings a user passes to `docker compose` (docs/DEPLOY.md); the
`secure` case adds compose.secure.yaml: development certificates made by scripts/make-dev-certs.sh, every service on
mutual TLS with its own identity, the router's access-control list, and the test's own status reader a TLS client too.
Needs podman, podman-compose, runc (./dev.sh setup installs them) and the Debian base image (`./dev.sh
container-base` makes it once, from the Debian mirror, and the podman store keeps it).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from semmap.core.messages import ServiceStatus
from semmap.runtime.orchestrator import free_loopback_port
from semmap.runtime.transport.bus import Bus, BusConfig

PROJECT = Path(__file__).resolve().parents[2]
CONTAINERS_CONF = PROJECT / "tests" / "deploy" / "containers.conf"
OVERRIDE = "tests/deploy/compose.podman.yaml"
SECURE = "compose.secure.yaml"
HOST_CA = Path("/etc/ssl/certs/ca-certificates.crt")  # pip in the build trusts it (TLS-intercepting proxies)
FRAMES = 60
DETECTORS = 2
SERVICES = ["zenoh", "odometry", "detector", "tracker", "associator", "backend", "player"]  # --profile player
PIPELINE = {"odometry": 1, "detector": DETECTORS, "tracker": 1, "associator": 1, "backend": 1, "player": 1}
HEALTHY_WITHIN_S = 300
BUILD_WITHIN_S = 2400  # cold: ~2 GB of wheels and the model sdist from PyPI
IMAGE = "semmap:0.1.0"
FINISHED_WITHIN_S = 600

pytestmark = [pytest.mark.slow, pytest.mark.container, pytest.mark.needs_data, pytest.mark.needs_model]


@pytest.fixture(scope="module")
def podman_env() -> dict[str, str]:
    """podman set up for this machine (runc, no default ulimits, cgroupfs) and the Debian base image in its store."""
    missing = [tool for tool in ("podman", "podman-compose", "runc") if shutil.which(tool) is None]
    if missing:
        pytest.skip(f"{', '.join(missing)} absent: ./dev.sh setup installs them")
    env = {**os.environ, "CONTAINERS_CONF": str(CONTAINERS_CONF)}
    made = subprocess.run(
        [str(PROJECT / "dev.sh"), "container-base"], cwd=PROJECT, env=env, capture_output=True, text=True, timeout=900
    )
    assert made.returncode == 0, made.stdout[-2000:] + made.stderr[-3000:]
    return env


def _podman(env: dict[str, str], *args: str, timeout: float = 120, check: bool = True) -> str:
    result = subprocess.run(["podman", *args], env=env, capture_output=True, text=True, timeout=timeout)
    assert not check or result.returncode == 0, f"podman {' '.join(args)}: {result.stderr[-2000:]}"
    return result.stdout


def _containers(env: dict[str, str], project: str) -> list[dict]:
    out = _podman(env, "ps", "-a", "--format", "json", "--filter", f"label=io.podman.compose.project={project}")
    return json.loads(out or "[]")


def _logs(env: dict[str, str], project: str, lines: int = 25) -> str:
    text = []
    for c in _containers(env, project):
        name = c["Names"][0]
        log = subprocess.run(
            ["podman", "logs", "--tail", str(lines), name], env=env, capture_output=True, text=True, timeout=60
        )
        text.append(f"--- {name} ({c['State']}) ---\n{log.stdout}{log.stderr}")
    return "\n".join(text)


def _wait_healthy(env: dict[str, str], project: str, expected: int) -> dict[str, str]:
    """Run every container's health check until all report healthy. (podman schedules health checks with systemd
    timers; where systemd is not PID 1, as on CI machines and in containers, `podman healthcheck run` is the
    scheduler: it runs the check in the container and records the result, which `podman inspect` then shows.)"""
    deadline = time.monotonic() + HEALTHY_WITHIN_S
    health: dict[str, str] = {}
    while time.monotonic() < deadline:
        containers = _containers(env, project)
        exited = [c["Names"][0] for c in containers if c["State"] not in ("running", "created", "configured")]
        assert not exited, f"containers exited: {exited}\n{_logs(env, project)}"
        for c in containers:
            _podman(env, "healthcheck", "run", c["Names"][0], check=False, timeout=60)
        names = [c["Names"][0] for c in containers]
        inspected = json.loads(_podman(env, "inspect", *names)) if names else []
        health = {i["Name"]: i["State"]["Health"]["Status"] for i in inspected}
        if len(health) == expected and all(s == "healthy" for s in health.values()):
            return health
        time.sleep(5)
    raise AssertionError(f"not healthy within {HEALTHY_WITHIN_S} s: {health}\n{_logs(env, project)}")


class StatusWatch:
    """The services' status messages, read through the router's published port (as a SLAM on the host would)."""

    def __init__(self, endpoint: str, zenoh_config: Path | None = None) -> None:
        self.statuses: dict[str, ServiceStatus] = {}
        self.lock = threading.Lock()
        config = BusConfig(
            mode="client",
            connect=[endpoint],
            listen=[],
            config_file=str(zenoh_config) if zenoh_config else None,
        )
        self.bus = Bus(config, "robot1")
        self.bus.subscribe(self.bus.keys.status_all, ServiceStatus, self._on_status)

    def _on_status(self, s: ServiceStatus) -> None:
        with self.lock:
            self.statuses[s.instance] = s

    def snapshot(self) -> dict[str, ServiceStatus]:
        with self.lock:
            return dict(self.statuses)

    def close(self) -> None:
        self.bus.close()


def _wait_finished(watch: StatusWatch, env: dict[str, str], project: str) -> dict[str, ServiceStatus]:
    deadline = time.monotonic() + FINISHED_WITHIN_S
    while time.monotonic() < deadline:
        statuses = watch.snapshot()
        failed = {i: s.message for i, s in statuses.items() if s.state == "failed"}
        assert not failed, f"failed: {failed}\n{_logs(env, project)}"
        per_service = {name: [s for s in statuses.values() if s.service == name] for name in PIPELINE}
        if all(
            len(per_service[n]) == count and all(s.state == "finished" for s in per_service[n])
            for n, count in PIPELINE.items()
        ):
            return statuses
        time.sleep(1)
    states = {i: (s.state, s.last_frame_id) for i, s in watch.snapshot().items()}
    raise AssertionError(f"not finished within {FINISHED_WITHIN_S} s: {states}\n{_logs(env, project)}")


def _leftovers(env: dict[str, str], project: str) -> dict[str, str]:
    found = {
        "containers": _podman(env, "ps", "-a", "-q", "--filter", f"label=io.podman.compose.project={project}"),
        "pods": _podman(env, "pod", "ps", "-q", "--filter", f"name={project}"),
        "networks": _podman(env, "network", "ls", "-q", "--filter", f"name={project}"),
        "volumes": _podman(env, "volume", "ls", "-q", "--filter", f"name={project}"),
    }
    return {k: v.strip() for k, v in found.items() if v.strip()}


def _down(compose: list[str], env: dict[str, str], project: str) -> None:
    """`down`, then what podman-compose 1.0.3 leaves: the project's network and (unlabelled) named volumes."""
    subprocess.run([*compose, "down"], cwd=PROJECT, env=env, capture_output=True, timeout=300)
    for name in _podman(env, "ps", "-a", "-q", "--filter", f"label=io.podman.compose.project={project}").split():
        _podman(env, "rm", "-f", "-t", "0", name, check=False)
    for net in _podman(env, "network", "ls", "-q", "--filter", f"name={project}").split():
        _podman(env, "network", "rm", "-f", net, check=False)
    for vol in _podman(env, "volume", "ls", "-q", "--filter", f"name={project}").split():
        _podman(env, "volume", "rm", "-f", vol, check=False)


def _build_args() -> str:
    build_args = "--network host --format docker"
    if HOST_CA.is_file():
        build_args += f" --secret id=ca,src={HOST_CA}"
    return build_args


def _image_id(env: dict[str, str]) -> str:
    return _podman(env, "image", "inspect", "--format", "{{.Id}}", IMAGE, check=False).strip()


def _secure_profile(tmp_path: Path, port: int) -> tuple[Path, Path]:
    """Development certificates for the stack (the router's name `zenoh` in its certificate), readable by the
    services' uid 10001, and a client config of the orchestrator's identity for this test's status reader."""
    certs = tmp_path / "certs"
    script = PROJECT / "scripts" / "make-dev-certs.sh"
    made = subprocess.run([str(script), str(certs), "zenoh"], capture_output=True, text=True, timeout=60)
    assert made.returncode == 0, made.stderr
    for key in certs.glob("*.key"):
        key.chmod(0o644)  # development keys only: the containers' user is not the owner of the bind-mounted files
    host_profile = tmp_path / "host-profile"
    written = subprocess.run(
        [sys.executable, "-m", "semmap.runtime.transport.secure_profile", str(certs), str(host_profile)]
        + ["--router", f"tls/127.0.0.1:{port}"],
        cwd=PROJECT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert written.returncode == 0, written.stderr
    return certs, host_profile / "orchestrator.json5"


@pytest.mark.parametrize("profile", ["plain", "secure"])
def test_compose_stack_in_containers_maps_like_the_embedded_run(
    tmp_path: Path,
    kitchen_dir: Path,
    podman_env: dict[str, str],
    semmap_run,  # noqa: ANN001
    profile: str,
) -> None:
    project = f"semmaptest{os.getpid()}{profile}"
    port = free_loopback_port()
    env = {
        **podman_env,
        "SEMMAP_MODE": "lockstep",
        "SEMMAP_DETECTORS": str(DETECTORS),
        "SEMMAP_MAX_FRAMES": str(FRAMES),
        "SEMMAP_ODOMETRY": "gt+drift",
        "SEMMAP_DATA": str(kitchen_dir.parent),
        "SEMMAP_DATASET": kitchen_dir.name,
        "SEMMAP_ROUTER_PORT": str(port),
    }
    files = ["-f", "compose.yaml", "-f", OVERRIDE]
    endpoint, reader_config = f"tcp/127.0.0.1:{port}", None
    if profile == "secure":
        certs, reader_config = _secure_profile(tmp_path, port)
        env["SEMMAP_CERTS"] = str(certs)
        files += ["-f", SECURE]
        endpoint = f"tls/127.0.0.1:{port}"
    compose = ["podman-compose", "-p", project, *files, "--podman-build-args", _build_args()]
    timings: dict[str, float] = {}
    watch: StatusWatch | None = None
    build: subprocess.Popen | None = None
    previous_image = _image_id(env)
    build_log = tmp_path / "build.log"
    try:
        # the build (mostly downloads when cold) and the embedded run of the same window overlap
        t0 = time.monotonic()
        with open(build_log, "w") as log:
            build = subprocess.Popen([*compose, "build", "zenoh"], cwd=PROJECT, env=env, stdout=log, stderr=log)
        embedded = tmp_path / "embedded"
        result = semmap_run(
            [str(kitchen_dir), "--out", str(embedded), "--lockstep", "--no-viz", "--odometry", "gt+drift"]
            + ["--max-frames", str(FRAMES), "--detectors", str(DETECTORS)],
            timeout=600,
        )
        assert result.returncode == 0, result.stderr[-3000:]
        assert build.wait(timeout=BUILD_WITHIN_S) == 0, build_log.read_text()[-5000:]
        timings["build_s"] = time.monotonic() - t0
        if previous_image and previous_image != _image_id(env):  # keep one image, not one per code change
            _podman(env, "rmi", previous_image, check=False)

        t0 = time.monotonic()
        # the README's `docker compose [-f compose.yaml -f compose.secure.yaml] --profile player up --build --scale
        # detector=2`, built above (podman-compose 1.0.3: no profiles, no --scale; the override sets the replicas)
        up = subprocess.run(
            [*compose, "up", "-d", "--no-build", *SERVICES],
            cwd=PROJECT,
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert up.returncode == 0, up.stdout[-3000:] + up.stderr[-3000:]
        health = _wait_healthy(env, project, expected=len(SERVICES) + DETECTORS - 1)
        timings["healthy_s"] = time.monotonic() - t0
        assert sum(name.startswith(f"{project}_detector_") for name in health) == DETECTORS

        watch = StatusWatch(endpoint, reader_config)
        statuses = _wait_finished(watch, env, project)
        timings["finished_s"] = time.monotonic() - t0
        detectors = [s for s in statuses.values() if s.service == "detector"]
        assert all(s.counters.get("frames_detected", 0) > 10 for s in detectors), [s.counters for s in detectors]

        mount = Path(_podman(env, "volume", "inspect", f"{project}_outputs", "--format", "{{.Mountpoint}}").strip())
        outputs = tmp_path / "containers"
        shutil.copytree(mount, outputs)
    finally:
        if watch is not None:
            watch.close()
        if build is not None and build.poll() is None:
            build.kill()
            build.wait()
        t0 = time.monotonic()
        _down(compose, env, project)
        timings["down_s"] = time.monotonic() - t0
        print(f"container test ({profile}): {json.dumps({k: round(v, 1) for k, v in timings.items()})}")
    assert _leftovers(env, project) == {}

    assert json.loads((outputs / "map.json").read_text()) == json.loads((embedded / "map.json").read_text())
    assert json.loads((outputs / "map.json").read_text())["landmarks"], "an empty map proves nothing"
    for name in ("trajectory_optimized.tum", "trajectory_odometry.tum", "groundtruth.tum"):
        assert (outputs / name).read_text() == (embedded / name).read_text(), name


def test_the_image_measures_the_machine_it_runs_on_and_its_real_time_detector_takes_the_choice(
    podman_env: dict[str, str],
) -> None:
    """Real time in containers on the CPU at hand, as compose.yaml documents it: `docker compose run --rm
    detector semmap models doctor` times the image's fp32 and int8 copies on this machine and keeps the choice in
    the `measurements` volume (the models belong to root, the services run as `semmap`: SEMMAP_CHOICE_DIR), and a
    real-time detector that `up` starts afterwards runs that choice instead of fp32 at full size."""
    project = f"semmaptest{os.getpid()}doctor"
    env = {**podman_env, "SEMMAP_MODE": "realtime", "SEMMAP_ROUTER_PORT": str(free_loopback_port())}
    compose = ["podman-compose", "-p", project, "-f", "compose.yaml", "-f", OVERRIDE, "--podman-build-args",
               _build_args()]  # fmt: skip
    try:
        build = subprocess.run([*compose, "build", "zenoh"], cwd=PROJECT, env=env, capture_output=True, text=True,
                               timeout=BUILD_WITHIN_S)  # fmt: skip (the layers of the stack test, where it ran first)
        assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
        doctor = subprocess.run(
            [*compose, "run", "--rm", "detector", "semmap", "models", "doctor", "--frames", "4"],
            cwd=PROJECT, env=env, capture_output=True, text=True, timeout=600,
        )  # fmt: skip
        assert doctor.returncode == 0, doctor.stdout[-3000:] + doctor.stderr[-3000:]
        assert "int8w7 640x480 1t" in doctor.stdout, doctor.stdout[-3000:]  # the image's 7-bit copy is a candidate
        chosen = next(line for line in doctor.stdout.splitlines() if line.startswith("choice (detector.precision auto"))
        precision, size = chosen.split(": ", 1)[1].split()[:2]  # "int8w7 512x384 1t, 2 x 1 thread"

        up = subprocess.run([*compose, "up", "-d", "--no-build", "zenoh", "detector"], cwd=PROJECT, env=env,
                            capture_output=True, text=True, timeout=300)  # fmt: skip
        assert up.returncode == 0, up.stdout[-3000:] + up.stderr[-3000:]
        deadline, model_line = time.monotonic() + 180, ""
        while not model_line and time.monotonic() < deadline:
            time.sleep(2)
            model_line = next((line for line in _logs(env, project, lines=200).splitlines()
                               if "detector INFO" in line and " model " in line), "")  # fmt: skip
        assert model_line, _logs(env, project)
        assert f"model {precision} {size} " in model_line and "measured on this machine" in model_line, model_line
    finally:
        _down(compose, env, project)
    assert _leftovers(env, project) == {}
