"""Builds `semmap-client` from the project's own modules (../../semmap): one copy of the code, not a fork.

The wheel holds exactly the modules the client imports: the closure of `semmap.runtime.client`'s `semmap.*`
imports (deferred ones too), read from the source with `ast` at build time, plus the default image codec that
frames find by name (`semmap.imaging.opencv`, for `publish_frame`'s JPEG). No hand-kept list to drift: a module
the client starts to import comes along, and `tests/client/test_light_client.py` (bare venvs, Python 3.10 and
3.12 where present) checks that nothing heavy does. setuptools refuses a package folder outside this one, so
the modules are copied into the build at build time; the message definitions are the services' own.
"""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

from setuptools import Distribution, setup
from setuptools.command.build_py import build_py

SOURCE = Path(__file__).resolve().parents[2] / "semmap"
ENTRY_MODULES = ("semmap.runtime.client", "semmap.imaging.opencv")


def _module_file(name: str) -> Path | None:
    path = SOURCE.joinpath(*name.split(".")[1:])
    if (path / "__init__.py").is_file():
        return path / "__init__.py"
    return path.with_suffix(".py") if path.with_suffix(".py").is_file() else None


def _imported(name: str, source: Path) -> list[str]:
    """The `semmap.*` names a module imports (absolute or relative; a `from X import y` may name module X.y)."""
    package = name.split(".") if source.name == "__init__.py" else name.split(".")[:-1]
    names = []
    for node in ast.walk(ast.parse(source.read_text())):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[: len(package) - node.level + 1] + ([base] if base else []))
            names += [base, *(f"{base}.{alias.name}" for alias in node.names)]
    return [n for n in names if n == "semmap" or n.startswith("semmap.")]


def client_modules() -> dict[str, Path]:
    """Module name -> source file, for the entry modules, everything they import and their parent packages."""
    todo, found = list(ENTRY_MODULES), {}
    while todo:
        name = todo.pop()
        source = _module_file(name)
        if name in found or source is None:
            continue
        found[name] = source
        parts = name.split(".")
        todo += [".".join(parts[:i]) for i in range(1, len(parts))]
        todo += _imported(name, source)
    return found


class BuildClientModules(build_py):
    def run(self) -> None:
        super().run()
        for source in client_modules().values():
            target = Path(self.build_lib) / "semmap" / source.relative_to(SOURCE)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, target)


class ClientDistribution(Distribution):
    def has_pure_modules(self) -> bool:  # build_py and install_lib run only for distributions with modules
        return True


if __name__ == "__main__":  # (setuptools runs this file as __main__; tests import client_modules from it)
    if not (SOURCE / "runtime" / "client.py").is_file():
        raise SystemExit(f"semmap-client builds from the semmap source tree: {SOURCE} not found")
    setup(packages=[], distclass=ClientDistribution, cmdclass={"build_py": BuildClientModules})
