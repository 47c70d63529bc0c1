"""Back-projection of a detection's depth patch into camera-frame point clouds of the boxed object.

Why not every pixel of the box: a bounding box always holds background (the wall behind a cup, the floor
between a chair's legs, the table under a bottle), and sometimes an occluder (the table top in front of a
chair on the far side of the table). Objects are compact in depth, so we split the box into depth
*surfaces* and rank them:

1. candidate depths: the modes of the box's depth histogram (bin width tied to the box's metric size), plus
   the mode of the box's central half (where the object most likely is);
2. each candidate's surface: the pixels within +-band of it (band scaled to the box's metric size, as an
   object is about as deep as it is wide), cut at the first depth gap wider than gap_m + gap_rel * depth on
   either side, so a wall 30 cm behind a small object is dropped even when the band would reach it;
3. score: sqrt(cover x fill) times the share of the box's four sides (outer 12% strips) the surface
   reaches, where cover = (share of the box's columns) x (share of its rows) holding a surface pixel and
   fill = the surface's share of the box's valid pixels. A tight box touches its object on all four sides;
   a table top in front of a chair spans the width but reaches neither the top nor the bottom of the chair's
   box; the floor behind reaches the bottom only. Cover alone rates a thin frame of wall around an object
   as high as the object, fill alone rates the wall behind a chair's legs higher than the chair; their
   geometric mean does neither. The preferred surface is the *nearest* one scoring within `cover_ratio` of
   the best (the background behind an object can score about as well as the object);
4. every surface is a deterministic uniform subsample of at most `max_points` points.

The other well-scoring surfaces come back too (`extract_surfaces`), so the mapper can pick, across several
views of one tracklet, the surface that stays put in 3-D (candidate.choose_surfaces): per-view box
segmentation alone cannot tell a chair from the table in front of it, several views can.

Everything is vectorised numpy on the (already strided) patch; a patch is strided further when it holds
more than `max_pixels` pixels so the cost stays bounded for boxes that fill the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from semmap.core.messages import Measurement


@dataclass(frozen=True)
class BackprojectParams:
    """Knobs of the foreground extraction (see module docstring)."""

    depth_min_m: float = 0.2  # paper: depth range of usable measurements
    depth_max_m: float = 25.0
    band_factor: float = 0.6  # depth band half-width / metric box size (geometric mean of width and height)
    band_min_m: float = 0.06
    band_max_m: float = 1.5
    gap_m: float = 0.04  # a depth gap wider than gap_m + gap_rel * depth separates object and background
    gap_rel: float = 0.02
    max_points: int = 500
    max_pixels: int = 4000
    min_points: int = 12  # fewer foreground points than this: the surface is unusable
    max_peaks: int = 5  # depth modes tried as the object's depth
    peak_min_frac: float = 0.08  # a mode needs this share of the densest mode's count
    edge_frac: float = (
        0.12  # the strips along the box sides that a surface must reach (12%: boxes ~10% loose pass)
    )
    cover_ratio: float = 0.7  # nearest surface scoring within this factor of the best is preferred
    alt_ratio: float = 0.3  # other surfaces scoring at least this share of the best are kept as alternatives
    max_surfaces: int = 3


@dataclass
class Surface:
    """One depth surface inside the box, in the camera frame (metres)."""

    points: np.ndarray  # (N, 3) float64
    ref_depth: float
    score: float


@dataclass
class Surfaces:
    """A measurement's surfaces, the preferred one first."""

    surfaces: list[Surface]
    ray: np.ndarray  # (3,) unit direction of the box centre's viewing ray
    metric: float  # the box's size at 1 m (geometric mean of width and height over focal length)


@dataclass
class ViewPoints:
    """The preferred foreground of one measurement, in the camera frame (metres)."""

    points: np.ndarray  # (N, 3) float64
    ref_depth: float  # the object's reference depth (metres)
    ray: np.ndarray  # (3,) unit direction of the box centre's viewing ray
    size_m: float  # metric size of the box at ref_depth (geometric mean of width and height)


def _patch_in_box(m: Measurement, max_pixels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(u, v, depth_units) of the patch pixels inside the box, further strided to at most max_pixels."""
    patch = m.detection.depth_patch
    if patch is None or patch.depth.size == 0:
        return None
    x1, y1, x2, y2 = m.detection.box
    s = patch.stride
    h, w = patch.depth.shape
    # Columns j with x1 <= x0 + j*s < x2, rows likewise.
    j0 = max(0, int(np.ceil((x1 - patch.x0) / s)))
    j1 = min(w, int(np.ceil((x2 - patch.x0) / s)))
    i0 = max(0, int(np.ceil((y1 - patch.y0) / s)))
    i1 = min(h, int(np.ceil((y2 - patch.y0) / s)))
    if j1 <= j0 or i1 <= i0:
        return None
    extra = max(1, int(np.ceil(np.sqrt((j1 - j0) * (i1 - i0) / max_pixels))))
    sub = patch.depth[i0:i1:extra, j0:j1:extra]
    u = patch.x0 + (np.arange(j0, j1, extra) * s)
    v = patch.y0 + (np.arange(i0, i1, extra) * s)
    return u.astype(np.float64), v.astype(np.float64), sub


def _depth_peaks(z: np.ndarray, bin_m: float, max_peaks: int, min_frac: float) -> list[float]:
    """Local maxima of the smoothed depth histogram (densest first), each refined to the count-weighted mean
    depth of its bin and the two neighbours (histogram arithmetic only: no pass over the pixels per peak)."""
    lo = float(z.min())
    nbins = int((float(z.max()) - lo) / bin_m) + 1
    idx = ((z - lo) * (1.0 / bin_m)).astype(np.int64)
    raw = np.bincount(idx, minlength=nbins).astype(np.float64)
    sums = np.bincount(idx, weights=z, minlength=nbins)
    pad = np.concatenate([[0.0], raw, [0.0]])
    counts = raw + 0.5 * (pad[:-2] + pad[2:])  # smoothed, so a surface split across two bins is one peak
    left = np.concatenate([[-1.0], counts[:-1]])
    right = np.concatenate([counts[1:], [-1.0]])
    is_peak = (counts > left) & (counts >= right) & (counts >= min_frac * counts.max())
    order = np.flatnonzero(is_peak)
    order = order[np.argsort(-counts[order], kind="stable")][:max_peaks]
    psum = np.concatenate([[0.0], sums, [0.0]])
    peaks = []
    for b in order:
        n = pad[b] + pad[b + 1] + pad[b + 2]
        peaks.append(float((psum[b] + psum[b + 1] + psum[b + 2]) / n) if n > 0 else lo + (b + 0.5) * bin_m)
    return peaks


def extract_surfaces(m: Measurement, params: BackprojectParams | None = None) -> Surfaces | None:
    """The measurement's depth surfaces, preferred first; None when too few valid pixels remain."""
    p = params or BackprojectParams()
    got = _patch_in_box(m, p.max_pixels)
    if got is None:
        return None
    u, v, raw = got
    k = m.intrinsics
    x1, y1, x2, y2 = m.detection.box
    z_all = raw.astype(np.float64) * m.depth_scale
    valid = (raw > 0) & (z_all >= p.depth_min_m) & (z_all <= p.depth_max_m)
    z_valid = z_all[valid]
    if z_valid.size < p.min_points:
        return None

    # Central half of the box: where the object most likely is.
    qw, qh = (x2 - x1) / 4.0, (y2 - y1) / 4.0
    cu = (u >= x1 + qw) & (u <= x2 - qw)
    cv = (v >= y1 + qh) & (v <= y2 - qh)
    central = valid & cv[:, None] & cu[None, :]
    zc = z_all[central] if int(central.sum()) >= p.min_points // 2 else z_valid

    # The median gives the scale; candidate depths are the modes at a bin width tied to the metric size.
    metric = float(np.sqrt((x2 - x1) / k.fx * (y2 - y1) / k.fy))  # box size at 1 m
    zm = float(np.partition(zc, zc.size // 2)[zc.size // 2])
    bin_m = max(0.02, min(0.25, 0.25 * metric * zm))
    peaks = _depth_peaks(z_valid, bin_m, p.max_peaks, p.peak_min_frac)
    for c in _depth_peaks(zc, bin_m, 1, 0.0):  # the central mode is always a candidate
        if all(abs(c - q) > bin_m for q in peaks):
            peaks.append(c)

    # Depth gaps split the box into surfaces: sort once, find the gaps once, then each candidate's band is
    # cut at the nearest gap on either side by binary search.
    zs = np.sort(z_valid)
    gaps = np.flatnonzero(np.diff(zs) > p.gap_m + p.gap_rel * zs[:-1])
    er = max(1, int(round(p.edge_frac * valid.shape[0])))
    ec = max(1, int(round(p.edge_frac * valid.shape[1])))
    scored: list[tuple[float, float, np.ndarray]] = []
    seen: set[tuple[float, float]] = set()
    for ref in peaks:
        band = min(max(p.band_factor * metric * ref, p.band_min_m), p.band_max_m)
        pos = int(np.searchsorted(zs, ref))  # then the index of the depth nearest to ref
        if pos == len(zs) or (pos > 0 and ref - zs[pos - 1] < zs[pos] - ref):
            pos -= 1
        below = gaps[gaps < pos]
        above = gaps[gaps >= pos]
        lo = max(ref - band, zs[below[-1] + 1] if below.size else zs[0])
        hi = min(ref + band, zs[above[0]] if above.size else zs[-1])
        if (lo, hi) in seen:  # two modes of one surface
            continue
        seen.add((lo, hi))
        mask = valid & (z_all >= lo) & (z_all <= hi)
        if int(mask.sum()) < p.min_points:
            continue
        cols, rows = mask.any(axis=0), mask.any(axis=1)
        cover = float(cols.mean()) * float(rows.mean())
        fill = float(mask.sum()) / z_valid.size
        edges = int(rows[:er].any()) + int(rows[-er:].any()) + int(cols[:ec].any()) + int(cols[-ec:].any())
        scored.append((ref, float(np.sqrt(cover * fill)) * edges / 4.0, mask))
    if not scored:
        return None
    top = max(s for _, s, _ in scored)
    preferred = min((t for t in scored if t[1] >= p.cover_ratio * top), key=lambda t: t[0])
    others = sorted(
        (t for t in scored if t is not preferred and t[1] >= p.alt_ratio * top), key=lambda t: (-t[1], t[0])
    )
    chosen = [preferred, *others][: max(1, p.max_surfaces)]

    surfaces = []
    for ref, score, mask in chosen:
        rows_i, cols_i = np.nonzero(mask)
        zz = z_all[rows_i, cols_i]
        if zz.size > p.max_points:
            sel = np.linspace(0, zz.size - 1, p.max_points).astype(np.int64)
            rows_i, cols_i, zz = rows_i[sel], cols_i[sel], zz[sel]
        pts = np.empty((zz.size, 3))
        pts[:, 0] = (u[cols_i] - k.cx) / k.fx * zz
        pts[:, 1] = (v[rows_i] - k.cy) / k.fy * zz
        pts[:, 2] = zz
        surfaces.append(Surface(pts, ref, score))
    ray = np.array([((x1 + x2) / 2 - k.cx) / k.fx, ((y1 + y2) / 2 - k.cy) / k.fy, 1.0])
    ray /= np.linalg.norm(ray)
    return Surfaces(surfaces, ray, metric)


def extract_view(m: Measurement, params: BackprojectParams | None = None) -> ViewPoints | None:
    """The preferred foreground of one measurement, or None when too few valid pixels remain."""
    got = extract_surfaces(m, params)
    if got is None:
        return None
    s = got.surfaces[0]
    return ViewPoints(s.points, s.ref_depth, got.ray, got.metric * s.ref_depth)


def measurement_points(m: Measurement, params: BackprojectParams | None = None) -> np.ndarray:
    """(N, 3) camera-frame points of the object in measurement `m` (N <= max_points; (0, 3) if unusable)."""
    view = extract_view(m, params)
    return np.zeros((0, 3)) if view is None else view.points
