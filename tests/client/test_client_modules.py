"""What goes into `semmap-client` (clients/python/setup.py): the import closure of the client, read from the source,
so the messages come from the same definitions as the services', and only the image codec touches OpenCV."""

from __future__ import annotations

import ast
import runpy
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[2]


def _client_modules() -> dict[str, Path]:
    setup = runpy.run_path(str(PROJECT / "clients" / "python" / "setup.py"), run_name="not_main")
    return setup["client_modules"]()


def _imports_cv2(source: Path) -> bool:
    for node in ast.walk(ast.parse(source.read_text())):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
            [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
        if any(n == "cv2" or n.startswith("cv2.") for n in names):
            return True
    return False


def test_the_client_ships_the_services_messages_and_opencv_only_in_the_image_codec() -> None:
    modules = _client_modules()
    assert {"semmap.runtime.client", "semmap.core.messages", "semmap.core.messages.frames",
            "semmap.core.keys", "semmap.imaging.opencv"} <= set(modules)
    assert all(path.is_relative_to(PROJECT / "semmap") for path in modules.values())
    assert [name for name, path in modules.items() if _imports_cv2(path)] == ["semmap.imaging.opencv"]
    heavy = ("open3d", "gtsam", "onnxruntime", "rerun", "evo", "scipy", "yaml", "pydantic")
    assert not [name for name in modules if name.startswith(("semmap.algorithms", "semmap.services",
                                                             "semmap.datasets", "semmap.cli"))]
    for path in modules.values():
        top = {n.split(".")[0] for node in ast.walk(ast.parse(path.read_text()))
               for n in ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])}
        assert not top & set(heavy), (path, top & set(heavy))
