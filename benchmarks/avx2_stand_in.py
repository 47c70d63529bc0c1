"""An onnxruntime whose kernels are an AVX2-only CPU's, on a CPU with AVX-512, AVX-VNNI or AMX: a stand-in for an
AVX2-only machine.

Why: real time on 2 cores is decided by the detector's speed *and* its numbers, and both depend on the CPU's SIMD
extensions: without VNNI the int8 model with 8-bit weights is barely faster than fp32 and disagrees with it (its
8-bit products saturate), so `semmap models doctor` chooses differently there than on a VNNI machine. Developers
are lent machines of either class by chance; on an AVX-512 one the AVX2 path is never exercised, and a bug that
only shows there (such as one in the doctor's tie margin) goes unseen. onnxruntime has no switch for its kernel
choice: MLAS, its math library, reads CPUID once at start-up and picks its kernels. So this script copies the
installed `onnxruntime` package and changes, in the copy's extension module, the branches of each copy of
MLAS's start-up check that take kernels an AVX2-only CPU lacks: AVX-VNNI (`test $0x10, %al; je` after cpuid(7,1)),
AVX-512F (`test $0x10000, <cpuid(7).ebx>; je`; AVX-512 VNNI lies behind it), AVX-VNNI-INT8 and AVX-NE-CONVERT
(tests of cpuid(7,1).edx) each become `jmp`, and AMX's `jne` (no AMX-TILE and AMX-INT8) an unconditional jump
(an Intel Xeon with AVX-VNNI and AMX, with only AVX-512F turned off, still runs its int8 on VNNI). Everything
else, the AVX2/FMA kernels and the u8s8 int8 path of a CPU without VNNI included, runs as on an
AVX2-only CPU. What it does not change: the core's speed (a Zen 4 core running AVX2 code is ~10 % faster per clock
than a Zen 2/3 one), and the CPU flags `/proc/cpuinfo` shows (so the doctor's cache key still names AVX-512: use a
model dir of its own).

    .venv/bin/python benchmarks/avx2_stand_in.py --out /tmp/ort-avx2
    PYTHONPATH=/tmp/ort-avx2 SEMMAP_MODEL_DIR=/tmp/models-avx2 .venv/bin/semmap models doctor --remeasure
    PYTHONPATH=/tmp/ort-avx2 SEMMAP_MODEL_DIR=/tmp/models-avx2 .venv/bin/python benchmarks/bench_realtime.py

(the model dir needs the models: link yolov5s.onnx, yolov5s.int8.onnx, yolov5s.int8w7.onnx and yolov5s.names.json
into it). Every process a run starts inherits PYTHONPATH, so all of them load the copy. A lab tool, never used by
semmap itself.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import shutil
import sys
from pathlib import Path

XGETBV = b"\x0f\x01\xd0"
CPUID_LEAF7 = re.compile(rb"\xb8\x07\x00\x00\x00\x0f\xa2", re.S)  # mov $7, %eax; cpuid
CPUID_LEAF7_1 = re.compile(rb"\xb8\x07\x00\x00\x00\xb9\x01\x00\x00\x00\x0f\xa2", re.S)  # eax 7, ecx 1; cpuid
# test $0x10000, %r32 (optionally REX.B) followed by je rel8: "AVX-512F in cpuid(7).ebx?"
AVX512F_TEST = re.compile(rb"(\x41)?\xf7[\xc0-\xc7]\x00\x00\x01\x00\x74(.)", re.S)
# test $0x10, %al; je rel8: "AVX-VNNI in cpuid(7,1).eax?" (MLAS's next check, just before AVX-512F)
AVX_VNNI_TEST = re.compile(rb"\xa8\x10\x74(.)", re.S)
# after AVX-512F, two tests of cpuid(7,1).edx: AVX-VNNI-INT8 (`test $0x10, %dl`) and AVX-NE-CONVERT (`and $0x20,
# %edx` or `%dl`), each followed by je rel8
EDX_TESTS = re.compile(rb"(?:\xf6\xc2\x10|\x83\xe2\x20|\x80\xe2\x20)\x74(.)", re.S)
# not %r32; and $0x3000000, %r32 (AMX-TILE and AMX-INT8 of cpuid(7).edx); then, at most one instruction later,
# jne rel32: "no AMX?"
AMX_TEST = re.compile(rb"(?:\x41)?\x81[\xe0-\xe7]\x00\x00\x00\x03(?:.{0,8}?)\x0f\x85", re.S)
WINDOW = 0x500  # MLAS's check of leaf 7 follows its xgetbv within a few hundred bytes


@dataclasses.dataclass(frozen=True)
class Site:
    """One branch of MLAS's start-up check, rewritten so that it never takes the kernels `feature` selects."""

    feature: str
    offset: int  # of the conditional jump
    patched: bytes  # what replaces its bytes

    def apply(self, blob: bytearray) -> None:
        blob[self.offset : self.offset + len(self.patched)] = self.patched


def _short_jump(at: int, feature: str) -> Site:
    """`je rel8` at `at` becomes `jmp rel8` to the same target: the kernels it guards are skipped."""
    return Site(feature, at, b"\xeb")


def patch_sites(blob: bytes) -> list[Site]:
    """Each branch of each copy of MLAS's start-up CPU check that takes kernels an AVX2-only CPU lacks: AVX-VNNI,
    AVX-512F (and with it AVX-512 VNNI), AVX-VNNI-INT8, AVX-NE-CONVERT and AMX."""
    sites: list[Site] = []
    at = blob.find(XGETBV)
    while at != -1:
        window = blob[at : at + WINDOW]
        leaf7 = CPUID_LEAF7.search(window)
        if leaf7 is not None:
            found = AVX512F_TEST.search(window, leaf7.end())
            leaf7_1 = CPUID_LEAF7_1.search(window, leaf7.end())
            vnni = AVX_VNNI_TEST.search(window, leaf7_1.end()) if leaf7_1 is not None else None
            # MLAS checks AVX-VNNI (cpuid(7,1).eax bit 4: `test $0x10, %al`) just before AVX-512F
            if found is not None and vnni is not None and vnni.end() <= found.start():
                sites.append(_short_jump(at + vnni.start() + 2, "AVX-VNNI"))
                sites.append(_short_jump(at + found.end() - 2, "AVX-512F"))
                edx = list(EDX_TESTS.finditer(window, found.end(), found.end() + 0x80))
                sites += [_short_jump(at + m.end() - 2, name)
                          for m, name in zip(edx, ("AVX-VNNI-INT8", "AVX-NE-CONVERT"), strict=False)]  # fmt: skip
                amx = AMX_TEST.search(window, found.end())
                if amx is not None:  # jne rel32 (0f 85 r32) -> nop; jmp rel32 (90 e9 r32): the same target
                    sites.append(Site("AMX", at + amx.end() - 2, b"\x90\xe9"))
        at = blob.find(XGETBV, at + 1)
    return sorted(set(sites), key=lambda s: s.offset)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="a directory to hold the patched onnxruntime")
    args = parser.parse_args(argv)
    import onnxruntime

    source = Path(onnxruntime.__file__).parent
    target = args.out / "onnxruntime"
    if target.exists():
        shutil.rmtree(target)
    shutil.copytree(source, target)
    modules = sorted((target / "capi").glob("onnxruntime_pybind11_state*.so"))
    if len(modules) != 1:
        print(f"expected one extension module in {target / 'capi'}, found {len(modules)}", file=sys.stderr)
        return 2
    blob = bytearray(modules[0].read_bytes())
    sites = patch_sites(bytes(blob))
    if not any(site.feature == "AVX-512F" for site in sites):
        print("MLAS's AVX-512F check was not found: another onnxruntime build; nothing patched", file=sys.stderr)
        return 2
    for site in sites:
        site.apply(blob)
    modules[0].write_bytes(bytes(blob))
    features = sorted({site.feature for site in sites})
    print(f"onnxruntime {onnxruntime.__version__} with AVX2 kernels only: {target} ({len(sites)} branches of "
          f"{sum(site.feature == 'AVX-512F' for site in sites)} copies of MLAS's CPU check patched: "
          f"{', '.join(features)} never taken)")  # fmt: skip
    print(f"use it with: PYTHONPATH={args.out} SEMMAP_MODEL_DIR=<a model dir of its own> ...")
    return 0


if __name__ == "__main__":
    sys.exit(main())
