"""Build an ORB vocabulary (a DBoW2 tree of binary words) from your own images, for ORB-SLAM2/3.

ORB-SLAM's `ORBvoc.txt` cannot be downloaded everywhere; this builds one the way DBoW2 does
(`TemplatedVocabulary::create`): hierarchical k-medians on 256-bit ORB descriptors (k-means++ seeding under
Hamming distance, assignment, bitwise-majority medians as in `FORB::meanValue`), `levels` deep with at most `k`
children a node, then TF-IDF weights: a word's IDF is ln(N_images / N_images_containing_it), found by quantising
every training descriptor down the finished tree exactly as DBoW2's `transform` does (nearest child at each level,
first one on ties). Words no image reaches keep weight 0 (DBoW2 ignores them, as it does words in every image).

Vectorised level by level: all nodes of one level are clustered together (one pass over every descriptor per
iteration, in chunks, so memory stays bounded), which keeps ~300k descriptors, k=10, L=5 to about a minute on one
core. Deterministic for a seed. `to_text` writes DBoW2's text format (`ORBVocabulary::loadFromTextFile`): first line
`k L  scoring weighting`, then one line per node after the root, `parent_id is_leaf d0 .. d31 weight`, node ids
being file order (root 0), a parent before its children, and no newline after the last line (the loader's
`while (!f.eof())` would read a trailing empty line as one more node). Pure computation: no file I/O here.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "DESCRIPTOR_BYTES",
    "ORBVocabulary",
    "VocabularyError",
    "build_vocabulary",
    "check_parameters",
    "orb_descriptors",
    "parse_text",
]

DESCRIPTOR_BYTES = 32
_WORDS = DESCRIPTOR_BYTES // 8  # a descriptor as 4 uint64 words for XOR + popcount
_CHUNK = 32768  # descriptors per distance block: chunk x k x 4 uint64 = 10 MB at k = 10
_FAR = np.iinfo(np.int32).max  # the distance to a missing centre
_BYTE_TEXT = np.array([str(v) for v in range(256)], dtype=object)
SCORING_L1 = 0  # DBoW2 ScoringType L1_NORM (ORB-SLAM's)
WEIGHTING_TF_IDF = 0  # DBoW2 WeightingType TF_IDF


class VocabularyError(ValueError):
    """The input cannot make a vocabulary (too few descriptors or images, bad parameters, bad text)."""


@dataclass(frozen=True)
class ORBVocabulary:
    """A DBoW2 tree. Node 0 is the root; arrays are indexed by node id (file order), parents before children."""

    k: int
    levels: int
    parent: np.ndarray  # (n,) int64, parent[0] = -1
    is_leaf: np.ndarray  # (n,) bool, False for the root
    descriptors: np.ndarray  # (n, 32) uint8, zeros for the root
    weights: np.ndarray  # (n,) float64: IDF for leaves, 0 for inner nodes
    scoring: int = SCORING_L1
    weighting: int = WEIGHTING_TF_IDF

    @property
    def n_nodes(self) -> int:
        return int(self.parent.shape[0])

    @property
    def n_words(self) -> int:
        return int(self.is_leaf.sum())

    def depth(self) -> np.ndarray:
        """(n,) depth of every node (root 0), relying on parents coming first."""
        depth = np.zeros(self.n_nodes, dtype=np.int64)
        for i in range(1, self.n_nodes):
            depth[i] = depth[self.parent[i]] + 1
        return depth

    def transform(self, descriptors: np.ndarray) -> np.ndarray:
        """Node id of the leaf each descriptor falls into, descending as DBoW2 does (nearest child, first on ties)."""
        return _descend(self, _as_u64(descriptors))

    def to_text(self) -> str:
        """DBoW2 text format (see the module doc); no trailing newline."""
        head = f"{self.k} {self.levels}  {self.scoring} {self.weighting}"
        byte_text = _BYTE_TEXT[self.descriptors]
        lines = [head]
        for i in range(1, self.n_nodes):
            lines.append(
                f"{int(self.parent[i])} {int(self.is_leaf[i])} {' '.join(byte_text[i])}  {float(self.weights[i]):.6g}"
            )
        return "\n".join(lines)


def check_parameters(k: int, levels: int) -> None:
    """VocabularyError unless DBoW2's text loader accepts this k and L (2..20, 1..10)."""
    if not 2 <= k <= 20 or not 1 <= levels <= 10:
        raise VocabularyError(f"k must be 2..20 and levels 1..10 (DBoW2's loader refuses others), got {k}, {levels}")


def orb_descriptors(image: np.ndarray, n_features: int = 1000) -> np.ndarray:
    """(m, 32) uint8 ORB descriptors of a grey or RGB image, with ORB-SLAM's extractor settings.

    ORB-SLAM (`ORBextractor`, settings `ORBextractor.*`): 1000 features, scale 1.2, 8 levels, FAST threshold 20,
    31-pixel patch; OpenCV's ORB computes the same rBRIEF descriptor (same pattern, same 7x7 blur), which is what
    the vocabulary is made of. Keypoints are placed differently (ORB-SLAM spreads them over a grid), which matters
    little for the words.
    """
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    orb = cv2.ORB_create(nfeatures=n_features, scaleFactor=1.2, nlevels=8, fastThreshold=20, patchSize=31)
    _, desc = orb.detectAndCompute(np.ascontiguousarray(grey), None)
    if desc is None:
        return np.zeros((0, DESCRIPTOR_BYTES), dtype=np.uint8)
    return np.asarray(desc, dtype=np.uint8)


def build_vocabulary(
    descriptors_per_image: Sequence[np.ndarray] | Iterable[np.ndarray],
    k: int = 10,
    levels: int = 5,
    seed: int = 0,
    iterations: int = 8,
) -> ORBVocabulary:
    """Hierarchical k-medians over all images' descriptors, then IDF weights per image (see the module doc).

    `descriptors_per_image`: one (m_i, 32) uint8 array per training image. `iterations`: at most this many
    median/assignment rounds per level (it stops earlier when no assignment changes).
    """
    check_parameters(k, levels)
    if iterations < 1:
        raise VocabularyError(f"iterations must be >= 1, got {iterations}")
    per_image = [np.asarray(d, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES) for d in descriptors_per_image]
    per_image = [d for d in per_image if len(d)]
    if len(per_image) < 2:
        raise VocabularyError(f"need descriptors from at least 2 images for IDF weights, got {len(per_image)}")
    desc8 = np.ascontiguousarray(np.concatenate(per_image))
    image_of = np.repeat(np.arange(len(per_image)), [len(d) for d in per_image])
    if len(desc8) < k or not (desc8 != desc8[0]).any():
        raise VocabularyError(f"too few descriptors: {len(desc8)} (or all identical), need at least k = {k}")
    rng = np.random.default_rng(seed)
    desc = _as_u64(desc8)

    parent: list[np.ndarray] = [np.array([-1])]
    is_leaf: list[np.ndarray] = [np.array([False])]
    centres: list[np.ndarray] = [np.zeros((1, _WORDS), dtype=np.uint64)]
    n_nodes = 1
    # descriptors still being split, grouped by the node they sit in (segments of `members`)
    members = np.arange(len(desc))
    seg_node = np.array([0])
    seg_start = np.array([0])
    for level in range(1, levels + 1):
        if not len(seg_node):
            break
        label, cent, valid = _kmedians(desc, members, seg_start, k, rng, iterations)
        seg_of = np.repeat(np.arange(len(seg_node)), np.diff(np.append(seg_start, len(members))))
        key = seg_of * k + label
        order = np.argsort(key, kind="stable")
        members, key = members[order], key[order]
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        child_key = key[starts]  # non-empty (segment, cluster), in node order (segment first)
        sizes = np.diff(np.append(starts, len(members)))
        child_desc = cent[child_key // k, child_key % k]
        # a child splits further unless it is at the last level, holds one descriptor or only copies of its centre
        dist = _popcount(desc[members] ^ child_desc[np.repeat(np.arange(len(starts)), sizes)])
        spread = np.maximum.reduceat(dist, starts) if len(starts) else dist
        leaf = (sizes == 1) | (spread == 0) | (level == levels)
        ids = n_nodes + np.arange(len(child_key))
        parent.append(seg_node[child_key // k])
        is_leaf.append(leaf)
        centres.append(child_desc)
        n_nodes += len(child_key)
        assert valid[child_key // k, child_key % k].all()
        # next level: the non-leaf children's descriptors, still contiguous
        keep = np.repeat(~leaf, sizes)
        members = members[keep]
        seg_node = ids[~leaf]
        kept_sizes = sizes[~leaf]
        seg_start = np.cumsum(np.r_[0, kept_sizes[:-1]]) if len(kept_sizes) else np.zeros(0, dtype=np.int64)

    cent_all = np.concatenate(centres)
    voc = ORBVocabulary(
        k=k,
        levels=levels,
        parent=np.concatenate(parent).astype(np.int64),
        is_leaf=np.concatenate(is_leaf),
        descriptors=np.ascontiguousarray(cent_all).view(np.uint8).reshape(-1, DESCRIPTOR_BYTES),
        weights=np.zeros(n_nodes, dtype=np.float64),
    )
    # IDF: ln(N / n_i), n_i = images with at least one descriptor quantised to word i (DBoW2's setNodeWeights)
    word = _descend(voc, desc)
    pairs = np.unique(word * len(per_image) + image_of)
    n_i = np.bincount(pairs // len(per_image), minlength=n_nodes)
    seen = n_i > 0
    voc.weights[seen] = np.log(len(per_image) / n_i[seen])
    voc.weights[~voc.is_leaf] = 0.0
    return voc


def parse_text(text: str) -> ORBVocabulary:
    """Read DBoW2's text format back (as `loadFromTextFile` does); VocabularyError on a malformed file."""
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    head = lines[0].split() if lines else []
    if len(head) != 4:
        raise VocabularyError(f"first line must be `k L scoring weighting`, got {lines[0] if lines else ''!r}")
    k, levels, scoring, weighting = (int(v) for v in head)
    n = len(lines)
    parent = np.full(n, -1, dtype=np.int64)
    is_leaf = np.zeros(n, dtype=bool)
    desc = np.zeros((n, DESCRIPTOR_BYTES), dtype=np.int64)
    weights = np.zeros(n, dtype=np.float64)
    for i, line in enumerate(lines[1:], start=1):
        fields = line.split()
        if len(fields) != DESCRIPTOR_BYTES + 3:
            raise VocabularyError(f"line {i + 1}: {len(fields)} fields, expected {DESCRIPTOR_BYTES + 3}")
        parent[i], is_leaf[i] = int(fields[0]), int(fields[1]) > 0
        desc[i] = [int(v) for v in fields[2 : 2 + DESCRIPTOR_BYTES]]
        weights[i] = float(fields[-1])
        if not 0 <= parent[i] < i:
            raise VocabularyError(f"line {i + 1}: parent {parent[i]} is not an earlier node")
        if is_leaf[parent[i]]:
            raise VocabularyError(f"line {i + 1}: parent {parent[i]} is a leaf")
    if ((desc < 0) | (desc > 255)).any():
        raise VocabularyError("descriptor bytes must be 0..255")
    return ORBVocabulary(k, levels, parent, is_leaf, desc.astype(np.uint8), weights, scoring, weighting)


# --- internals -------------------------------------------------------------------------------------------------


def _as_u64(desc8: np.ndarray) -> np.ndarray:
    desc8 = np.ascontiguousarray(np.asarray(desc8, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES))
    return desc8.view(np.uint64).reshape(-1, _WORDS)


def _popcount(x: np.ndarray) -> np.ndarray:
    """Hamming weight summed over the last axis (uint64 words) as int32."""
    return np.bitwise_count(x).sum(axis=-1, dtype=np.int32)


def _assign(
    desc: np.ndarray, members: np.ndarray, seg_of: np.ndarray, cent: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest valid centre of its own segment for every member (first on ties): (label, distance)."""
    label = np.empty(len(members), dtype=np.int64)
    best = np.empty(len(members), dtype=np.int32)
    for lo in range(0, len(members), _CHUNK):
        sl = slice(lo, lo + _CHUNK)
        seg = seg_of[sl]
        d = _popcount(desc[members[sl]][:, None, :] ^ cent[seg])
        d[~valid[seg]] = _FAR
        label[sl] = d.argmin(axis=1)
        best[sl] = np.take_along_axis(d, label[sl, None], axis=1)[:, 0]
    return label, best


def _kmedians(
    desc: np.ndarray, members: np.ndarray, seg_start: np.ndarray, k: int, rng: np.random.Generator, iterations: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """k-medians in every segment at once. Returns per-member label, centres (S, k, 4) and their validity (S, k)."""
    n, n_seg = len(members), len(seg_start)
    sizes = np.diff(np.append(seg_start, n))
    seg_of = np.repeat(np.arange(n_seg), sizes)
    cent = np.zeros((n_seg, k, _WORDS), dtype=np.uint64)
    valid = np.zeros((n_seg, k), dtype=bool)

    # k-means++ seeding (D^2 sampling under Hamming distance), one draw per segment per round
    first = seg_start + np.minimum((rng.random(n_seg) * sizes).astype(np.int64), sizes - 1)
    cent[:, 0] = desc[members[first]]
    valid[:, 0] = True
    mind = _popcount(desc[members] ^ cent[seg_of, 0]).astype(np.float64)
    active = np.ones(n_seg, dtype=bool)
    for j in range(1, k):
        w = mind * mind
        cum = np.cumsum(w)
        before = np.where(seg_start > 0, cum[np.maximum(seg_start - 1, 0)], 0.0)
        total = cum[seg_start + sizes - 1] - before
        active &= total > 0
        if not active.any():
            break
        target = before + (1.0 - rng.random(n_seg)) * total  # in (before, before + total]
        pos = np.searchsorted(cum, target, side="left")
        pos = np.clip(pos, seg_start, seg_start + sizes - 1)
        cent[active, j] = desc[members[pos[active]]]
        valid[active, j] = True
        upd = active[seg_of]
        d = _popcount(desc[members[upd]] ^ cent[seg_of[upd], j]).astype(np.float64)
        mind[upd] = np.minimum(mind[upd], d)

    label, _ = _assign(desc, members, seg_of, cent, valid)
    for _ in range(iterations):
        cent, valid = _medians(desc, members, seg_of, label, n_seg, k)
        new_label, _ = _assign(desc, members, seg_of, cent, valid)
        changed = bool((new_label != label).any())
        label = new_label
        if not changed:
            break
    return label, cent, valid


def _medians(
    desc: np.ndarray, members: np.ndarray, seg_of: np.ndarray, label: np.ndarray, n_seg: int, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Bitwise majority of each (segment, cluster): a bit is set when at least half the members have it."""
    key = seg_of * k + label
    order = np.argsort(key, kind="stable")
    key_sorted = key[order]
    starts = np.flatnonzero(np.r_[True, key_sorted[1:] != key_sorted[:-1]])
    groups = key_sorted[starts]
    counts = np.diff(np.append(starts, len(key_sorted)))
    out8 = np.zeros((len(groups), DESCRIPTOR_BYTES), dtype=np.uint8)
    step = 8  # bytes at a time: n x 64 bits unpacked
    for b in range(0, DESCRIPTOR_BYTES, step):
        chunk = np.empty((len(order), step), dtype=np.uint8)
        for lo in range(0, len(order), 4 * _CHUNK):
            idx = members[order[lo : lo + 4 * _CHUNK]]
            chunk[lo : lo + 4 * _CHUNK] = desc[idx].view(np.uint8)[:, b : b + step]
        bits = np.unpackbits(chunk, axis=1)
        sums = np.add.reduceat(bits, starts, axis=0, dtype=np.int32)
        out8[:, b : b + step] = np.packbits(2 * sums >= counts[:, None], axis=1)
    cent = np.zeros((n_seg, k, _WORDS), dtype=np.uint64)
    valid = np.zeros((n_seg, k), dtype=bool)
    cent[groups // k, groups % k] = out8.view(np.uint64).reshape(-1, _WORDS)
    valid[groups // k, groups % k] = True
    return cent, valid


def _descend(voc: ORBVocabulary, desc: np.ndarray) -> np.ndarray:
    """DBoW2's `transform` for many descriptors: from the root, go to the nearest child until a leaf."""
    n = voc.n_nodes
    child_count = np.bincount(voc.parent[1:], minlength=n)
    width = max(int(child_count.max()), 1)
    children = np.full((n, width), -1, dtype=np.int64)
    order = np.argsort(voc.parent[1:], kind="stable") + 1  # children in file order, grouped by parent
    par = voc.parent[order]
    rank = np.arange(len(order)) - np.searchsorted(par, par, side="left")
    children[par, rank] = order
    node_desc = _as_u64(voc.descriptors)
    has_child = child_count > 0
    out = np.zeros(len(desc), dtype=np.int64)
    for lo in range(0, len(desc), _CHUNK):
        d = desc[lo : lo + _CHUNK]
        cur = np.zeros(len(d), dtype=np.int64)
        going = has_child[cur]
        while going.any():
            idx = np.flatnonzero(going)
            cand = children[cur[idx]]
            dist = _popcount(d[idx][:, None, :] ^ node_desc[np.maximum(cand, 0)])
            dist[cand < 0] = _FAR
            cur[idx] = cand[np.arange(len(idx)), dist.argmin(axis=1)]
            going[idx] = has_child[cur[idx]]
        out[lo : lo + _CHUNK] = cur
    return out
