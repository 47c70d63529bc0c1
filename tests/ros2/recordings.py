"""The reference a ROS 2 camera's map is compared with: the same frames as raw images in a bag.

The folder's JPEG files travel as stored, while a ROS camera's raw pixels are JPEG-encoded for the wire (as a bag's
raw images are): a JPEG generation apart, which can flip a class vote. The same raw images recorded in a bag go
through the same encoding, so the bridge's map must equal the bag's exactly.
"""

from __future__ import annotations

from pathlib import Path

from semmap.datasets import open_dataset
from tests.datasets.bag_writer import write_bag


def raw_recording(tmp_path: Path, kitchen_dir: Path, frames: int) -> Path:
    """The first `frames` 7-Scenes frames as an MCAP bag of raw rgb8 / 16UC1 images with the ground truth as odom."""
    folder = open_dataset(kitchen_dir)
    return write_bag(tmp_path / "raw_recording", [folder[i] for i in range(frames)], "mcap", pose="odom")
