"""Every shell command in the README is exercised: by a named test (which must exist and use the command's own
options), or by CI itself (.ci/run runs `./dev.sh test`). A command added to the README without a test fails here."""

from __future__ import annotations

import re
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[2]

# README command (regex on the command with `.venv/bin/` dropped) -> tests that run it, and what their source must
# contain (the options the README shows). "CI" -> .ci/run must run exactly that command.
COVERAGE: list[tuple[str, list[str], list[str]]] = [
    (r"^\./dev\.sh test$", ["CI"], []),
    # `./dev.sh demo` is `semmap run synthetic --out out/demo` after the set-up that `./dev.sh test` runs in CI
    (r"^\./dev\.sh demo$", ["tests/pipeline/test_run.py::test_synthetic_run_writes_every_output"], ["synthetic"]),
    (
        r"^semmap run \S*7scenes-redkitchen --out \S+$",
        [
            "tests/pipeline/test_run.py::test_7scenes_run_through_separate_processes",
            "tests/pipeline/test_first_hour.py::test_official_7scenes_layout_runs_and_ends_with_the_summary",
        ],
        ["--out"],
    ),
    (
        r"^semmap view \S+ --web$",
        ["tests/viz/test_web_viewer_screenshot.py::test_web_viewer_screenshot_shows_the_landmark_spheres"],
        ["--web"],
    ),
    (
        r"^semmap query \S+ --class \S+$",
        ["tests/core/test_map_tools.py::test_query_class_is_case_insensitive_and_a_miss_lists_the_classes"],
        ["--class"],
    ),
    (
        r"^semmap run \S+ --out \S+ --odometry file:\S+ --time-offset \S+$",
        [
            "tests/pipeline/test_first_hour.py::test_a_trajectory_on_another_clock_is_refused_and_time_offset_fixes_it",
            "tests/pipeline/test_first_hour.py::test_tum_folder_with_camera_yaml_and_a_slam_trajectory_runs",
        ],
        ["--time-offset", "file:", "camera.yaml"],
    ),
    (
        r"^semmap run external --out \S+$",
        ["tests/pipeline/test_external_slam.py::test_example_client_gives_the_same_map_as_the_builtin_front_end"],
        ['"external"'],
    ),
    (
        r"^semmap run \S+\.mcap --out \S+ --odometry gt$",
        ["tests/datasets/test_ds_rosbag.py::test_bags_map_the_same_as_the_folder"],
        ['"mcap"', '"--odometry", "gt"'],
    ),
    (
        r"^semmap ros2 --run \S+$",
        [
            "tests/ros2/test_bridge_live.py::test_lockstep_with_the_documented_settings_processes_every_frame_the_camera_sent",
            "tests/ros2/test_bridge_live.py::test_real_time_at_30_hz_best_effort_maps_and_counts_every_lost_frame",
        ],
        ['"ros2"', '"--run"'],
    ),
    (
        r"^semmap diff \S+ \S+$",
        ["tests/maps/test_diff_merge.py::test_cli", "tests/maps/test_sessions.py::test_diff_names_the_changes"],
        ['"diff"'],
    ),
    (
        r"^docker compose (-f compose\.yaml -f compose\.secure\.yaml )?--profile player up --build --scale detector=2$",
        ["tests/deploy/test_containers.py::test_compose_stack_in_containers_maps_like_the_embedded_run"],
        ["--profile player up", "compose.yaml", "compose.secure.yaml", "DETECTORS = 2", '"secure"'],
    ),
    (
        r"^pip install \./clients/python$",
        ["tests/client/test_light_client.py::test_light_client_installs_without_the_heavy_stack_and_talks_to_the_bus"],
        ['"clients" / "python"', "pip"],
    ),
]


def readme_commands(text: str) -> list[str]:
    """Each command line of the README's ```bash blocks, comments and the `.venv/bin/` prefix dropped."""
    commands = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        for line in block.splitlines():
            command = re.sub(r"\s+#.*$", "", line).strip()
            if command and not command.startswith("#"):
                commands.append(re.sub(r"^\.venv/bin/", "", command))
    return commands


def test_every_readme_command_is_run_by_a_test_or_ci() -> None:
    commands = readme_commands((PROJECT / "README.md").read_text())
    assert len(commands) >= 5
    ci = (PROJECT / ".ci" / "run").read_text()
    uncovered = []
    for command in commands:
        rules = [(tests, needles) for pattern, tests, needles in COVERAGE if re.match(pattern, command)]
        if not rules:
            uncovered.append(command)
            continue
        for tests, needles in rules:
            for test in tests:
                if test == "CI":
                    assert re.search(rf"^{re.escape(command)}$", ci, flags=re.M), f"CI does not run {command!r}"
                    continue
                path, name = test.split("::")
                source = (PROJECT / path).read_text()
                assert re.search(rf"^(async )?def {name}\(", source, flags=re.M), f"{test} does not exist"
                for needle in needles:
                    assert needle in source, f"{path} never uses {needle!r} (README: {command})"
    assert not uncovered, f"README commands no test or CI runs: {uncovered}"


def test_the_set_up_commands_and_the_demo_are_what_dev_sh_does() -> None:
    readme = (PROJECT / "README.md").read_text()
    assert "./dev.sh demo" in readme and "./dev.sh test" in readme
    dev = (PROJECT / "dev.sh").read_text()
    assert re.search(r"demo\) setup; exec \.venv/bin/semmap run synthetic --out out/demo", dev)
    assert len(readme.splitlines()) <= 150


def test_readme_links_resolve() -> None:
    readme = (PROJECT / "README.md").read_text()
    missing = [
        link
        for link in re.findall(r"\]\(([^)#]+)\)", readme)
        if not link.startswith("http") and not (PROJECT / link).exists()
    ]
    assert not missing, missing
