"""Per-view object measurements, candidate validation, and the MAP centroid.

A *view* is one usable measurement of an object: the depth surfaces of its box (see backproject.py), each
as a thinned camera-frame cloud plus a centroid, and which surface is the object (`choice`). Views keep
everything in their own camera frame plus the pose used to place them in the world; their world positions
are cached, and `View.refresh(lookup)` re-places them when the backend has corrected that frame's pose
(`LandmarkMapper.refine`). So the same views serve odometry poses first and corrected poses later.

Per-view centroid: the centre of the robust (2-98 percentile) axis-aligned box of the surface's points in
world axes. Measured on the synthetic scene (ground truth: the centre of each object's axis-aligned box), it
is 2-3x closer to the truth than the mean of the visible points, which is pulled towards the camera.

Surface choice (`choose_surfaces`): box segmentation alone cannot tell a chair from the table top in front
of it, but across views the chair's surfaces stay put in 3-D while the table-top patches in its boxes move
with the viewpoint; the surface that agrees with the most other views, weighted by how well it fills its
box, wins.

Validation (measured on the synthetic scene: a static object's per-view centroids scatter by a few cm, up to
~0.35 m for a chair seen only over the table's edge; a walking person's drift steadily):
- motion: the views of the last `motion_window_s` split by time into 3-5 segments whose median centroids
  move steadily one way (no step back, no single step carrying most of it) by more than
  max(min_motion_m, motion_size_factor * s) at more than max_speed_mps. Steadiness is what separates a
  person from a chair whose visible part changes (one jump) or whose views alternate between surfaces
  (back and forth). Only whole views count (a box cut by the image border slides with the viewpoint), so
  a new candidate becomes a landmark only once the test could run (`motion_testable`) or, never seen
  whole, after `untestable_span_s`; it runs after the surface choice, which cannot hide motion: the
  background in a walking person's box walks along with them;
- spread (the paper's test): the trimmed mean absolute deviation of the centroids from their median (largest
  30% left out: wrong-surface views) above max(mad_min_m, mad_size_factor * s);
- consistency: fewer than half of the views agree with the median centroid.
s is the 80th percentile of the views' metric box sizes: not the fused cloud (a moving object smears it, which
would raise the threshold exactly when it should not), and not the median (partial views shrink the box).

MAP centroid: the measurement model is Gaussian per view with a sigma growing with depth and size, made
robust by a likelihood floor (a view beyond ~3 sigma costs a constant instead of pulling the estimate), plus a
weak Gaussian prior around the start point. The start point blends a triangulation (the least-squares point
closest to all camera-centre -> box-centre rays, which does not depend on depth and so is not pulled towards
the visible surface) with the median of the per-view centroids, weighted by how well the rays' directions
constrain the point. The posterior is explored by seeded random-walk Metropolis chains at two step scales,
all chains of all objects in one vectorised array; the best sample is polished to the exact mode by a few
fixed-point (IRLS) steps and returned. The robust posterior is multi-modal (one mode per cluster of views),
which is why sampling beats a closed form here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from semmap.core.messages import Measurement
from semmap.core.stamps import below, reaches, time_bins, within

from .backproject import BackprojectParams, extract_surfaces
from .geometry import fast_median, inverse_transform, robust_box, thin, transform
from .params import MapperParams

PoseLookup = Callable[[int], np.ndarray | None]


@dataclass
class View:
    """One usable measurement of an object.

    `choice` selects the surface that is the object; `pose` is the pose its world positions were computed
    with, `alt_world` those positions (the surfaces' centroids in the world).
    """

    frame_id: int
    stamp: float
    track_id: int
    alt_points: list[np.ndarray]  # per surface: (k, 3) float32, camera frame, thinned for storage
    alt_centroids: np.ndarray  # (a, 3) camera frame
    alt_depths: np.ndarray  # (a,) reference depths (metres)
    alt_scores: np.ndarray  # (a,) how well each surface fills its box (backproject's score)
    ray: np.ndarray  # (3,) unit direction of the box-centre ray, camera frame
    metric: float  # the box's size at 1 m (metres per metre of depth)
    pose: np.ndarray  # (4, 4) camera-to-world used for the cached world positions
    truncated: bool = False  # the box touches the image border: only part of the object is in view
    choice: int = 0
    inlier: bool = True  # agrees with its landmark's MAP centroid (used for the landmark's cloud)
    alt_world: np.ndarray | None = None  # (a, 3) cached world centroids
    occluded: bool = False  # a dynamic object's box (a person) covers part of it: its depth may be the person's
    # the pose object `refresh` last looked at: the pose book hands out the same object until a correction for that
    # frame arrives, so a refine over tens of thousands of stored views skips the unchanged ones by identity
    _looked_at: object = field(default=None, repr=False, compare=False)

    def shows_motion(self, trust_occluded: bool) -> bool:
        """May this view's centroid speak for the object's motion? Not when truncated (its centre slides with
        what is in view); not when occluded unless `trust_occluded` (its centre may follow the person in front
        of or behind the object). A new candidate trusts occluded views (a cup a person carries is covered by
        the person: it must still not become a landmark); an established landmark does not (a person passing a
        chair must not retire it)."""
        return not self.truncated and (trust_occluded or not self.occluded)

    def __post_init__(self) -> None:
        if self.alt_world is None:
            self.alt_world = transform(self.pose, self.alt_centroids)

    @property
    def points(self) -> np.ndarray:
        return self.alt_points[self.choice]

    @property
    def centroid(self) -> np.ndarray:
        return self.alt_centroids[self.choice]

    @property
    def world(self) -> np.ndarray:
        assert self.alt_world is not None
        return self.alt_world[self.choice]

    @property
    def depth(self) -> float:
        return float(self.alt_depths[self.choice])

    @property
    def size(self) -> float:
        """Metric size of the box at the chosen surface's depth."""
        return self.metric * self.depth

    def world_points(self) -> np.ndarray:
        return transform(self.pose, self.points.astype(np.float64))

    def refresh(self, lookup: PoseLookup, tolerance_m: float = 0.0) -> bool:
        """Take the frame's current pose from the lookup (if it has one); True if it changed. With a tolerance, a
        pose that moves the chosen surface's centre by less than `tolerance_m` from where this view put it is not
        taken (the view keeps its pose; moves add up until they pass the tolerance)."""
        pose = lookup(self.frame_id)
        if pose is None or pose is self._looked_at:
            return False
        self._looked_at = pose
        if np.array_equal(pose, self.pose):
            return False
        if tolerance_m > 0.0 and len(self.alt_centroids):
            c = self.alt_centroids[self.choice]
            shift = (pose[:3, :3] - self.pose[:3, :3]) @ c + (pose[:3, 3] - self.pose[:3, 3])
            if float(np.linalg.norm(shift)) < tolerance_m:
                return False
        self.pose = np.asarray(pose, dtype=np.float64).copy()
        self.alt_world = transform(self.pose, self.alt_centroids)
        return True


def backproject_params(p: MapperParams) -> BackprojectParams:
    return BackprojectParams(
        depth_min_m=p.depth_min_m,
        depth_max_m=p.depth_max_m,
        band_factor=p.band_factor,
        band_min_m=p.band_min_m,
        band_max_m=p.band_max_m,
        gap_m=p.gap_m,
        gap_rel=p.gap_rel,
        max_points=p.view_points_max,
    )


def is_truncated(m: Measurement, margin_px: float) -> bool:
    """Does the box touch the image border? Then its centroid shifts as the object slides into view."""
    x1, y1, x2, y2 = m.detection.box
    k = m.intrinsics
    return x1 <= margin_px or y1 <= margin_px or x2 >= k.width - margin_px or y2 >= k.height - margin_px


def surface_tolerance(size: float, p: MapperParams) -> float:
    """How far a surface's centre may be from where the object is and still be the object."""
    return max(p.inlier_min_m, p.surface_tol_size_factor * size)


def make_view(
    m: Measurement,
    pose: np.ndarray,
    track_id: int,
    bp: BackprojectParams,
    p: MapperParams,
    expected: tuple[np.ndarray, float] | None = None,
) -> View | None:
    """Back-project one measurement; None when its depth holds too little of the object.

    expected: (world centre, size) of the object when already known (its landmark's): the surface whose
    centre is nearest to it, within the surface tolerance, is chosen.
    """
    got = extract_surfaces(m, bp)
    if got is None:
        return None
    pose = np.asarray(pose, dtype=np.float64)
    world, points = [], []
    for surf in got.surfaces:
        centre_w, _ = robust_box(transform(pose, surf.points), 2.0)
        world.append(centre_w)
        points.append(thin(surf.points, p.stored_points_max).astype(np.float32))
    alt_world = np.array(world)
    depths = np.array([surf.ref_depth for surf in got.surfaces])
    scores = np.array([surf.score for surf in got.surfaces])
    view = View(
        m.frame_id,
        m.stamp,
        track_id,
        points,
        inverse_transform(pose, alt_world),
        depths,
        scores,
        got.ray,
        got.metric,
        pose.copy(),
        is_truncated(m, p.border_margin_px),
        alt_world=alt_world,
        occluded=m.occluded,
    )
    if expected is not None and len(world) > 1:
        d = np.linalg.norm(alt_world - expected[0], axis=1)
        j = int(np.argmin(d))
        if d[j] <= surface_tolerance(expected[1], p):
            view.choice = j
    return view


def world_centroids(views: list[View]) -> np.ndarray:
    """(n, 3) world centroids of the views' chosen surfaces (cached; see `View.refresh`)."""
    if not views:
        return np.zeros((0, 3))
    return np.stack([v.world for v in views])


def view_sigmas(views: list[View], size: float, p: MapperParams) -> np.ndarray:
    """Per-view centroid sigma: grows with depth (depth noise, box jitter) and size (partial views)."""
    depth = np.array([v.depth for v in views])
    return p.sigma_base_m + p.sigma_depth_factor * depth + p.sigma_size_factor * size


def inlier_limit(views: list[View], sig: np.ndarray, size: float, p: MapperParams) -> np.ndarray:
    """How far each view's centroid may be from the MAP centroid; a truncated view's centre may be off by
    up to half the object, so it gets that much slack."""
    limit = np.maximum(p.inlier_min_m, p.inlier_sigmas * sig)
    return limit + 0.5 * size * np.array([v.truncated for v in views])


def whole_views(views: list[View], min_views: int) -> list[View]:
    """The views that saw the whole object (box clear of the image border), or all when too few did."""
    whole = [v for v in views if not v.truncated]
    return whole if len(whole) >= min_views else views


def choose_surfaces(views: list[View], p: MapperParams) -> None:
    """Multi-view consensus: pick, in every view, the surface that is where the other views put the object.

    Each view is a mixture of its surfaces, weighted by how well each fills its box (backproject's score).
    For every surface centre h as a hypothesis, the score is sum over views of
    log(max_j score_j * exp(-|c_j - h|^2 / 2 sigma^2) + floor), with sigma = max(inlier_min_m,
    surface_tol_size_factor * s) wide enough for a chair's back-only view and a full view (0.4 m apart) to
    agree. The best hypothesis wins and every view takes its best-weighted surface near it (or its nearest
    surface within 3 sigma, or else keeps its preference). A table top stays in a far chair's box over a
    few views too, but it fills that box worse than the chair does, and the chair is in every view.
    """
    if len(views) < 2 or all(len(v.alt_depths) == 1 for v in views):
        return
    counts = np.array([len(v.alt_depths) for v in views])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    h = np.concatenate([v.alt_world for v in views])  # type: ignore[misc]
    w = np.concatenate([v.alt_scores for v in views])
    size = float(np.percentile([v.metric * v.alt_depths[0] for v in views], 80))
    sigma = max(p.inlier_min_m, p.surface_tol_size_factor * size)
    d2 = np.square(h[:, None, :] - h[None, :, :]).sum(axis=-1)  # (hypothesis, surface)
    g = np.exp(-0.5 / sigma**2 * d2) * w[None, :]
    per_view = np.maximum.reduceat(g, starts, axis=1)  # (hypothesis, view)
    floor = 0.05 * float(w.max())
    best = int(np.argmax(np.log(per_view + floor).sum(axis=1)))
    for i, v in enumerate(views):
        gi = g[best, starts[i] : starts[i] + counts[i]]
        j = int(np.argmax(gi))
        if gi[j] <= floor:  # nothing agrees well: the nearest surface if it is within 3 sigma at all
            di = d2[best, starts[i] : starts[i] + counts[i]]
            j = int(np.argmin(di)) if float(di.min()) <= 9.0 * sigma**2 else 0
        v.choice = j


# ---------------------------------------------------------------------------------------------------------
# validation


@dataclass
class Validation:
    ok: bool
    spread_m: float
    spread_limit_m: float
    speed_mps: float
    displacement_m: float
    reason: str = ""


def medoid(points: np.ndarray) -> np.ndarray:
    """The point with the smallest summed distance to the others. Why not the per-axis median: a segment whose
    views switch between two surfaces of a static object (a chair's back, then its seat) has a median halfway
    between them, and a jump then reads as two steady steps; the medoid stays on one of the surfaces."""
    if len(points) <= 2:
        return fast_median(points)
    d = np.linalg.norm(points[:, None, :] - points[None, :, :], axis=2).sum(axis=1)
    return points[int(np.argmin(d))].copy()


def coherent_motion(views: list[View], p: MapperParams, trust_occluded: bool = True) -> tuple[bool, float, float]:
    """(moving, speed, displacement) from the views of the last `motion_window_s`, split by time into 3 to 5
    equal segments.

    Moving: the median centroids of the first and last segment are further apart than the object allows
    (max(min_motion_m, motion_size_factor * s)), at more than max_speed_mps, no step between consecutive
    segments goes back (beyond 10% of the displacement), no single step carries most of it (75% of it
    with 3 segments, 60% with 5), and the views sit within half a step of their segment's median.
    Only views that may show motion count (`View.shows_motion`): the visible part of a box cut by the image
    border slides as the object enters
    the image, and even its far edge moves with the viewpoint for a large object (a table's far edge).
    """
    recent = [v for v in views if within(views[-1].stamp - v.stamp, p.motion_window_s)] if views else []
    use = [v for v in recent if v.shows_motion(trust_occluded)]
    if len(use) < p.motion_min_views or below(use[-1].stamp - use[0].stamp, p.min_motion_span_s):
        return False, 0.0, 0.0
    c = world_centroids(use)
    stamps = np.array([v.stamp for v in use])
    # Segments of 3+ views: the median of two views halfway through a jump would fake a steady step.
    k = int(np.clip(len(use) // 3, 3, 5))
    parts = np.array_split(np.arange(len(use)), k)
    m = np.stack([medoid(c[i]) for i in parts])
    t = np.array([float(np.median(stamps[i])) for i in parts])
    total = m[-1] - m[0]
    displacement = float(np.linalg.norm(total))
    speed = displacement / max(float(t[-1] - t[0]), 1e-6)
    size = float(np.percentile([v.size for v in use], 80))
    limit = max(p.min_motion_m, p.motion_size_factor * size)
    if speed <= p.max_speed_mps or displacement <= limit:
        return False, speed, displacement
    along = np.diff(m, axis=0) @ (total / displacement)  # each step's progress along the total motion
    # Even steps would carry 1/(k-1) each; a single jump carries ~all of it. And the views must sit tight
    # around their segment's median: erratic centroids (surface switching) can line up by chance.
    share = displacement / (k - 1)
    scatter = float(np.median(np.concatenate([np.linalg.norm(c[i] - m[j], axis=1) for j, i in enumerate(parts)])))
    steady = bool(
        np.all(along >= -0.1 * displacement)
        and np.max(along) <= (0.45 + 0.6 / (k - 1)) * displacement
        and scatter <= 0.5 * share
    )
    return steady, speed, displacement


def track_motion(
    stamps: np.ndarray,
    centroids: np.ndarray,
    unclear: np.ndarray,
    size: float,
    p: MapperParams,
    whole_only: bool = True,
) -> tuple[bool, float]:
    """(moving, displacement) over a whole track: its views' world centroids binned by `track_motion_bin_s`,
    each bin with `track_motion_bin_views` views summarised by its median; moving when two bin medians are
    further apart than
    max(track_motion_min_m, track_motion_size_factor * min(size, track_motion_size_cap_m)).

    Why whole-track and not `coherent_motion`'s recent window: a person the camera follows keeps a high IOU and
    a long track, and walks, stops and turns; a steady-motion test over 1.5 s misses much of that, but where
    the person stood 3 s ago and stands now are metres apart. Why capped with size: a static object's bin
    medians scatter with its size (partial views), but a person's do not need 0.9 m of slack.
    unclear: per view, not `View.shows_motion`.
    whole_only: only clear views count (a large static object's centroid slides with what
    is in view: the synthetic room's table moves by more than its size allows); otherwise all views, while
    whole views are too few (for a track that must prove it stood still, see `_short_but_static`).
    """
    if len(stamps) < 2 * p.track_motion_bin_views:
        return False, 0.0
    whole = ~unclear
    enough = int(whole.sum()) >= 2 * p.track_motion_bin_views
    if whole_only and not enough:
        return False, 0.0
    use = whole if enough else np.ones_like(whole)
    t, c = stamps[use], centroids[use]
    order = np.argsort(t, kind="stable")
    t, c = t[order], c[order]
    bins = time_bins(t - t[0], max(p.track_motion_bin_s, 1e-3))
    edges = np.flatnonzero(np.diff(bins)) + 1
    medians = [fast_median(c[i]) for i in np.split(np.arange(len(t)), edges) if len(i) >= p.track_motion_bin_views]
    if len(medians) < 2:
        return False, 0.0
    m = np.stack(medians)
    d = np.sqrt(np.square(m[:, None, :] - m[None, :, :]).sum(axis=-1))
    displacement = float(d.max())
    limit = max(p.track_motion_min_m, p.track_motion_size_factor * min(size, p.track_motion_size_cap_m))
    return displacement > limit, displacement


def motion_testable(views: list[View], p: MapperParams) -> bool:
    """Enough whole views, over enough time, for `coherent_motion` to have had its say."""
    whole = [v for v in views if not v.truncated]
    return len(whole) >= p.motion_min_views and reaches(whole[-1].stamp - whole[0].stamp, p.min_motion_span_s)


def validate(views: list[View], p: MapperParams, trust_occluded: bool = True) -> Validation:
    """Is this candidate a static, stable object? (see module docstring).

    Views whose box touches the image border show a centroid that slides as the object enters or leaves
    the image, so the motion test uses whole views only and is skipped when there are too few of them; the
    spread tests then run on all views.
    """
    recent = views[-p.validation_window :]
    moving, speed, displacement = coherent_motion(recent, p, trust_occluded)
    use = whole_views(recent, p.min_views)
    c = world_centroids(use)
    size = float(np.percentile([v.size for v in use], 80))
    dev = np.linalg.norm(c - fast_median(c), axis=1)
    keep = max(1, int(np.ceil(len(dev) * (1.0 - p.mad_trim))))
    spread = float(np.mean(np.partition(dev, keep - 1)[:keep]))
    limit = max(p.mad_min_m, p.mad_size_factor * size)
    consistent = float(np.mean(dev <= max(limit, surface_tolerance(size, p))))
    if moving:
        return Validation(False, spread, limit, speed, displacement, "motion")
    if len(use) < p.min_views_spread:  # too few views to condemn a scatter (one wrong surface of three)
        return Validation(True, spread, limit, speed, displacement)
    if spread > limit:
        return Validation(False, spread, limit, speed, displacement, "spread")
    if consistent < p.min_consistent_fraction:
        return Validation(False, spread, limit, speed, displacement, "inconsistent")
    return Validation(True, spread, limit, speed, displacement)


# ---------------------------------------------------------------------------------------------------------
# MAP centroid


def triangulate(views: list[View]) -> tuple[np.ndarray, float]:
    """Least-squares point closest to the box-centre rays; and the smallest eigenvalue of the normal
    matrix per ray (0: parallel rays, depth unconstrained; 2/3: rays from all around)."""
    poses = np.stack([v.pose for v in views])
    origins = poses[:, :3, 3]
    dirs = np.einsum("nij,nj->ni", poses[:, :3, :3], np.stack([v.ray for v in views]))
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]
    a = proj.sum(axis=0)
    b = np.einsum("nij,nj->i", proj, origins)
    eig = float(np.linalg.eigvalsh(a / len(views))[0])
    if eig < 1e-6:
        return origins.mean(axis=0), 0.0
    return np.linalg.solve(a, b), eig


def start_point(
    views: list[View], centroids: np.ndarray, tri_eig_full: float = 0.1, tri_max_weight: float = 0.5
) -> np.ndarray:
    """Blend of the triangulated point and the median centroid, trusting triangulation by its conditioning."""
    median = fast_median(centroids)
    if len(views) < 2:
        return median
    tri, eig = triangulate(views)
    w = tri_max_weight * min(1.0, eig / tri_eig_full)
    reach = 1.0 + 2.0 * float(np.max(np.linalg.norm(centroids - median, axis=1)))
    if not np.all(np.isfinite(tri)) or float(np.linalg.norm(tri - median)) > reach:
        return median
    return w * tri + (1.0 - w) * median


@dataclass
class MapProblem:
    """One object's MAP problem: its per-view centroids and sigmas, a start point and a seed."""

    centroids: np.ndarray  # (n, 3)
    sigmas: np.ndarray  # (n,)
    start: np.ndarray  # (3,)
    seed: tuple[int, ...]
    prior_sigma: float = 1.0


def map_centroids(problems: list[MapProblem], p: MapperParams) -> list[np.ndarray]:
    """MAP centroids of several objects at once (one vectorised Metropolis run over all their chains)."""
    if not problems:
        return []
    n_obj, k, steps = len(problems), max(2, p.mc_chains), max(1, p.mc_steps)
    n_max = max(len(q.centroids) for q in problems)
    cent = np.zeros((n_obj, 1, n_max, 3))
    inv_var = np.zeros((n_obj, 1, n_max))  # 0 for padding: contributes log(1 + floor), a constant
    start = np.zeros((n_obj, 1, 3))
    prior = np.zeros((n_obj, 1))
    step = np.zeros((n_obj, k, 1))
    noise = np.zeros((steps, n_obj, k, 3))
    log_u = np.zeros((steps, n_obj, k))
    init = np.zeros((n_obj, k, 3))
    for o, q in enumerate(problems):
        n = len(q.centroids)
        cent[o, 0, :n] = q.centroids
        inv_var[o, 0, :n] = 1.0 / np.square(q.sigmas)
        start[o, 0] = q.start
        prior[o, 0] = 1.0 / q.prior_sigma**2
        base = float(np.median(q.sigmas)) / np.sqrt(max(n, 1)) * 1.5 + 1e-3
        step[o, : k // 2, 0] = base
        step[o, k // 2 :, 0] = base * 5.0  # coarse chains hop between modes
        rng = np.random.default_rng(list(q.seed))
        noise[:, o] = rng.standard_normal((steps, k, 3))
        log_u[:, o] = np.log(rng.random((steps, k)))
        # Chains start at the start point, the median and the precision-weighted mean, then jittered copies.
        w = inv_var[o, 0, :n]
        guesses = [q.start, fast_median(q.centroids), (q.centroids * w[:, None]).sum(axis=0) / w.sum()]
        init[o, : len(guesses)] = guesses[:k]
        if k > len(guesses):
            init[o, len(guesses) :] = q.start + rng.standard_normal((k - len(guesses), 3)) * base * 3.0
    floor = p.outlier_floor
    c_sq = np.square(cent).sum(axis=-1)  # (n_obj, 1, n_max)

    def log_post(x: np.ndarray) -> np.ndarray:  # x (n_obj, k, 3) -> (n_obj, k)
        cross = np.matmul(x, cent[:, 0].transpose(0, 2, 1))  # (n_obj, k, n_max)
        d2 = np.maximum(c_sq - 2.0 * cross + np.square(x).sum(axis=-1)[:, :, None], 0.0)
        lik = np.log(np.exp(-0.5 * d2 * inv_var) + floor).sum(axis=-1)
        return lik - 0.5 * prior * np.square(x - start).sum(axis=-1)

    rows = np.arange(n_obj)
    x = init
    lp = log_post(x)
    i = np.argmax(lp, axis=1)
    best_x, best_lp = x[rows, i].copy(), lp[rows, i]
    for s in range(steps):
        prop = x + noise[s] * step
        lp_prop = log_post(prop)
        acc = log_u[s] < (lp_prop - lp)
        x = np.where(acc[:, :, None], prop, x)
        lp = np.where(acc, lp_prop, lp)
        i = np.argmax(lp, axis=1)
        better = lp[rows, i] > best_lp
        best_lp = np.where(better, lp[rows, i], best_lp)
        best_x = np.where(better[:, None], x[rows, i], best_x)
    # Polish the best sample to the mode it sits in: the fixed point of the robust likelihood (each view
    # weighted by its Gaussian's share against the floor), kept only where it does not lower the posterior.
    for _ in range(p.mc_polish_steps):
        d2 = np.square(cent[:, 0] - best_x[:, None, :]).sum(axis=-1)  # (n_obj, n_max)
        g = np.exp(-0.5 * d2 * inv_var[:, 0])
        w = g / (g + floor) * inv_var[:, 0]
        num = (w[:, :, None] * cent[:, 0]).sum(axis=1) + prior * start[:, 0]
        cand = num / (w.sum(axis=1) + prior[:, 0])[:, None]
        lp_c = log_post(cand[:, None, :])[:, 0]
        better = lp_c > best_lp
        best_lp = np.where(better, lp_c, best_lp)
        best_x = np.where(better[:, None], cand, best_x)
    return [best_x[o].copy() for o in range(n_obj)]


def map_problem(views: list[View], p: MapperParams, seed: tuple[int, ...], size: float | None = None) -> MapProblem:
    """The MAP problem of a set of views (a candidate's or a landmark's): whole views when enough."""
    views = whole_views(views, 3)
    c = world_centroids(views)
    s = float(np.percentile([v.size for v in views], 80)) if size is None else size
    return MapProblem(c, view_sigmas(views, s, p), start_point(views, c), seed, prior_sigma=1.0 + s)
