"""The README's picture: a top-down view of a real run's map (landmark boxes, classes, camera path), as a PNG.

    .venv/bin/python scripts/make_readme_figure.py RUN_DIR [--out docs/map_topdown.png]

RUN_DIR is a finished `semmap run` folder (map.json, trajectory_optimized.tum, groundtruth.tum if any). The view
looks down the gravity axis, taken as the first camera's -y (image y points down; handheld and robot data start
upright). Needs matplotlib (installed with evo).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from semmap.datasets.trajectory_io import read_tum  # noqa: E402
from semmap.services.viz.service import landmark_color  # noqa: E402


def plane_basis(first_pose: np.ndarray) -> np.ndarray:
    """3x2 basis of the ground plane: the first camera's viewing direction and its right, both made level."""
    up = -first_pose[:3, 1] / np.linalg.norm(first_pose[:3, 1])
    ahead = first_pose[:3, 2] - up * float(np.dot(first_pose[:3, 2], up))
    ahead /= np.linalg.norm(ahead)
    right = np.cross(ahead, up)
    return np.stack([right, ahead], axis=1)


def make_figure(run_dir: Path, out: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    landmarks = json.loads((run_dir / "map.json").read_text())["landmarks"]
    path = read_tum(run_dir / "trajectory_optimized.tum")
    basis = plane_basis(path[0][1])
    fig, ax = plt.subplots(figsize=(9, 7), dpi=110)
    if (run_dir / "groundtruth.tum").is_file():
        gt = np.array([p[:3, 3] for _, p in read_tum(run_dir / "groundtruth.tum")]) @ basis
        ax.plot(gt[:, 0], gt[:, 1], color="0.75", lw=2.5, label="ground truth")
    xy = np.array([p[:3, 3] for _, p in path]) @ basis
    ax.plot(xy[:, 0], xy[:, 1], color=(0.16, 0.55, 1.0), lw=1.2, label="camera path (optimised)")
    placed: list[np.ndarray] = []
    for lm in sorted(landmarks, key=lambda lm: -np.prod(lm["extent"])):  # big ones first, small ones on top
        c = np.asarray(lm["centroid"]) @ basis
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * np.asarray(
            lm["extent"]
        ) / 2 + np.asarray(lm["centroid"])
        flat = corners @ basis
        lo, hi = flat.min(axis=0), flat.max(axis=0)
        colour = np.array(landmark_color(lm["id"])) / 255
        ax.add_patch(Rectangle(lo, *(hi - lo), facecolor=(*colour, 0.18), edgecolor=colour, lw=1.5))
        ax.plot(*c, "o", color=colour, ms=4)
        label = c + np.array([0.0, 0.04])
        while any(np.linalg.norm(label - q) < 0.12 for q in placed):  # stack labels that would overlap
            label = label + np.array([0.0, 0.1])
        placed.append(label)
        ax.annotate(
            lm["class"],
            c,
            label,
            fontsize=8,
            color=colour * 0.7,
            ha="center",
            arrowprops={"arrowstyle": "-", "color": colour, "lw": 0.6} if label[1] - c[1] > 0.05 else None,
        )
    ax.set_aspect("equal")
    ax.set_xlabel("m (level, across the first view)")
    ax.set_ylabel("m (level, along the first view)")
    ax.set_title(f"semmap on {title}: {len(landmarks)} landmarks, top-down", fontsize=11)
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--out", type=Path, default=Path("docs/map_topdown.png"))
    ap.add_argument("--title", default="7-Scenes redkitchen", help="what the map is of")
    args = ap.parse_args(argv)
    print(make_figure(args.run_dir, args.out, args.title))
    return 0


if __name__ == "__main__":
    sys.exit(main())
