"""The in-process driver runs prior maps as the services do (the prior-map policy lives in
`AssociatorStage`, not in the associator service): a second session, in a frame of its own
(`odometry.frame_offset`), started from the first session's map, relocalises against it, maps in its frame and
keeps every prior landmark under its id.

The fast test is the analytic sphere scene (seconds); the slow one is `python -m semmap.runtime.pipeline.inprocess
--map`
on the synthetic room, the scene of tests/maps/test_sessions.py (minutes: it renders the frames).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from semmap.algorithms.odometry.frontends import frame_offset
from semmap.algorithms.relocalize import rotation_angle_deg
from semmap.core.config import load_config
from semmap.runtime.maps.map_store import read_map_json
from semmap.runtime.pipeline import inprocess
from semmap.runtime.pipeline.inprocess import run_loop
from tests.associator.helpers import TABLE_SPHERES, Sphere
from tests.maps.session_checks import orbit_recording

OFFSET = [1.5, -2.0, 0.3, 5.0, -3.0, 40.0]
SPHERES = [
    *TABLE_SPHERES,
    Sphere((0.3, 0.35, 0.7), 0.05, "orange"),
    Sphere((-0.35, -0.3, 0.9), 0.06, "vase"),
]


def _close_to_the_offset(transform: np.ndarray) -> None:
    """The relocalisation's transform (session frame -> prior frame) undoes the session's frame offset."""
    error = np.linalg.inv(frame_offset(OFFSET)) @ transform
    assert np.linalg.norm(error[:3, 3]) < 0.15 and rotation_angle_deg(error[:3, :3]) < 3.0


def test_a_second_session_relocalises_against_the_first_in_process(tmp_path: Path) -> None:
    day1 = run_loop(orbit_recording(360, SPHERES), load_config(None, ["odometry.mode=gt"]), "gt")
    day1.write_outputs(tmp_path / "day1")  # map.sqlite: a prior map
    config = load_config(None, ["odometry.mode=gt", f"odometry.frame_offset={OFFSET}"])
    day2 = run_loop(orbit_recording(200, SPHERES), config, "gt", prior_map=tmp_path / "day1" / "map.sqlite")
    day2.write_outputs(tmp_path / "day2")
    prior = day2.associator.prior
    assert prior is not None and prior.relocalised and prior.fit is not None  # (measured: frame 30, 6 inliers)
    _close_to_the_offset(prior.transform)
    record = json.loads((tmp_path / "day2" / "relocalization.json").read_text())
    assert record["frame_id"] == prior.aligned_at and record["inliers"] >= 5
    # every prior landmark kept under its id, in the prior map's frame, and no duplicate of one
    before = {lm.id: lm for lm in read_map_json(tmp_path / "day1" / "map.json")}
    after = {lm.id: lm for lm in read_map_json(tmp_path / "day2" / "map.json")}
    assert len(before) == len(SPHERES) and set(before) <= set(after) and len(after) == len(SPHERES)
    for lid, lm in before.items():
        assert math.dist(lm.centroid, after[lid].centroid) < 0.05


@pytest.mark.slow
def test_the_inprocess_command_runs_a_prior_map(tmp_path: Path) -> None:
    """`python -m semmap.runtime.pipeline.inprocess --map DAY1`: the two sessions of tests/maps/test_sessions.py."""
    cache = ["--cache-dir", str(tmp_path / "cache"), "--odometry", "gt"]
    assert inprocess.main(["synthetic:frames=300,seed=0", *cache, "--out", str(tmp_path / "day1")]) == 0
    assert inprocess.main(["synthetic:frames=300,seed=0,moved=2,removed=1", *cache, "--frames", "150",
                           "--set", f"odometry.frame_offset={OFFSET}", "--map", str(tmp_path / "day1"),
                           "--out", str(tmp_path / "day2")]) == 0
    fit = json.loads((tmp_path / "day2" / "relocalization.json").read_text())
    assert fit["inliers"] >= 5 and fit["rms_m"] < 0.1 and fit["runner_up"] < fit["inliers"]
    _close_to_the_offset(np.array(fit["transform"]).reshape(4, 4))
    day1 = {lm.id for lm in read_map_json(tmp_path / "day1" / "map.json")}
    assert day1 <= {lm.id for lm in read_map_json(tmp_path / "day2" / "map.json")}


def test_the_inprocess_command_refuses_a_folder_without_a_map(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    recording = orbit_recording(3, SPHERES)  # (no rendering: the prior map is what fails)
    monkeypatch.setattr(inprocess, "detect_recording", lambda *args, **kwargs: recording)
    monkeypatch.setattr(inprocess, "_open", lambda *args, **kwargs: None)
    (tmp_path / "empty").mkdir()
    assert inprocess.main(["synthetic", "--odometry", "gt", "--map", str(tmp_path / "empty")]) == 2
    assert "--map" in capsys.readouterr().err
