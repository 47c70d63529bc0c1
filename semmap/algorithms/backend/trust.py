"""How far the pose graph trusts the odometry: as far as it earned against semmap's own evidence.

A front end declares a sigma per frame and the graph adds them up between its nodes (a random walk). A SLAM is
not a random walk: its local bundle adjustment and its own loop closing keep its error bounded, so over the gap
of a loop closure (hundreds of frames) the declared chain is far looser than the SLAM really is. Then every
closure (an ICP of two depth clouds, good to about a centimetre) and every landmark (object centroids that scatter
3-14 cm with the viewpoint) pulls the trajectory towards its own noise: a 1.7 cm ORB-SLAM3 trajectory came out at
2.2 cm (TUM fr1_desk), a perfect one (7-Scenes ground truth as `file:`) at 3.5 cm.

So every accepted closure is first a *witness*: its residual against the odometry's own relative pose of the two
frames says how much the odometry drifted over that gap, beyond the closure's own noise. Per axis group
(translation, rotation) the excess variance over the declared chain variance, `max(0, r^2/3 - sigma_closure^2) /
sigma_chain^2`, is one sample of the variance factor the odometry earned; the graph scales every chain's variance
by the median of the samples (once `min_witnesses` are in), never above 1 (the declared sigma is the most it is
trusted less than claimed; a front end that drifts keeps its declared sigma and the closures correct it as before),
never below `floor^2`. A good SLAM ends tight, and evidence that only agrees with it within its own noise moves it
by no more than that; a drifting odometry (simulated drift, a repaired chain of registrations) keeps the pull of
the evidence. The median, not the mean: one wrong closure says nothing of the odometry.

Pure arithmetic: residuals in, factors out (pose_graph.py applies them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass
class OdometryTrust:
    """The variance factors (translation, rotation) the odometry earned from the closures that witnessed it, and
    the closures' own noise as the same witnesses measured it."""

    min_witnesses: int = 3
    regression_witnesses: int = 8  # from this many on, the closures' own noise is measured too (see `factors`)
    floor: float = 0.03  # the tightest trust: sigmas scaled by this at most (0.3 mm a frame for 1 cm declared)
    # per witness and axis group: (declared chain variance, squared residual per axis, declared closure variance)
    samples_t: list[tuple[float, float, float]] = field(default_factory=list)
    samples_r: list[tuple[float, float, float]] = field(default_factory=list)

    def witness(self, odometry_relative: np.ndarray, measured_relative: np.ndarray, chain_sigmas: tuple[float, float],
                closure_sigmas: tuple[float, float]) -> None:
        """One closure's measured relative pose of two frames against the odometry's, with the chain's declared
        (m, rad) sigmas between them and the closure's own."""
        error = np.linalg.inv(measured_relative) @ odometry_relative
        r_t = float(np.linalg.norm(error[:3, 3]))
        r_r = float(np.linalg.norm(Rotation.from_matrix(error[:3, :3]).as_rotvec()))
        self.samples_t.append((chain_sigmas[0] ** 2, r_t * r_t / 3.0, closure_sigmas[0] ** 2))
        self.samples_r.append((chain_sigmas[1] ** 2, r_r * r_r / 3.0, closure_sigmas[1] ** 2))

    def factors(self) -> tuple[float, float]:
        """(translation, rotation) sigma factors in [floor, 1]: 1 until `min_witnesses` closures witnessed."""
        if len(self.samples_t) < self.min_witnesses:
            return 1.0, 1.0
        return tuple(min(1.0, max(self.floor, math.sqrt(self._variance_factor(s))))
                     for s in (self.samples_t, self.samples_r))

    def closure_sigmas(self, declared: tuple[float, float]) -> tuple[float, float]:
        """The closures' (m, rad) sigmas: never tighter than declared, looser where the witnesses measured more."""
        if len(self.samples_t) < self.regression_witnesses:
            return declared
        return tuple(max(d, math.sqrt(self._fit(s)[1])) for d, s in zip(declared, (self.samples_t, self.samples_r),
                                                                         strict=True))

    def _variance_factor(self, samples: list[tuple[float, float, float]]) -> float:
        if len(samples) >= self.regression_witnesses:
            return self._fit(samples)[0]
        # few witnesses: each one's excess over the closure's declared noise, relative to the chain's
        return float(np.median([max(0.0, r2 - c2) / max(v, 1e-18) for v, r2, c2 in samples]))

    @staticmethod
    def _fit(samples: list[tuple[float, float, float]]) -> tuple[float, float]:
        """(slope, intercept) of residual^2 = slope * chain variance + intercept, robustly (Theil-Sen): how much of
        the declared chain variance the odometry really drifts, and the closures' own variance. A SLAM whose error
        stays bounded shows no slope however long the gap; a random walk shows its full declared variance."""
        v = np.array([s[0] for s in samples])
        r2 = np.array([s[1] for s in samples])
        i, j = np.triu_indices(len(v), 1)
        dv = v[j] - v[i]
        keep = np.abs(dv) > 1e-12 * max(float(v.max()), 1e-18)
        slope = float(np.median((r2[j] - r2[i])[keep] / dv[keep])) if keep.any() else 0.0
        slope = max(slope, 0.0)
        intercept = max(float(np.median(r2 - slope * v)), 0.0)
        return slope, intercept

    def state(self) -> dict:
        return {"t": [list(x) for x in self.samples_t], "r": [list(x) for x in self.samples_r]}

    def restore(self, state: dict | None) -> None:
        self.samples_t = [tuple(float(v) for v in x) for x in (state or {}).get("t", [])]
        self.samples_r = [tuple(float(v) for v in x) for x in (state or {}).get("r", [])]
