"""`semmap diff` / `semmap merge` on saved maps: registration by objects, moved / missing / added, fusion."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from msgspec.structs import replace
from scipy.spatial.transform import Rotation

from semmap.algorithms.map_merge import diff_maps, merge_maps, register, transform_landmark
from semmap.core.messages import Landmark
from semmap.runtime.maps.map_store import read_map_json, write_map_json

PROJECT = Path(__file__).resolve().parents[2]
CLASSES = ("chair", "cup", "tv", "book", "bottle", "laptop", "clock", "plant", "chair", "cup", "vase", "bowl")


def _room(seed: int = 0) -> list[Landmark]:
    rng = np.random.default_rng(seed)
    out = []
    for i, cls in enumerate(CLASSES):
        c = rng.uniform([0, 0, 0], [5, 4, 1.8])
        r = float(rng.uniform(0.05, 0.4))
        out.append(Landmark(i, cls, tuple(float(v) for v in c), r, (r, r, r), 10 + i, 0.0, 30.0))
    return out


def _frame() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("zyx", [35, 8, -5], degrees=True).as_matrix()
    T[:3, 3] = [2.5, -1.2, 0.3]
    return T


def _second_session(a: list[Landmark]) -> tuple[list[Landmark], np.ndarray]:
    """The room a day later, mapped in another frame: two objects moved, one gone, one new; ids of its own."""
    T_b_from_a = _frame()
    b = []
    for lm in a:
        if lm.id == 5:
            continue  # the laptop was taken away
        c = np.array(lm.centroid) + (np.array([1.5, 0.5, 0.0]) if lm.id in (1, 3) else 0.0)  # cup, book moved
        c = c + np.random.default_rng(lm.id).normal(0, 0.02, 3)
        b.append(replace(lm, id=100 + lm.id, centroid=tuple(float(v) for v in c)))
    b.append(Landmark(200, "backpack", (1.0, 1.0, 0.3), 0.2, (0.3, 0.2, 0.4), 7, 40.0, 60.0))
    return [transform_landmark(lm, T_b_from_a) for lm in b], T_b_from_a


def test_register_diff_and_merge() -> None:
    a = _room()
    b, T_b_from_a = _second_session(a)
    fit = register(a, b).result
    assert fit is not None
    D = fit.transform @ T_b_from_a  # should be the identity
    assert np.linalg.norm(D[:3, 3]) < 0.05 and np.degrees(np.arccos((np.trace(D[:3, :3]) - 1) / 2)) < 1.0
    b_in_a = [transform_landmark(lm, fit.transform) for lm in b]
    d = diff_maps(a, b_in_a)
    assert sorted((x.id, y.id) for x, y in d.moved) == [(1, 101), (3, 103)]
    assert [lm.id for lm in d.missing] == [5]
    assert [lm.id for lm in d.added] == [200]
    assert len(d.kept) == len(a) - 3 and not d.unseen
    merged = merge_maps(a, b_in_a)
    # every kept object once, at A's place (B's 2 cm noise moves it by less); moved ones stay two (two places, 1.5
    # m apart: beyond the pairing gate), the new one is appended after A's ids
    assert len(merged) == len(a) + 2 + 1
    assert [lm.id for lm in merged][-3:] == [12, 13, 14]
    chair = next(lm for lm in merged if lm.id == 0)
    assert chair.observations == 20 and abs(chair.centroid[0] - a[0].centroid[0]) < 0.03


def test_a_refitted_merge_pairs_objects_a_rigid_one_would_not_trust() -> None:
    """B's drift inflates the centres' residual and so the rotation uncertainty: where B's trajectory is then
    re-optimised from the fit, the fit only has to pair the objects (a looser rotation guard); moved rigidly, the
    relocalisation's guard holds."""
    a = _room()[:8]
    centre = np.mean([lm.centroid for lm in a], axis=0)
    close = [replace(lm, centroid=tuple(float(v) for v in centre + 0.3 * (np.array(lm.centroid) - centre)))
             for lm in a]  # the objects within ~1 m: centres pin the rotation less
    rng = np.random.default_rng(7)
    b = [transform_landmark(replace(lm, id=100 + lm.id, centroid=tuple(float(v) for v in np.array(lm.centroid)
                                                                         + rng.normal(0, 0.06, 3))), _frame())
         for lm in close]
    rigid, refit = register(close, b), register(close, b, refit=True)
    assert rigid.result is None and rigid.reason.startswith("weak geometry"), rigid.reason
    assert refit.result is not None and 1.5 < refit.result.rotation_sigma_deg <= 3.0
    assert len(refit.result.matches) == len(a)


def test_statuses_of_a_relocalised_session() -> None:
    """B made from A with --map: `prior` landmarks were never looked at (unseen), `missing` ones were."""
    a = _room()
    b = [replace(lm, status="prior") if lm.id in (7, 8) else lm for lm in a]
    b = [replace(lm, status="missing") if lm.id == 2 else lm for lm in b]
    d = diff_maps(a, b)
    assert sorted(lm.id for lm in d.unseen) == [7, 8]
    assert [lm.id for lm in d.missing] == [2]
    assert not d.added and not d.moved
    merged = merge_maps(a, b)
    assert len(merged) == len(a) and next(lm for lm in merged if lm.id == 2).status == "present"
    assert {lm.status for lm in merge_maps(b, b)} == {"present", "prior", "missing"}


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "semmap.cli", *args], cwd=PROJECT, capture_output=True, text=True, timeout=120
    )


def test_cli(tmp_path: Path) -> None:
    a = _room()
    b, _ = _second_session(a)
    write_map_json(tmp_path / "a.json", a)
    (tmp_path / "b").mkdir()
    write_map_json(tmp_path / "b" / "map.json", b)
    out = _cli("diff", str(tmp_path / "a.json"), str(tmp_path / "b"), "--json")
    assert out.returncode == 0, out.stderr
    body = json.loads(out.stdout)
    assert sorted(m["a"]["id"] for m in body["moved"]) == [1, 3]
    assert [m["id"] for m in body["missing"]] == [5] and [m["id"] for m in body["added"]] == [200]
    assert body["registration"]["inliers"] >= 8
    text = _cli("diff", str(tmp_path / "a.json"), str(tmp_path / "b"))
    assert "9 kept, 2 moved, 1 missing, 1 added" in text.stdout, text.stdout
    merged = _cli("merge", str(tmp_path / "a.json"), str(tmp_path / "b"), "--out", str(tmp_path / "c"))
    assert merged.returncode == 0, merged.stderr
    assert len(read_map_json(tmp_path / "c" / "map.json")) == len(a) + 3


@pytest.mark.parametrize("what", ["unrelated", "too few"])
def test_cli_refuses_an_uncertain_registration(tmp_path: Path, what: str) -> None:
    a = _room(0)
    b = _room(1) if what == "unrelated" else a[:2]
    write_map_json(tmp_path / "a.json", a)
    write_map_json(tmp_path / "b.json", b)
    out = _cli("merge", str(tmp_path / "a.json"), str(tmp_path / "b.json"), "--out", str(tmp_path / "c"))
    assert out.returncode == 2 and "cannot register" in out.stderr, out.stderr
    assert not (tmp_path / "c").exists()
    same = _cli("diff", str(tmp_path / "a.json"), str(tmp_path / "a.json"), "--same-frame")
    assert same.returncode == 0 and f"{len(a)} kept, 0 moved, 0 missing, 0 added" in same.stdout


def test_cli_refuses_a_map_of_another_version(tmp_path: Path) -> None:
    write_map_json(tmp_path / "a.json", _room())
    body = json.loads((tmp_path / "a.json").read_text())
    body["schema"] = "semmap.map/9"
    (tmp_path / "b.json").write_text(json.dumps(body))
    out = _cli("diff", str(tmp_path / "a.json"), str(tmp_path / "b.json"))
    assert out.returncode == 2 and "newer semmap" in out.stderr


def test_merge_pairs_two_sides_of_one_object_by_their_clouds() -> None:
    """Two maps of one table, each from its own side: centres 40 cm apart (beyond the gate), clouds overlapping
    where both saw the top. With clouds they are one landmark; a same-class neighbour that does not touch is not.
    The landmark stays at A's place (B saw other parts of one object in place: no evidence that it moved, and a
    session relocalised against A would hold it there too) and spans both sides."""
    rng = np.random.default_rng(0)
    top = rng.uniform([-0.6, -0.4, 0.7], [0.6, 0.4, 0.75], (800, 3))
    side_a, side_b = top[top[:, 0] < 0.2], top[top[:, 0] > -0.2]
    table_a = Landmark(0, "dining table", tuple(side_a.mean(0)), 0.3, (0.8, 0.8, 0.05), 40, 0.0, 10.0)
    table_b = Landmark(7, "dining table", tuple(side_b.mean(0)), 0.3, (0.8, 0.8, 0.05), 60, 20.0, 30.0)
    assert np.linalg.norm(np.subtract(table_a.centroid, table_b.centroid)) > 0.35
    other = rng.uniform([1.5, -0.4, 0.7], [2.7, 0.4, 0.75], (400, 3))  # another table beside it
    table_c = Landmark(8, "dining table", tuple(other.mean(0)), 0.3, (0.8, 0.8, 0.05), 30, 20.0, 30.0)
    merged = merge_maps([table_a], [table_b, table_c], None, {0: side_a}, {7: side_b, 8: other})
    assert [(lm.id, lm.observations) for lm in merged] == [(0, 100), (1, 30)]
    assert np.linalg.norm(np.subtract(merged[0].centroid, table_a.centroid)) < 0.03  # A's place
    assert merged[0].extent[0] > 1.0  # both sides
    assert len(merge_maps([table_a], [table_b, table_c])) == 3  # no clouds: the centres decide


def test_refit_needs_the_run_beside_the_map(tmp_path: Path) -> None:
    from semmap.runtime.maps.map_refit import refit_run

    a = _room()
    b, _ = _second_session(a)
    fit = register(a, b).result
    assert fit is not None
    assert "backend.sqlite not found" in refit_run(tmp_path / "map.sqlite", None, fit, a)
