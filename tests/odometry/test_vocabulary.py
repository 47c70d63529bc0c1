"""ORB vocabulary building (semmap/algorithms/odometry/vocabulary.py, `semmap models vocabulary`).

The DBoW2 text format read back (tree shape, bytes, weights), the vectorised descent and IDF against a plain
per-descriptor reference, determinism, the CLI's folder handling and errors, and, on the real 7-Scenes frames, that
ORB-SLAM3 (the PyPI wheel) loads a vocabulary built here and tracks with it.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

from semmap.algorithms.odometry.vocabulary import (
    ORBVocabulary,
    VocabularyError,
    build_vocabulary,
    orb_descriptors,
    parse_text,
)
from semmap.cli.main import main as cli_main
from semmap.runtime.models.orb_vocabulary import colour_images, spread


def _synthetic_images(n_images: int = 12, per_image: int = 150, seed: int = 1) -> list[np.ndarray]:
    """Descriptors scattered around 30 random prototypes (a few bits flipped), so the tree has structure."""
    rng = np.random.default_rng(seed)
    protos = rng.integers(0, 256, (30, 32), dtype=np.uint8)
    out = []
    for _ in range(n_images):
        pick = protos[rng.integers(0, len(protos), per_image)]
        flips = np.packbits(rng.random((per_image, 256)) < 0.05, axis=1)
        out.append(pick ^ flips)
    return out


def _hamming(a: np.ndarray, b: np.ndarray) -> int:
    return int(np.unpackbits(np.bitwise_xor(a, b)).sum())


def _reference_descend(voc: ORBVocabulary, d: np.ndarray) -> int:
    """DBoW2's TemplatedVocabulary::transform, one descriptor at a time."""
    children: dict[int, list[int]] = {}
    for i in range(1, voc.n_nodes):
        children.setdefault(int(voc.parent[i]), []).append(i)
    node = 0
    while node in children:
        kids = children[node]
        dists = [_hamming(d, voc.descriptors[c]) for c in kids]
        node = kids[int(np.argmin(dists))]  # first on ties, as DBoW2
    return node


def test_text_round_trip_has_dbow2_shape():
    voc = build_vocabulary(_synthetic_images(), k=4, levels=3, seed=3)
    text = voc.to_text()
    assert text.split("\n", 1)[0] == "4 3  0 0"  # as DBoW2's saveToTextFile writes it (L1 scoring, TF-IDF)
    assert not text.endswith("\n")  # loadFromTextFile would read a trailing empty line as one more node
    back = parse_text(text)
    assert back.n_nodes == voc.n_nodes == len(text.split("\n"))
    assert (back.k, back.levels, back.scoring, back.weighting) == (4, 3, 0, 0)
    assert (back.parent[1:] < np.arange(1, back.n_nodes)).all()  # parents come first
    np.testing.assert_array_equal(back.parent, voc.parent)
    np.testing.assert_array_equal(back.is_leaf, voc.is_leaf)
    np.testing.assert_array_equal(back.descriptors, voc.descriptors)
    np.testing.assert_allclose(back.weights, voc.weights, rtol=1e-5)
    depth = back.depth()
    assert depth[back.is_leaf].max() <= 3 and depth[back.is_leaf].min() >= 1
    n_children = np.bincount(back.parent[1:], minlength=back.n_nodes)
    assert (n_children[1:][~back.is_leaf[1:]] >= 1).all() and (n_children[back.is_leaf] == 0).all()
    assert n_children.max() <= 4
    assert back.n_words == int(back.is_leaf.sum()) > 16
    assert (back.weights[~back.is_leaf] == 0).all() and (back.weights[back.is_leaf] >= 0).all()
    lines = text.split("\n")[1:]
    assert all(0 <= int(v) <= 255 for line in lines[:50] for v in line.split()[2:34])


def test_descent_and_idf_match_a_plain_reference():
    images = _synthetic_images(n_images=6, per_image=60)
    voc = build_vocabulary(images, k=3, levels=3, seed=0)
    all_desc = np.concatenate(images)
    words = voc.transform(all_desc)
    assert [_reference_descend(voc, d) for d in all_desc[:120]] == words[:120].tolist()
    assert voc.is_leaf[words].all()
    per_image_words = [set(voc.transform(d).tolist()) for d in images]
    for leaf in np.flatnonzero(voc.is_leaf)[:40]:
        n_i = sum(leaf in s for s in per_image_words)
        expected = math.log(len(images) / n_i) if n_i else 0.0
        assert voc.weights[leaf] == pytest.approx(expected)


def test_same_seed_same_file_other_seed_other_file():
    images = _synthetic_images()
    a = build_vocabulary(images, k=5, levels=3, seed=7).to_text()
    assert build_vocabulary(images, k=5, levels=3, seed=7).to_text() == a
    assert build_vocabulary(images, k=5, levels=3, seed=8).to_text() != a


def test_refuses_what_cannot_make_a_vocabulary():
    images = _synthetic_images(n_images=3, per_image=20)
    with pytest.raises(VocabularyError, match="at least 2 images"):
        build_vocabulary(images[:1])
    with pytest.raises(VocabularyError, match="too few descriptors"):
        build_vocabulary([images[0][:3], images[1][:3]], k=10)
    with pytest.raises(VocabularyError, match="too few descriptors"):
        build_vocabulary([np.zeros((20, 32), np.uint8)] * 2, k=4)
    with pytest.raises(VocabularyError, match="k must be"):
        build_vocabulary(images, k=21)
    with pytest.raises(VocabularyError, match="first line"):
        parse_text("garbage")


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    return cv2.resize(small, (640, 480), interpolation=cv2.INTER_NEAREST)


def test_orb_descriptors_finds_features_on_texture():
    desc = orb_descriptors(_texture(0))
    assert desc.dtype == np.uint8 and desc.shape[1] == 32 and 200 <= len(desc) <= 1000
    assert orb_descriptors(np.zeros((480, 640), np.uint8)).shape == (0, 32)


def test_folders_give_their_colour_images(tmp_path: Path):
    scenes = tmp_path / "7scenes"
    scenes.mkdir()
    tum = tmp_path / "tum"
    (tum / "rgb").mkdir(parents=True)
    (tum / "depth").mkdir()
    for i in range(3):
        (scenes / f"frame-{i:06d}.color.png").write_bytes(b"x")
        (scenes / f"frame-{i:06d}.depth.png").write_bytes(b"x")
        (tum / "rgb" / f"{i}.png").write_bytes(b"x")
        (tum / "depth" / f"{i}.png").write_bytes(b"x")
    assert [p.name for p in colour_images([scenes])] == [f"frame-{i:06d}.color.png" for i in range(3)]
    assert [p.parent.name for p in colour_images([tum])] == ["rgb"] * 3
    assert len(colour_images([tmp_path])) == 6  # a folder of sequences
    assert [p.name for p in spread(colour_images([scenes]), 2)] == ["frame-000000.color.png", "frame-000002.color.png"]
    with pytest.raises(VocabularyError, match="no such file"):
        colour_images([tmp_path / "absent"])


def test_cli_writes_a_vocabulary_and_says_what_went_wrong(tmp_path: Path, capsys):
    images = tmp_path / "imgs"
    images.mkdir()
    for i in range(4):
        cv2.imwrite(str(images / f"{i}.png"), _texture(i))
    out = tmp_path / "voc.txt"
    assert cli_main(["models", "vocabulary", str(images), "--out", str(out), "--k", "4", "--levels", "3"]) == 0
    voc = parse_text(out.read_text())
    assert (voc.k, voc.levels) == (4, 3) and voc.n_words > 20
    assert not list(tmp_path.glob(".voc.txt.*"))  # the atomic write left no temporary file

    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli_main(["models", "vocabulary", str(empty), "--out", str(tmp_path / "x.txt")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: no images found")
    (images / "bad.png").write_bytes(b"not an image")
    assert cli_main(["models", "vocabulary", str(images), "--out", str(tmp_path / "x.txt")]) == 2
    assert "cannot decode" in capsys.readouterr().err.strip().splitlines()[-1]
    blank = tmp_path / "blank"
    blank.mkdir()
    for i in range(2):
        cv2.imwrite(str(blank / f"{i}.png"), np.zeros((48, 64, 3), np.uint8))
    assert cli_main(["models", "vocabulary", str(blank), "--out", str(tmp_path / "x.txt")]) == 2
    assert "at least 2 images" in capsys.readouterr().err.strip().splitlines()[-1]
    assert cli_main(["models", "vocabulary", str(images), "--k", "30", "--out", str(tmp_path / "x.txt")]) == 2
    assert "k must be 2..20" in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (tmp_path / "x.txt").exists()


SEVEN_SCENES_SETTINGS = """\
%YAML:1.0
File.version: "1.0"
Camera.type: "PinHole"
Camera1.fx: 585.0
Camera1.fy: 585.0
Camera1.cx: 320.0
Camera1.cy: 240.0
Camera1.k1: 0.0
Camera1.k2: 0.0
Camera1.p1: 0.0
Camera1.p2: 0.0
Camera1.k3: 0.0
Camera.width: 640
Camera.height: 480
Camera.fps: 30
Camera.RGB: 1
Stereo.ThDepth: 40.0
Stereo.b: 0.07732
RGBD.DepthMapFactor: 1000.0
ORBextractor.nFeatures: 1000
ORBextractor.scaleFactor: 1.2
ORBextractor.nLevels: 8
ORBextractor.iniThFAST: 20
ORBextractor.minThFAST: 7
Viewer.KeyFrameSize: 0.05
Viewer.KeyFrameLineWidth: 1.0
Viewer.GraphLineWidth: 0.9
Viewer.PointSize: 2.0
Viewer.CameraSize: 0.08
Viewer.CameraLineWidth: 3.0
Viewer.ViewpointX: 0.0
Viewer.ViewpointY: -0.7
Viewer.ViewpointZ: -1.8
Viewer.ViewpointF: 500.0
"""


@pytest.mark.slow  # 19 s on a shared 2-core machine (build ~60 frames, load, track 30)
@pytest.mark.needs_data
def test_orbslam3_loads_and_tracks_with_a_vocabulary_built_here(kitchen_dir: Path, tmp_path: Path):
    pyorbslam3 = pytest.importorskip("pyorbslam3", reason="pyorbslam3 (ORB-SLAM3 wheel) not installed")
    from semmap.runtime.models.orb_vocabulary import write_vocabulary

    frames = sorted(kitchen_dir.glob("frame-*.color.jpg"))
    assert len(frames) >= 600, kitchen_dir
    voc_path = tmp_path / "ORBvoc.txt"
    built = write_vocabulary([kitchen_dir], voc_path, max_images=60, seed=0)
    assert built.images == 60 and built.words > 10_000
    settings = tmp_path / "7scenes.yaml"
    settings.write_text(textwrap.dedent(SEVEN_SCENES_SETTINGS))
    slam = pyorbslam3.Slam(str(voc_path), str(settings), sensor=pyorbslam3.Sensor.RGBD, use_viewer=False)
    states = []
    try:
        for i, colour in enumerate(frames[500:530]):  # frames the vocabulary was not all built from
            rgb = cv2.cvtColor(cv2.imread(str(colour)), cv2.COLOR_BGR2RGB)
            depth_path = colour.with_name(colour.name.replace(".color.jpg", ".depth.png"))
            depth = cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED).astype(np.float32)
            depth[depth >= 65535] = 0  # 7-Scenes marks invalid depth 65535
            states.append(slam.track_rgbd(rgb, depth, i / 30.0).state)
    finally:
        slam.shutdown()
    ok = sum(s == pyorbslam3.TrackingState.OK for s in states)
    assert ok >= 25, states
