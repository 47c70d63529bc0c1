"""compose.yaml, checked without a Docker engine: the Compose Specification schema, every command exists, and the
wiring is the declared dataflow's (semmap/core/dataflow.py)."""

from __future__ import annotations

import importlib
import json
import re
from pathlib import Path

import jsonschema
import pytest
import yaml

from semmap.core import dataflow

PROJECT = Path(__file__).resolve().parents[2]
SCHEMA = PROJECT / ".cache" / "compose_spec.json"


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((PROJECT / "compose.yaml").read_text())


def test_compose_file_matches_the_compose_specification(compose: dict) -> None:
    if not SCHEMA.is_file():
        pytest.skip("the Compose Specification schema is fetched by ./dev.sh setup (.cache/compose_spec.json)")
    schema = json.loads(SCHEMA.read_text())
    jsonschema.Draft201909Validator(schema).validate(compose)  # the draft the schema names


def test_services_join_the_router_and_detectors_scale(compose: dict) -> None:
    services = compose["services"]
    assert services["zenoh"]["image"].startswith("eclipse/zenoh:")
    for name, service in services.items():
        if name == "zenoh":
            continue
        env = service["environment"]
        assert env["SEMMAP_ZENOH_CONNECT"] == "tcp/zenoh:7447" and env["SEMMAP_ZENOH_MODE"] == "client", name
        assert "container_name" not in service, f"{name}: a fixed name would stop --scale"
    detector = services["detector"]
    assert "ports" not in detector, "published ports would stop --scale detector=3"
    images = {s.get("image") for n, s in services.items() if n != "zenoh"}
    assert images == {"semmap:0.1.0"}, "one image for every service"


def test_published_ports_are_loopback_only(compose: dict) -> None:
    for name, service in compose["services"].items():
        for port in service.get("ports", []):
            assert port.startswith("127.0.0.1:"), f"{name}: {port} would listen on every interface"


def _service_parser(module_name: str):
    module = importlib.import_module(f"semmap.services.{module_name}.service")
    return module


@pytest.mark.parametrize("name", ["odometry", "detector", "tracker", "associator", "backend", "viz", "player"])
def test_every_command_names_a_real_service_with_real_flags(compose: dict, name: str) -> None:
    command = compose["services"][name]["command"]
    assert command[:2] == ["python", "-m"], command
    module = command[2]
    assert module == f"semmap.services.{name}"
    assert importlib.util.find_spec(f"{module}.__main__") is not None
    # the flags parse with the service's own parser (no process started)
    import argparse

    from semmap.runtime.transport.service import common_arguments

    service_module = importlib.import_module(f"{module}.service")
    parser = argparse.ArgumentParser(exit_on_error=False)
    common_arguments(parser)
    if hasattr(service_module, "_arguments"):  # the service's own flags
        service_module._arguments(parser)
    args = [re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", a) for a in command[3:]]  # ${VAR:-default} -> default
    parser.parse_args(args)


def test_dockerfile_builds_one_non_root_image_with_the_model() -> None:
    text = (PROJECT / "docker" / "Dockerfile").read_text()
    assert "ARG BASE=python:3.11-slim-bookworm" in text
    assert "USER semmap" in text and "HEALTHCHECK" in text and "semmap models fetch" in text
    assert "--mount=type=secret,id=ca" in text  # a proxy's CA bundle for pip, never stored in a layer


def test_podman_override_only_swaps_router_base_and_scale(compose: dict) -> None:
    """tests/deploy/compose.podman.yaml (what the container test adds) names only compose.yaml's services and adds no
    list a service already has: podman-compose 1.0.3 appends lists instead of replacing them."""
    override = yaml.safe_load((PROJECT / "tests" / "deploy" / "compose.podman.yaml").read_text())
    for name, service in override["services"].items():
        assert name in compose["services"], name
        base = compose["services"][name]
        for key, value in service.items():
            assert not (isinstance(value, list) and key in base), f"{name}.{key} would be appended to"
        assert service["build"]["args"]["BASE"].startswith("${SEMMAP_BASE_IMAGE:-")
    assert override["services"]["zenoh"]["entrypoint"] == ["python", "-m", "semmap.runtime.transport.router"]


def test_secure_override_adds_tls_to_every_service(compose: dict) -> None:
    """compose.secure.yaml: every service of compose.yaml on TLS with its own identity's Zenoh config, certificates
    mounted, the router started on the secure profile's config; it adds no list that either file it goes on top of
    already has except volumes (podman-compose 1.0.3 appends lists: extra mounts are what is wanted)."""
    secure = yaml.safe_load((PROJECT / "compose.secure.yaml").read_text())
    podman = yaml.safe_load((PROJECT / "tests" / "deploy" / "compose.podman.yaml").read_text())
    assert set(secure["services"]) == set(compose["services"])
    for name, service in secure["services"].items():
        for key, value in service.items():
            below = [compose["services"][name], podman["services"].get(name) or {}]
            assert key == "volumes" or not (isinstance(value, list) and any(key in b for b in below)), (name, key)
        assert any(v.endswith(":/certs:ro") for v in service["volumes"]), name
        if name == "zenoh":
            assert service["command"] == ["-c", "/secure/router.json5"]
            continue
        env = service["environment"]
        assert env["SEMMAP_ZENOH_CONNECT"] == "tls/zenoh:7447", name
        config = env["SEMMAP_ZENOH_CONFIG"]
        assert config == f"/secure/{name}.json5" and (PROJECT / "deploy" / "secure" / f"{name}.json5").is_file()


def _unexpanded(arg: str) -> str:
    """`${VAR:-default}` -> `default` (what compose runs with nothing set)."""
    return re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", arg)


def test_compose_runs_every_service_of_the_dataflow(compose: dict) -> None:
    """One container per service node of the dataflow, none that is not one (the router aside)."""
    assert set(compose["services"]) - {"zenoh"} == set(dataflow.SERVICES)


@pytest.mark.parametrize("name", dataflow.SERVICES)
def test_compose_passes_the_declared_wiring_flags(compose: dict, name: str) -> None:
    """Every stage of compose's stack runs, so each node gets every wiring flag the dataflow declares for it, as
    `semmap run` passes them (e.g. `--await-dynamic`, `--wait-for-map`); and no wiring flag of another node."""
    command = compose["services"][name]["command"]
    wanted = dataflow.wiring_flags(name, list(compose["services"]))
    assert wanted == [f.flag for f in dataflow.node(name).flags]
    for flag in wanted:
        assert flag in command, f"{name}: compose leaves out {flag} (semmap/core/dataflow.py)"
    others = {f.flag for n in dataflow.NODES if n.name != name for f in n.flags}
    assert not others & set(command), f"{name}: {others & set(command)} belong to other nodes"


def test_compose_player_waits_for_the_lockstep_nodes(compose: dict) -> None:
    """The player's `--wait-for` is the dataflow's lockstep nodes (the detector as many as it is scaled to), and
    the player starts after each of them is healthy."""
    player = compose["services"]["player"]
    command = player["command"]
    wait_for = command[command.index("--wait-for") + 1]
    assert wait_for == dataflow.player_wait_for({"detector": "${SEMMAP_DETECTORS:-1}"})
    lockstep = [n.name for n in dataflow.NODES if n.lockstep]
    assert set(player["depends_on"]) - {"zenoh"} == set(lockstep)
    assert [item.partition(":")[0] for item in _unexpanded(wait_for).split(",")] == lockstep
