"""Map queries, shared by the associator's Zenoh queryable and `semmap query` on a saved map.json.

A query is a set of optional filters: class (case-insensitive), a point (near: results nearest first; with a
radius, only those within it), ids. Over Zenoh it travels as selector
parameters: `semmap/v1/<robot>/map/query?class=cup;near=1.0,0.5,0.8;radius=0.5;id=3,7`; the reply is a
`semmap.map/2` document (the same layout as map.json), as JSON.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from semmap.core.messages import Landmark
from semmap.runtime.maps.map_store import MAP_SCHEMA, landmark_json


class QueryError(ValueError):
    """A malformed query (bad numbers, a radius without a point, ...)."""


@dataclass(frozen=True)
class MapQuery:
    class_name: str | None = None
    near: tuple[float, float, float] | None = None
    radius: float | None = None
    ids: frozenset[int] | None = None

    @classmethod
    def from_parameters(cls, params: Mapping[str, str]) -> MapQuery:
        """From selector parameters / CLI strings: class, near ('x,y,z'), radius, id ('3,7')."""
        unknown = set(params) - {"class", "near", "radius", "id"}
        if unknown:
            raise QueryError(f"unknown query parameter(s) {', '.join(sorted(unknown))}: use class, near, radius, id")
        near = radius = ids = None
        try:  # each error names its parameter (`semmap query` shows it as the flag: --near, --radius, --id)
            if params.get("near"):
                near = tuple(float(v) for v in params["near"].split(","))
        except ValueError:
            raise QueryError(f"near: expected three numbers x,y,z (metres), got {params['near']!r}") from None
        try:
            if params.get("radius"):
                radius = float(params["radius"])
        except ValueError:
            raise QueryError(f"radius: expected a number of metres, got {params['radius']!r}") from None
        try:
            if params.get("id"):
                ids = frozenset(int(v) for v in params["id"].split(","))
        except ValueError:
            raise QueryError(f"id: expected landmark ids (whole numbers, comma-separated), got {params['id']!r}"
                             ) from None
        if near is not None and (len(near) != 3 or not all(math.isfinite(v) for v in near)):
            raise QueryError(f"near: expected three finite numbers x,y,z, got {params['near']!r}")
        if radius is not None and near is None:
            raise QueryError("radius: needs near=x,y,z")
        if radius is not None and not (math.isfinite(radius) and radius >= 0):
            raise QueryError(f"radius: expected a finite number >= 0, got {radius:g}")
        return cls(params.get("class") or None, near, radius, ids)  # type: ignore[arg-type]

    def to_parameters(self) -> str:
        parts = []
        if self.class_name:
            parts.append(f"class={self.class_name}")
        if self.near is not None:
            parts.append("near=" + ",".join(f"{v:g}" for v in self.near))
            if self.radius is not None:
                parts.append(f"radius={self.radius:g}")
        if self.ids:
            parts.append("id=" + ",".join(str(i) for i in sorted(self.ids)))
        return ";".join(parts)

    def matches(self, lm: Landmark) -> bool:
        if self.class_name is not None and lm.class_name.casefold() != self.class_name.casefold():
            return False
        if self.ids is not None and lm.id not in self.ids:
            return False
        if self.near is not None and self.radius is not None:
            return math.dist(lm.centroid, self.near) <= self.radius
        return True


def run_query(query: MapQuery, landmarks: Iterable[Landmark]) -> list[Landmark]:
    """Matching landmarks, by id; nearest first when the query names a point."""
    found = sorted((lm for lm in landmarks if query.matches(lm)), key=lambda lm: lm.id)
    if query.near is not None:
        found.sort(key=lambda lm: math.dist(lm.centroid, query.near))
    return found


def class_counts(landmarks: Iterable[Landmark]) -> dict[str, int]:
    """{class: number of landmarks}, most frequent first: what to suggest when a class filter finds nothing."""
    counts: dict[str, int] = {}
    for lm in landmarks:
        counts[lm.class_name] = counts.get(lm.class_name, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def reply_document(landmarks: Iterable[Landmark]) -> bytes:
    return json.dumps({"schema": MAP_SCHEMA, "landmarks": [landmark_json(lm) for lm in landmarks]}).encode()


RETRY_EVERY_S = 0.2


def ask_live_map(session, selector: str, timeout: float) -> list[Landmark] | None:  # noqa: ANN001 - zenoh.Session
    """The landmarks the map service answers to `selector`, asking again until one answers or `timeout` passes
    (None then); QueryError when it answers with an error or an unknown document.

    Why again: a session that has just opened does not yet know the associator's queryable (its declaration comes
    with the routing information after the link is up), and a `get` that finds no queryable ends at once with no
    reply. Measured: one query per fresh `semmap query` during a run, 10 of 20 got no answer (after 1.4-4.9 s, of
    a 10 s timeout); asking again within the timeout: 20 of 20."""
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return None
        for reply in session.get(selector, timeout=left):
            if reply.ok is None:
                raise QueryError(f"the map service answered: {reply.err.payload.to_bytes().decode(errors='replace')}")
            body = json.loads(reply.ok.payload.to_bytes())
            if not isinstance(body, dict) or body.get("schema") != MAP_SCHEMA:
                raise QueryError(f"unexpected reply schema {body.get('schema') if isinstance(body, dict) else body!r}")
            return [Landmark.from_dict(item) for item in body["landmarks"]]
        time.sleep(min(RETRY_EVERY_S, max(0.0, deadline - time.monotonic())))
