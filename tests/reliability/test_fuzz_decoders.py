"""Every message decoder under fuzzing: generated and mutated payloads never crash, they are rejected clearly.

Per message kind: 10,000 seeded mutations of a valid message (bit flips, truncation, splices, field deletions,
type swaps, huge or non-finite numbers, wrong versions) and random msgpack documents from hypothesis (300 in the
fast suite, 400 with `-m slow`).
"""

from __future__ import annotations

import contextlib
import math
import random

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from semmap.core.messages import ALL_MESSAGES, Frame, Message, MessageError

from ..core.test_messages import _samples  # noqa: TID252 - the valid samples are the seeds

MUTATIONS_PER_KIND = 10_000


def _decode(kind: type[Message], payload: bytes) -> bool:
    """True if accepted; MessageError is a clean rejection; anything else fails the test."""
    try:
        message = kind.decode(payload)
    except MessageError:
        return False
    if isinstance(message, Frame):  # lazily decoded images must fail cleanly too
        for lazy in (message.rgb, message.depth):
            with contextlib.suppress(MessageError):
                lazy()
    return True


_WEIRD = [None, True, -1, 2**63, -(2**63), 1e308, float("nan"), float("inf"), "", "x" * 300, b"\x00" * 7, [], {},
          [1.0] * 16, {"dtype": "uint16", "shape": [2, 2], "data": b"\x00"}, {"a": 1}]


def _mutate_structure(body: dict, rng: random.Random) -> dict:
    body = dict(body)
    keys = list(body)
    op = rng.randrange(5)
    key = rng.choice(keys)
    if op == 0:
        del body[key]
    elif op == 1:
        body[key] = rng.choice(_WEIRD)
    elif op == 2 and isinstance(body[key], list) and body[key]:
        items = list(body[key])
        i = rng.randrange(len(items))
        items[i] = rng.choice(_WEIRD) if rng.random() < 0.5 else (
            _mutate_structure(items[i], rng) if isinstance(items[i], dict) else items[i])
        body[key] = items
    elif op == 3 and isinstance(body[key], dict) and body[key]:
        body[key] = _mutate_structure(body[key], rng)
    else:
        body[rng.choice(["extra", key])] = rng.choice(_WEIRD)
    return body


def _mutate_bytes(payload: bytes, rng: random.Random) -> bytes:
    data = bytearray(payload)
    op = rng.randrange(4)
    if op == 0 and data:
        for _ in range(rng.randint(1, 8)):
            data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
    elif op == 1:
        data = data[: rng.randrange(len(data) + 1)]
    elif op == 2 and data:
        i = rng.randrange(len(data))
        data[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
    else:
        data = data[::-1] if rng.random() < 0.1 else data + data[: rng.randrange(len(data) + 1)]
    return bytes(data)


@pytest.mark.parametrize("sample", _samples(), ids=lambda m: type(m).__name__)
def test_mutated_messages_are_rejected_or_valid(sample: Message) -> None:
    kind = type(sample)
    rng = random.Random(hash(kind.SCHEMA) & 0xFFFF)
    valid = sample.encode()
    body = msgpack.unpackb(valid, raw=False)
    if isinstance(sample, Frame):  # keep frames small so 9,000 of them stay fast
        body["rgb_jpeg"] = body["rgb_jpeg"][:64]
    rejected = 0
    for i in range(MUTATIONS_PER_KIND):
        if i % 3 == 0:
            payload = _mutate_bytes(valid, rng)
        else:
            mutated = _mutate_structure(body, rng)
            if i % 7 == 0:
                mutated["schema"] = rng.choice([kind.SCHEMA.replace("/1", "/2"), "semmap.other/1", 5, None])
            try:
                payload = msgpack.packb(mutated, use_bin_type=True)
            except (OverflowError, ValueError, TypeError):
                continue
        rejected += not _decode(kind, payload)
    assert rejected > MUTATIONS_PER_KIND // 3, "the mutations should mostly produce invalid messages"


_LEAVES = st.one_of(st.none(), st.booleans(), st.integers(-(2**64), 2**64), st.floats(allow_nan=True),
                    st.text(max_size=20), st.binary(max_size=40))
_DOCS = st.recursive(_LEAVES, lambda inner: st.one_of(st.lists(inner, max_size=6),
                                                      st.dictionaries(st.text(max_size=12), inner, max_size=6)),
                     max_leaves=30)


def _fuzz_generated(kind: type[Message], examples: int) -> None:
    names = [f for f in msgpack.unpackb(next(m for m in _samples() if type(m) is kind).encode(), raw=False)]

    @settings(max_examples=examples, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(doc=st.dictionaries(st.sampled_from(names), _DOCS, max_size=len(names)), raw=st.binary(max_size=64))
    def run(doc: dict, raw: bytes) -> None:
        doc = {**doc, "schema": kind.SCHEMA}
        try:
            payload = msgpack.packb(doc, use_bin_type=True)
        except (OverflowError, ValueError, TypeError):
            payload = raw
        _decode(kind, payload)
        _decode(kind, raw)

    run()


@pytest.mark.parametrize("kind", ALL_MESSAGES, ids=lambda k: k.__name__)
def test_generated_documents_never_crash_a_decoder(kind: type[Message]) -> None:
    _fuzz_generated(kind, 300)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ALL_MESSAGES, ids=lambda k: k.__name__)
def test_many_generated_documents_never_crash_a_decoder(kind: type[Message]) -> None:
    # 400 each (12 kinds, 1.2 min on 2 cores; 1,000 take 4.3 min, 3,000 ~10 min): the
    # 10,000 mutations of a valid message above reach the decoders' edge cases more cheaply than hypothesis'
    # recursive documents, and with `derandomize` every run draws the same documents anyway
    _fuzz_generated(kind, 400)


def test_oversized_messages_are_refused_before_parsing() -> None:
    from semmap.core import messages

    huge = b"\x00" * (messages.MAX_MESSAGE_BYTES + 1)
    with pytest.raises(MessageError, match="exceeds the limit"):
        Frame.decode(huge)


def test_non_finite_arrays_are_refused() -> None:
    from semmap.core.messages import CorrectedPoses

    sample = next(m for m in _samples() if isinstance(m, CorrectedPoses))
    sample.landmark_positions = np.array([[math.nan, 0.0, 0.0]])
    with pytest.raises(MessageError, match="non-finite"):
        CorrectedPoses.decode(sample.encode())
