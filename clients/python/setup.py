"""Builds `semmap-client` from the project's own modules (../../semmap): one copy of the code, not a fork.

Only the modules the client needs go into the wheel, copied at build time (setuptools refuses a package folder
outside this one); the heavy stack (Open3D, GTSAM, ONNX Runtime, Rerun, evo) is never imported by them.
`tests/client/test_light_client.py` installs this package into bare venvs (Python 3.10 and 3.12 where present)
and checks that nothing else comes along.
"""

import shutil
from pathlib import Path

from setuptools import Distribution, setup
from setuptools.command.build_py import build_py

SOURCE = Path(__file__).resolve().parents[2] / "semmap"
MODULES = (
    "__init__",
    "core/__init__",
    "core/messages",
    "core/keys",
    "core/outputs",
    "runtime/__init__",
    "runtime/client",
    "runtime/bus",
    "runtime/map_query",
    "runtime/map_store",
    "runtime/run_registry",  # SemmapClient.attach: the run's recorded endpoint
)


class BuildClientModules(build_py):
    def run(self) -> None:
        super().run()
        target = Path(self.build_lib) / "semmap"
        target.mkdir(parents=True, exist_ok=True)
        for name in MODULES:
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(SOURCE / f"{name}.py", target / f"{name}.py")


class ClientDistribution(Distribution):
    def has_pure_modules(self) -> bool:  # build_py and install_lib run only for distributions with modules
        return True


if not (SOURCE / "runtime" / "client.py").is_file():
    raise SystemExit(f"semmap-client builds from the semmap source tree: {SOURCE} not found")
setup(packages=[], distclass=ClientDistribution, cmdclass={"build_py": BuildClientModules})
