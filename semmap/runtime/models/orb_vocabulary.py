"""`semmap models vocabulary`: find a user's colour images, build an ORB vocabulary from them, write it atomically.

The clustering itself is pure computation (semmap/algorithms/odometry/vocabulary.py); this module does the file
work around it: which images a folder holds (a plain folder, a TUM folder with rgb/, a 7-Scenes folder with
*.color.png next to *.depth.png, or a folder of such sequences), reading them, and the atomic write.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from semmap.algorithms.odometry.vocabulary import (
    VocabularyError,
    build_vocabulary,
    check_parameters,
    orb_descriptors,
)
from semmap.core.outputs import atomic_write_text
from semmap.datasets.images import read_rgb

__all__ = ["VocabularyBuild", "VocabularyError", "colour_images", "spread", "write_vocabulary"]

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")
_COLOUR_HINTS = ("color", "colour", "rgb")
_NOT_COLOUR_HINTS = ("depth", "mask", "label", "seg", "normal")
_COLOUR_DIRS = ("rgb", "color", "colour", "image_2", "image_0", "images", "image", "cam0")


@dataclass(frozen=True)
class VocabularyBuild:
    path: Path
    images: int
    descriptors: int
    nodes: int
    words: int
    seconds: float


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _folder_colour(folder: Path, depth: int = 0) -> list[Path]:
    files = _image_files(folder)
    colour = [p for p in files if any(h in p.name.lower() for h in _COLOUR_HINTS)]
    if colour:
        return colour
    plain = [p for p in files if not any(h in p.name.lower() for h in _NOT_COLOUR_HINTS)]
    if plain:
        return plain
    for name in _COLOUR_DIRS:  # TUM rgb/, KITTI image_2/, EuRoC cam0/ ...
        if (folder / name).is_dir() and (found := _folder_colour(folder / name, depth + 1)):
            return found
    if depth >= 1:
        return []
    out: list[Path] = []  # a folder of sequences (7-Scenes seq-01, seq-02, ...)
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and p.name.lower() not in ("depth",)):
        out.extend(_folder_colour(sub, depth + 1))
    return out


def colour_images(paths: Sequence[str | Path]) -> list[Path]:
    """The colour images named by files and folders, in order (see the module doc for what a folder gives)."""
    out: list[Path] = []
    for raw in paths:
        p = Path(raw)
        if p.is_dir():
            out.extend(_folder_colour(p))
        elif p.exists():
            out.append(p)
        else:
            raise VocabularyError(f"no such file or folder: {p}")
    return out


def spread(items: Sequence[Path], limit: int | None) -> list[Path]:
    """At most `limit` items, evenly spread over the sequence (first and last included)."""
    if limit is None or len(items) <= limit:
        return list(items)
    idx = np.unique(np.linspace(0, len(items) - 1, limit).round().astype(int))
    return [items[i] for i in idx]


def write_vocabulary(
    paths: Sequence[str | Path],
    out: str | Path,
    k: int = 10,
    levels: int = 5,
    max_images: int | None = 400,
    seed: int = 0,
    log: Callable[[str], None] | None = None,
) -> VocabularyBuild:
    """Build a DBoW2 vocabulary from the images under `paths` and write it to `out` (atomic).

    Raises VocabularyError (no images, too few descriptors, bad parameters), DatasetError (an unreadable image)
    or OSError (the output cannot be written); each message is one line.
    """
    out = Path(out)
    check_parameters(k, levels)
    if max_images is not None and max_images < 2:
        raise VocabularyError(f"--max-images must be at least 2, got {max_images}")
    if not out.parent.is_dir():
        raise VocabularyError(f"output folder does not exist: {out.parent}")
    images = spread(colour_images(paths), max_images)
    if not images:
        raise VocabularyError(f"no images found in {', '.join(str(p) for p in paths)}")
    t0 = time.perf_counter()
    descriptors = []
    for i, path in enumerate(images):
        descriptors.append(orb_descriptors(read_rgb(path)))
        if log and (i + 1) % 100 == 0:
            log(f"ORB features: {i + 1}/{len(images)} images")
    n_desc = sum(len(d) for d in descriptors)
    if log:
        log(f"clustering {n_desc} descriptors of {len(images)} images (k={k}, L={levels}) ...")
    voc = build_vocabulary(descriptors, k=k, levels=levels, seed=seed)
    atomic_write_text(out, voc.to_text())
    return VocabularyBuild(out, len(images), n_desc, voc.n_nodes - 1, voc.n_words, time.perf_counter() - t0)


def vocabulary_for(data: str | Path, out: Path, max_images: int = 300,
                   log: Callable[[str], None] | None = None) -> tuple[Path | None, str]:
    """ORB-SLAM3's vocabulary for a run where none is at hand (no `odometry.orbslam3_vocabulary`, none in the model
    dir): built from the recording's own colour frames and kept at `out` for later runs, so that `auto` gets the
    good front end on any machine (ORB-SLAM3 0.017 m on TUM fr1_desk where the built-in `rgbd` gets 0.33 m).
    Returns (path, how it came) or (None, why not): a recording without colour image files (a bag) has nothing to
    build one from."""
    try:
        images = colour_images([data])
    except VocabularyError:
        images = []
    if len(images) < 2:
        return None, "no vocabulary at hand and no colour image files in the recording to build one from"
    try:
        built = write_vocabulary([data], out, max_images=max_images, log=log)
    except (VocabularyError, OSError, ValueError) as exc:
        return None, f"no vocabulary at hand and building one from the recording failed: {exc}"
    return built.path, (f"vocabulary built from this recording's frames ({built.images} images, {built.seconds:.0f} s) "
                        f"and kept at {built.path} for later runs")
