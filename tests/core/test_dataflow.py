"""The dataflow declared once (semmap/core/dataflow.py): the service modules, the access-control list, the
signature owners and docs/DESIGN.md agree with it, and a service refuses a key it does not declare."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path
from types import SimpleNamespace

import pytest

from semmap.core import dataflow, messages
from semmap.core.keys import PUBLISHERS, Keys
from semmap.runtime.transport import secure_profile

PROJECT = Path(__file__).resolve().parents[2]
KEYS = Keys("robot1")


def _topic_of(node: ast.expr) -> str | None:
    """`self.bus.keys.frames` -> `frames` (None: not a plain Keys property)."""
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Attribute) and node.value.attr == "keys":
        value = getattr(Keys, node.attr, None)
        if isinstance(value, property):
            return KEYS.topic(getattr(KEYS, node.attr))
    return None


def keys_used(source: str) -> dict[str, set[str]]:
    """What a service module's source subscribes to (`self.listen`), publishes on (`self.publisher`), asks
    (`session.get`), answers (`declare_queryable`) and declares liveliness on (`declare_token`, read as the
    wildcard of its family)."""
    used: dict[str, set[str]] = {"inputs": set(), "outputs": set(), "asks": set(), "answers": set(),
                                 "liveliness": set()}
    calls = {"listen": "inputs", "publisher": "outputs", "get": "asks", "declare_queryable": "answers"}
    for call in ast.walk(ast.parse(source)):
        if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute) and call.args):
            continue
        what = calls.get(call.func.attr)
        arg = call.args[0]
        if isinstance(arg, ast.BinOp):  # `keys.map_query + "?..."`
            arg = arg.left
        if what and (topic := _topic_of(arg)):
            used[what].add(topic)
        if call.func.attr == "declare_token" and isinstance(arg, ast.Call) and isinstance(arg.func, ast.Attribute) \
                and arg.func.attr == "detector_replica":
            used["liveliness"].add("detector/replicas/**")
    return used


@pytest.mark.parametrize("name", dataflow.SERVICES)
def test_the_table_is_what_a_service_runs(name: str) -> None:
    """A service subscribes and publishes through the table (`Service.subscribe`, `open_outputs`), never by hand:
    its module calls neither `listen` nor `publisher`, each port names a handler the service has, and each `when` an
    attribute it has. What stays hand-written (a query, a queryable, liveliness tokens) is what the table declares."""
    node = dataflow.node(name)
    path = PROJECT / "semmap" / "services" / name / "service.py"
    source = path.read_text()
    used = keys_used(source)
    assert not used["inputs"] and not used["outputs"], f"{name} subscribes or publishes by hand"
    assert used["asks"] == set(node.asks) and used["answers"] == set(node.answers), name
    assert used["liveliness"] == set(node.liveliness), name
    cls = next(v for v in vars(importlib.import_module(node.module + ".service")).values()
               if isinstance(v, type) and getattr(v, "name", None) == name)
    for port in node.ports:
        assert callable(getattr(cls, port.handler, None)), f"{name}: no handler {port.handler} for {port.topic}"
        assert not port.when or hasattr(cls, port.when), f"{name}: no attribute {port.when}"


def test_the_lockstep_order_and_its_feedback_come_from_the_ports() -> None:
    assert dataflow.lockstep_order() == ("detector", "tracker", "odometry", "associator", "backend")
    assert [(stage, port.topic) for stage, port in dataflow.feedback_ports()] == [
        ("associator", "poses/corrected"), ("tracker", "map/updates")]


def test_every_topic_is_declared_once_with_a_message_class() -> None:
    names = [t.name for t in dataflow.TOPICS]
    assert len(names) == len(set(names))
    for node in dataflow.NODES:
        for topic in (*node.inputs, *node.outputs, *node.asks, *node.answers, *node.liveliness):
            assert topic in names, f"{node.name}: {topic} is not in TOPICS"
        assert all(name in dataflow.BY_NAME for f in node.flags for name in f.with_nodes), node.name
        assert node.replicas == "1" or node.replicas.startswith("--")
    for topic in dataflow.TOPICS:
        assert topic.message.startswith("(") or hasattr(messages, topic.message), topic


def test_every_input_has_a_publisher_and_every_output_a_reader() -> None:
    outputs = {t for n in dataflow.NODES for t in n.outputs} | {"progress/*", "status/**"}
    inputs = {t for n in dataflow.NODES for t in n.inputs}
    assert inputs <= outputs, inputs - outputs
    assert {t for n in dataflow.NODES for t in n.outputs} <= inputs


def test_publishers_are_the_declared_outputs() -> None:
    assert dataflow.publishers() == PUBLISHERS
    assert PUBLISHERS["frames"] == ("player", "external") and PUBLISHERS["poses/corrected"] == ("backend",)
    assert set(PUBLISHERS["control"]) == {"orchestrator", "player", "external"}


def _rule_keys(acl: dict, rule_id: str) -> list[str]:
    rule = next((r for r in acl["rules"] if r["id"] == rule_id), None)
    return [] if rule is None else [k.removeprefix(f"{secure_profile.ROBOTS}/") for k in rule["key_exprs"]]


@pytest.mark.parametrize("node", dataflow.NODES, ids=lambda n: n.name)
def test_the_access_control_list_grants_what_the_node_declares(node: dataflow.Node) -> None:
    """Each identity may receive exactly what its node reads, put exactly what it writes (and a service its
    status and progress), ask and answer what it declares: no more, no less."""
    acl = secure_profile.access_control()
    reports = list(dataflow.service_reports(node.name)) if node.kind == "service" else []
    assert _rule_keys(acl, f"{node.name}-sub") == list(node.reads())
    assert _rule_keys(acl, f"{node.name}-receive") == list(node.reads())
    assert _rule_keys(acl, f"{node.name}-put") == [*node.outputs, *reports]
    assert _rule_keys(acl, f"{node.name}-query") == list(node.asks)
    assert _rule_keys(acl, f"{node.name}-queryable") == list(node.answers)
    assert _rule_keys(acl, f"{node.name}-replicas") == list(node.liveliness)
    assert set(secure_profile.IDENTITIES) == set(dataflow.BY_NAME)


def test_viz_reads_no_status_and_may_ask_the_map() -> None:
    """The list grants viz what it uses: not `status/**` (it would ignore it), not `observations` and `dynamic`
    (it never reads them), but the map query it makes at its start."""
    viz = dataflow.node("viz")
    assert "status/**" not in viz.inputs and not {"observations", "dynamic"} & set(viz.inputs)
    assert viz.asks == ("map/query",)


def test_the_player_waits_for_the_lockstep_stages() -> None:
    assert dataflow.player_wait_for({"detector": 2}) == "odometry,detector:2,tracker,associator,backend"
    assert dataflow.player_wait_for({}, lockstep=False) == "viz"
    assert dataflow.player_wait_for({}, running=["detector", "tracker"]) == "detector,tracker"
    assert dataflow.wiring_flags("odometry", ["odometry", "detector"]) == []
    assert dataflow.wiring_flags("odometry", ["detector", "tracker"]) == ["--await-dynamic"]


def test_semmap_run_passes_the_declared_wiring() -> None:
    from semmap.cli.run import pipeline_specs
    from semmap.core.config import load_config

    specs = {s.name: s for s in pipeline_specs("synthetic", load_config(), 2, True)}
    assert list(specs) == list(dataflow.PIPELINE)
    assert "--await-backend" in specs["associator"].extra_args and "--await-dynamic" in specs["odometry"].extra_args
    assert "--wait-for-map" in specs["viz"].extra_args and specs["detector"].replicas == 2
    assert [s for s in specs if specs[s].lockstep] == [n.name for n in dataflow.NODES if n.lockstep]
    alone = {s.name: s for s in pipeline_specs("synthetic", load_config(), 1, False, only=["odometry", "tracker"])}
    assert alone["odometry"].extra_args == [] and "viz" not in alone


def _bare(service_module: str, class_name: str) -> object:
    """A service object with just what `listen` / `publisher` look at (no bus, no process)."""
    cls = getattr(importlib.import_module(service_module), class_name)
    service = cls.__new__(cls)
    service.lockstep = True
    service.bus = SimpleNamespace(keys=KEYS, publisher=lambda key: key, subscribe=lambda *a, **k: None)
    return service


def test_a_service_refuses_a_key_its_node_does_not_declare() -> None:
    viz = _bare("semmap.services.viz.service", "VizService")
    with pytest.raises(dataflow.UndeclaredKeyError, match="status"):
        viz.listen(KEYS.status_all, messages.ServiceStatus, print)  # type: ignore[attr-defined]
    with pytest.raises(dataflow.UndeclaredKeyError, match="frames"):
        viz.publisher(KEYS.frames)  # type: ignore[attr-defined]
    tracker = _bare("semmap.services.tracker.service", "TrackerService")
    assert tracker.publisher(KEYS.tracks) == KEYS.tracks  # type: ignore[attr-defined]
    with pytest.raises(dataflow.UndeclaredKeyError, match="not a node"):
        dataflow.check_input("stranger", "frames")


def test_design_doc_shows_the_declared_dataflow() -> None:
    """docs/DESIGN.md's dataflow section is what `python -m semmap.core.dataflow --write docs/DESIGN.md` writes."""
    text = (PROJECT / "docs" / "DESIGN.md").read_text()
    assert dataflow.with_section(text) == text, "regenerate: python -m semmap.core.dataflow --write docs/DESIGN.md"
