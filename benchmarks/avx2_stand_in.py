"""An onnxruntime whose kernels are an AVX2-only CPU's, on a CPU with AVX-512: a stand-in for the machines of issue 31.

Why: real time on 2 cores is decided by the detector's speed *and* its numbers, and both depend on the CPU's SIMD
extensions: without VNNI the int8 model is no faster than fp32 and disagrees with it (its 8-bit products saturate),
so `semmap models doctor` chooses fp32 512x384 there and int8 640x480 on a VNNI machine. Developers are lent
machines of either class by chance; on an AVX-512 one the AVX2 path was never exercised, and a bug that only shows
there went unseen for four sessions (session 24: the doctor's tie margin). onnxruntime has no switch for its
kernel choice: MLAS, its math library, reads CPUID once at start-up and picks its kernels. So this script copies
the installed `onnxruntime` package and changes, in the copy's extension module, the one branch of each copy of
MLAS's start-up check that takes the AVX-512F kernels (`test $0x10000, <cpuid leaf 7 ebx>; je <skip>` becomes
`jmp <skip>`). Everything else, the AVX2/FMA kernels and the u8s8 int8 path of a CPU without VNNI included, runs
as on an AVX2-only CPU. What it does not change: the core's speed (a Zen 4 core running AVX2 code is ~10 % faster
per clock than a Zen 2/3 one), and the CPU flags `/proc/cpuinfo` shows (so the doctor's cache key still names
AVX-512: use a model dir of its own).

    .venv/bin/python benchmarks/avx2_stand_in.py --out /tmp/ort-avx2
    PYTHONPATH=/tmp/ort-avx2 SEMMAP_MODEL_DIR=/tmp/models-avx2 .venv/bin/semmap models doctor --remeasure
    PYTHONPATH=/tmp/ort-avx2 SEMMAP_MODEL_DIR=/tmp/models-avx2 .venv/bin/python benchmarks/bench_realtime.py

(the model dir needs the models: link yolov5s.onnx, yolov5s.int8.onnx and yolov5s.names.json into it). Every
process a run starts inherits PYTHONPATH, so all of them load the copy. A lab tool, never used by semmap itself.
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
from pathlib import Path

XGETBV = b"\x0f\x01\xd0"
CPUID_LEAF7 = re.compile(rb"\xb8\x07\x00\x00\x00\x0f\xa2", re.S)  # mov $7, %eax; cpuid
# test $0x10000, %r32 (optionally REX.B) followed by je rel8: "AVX-512F in cpuid(7).ebx?"
AVX512F_TEST = re.compile(rb"(\x41)?\xf7[\xc0-\xc7]\x00\x00\x01\x00\x74(.)", re.S)
WINDOW = 0x500  # MLAS's check of leaf 7 follows its xgetbv within a few hundred bytes


def patch_sites(blob: bytes) -> list[tuple[int, int]]:
    """(offset, jump target) of each AVX-512F branch of MLAS's start-up CPU check in `blob`."""
    sites = []
    at = blob.find(XGETBV)
    while at != -1:
        window = blob[at : at + WINDOW]
        leaf7 = CPUID_LEAF7.search(window)
        if leaf7 is not None:
            found = AVX512F_TEST.search(window, leaf7.end())
            # MLAS checks AVX-VNNI (cpuid(7,1).eax bit 4: `test $0x10, %al`) just before AVX-512F
            if found is not None and b"\xa8\x10" in window[leaf7.end() : found.start()]:
                insn = at + found.start()
                length = 9 if found.group(1) else 8  # test (6 or 7 bytes) + je rel8 (2)
                target = insn + length + int.from_bytes(found.group(2), "little", signed=True)
                sites.append((insn, target))
        at = blob.find(XGETBV, at + 1)
    return sorted(set(sites))


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
    if not sites:
        print("MLAS's AVX-512F check was not found: another onnxruntime build; nothing patched", file=sys.stderr)
        return 2
    for insn, to in sites:
        rel = to - (insn + 2)
        if not -128 <= rel <= 127:
            print(f"jump at {insn:#x} out of reach", file=sys.stderr)
            return 2
        blob[insn : insn + 2] = bytes((0xEB, rel & 0xFF))  # jmp rel8: never take the AVX-512F kernels
    modules[0].write_bytes(bytes(blob))
    print(f"onnxruntime {onnxruntime.__version__} with AVX2 kernels only: {target} ({len(sites)} checks patched at "
          f"{', '.join(hex(s) for s, _ in sites)})")  # fmt: skip
    print(f"use it with: PYTHONPATH={args.out} SEMMAP_MODEL_DIR=<a model dir of its own> ...")
    return 0


if __name__ == "__main__":
    sys.exit(main())
