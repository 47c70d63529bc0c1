"""Rerun sink: records the run to `DIR/run.rrd` (and optionally serves the web viewer for a live run).

Entity layout (Rerun 0.41):
- `world/landmarks/<tile>`: the landmarks whose centroid lies in one cube of `MAP_TILE_M` (`tile_<i>_<j>_<k>`,
  `m` for a minus sign), each as the outline of its extent's box (`Boxes3D`, wireframe: nothing solid hides what
  lies inside, a cup on the table stays visible) in a stable colour per landmark id, and a small solid sphere at
  its centroid (`.../centres`); labels `class #id` sit on leader lines above the boxes (`.../labels`,
  `.../leaders`), raised where they would pile up on each other. Why tiles: a map update re-logs only the tiles
  it touched, so drawing costs the same per frame in a kitchen and on a street of thousands of landmarks (one
  batch of all of them every frame grew the recording and the viewer's work with the map's size), and a tile's
  labels stay few enough for Rerun to show them.
- `world/trajectory/odometry/part_<n>`, `world/trajectory/optimized/part_<n>`: camera paths as line strips, one per
  `PATH_PART_FRAMES` frame ids (each joined to the next one's first point). Why parts: a redraw re-logs only the
  parts whose poses changed, so it costs the same an hour into a run as at its start (one strip of the whole path
  at every redraw grew the viewer's work and the recording with the square of the run's length).
- `world/camera`: the current camera pose and pinhole; `world/camera/image` the RGB frame (JPEG as sent),
  `.../detections` (yellow) and `.../tracks` as 2D boxes: tentative tracklets grey, candidates green,
  rejected candidates (moving / unstable) red; `world/rejected` logs each rejection;
  `world/camera/depth` every `viz.depth_every` frames. A frame the detector passed over keeps the last
  detected frame's boxes, detected and tracked.
- `timings/<service>/<stage>`: per-stage latency time series in ms, on the `frame` timeline, sent in batches once
  a second (`TimingColumns`).

Blueprint: the 3D map, a top-down view of it (looking down the gravity axis, once a pose says where that is), and
the camera image; the latency plot is a second tab behind the camera (collapsed by default).
"""

from __future__ import annotations

import argparse
import colorsys
import os
import time
import uuid
from pathlib import Path

import numpy as np

from semmap.core.geometry import carry_correction
from semmap.core.messages import (
    CorrectedPoses,
    Detections,
    Frame,
    Landmark,
    MapUpdate,
    OdometryPose,
    Tracks,
)
from semmap.runtime.transport.service import Service, service_main

OPTIMIZED_DRAW_PERIOD_S = 0.5  # the optimised path is redrawn (the parts that moved) at most this often
TIMINGS_SEND_PERIOD_S = 1.0  # the latency plot's samples go to Rerun in a batch this often (and at the end)
MAP_TILE_M = 16.0  # landmarks are drawn in cubes of this size; an update re-logs the cubes it touched
PATH_UNMOVED_M = 1e-3  # a camera position that moved less than this is not drawn again
PATH_PART_FRAMES = 1000  # camera paths are drawn in strips of this many frame ids; a redraw re-logs those it touched
LABEL_GAP_M = 0.12  # labels closer than this (horizontally and vertically) would overlap: the later is raised
CORE_RADIUS_M = (0.03, 0.06)  # the centroid sphere: a fifth of the landmark's radius, within these bounds

TRACK_COLORS = {"tentative": (160, 160, 160), "candidate": (40, 200, 90), "rejected": (230, 40, 40)}


def landmark_color(landmark_id: int) -> tuple[int, int, int]:
    """A stable, well-spread colour per id (golden-ratio hue steps)."""
    hue = (landmark_id * 0.618033988749895) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.75, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def label_anchors(centres: np.ndarray, tops: np.ndarray, up: np.ndarray, gap: float = LABEL_GAP_M) -> np.ndarray:
    """Where each label goes: just above its box top, raised along `up` by steps of `gap` until it is at least
    `gap` from every label placed before it (in id order), so near-by objects' labels stack instead of piling."""
    up = np.asarray(up, float) / np.linalg.norm(up)
    centres, tops = np.asarray(centres, float).reshape(-1, 3), np.asarray(tops, float).reshape(-1, 3)
    placed = np.zeros_like(centres)
    for i, (c, top) in enumerate(zip(centres, tops, strict=True)):
        anchor = c + up * (float(np.dot(top - c, up)) + 0.05)
        for _ in range(50):
            if i == 0 or np.min(np.linalg.norm(placed[:i] - anchor, axis=1)) >= gap:
                break
            anchor = anchor + up * gap
        placed[i] = anchor
    return placed


def map_tile(centroid: tuple[float, float, float] | np.ndarray) -> str:
    """The entity name of the `MAP_TILE_M` cube a centroid lies in (Rerun path parts: no minus signs)."""
    ijk = (int(np.floor(float(c) / MAP_TILE_M)) for c in centroid)
    return "tile_" + "_".join(str(i).replace("-", "m") for i in ijk)


class TimingColumns:
    """Per-stage latency samples held back and sent to Rerun as one column per stage (`rr.send_columns`).

    Why: a run carries ~9 timings a frame (detector, tracker, associator, backend stages), 8.5 of the viewer's 14.7
    Rerun calls a frame, and one `rr.log` call costs ~0.15 ms of CPU: on 2 cores that CPU is the detector's. A
    column a second costs about as much as one sample; the plot lags by up to a second."""

    def __init__(self) -> None:
        self.samples: dict[str, tuple[list[int], list[float]]] = {}

    def add(self, path: str, frame_id: int, ms: float) -> None:
        frames, values = self.samples.setdefault(path, ([], []))
        frames.append(int(frame_id))
        values.append(float(ms))

    def take(self) -> dict[str, tuple[list[int], list[float]]]:
        """Every waiting sample by entity path (in arrival order), and forget them."""
        samples, self.samples = self.samples, {}
        return samples

    def __len__(self) -> int:
        return sum(len(frames) for frames, _ in self.samples.values())


class MapTiles:
    """Which drawn tile each landmark is in (`map_tile` of its centroid when last drawn), so that a map update
    re-logs only the tiles it touched: the one a landmark left and the one it is in now."""

    def __init__(self) -> None:
        self.members: dict[str, set[int]] = {}
        self.tile_of: dict[int, str] = {}

    def place(self, changed: set[int], landmarks: dict[int, Landmark]) -> dict[str, list[int]]:
        """Move the `changed` landmarks (gone ones: absent from `landmarks`) to their tiles; returns every touched
        tile with its members in id order (an empty list: the tile is empty now)."""
        touched: set[str] = set()
        for lid in changed:
            old = self.tile_of.pop(lid, None)
            if old is not None:
                touched.add(old)
                self.members[old].discard(lid)
            lm = landmarks.get(lid)
            if lm is not None:
                tile = map_tile(lm.centroid)
                self.tile_of[lid] = tile
                self.members.setdefault(tile, set()).add(lid)
                touched.add(tile)
        out = {tile: sorted(self.members.get(tile, ())) for tile in sorted(touched)}
        for tile, ids in out.items():
            if not ids:
                self.members.pop(tile, None)
        return out


class PathParts:
    """A camera path (frame id -> position) kept as parts of `PATH_PART_FRAMES` frame ids, and which parts changed
    since they were last drawn (`take`). A part's strip ends at the next part's first point, so the strips join;
    a new first point of a part therefore also changes the part before it."""

    def __init__(self, part_frames: int = PATH_PART_FRAMES) -> None:
        self.part_frames = part_frames
        self.parts: dict[int, dict[int, np.ndarray]] = {}
        self.first: dict[int, int] = {}  # per part, its smallest frame id
        self.changed: set[int] = set()
        self.drawn: set[int] = set()  # parts whose strip was taken (and so is on screen)

    def set(self, frame_id: int, position: np.ndarray) -> None:
        """A frame's position; one within `PATH_UNMOVED_M` of the drawn one changes nothing (the backend's
        rolling refresh re-sends poses that did not move)."""
        part = frame_id // self.part_frames
        points = self.parts.setdefault(part, {})
        position = np.asarray(position, float)[:3]
        old = points.get(frame_id)
        if old is not None and float(np.abs(old - position).max()) <= PATH_UNMOVED_M:
            return
        points[frame_id] = position.copy()
        self.changed.add(part)
        if frame_id <= self.first.get(part, frame_id):
            self.first[part] = frame_id
            self.changed.add(part - 1)

    def reset(self, positions: dict[int, np.ndarray]) -> None:
        """Replace the whole path (every part drawn again; parts left empty are to be cleared)."""
        self.changed |= set(self.parts)
        self.parts.clear()
        self.first.clear()
        for frame_id in sorted(positions):
            self.set(frame_id, positions[frame_id])

    def take(self) -> dict[int, np.ndarray]:
        """Each changed part's strip (N x 3, in frame order; empty: the part has no frame now), and forget them."""
        out: dict[int, np.ndarray] = {}
        for part in sorted(self.changed):
            points = self.parts.get(part)
            if points is None:
                if part in self.drawn:  # emptied by a reset: its strip is to go
                    out[part] = np.empty((0, 3))
                    self.drawn.discard(part)
                continue
            strip = [points[f] for f in sorted(points)]
            if part + 1 in self.first:
                strip.append(self.parts[part + 1][self.first[part + 1]])
            out[part] = np.array(strip)
            self.drawn.add(part)
        self.changed.clear()
        return out


def blueprint(up: np.ndarray | None = None, centre: np.ndarray | None = None, span: float = 4.0) -> object:
    """Map, top-down view (looking along -up at `centre` from `span` metres; world Z-up until a pose tells) and
    the camera, with the latency plot in a tab behind it."""
    import rerun.blueprint as rrb

    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float) / np.linalg.norm(up)
    centre = np.zeros(3) if centre is None else np.asarray(centre, float)
    side = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(side) < 1e-3:
        side = np.cross(up, [0.0, 1.0, 0.0])
    eye = rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=centre + up * max(span, 1.0), look_target=centre,
                            eye_up=side / np.linalg.norm(side))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="map"),
            rrb.Vertical(
                rrb.Spatial3DView(origin="world", name="top-down", contents=["world/landmarks/**",
                                                                            "world/trajectory/**"],
                                  eye_controls=eye),
                rrb.Tabs(rrb.Spatial2DView(origin="world/camera/image", name="camera"),
                         rrb.TimeSeriesView(origin="timings", name="latency (ms)"), active_tab=0),
                row_shares=[1, 1]),
            column_shares=[3, 2]),
        rrb.TimePanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))


class VizService(Service):
    """Logs everything on the bus worth seeing to Rerun (see module docstring)."""

    name = "viz"

    def setup(self) -> None:
        import rerun as rr

        self.rr = rr
        cfg = self.config.viz
        self.images = cfg.images
        self.depth_every = cfg.depth_every
        # one recording id per run, so what a restarted sink records merges into the same recording
        run_key = str(self.out_dir.resolve()) if self.out_dir is not None else self.robot
        recording_id = f"semmap-{self.robot}-{uuid.uuid5(uuid.NAMESPACE_URL, run_key).hex[:12]}"
        rr.init(f"semmap-{self.robot}", recording_id=recording_id, spawn=False)
        self.parts: list[Path] = []
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            rrd = self.out_dir / "run.rrd"
            self.parts = sorted(self.out_dir.glob("run.part-*.rrd")) if self.resume else []
            if self.resume and rrd.is_file():  # keep what the crashed sink recorded; merged when we finish
                part = self.out_dir / f"run.part-{len(self.parts) + 1}.rrd"
                rrd.rename(part)
                self.parts.append(part)
        sinks: list = [rr.FileSink(str(rrd))] if self.out_dir is not None else []
        if self.args.serve:  # the live run in the web viewer as well as the file
            # loopback only (its default is every interface); a browser that connects late gets the newest data
            # first (the current map), not every camera image since the start before the first landmark
            server = rr.GrpcServerSink(bind_ip="127.0.0.1", port=self.args.grpc_port, newest_first=True)
            sinks.append(server)
            uri = f"rerun+http://127.0.0.1:{self.args.grpc_port}/proxy"  # as the browser on this host sees it
            rr.serve_web_viewer(web_port=self.args.web_port, open_browser=False, connect_to=uri)
            self.log.info("web viewer: http://localhost:%d/?url=%s", self.args.web_port, uri)
        if sinks:
            rr.set_sinks(*sinks)
        rr.send_blueprint(blueprint())
        self.up: np.ndarray | None = None  # gravity's opposite, from the first pose (image y points down)
        rr.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.landmarks: dict[int, Landmark] = {}
        self.tiles = MapTiles()
        self.odometry: dict[int, np.ndarray] = {}  # frame id -> 4x4
        self._last_step_source = ""  # whose step the last odometry pose took (logged when it changes)
        self.optimized: dict[int, np.ndarray] = {}  # frame id -> corrected pose (the backend sends deltas)
        self.optimized_drawn_at = 0.0
        self.odometry_path, self.optimized_path = PathParts(), PathParts()  # what is drawn of each, by part
        self.correction: tuple[np.ndarray, np.ndarray] | None = None  # (corrected, odometry) of one frame
        self.map_frame = -1
        self.pinhole = None  # the intrinsics last logged
        self.rejected: set[int] = set()  # track ids of rejected candidates
        self.timings = TimingColumns()
        self.timings_sent_at = time.monotonic()
        self.subscribe()
        self._load_current_map()

    def listen_options(self, topic: str) -> dict:
        return {"realtime_capacity": 8} if topic == "frames" else {}

    def _load_current_map(self) -> None:
        """Start from the map as it is (a sink started late or restarted would see only later changes)."""
        import json

        for reply in self.bus.session.get(self.bus.keys.map_query, timeout=1.0):
            if reply.ok is not None:
                body = json.loads(reply.ok.payload.to_bytes())
                self.landmarks = {lm.id: lm for lm in map(Landmark.from_dict, body.get("landmarks", []))}
                if self.landmarks:
                    self._log_landmarks(set(self.landmarks))
                break

    def _at(self, frame_id: int) -> None:
        self.rr.set_time("frame", sequence=frame_id)

    def on_frame(self, frame: Frame) -> None:
        with self.metrics.timer("log_frame_ms"):
            self._log_frame(frame)
        self.metrics.count("frames")
        self.last_frame_id = max(self.last_frame_id, frame.frame_id)
        if self.end_of_stream is not None:
            self.on_end_of_stream(self.end_of_stream)

    def _log_frame(self, frame: Frame) -> None:
        rr = self.rr
        self._at(frame.frame_id)
        k = frame.intrinsics
        if k != self.pinhole:  # the camera's model: logged when it changes, not with every frame
            self.pinhole = k
            rr.log("world/camera", rr.Pinhole(focal_length=[k.fx, k.fy], principal_point=[k.cx, k.cy],
                                              resolution=[k.width, k.height], image_plane_distance=0.3))
        if self.images:
            rr.log("world/camera/image", rr.EncodedImage(contents=frame.rgb_jpeg, media_type="image/jpeg"))
        if self.depth_every and frame.frame_id % self.depth_every == 0:
            rr.log("world/camera/depth", rr.DepthImage(frame.depth(), meter=1.0 / frame.depth_scale))

    def on_odometry(self, pose: OdometryPose) -> None:
        rr = self.rr
        self._at(pose.frame_id)
        self.odometry[pose.frame_id] = pose.pose.copy()
        if self.up is None:  # the first camera's -y is "up" for handheld and robot data: the top-down axis
            self.up = -pose.pose[:3, 1]
            rr.send_blueprint(blueprint(self.up, pose.pose[:3, 3] + 1.5 * pose.pose[:3, 2]))
        # show the camera where the optimised map puts it: the newest correction applied to the odometry
        current = pose.pose if self.correction is None else carry_correction(*self.correction, pose.pose)
        rr.log("world/camera", rr.Transform3D(translation=current[:3, 3], mat3x3=current[:3, :3]))
        self.odometry_path.set(pose.frame_id, pose.pose[:3, 3])
        if pose.frame_id % 5 == 0:
            self._draw_path("world/trajectory/odometry", self.odometry_path, (230, 120, 30), 0.005)
        if pose.step and pose.step != self._last_step_source:  # whose step the pose took, where semmap checked a SLAM
            why = {"slam": "the SLAM's own step", "semmap": "semmap's registration (the static scene favoured it)",
                   "motion": "the motion model (no witness; the scene favoured it over the SLAM's jump)",
                   "copied": "the SLAM's step, unchecked"}.get(pose.step, pose.step)
            rr.log("world/camera/repair", rr.TextLog(f"frame {pose.frame_id}: {why}"
                                                     + (" (bridged: the SLAM had no pose)" if pose.bridged else "")))
            self._last_step_source = pose.step

    def on_corrected(self, poses: CorrectedPoses) -> None:
        changed = poses.apply_to(self.optimized)
        if poses.full:
            self.optimized_path.reset({f: pose[:3, 3] for f, pose in self.optimized.items()})
        else:
            for frame_id in changed:
                self.optimized_path.set(frame_id, self.optimized[frame_id][:3, 3])
        if len(poses.poses) == 0:
            return
        self._at(poses.frame_id)
        # at most twice a second (and whenever a full message comes): a loop closure moves many parts of the path
        now = time.monotonic()
        if poses.full or now - self.optimized_drawn_at >= OPTIMIZED_DRAW_PERIOD_S:
            self.optimized_drawn_at = now
            self._draw_optimized()
        last_id = int(poses.frame_ids[-1])
        if last_id in self.odometry:
            self.correction = (poses.poses[-1], self.odometry[last_id])  # the newest corrected frame, its odometry
        for name, ms in poses.timing_ms.items():
            self.timings.add(f"timings/backend/{name}", poses.frame_id, ms)

    def _draw_optimized(self) -> None:
        self._draw_path("world/trajectory/optimized", self.optimized_path, (40, 140, 255), 0.006)

    def _draw_path(self, entity: str, path: PathParts, color: tuple[int, int, int], radius: float) -> None:
        """Re-log the parts of a camera path that changed since it was last drawn (`PathParts`)."""
        rr = self.rr
        for part, strip in path.take().items():
            if len(strip):
                rr.log(f"{entity}/part_{part}", rr.LineStrips3D([strip], colors=[color], radii=radius))
            else:
                rr.log(f"{entity}/part_{part}", rr.Clear(recursive=False))

    def on_detections(self, det: Detections) -> None:
        rr = self.rr
        if det.skipped:  # a frame the detector passed over (cadence, overload): the last boxes stay up; clearing
            return  # them would make the overlay blink at every skipped frame
        self._at(det.frame_id)
        if det.detections:
            rr.log("world/camera/image/detections", rr.Boxes2D(
                array=[d.box for d in det.detections], array_format=rr.Box2DFormat.XYXY,
                labels=[f"{d.class_name} {d.score:.2f}" for d in det.detections], colors=[(255, 210, 0)]))
        else:
            rr.log("world/camera/image/detections", rr.Clear(recursive=False))
        for name, ms in det.timing_ms.items():
            self.timings.add(f"timings/detector/{name}", det.frame_id, ms)

    def on_tracks(self, tracks: Tracks) -> None:
        rr = self.rr
        if "proposal" in tracks.timing_ms:
            self.timings.add("timings/tracker/proposal", tracks.frame_id, tracks.timing_ms["proposal"])
        if tracks.skipped:  # a frame the detector passed over carries no boxes: the last tracked ones stay up, as
            return  # the detections do (clearing them made the overlay blink at every skipped frame)
        self._at(tracks.frame_id)
        if tracks.boxes:
            states = ["rejected" if b.track_id in self.rejected else "candidate" if b.candidate else "tentative"
                      for b in tracks.boxes]
            rr.log("world/camera/image/tracks", rr.Boxes2D(
                array=[b.box for b in tracks.boxes], array_format=rr.Box2DFormat.XYXY,
                labels=[f"{b.class_name} t{b.track_id}" for b in tracks.boxes],  # the state is the colour
                colors=[TRACK_COLORS[s] for s in states]))
        else:
            rr.log("world/camera/image/tracks", rr.Clear(recursive=False))

    def on_map(self, update: MapUpdate) -> None:
        with self.metrics.timer("log_map_ms"):
            self._log_map(update)
        if self.end_of_stream is not None:
            self.on_end_of_stream(self.end_of_stream)

    def _log_map(self, update: MapUpdate) -> None:
        rr = self.rr
        self._at(update.frame_id)
        changed = set(self.landmarks) if update.full else set()
        if update.full:
            self.landmarks.clear()
        for gone in update.removed:
            self.landmarks.pop(gone, None)
            changed.add(gone)
        for absorbed, _ in update.merges:
            self.landmarks.pop(absorbed, None)
            changed.add(absorbed)
        for lm in update.landmarks:
            self.landmarks[lm.id] = lm
            changed.add(lm.id)
        self.map_frame = max(self.map_frame, update.frame_id)
        if changed:
            self._log_landmarks(changed)
        if update.rejected_candidates:
            # drawn red on the image from now on (see on_tracks), and noted in the log view
            self.rejected.update(update.rejected_candidates)
            rr.log("world/rejected", rr.TextLog(f"rejected candidates (moving / unstable): tracks "
                                                f"{update.rejected_candidates}", level="WARN"))
        for name, ms in update.timing_ms.items():
            self.timings.add(f"timings/associator/{name}", update.frame_id, ms)

    def _log_landmarks(self, changed: set[int]) -> None:
        """Re-log the tiles that the `changed` landmarks left or lie in (a tile left empty is cleared)."""
        for tile, ids in self.tiles.place(changed, self.landmarks).items():
            if ids:
                self._log_tile(tile, [self.landmarks[i] for i in ids])
            else:
                self.rr.log(f"world/landmarks/{tile}", self.rr.Clear(recursive=True))

    def _log_tile(self, tile: str, items: list[Landmark]) -> None:
        """One tile's boxes, centre spheres, labels and leader lines (the whole tile: Rerun keeps the latest)."""
        rr = self.rr
        path = f"world/landmarks/{tile}"
        centres = np.array([lm.centroid for lm in items], float)
        half = np.array([np.maximum(np.asarray(lm.extent, float), 0.04) / 2 for lm in items])
        colors = [landmark_color(lm.id) for lm in items]
        labels = [f"{lm.class_name} #{lm.id}" for lm in items]
        rr.log(path, rr.Boxes3D(centers=centres, half_sizes=half, colors=colors, radii=0.005,
                                fill_mode="majorwireframe", labels=labels, show_labels=False))
        core = np.clip([0.2 * lm.radius for lm in items], *CORE_RADIUS_M)
        rr.log(f"{path}/centres", rr.Ellipsoids3D(centers=centres, half_sizes=np.repeat(core[:, None], 3, 1),
                                                  colors=colors, fill_mode="solid"))
        up = self.up if self.up is not None else np.array([0.0, 0.0, 1.0])
        up = up / np.linalg.norm(up)
        tops = centres + up * np.abs(half @ np.abs(up))[:, None] if len(items) else centres
        anchors = label_anchors(centres, tops, up)
        rr.log(f"{path}/labels", rr.Points3D(anchors, colors=colors, radii=0.006, labels=labels, show_labels=True))
        rr.log(f"{path}/leaders", rr.LineStrips3D(np.stack([centres, anchors], axis=1), colors=colors, radii=0.002))

    def tick(self) -> None:
        if time.monotonic() - self.timings_sent_at >= TIMINGS_SEND_PERIOD_S:
            self._send_timings()

    def _send_timings(self) -> None:
        """The latency samples held back since the last send, one column per stage."""
        self.timings_sent_at = time.monotonic()
        rr = self.rr
        for path, (frames, values) in self.timings.take().items():
            rr.send_columns(path, indexes=[rr.TimeColumn("frame", sequence=frames)],
                            columns=rr.Scalars.columns(scalars=values))

    def on_end_of_stream(self, control) -> None:  # noqa: ANN001 - Control
        frames_done = self.last_frame_id >= control.last_frame_id
        if frames_done:
            self._draw_optimized()  # the newest path, whatever the redraw period left out
        if frames_done and (self.map_frame >= control.last_frame_id or not self.args.wait_for_map):
            self.finish()

    def _frame_the_map(self) -> None:
        """Point the top-down view at the whole map (its bounding box, from high enough to see all of it)."""
        if not self.landmarks:
            return
        centres = np.array([lm.centroid for lm in self.landmarks.values()], float)
        lo, hi = centres.min(axis=0), centres.max(axis=0)
        span = max(2.0, 1.3 * float(np.linalg.norm(hi - lo)))
        self.rr.send_blueprint(blueprint(self.up, (lo + hi) / 2, span))

    def write_outputs(self) -> None:
        """Frame the map in the top-down view; after a restart, merge the earlier parts and this one into run.rrd."""
        self._send_timings()
        self._frame_the_map()
        if not self.parts or self.out_dir is None:
            return
        import shutil
        import subprocess
        import sys

        self.rr.disconnect()
        rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
        rrd = self.out_dir / "run.rrd"
        merged = self.out_dir / "run.merged.rrd"
        if rerun is None:
            self.log.warning("rerun CLI missing: the recording stays in parts %s", [p.name for p in self.parts])
            return
        result = subprocess.run([rerun, "rrd", "merge", *map(str, self.parts), str(rrd), "-o", str(merged)],
                                capture_output=True, text=True, env={**os.environ, "CI": "true"})
        if result.returncode == 0:
            merged.replace(rrd)
            for part in self.parts:
                part.unlink()
            self.parts = []
        else:
            self.log.warning("could not merge the recording parts: %s", result.stderr[-500:])

    def teardown(self) -> None:
        if len(self.timings):
            self._send_timings()
        self.rr.disconnect()


def _arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--serve", action="store_true", help="also serve the Rerun web viewer (live run)")
    parser.add_argument("--web-port", type=int, default=9090, help="web viewer port (with --serve)")
    parser.add_argument("--grpc-port", type=int, default=9876, help="Rerun gRPC port (with --serve)")
    parser.add_argument("--wait-for-map", action="store_true",
                        help="finish only after the map update of the last frame (the run has an associator)")


def main(argv: list[str] | None = None) -> int:
    return service_main(VizService, argv, _arguments)
