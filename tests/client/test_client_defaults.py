"""The client's keyframe default follows the configuration's, which the light client cannot import."""

from __future__ import annotations

from semmap.core.config import OdometryConfig
from semmap.runtime.client import DEFAULT_KEYFRAME_EVERY


def test_the_client_marks_keyframes_as_the_built_in_front_ends_do() -> None:
    assert OdometryConfig().keyframe_every == DEFAULT_KEYFRAME_EVERY
