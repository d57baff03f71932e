"""A saved map: what a dense SLAM run leaves for a later one to track against, extend or mesh (docs/MAPS.md).

    saved = slam.map_state()                  # SavedMap: copies of the surfels, keyframes, places, pose graph
    slam.save_map("run/map")                  # the same, on disk (ti_fusion/io/map_files.py's layout)
    saved = load_map("run")                   # a map folder, its map.json, or a run folder holding map/
    slam2 = DenseSLAM.from_map(saved)         # a DenseSLAM whose next frames track against it
    check_camera(saved, dataset.intrinsics, "run")   # InputError naming both cameras when they differ

The map's world frame is the trajectory frame of the run that made it (its first pose: the identity, or the
first frame's ground truth with ``slam.start_at_ground_truth``). Everything is kept as the run holds it
(float32 surfels, float64 poses), so a map saved, loaded and saved again is the same bytes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ti_fusion.camera import Intrinsics
from ti_fusion.config import Config, apply_dict
from ti_fusion.errors import InputError
from ti_fusion.geometry import invert, renormalize
from ti_fusion.io.map_files import VERSION, read_map_folder, write_map_folder
from ti_fusion.loop.keyframes import Keyframe, grid_points
from ti_fusion.loop.pose_graph import Edge
from ti_fusion.tracking.features import FrameFeatures

# The surfel attributes a map keeps (kernels/surfels.py STORED): position, normal (world frame; metres, unit),
# colour (RGB 0-255), weight (confidence), radius (metres), t_created / t_updated (fused-frame counts of the
# map's clock, ``frames_fused``) and anchor (the keyframe a loop correction moves the surfel with).
SURFEL_ATTRIBUTES = ("position", "normal", "color", "weight", "radius", "t_created", "t_updated", "anchor")


@dataclass
class PlaceState:
    """Place recognition's learnt state (``PlaceDatabase``): the vocabulary (W×32 uint8 binary words, None
    before the fourth keyframe), each keyframe's word counts (K×W float32), how often it was learnt, and
    the state of the random generator that picks its training descriptors."""

    vocabulary: np.ndarray | None
    word_counts: np.ndarray
    trainings: int
    rng: dict


@dataclass
class MapTrajectory:
    """Every posed frame of the sessions that made the map, each anchored to a keyframe: its pose is kept relative
    to that keyframe's (``relative`` = T_wk⁻¹ T_wc), so a loop that moves the keyframe moves the frame with it, as it
    moves the surfels anchored there; anchor -1: the pose is in the world frame (a run without loop closure)."""

    session: np.ndarray    # N int32: 0 for the run that started the map, 1 for the first session that extended it, ...
    frame: np.ndarray      # N int32: the frame's index in its session's data
    timestamp: np.ndarray  # N float64: seconds, as in that session's trajectory.tum
    anchor: np.ndarray     # N int32: the keyframe id, or -1
    relative: np.ndarray   # N×4×4 float64: the camera-to-keyframe pose (camera-to-world where anchor is -1)
    sessions: int = 0      # the sessions that posed frames in the map (a version 1 map: 1, its frames unknown)

    ARRAYS = ("session", "frame", "timestamp", "anchor", "relative")
    DTYPES = (np.int32, np.int32, np.float64, np.int32, np.float64)

    @classmethod
    def empty(cls, sessions: int = 0) -> "MapTrajectory":
        return cls(*(np.zeros((0, 4, 4) if name == "relative" else 0, dtype)
                     for name, dtype in zip(cls.ARRAYS, cls.DTYPES)), sessions=sessions)

    def __len__(self) -> int:
        return len(self.frame)

    def poses(self, keyframes: list) -> np.ndarray:
        """N×4×4 camera-to-world poses: each relative pose composed with its keyframe's current pose."""
        out = self.relative.copy()
        for i, k in enumerate(self.anchor):
            if k >= 0:
                out[i] = keyframes[k].pose @ self.relative[i]
        return out

    def then(self, frames: list[tuple[int, float, np.ndarray, int]], keyframes: list) -> "MapTrajectory":
        """This trajectory and the next session's posed ``frames`` ((frame, timestamp, camera-to-world pose,
        anchor), ``PoseStore.posed``), each made relative to its anchor among ``keyframes`` (-1 past them)."""
        if not frames:  # a session that posed no frame (a map loaded and saved again) adds none
            return self
        rows = []
        for frame, stamp, pose, k in frames:
            k = k if 0 <= k < len(keyframes) else -1
            rows.append((frame, stamp, k, pose if k < 0 else renormalize(invert(keyframes[k].pose) @ pose)))
        new = MapTrajectory(np.full(len(rows), self.sessions, np.int32), np.array([r[0] for r in rows], np.int32),
                            np.array([r[1] for r in rows], np.float64), np.array([r[2] for r in rows], np.int32),
                            np.array([r[3] for r in rows], np.float64).reshape(-1, 4, 4), self.sessions + 1)
        return MapTrajectory(*(np.concatenate([getattr(self, n), getattr(new, n)]) for n in self.ARRAYS),
                             sessions=new.sessions)


@dataclass
class SavedMap:
    """Everything a later run needs to track against a map, extend it and close loops into it."""

    intrinsics: Intrinsics          # the camera of the frames (as DenseSLAM got them: after --downsample)
    map_level: int                  # fusion.level as it resolved for them (the surfels' and keyframe depths' scale)
    config: dict                    # Config.to_dict() of the run that made (or last extended) the map
    surfels: dict[str, np.ndarray]  # SURFEL_ATTRIBUTES, the live surfels in map order
    frames_fused: int               # the map's clock: frames fused into it so far (t_created / t_updated count them)
    anchor: int                     # the keyframe that the surfels fused next are anchored to (the last one's id)
    last_frame: int                 # the index of the last frame the run registered (-1: none)
    keyframes: list[Keyframe] = field(default_factory=list)  # loop closure's keyframes (poses: current estimates)
    places: PlaceState | None = None  # place recognition (None: the run had no loop closure)
    graph_poses: list[np.ndarray] = field(default_factory=list)  # the pose graph's keyframe poses
    graph_edges: list[Edge] = field(default_factory=list)  # its odometry, PnP and loop edges
    loops: dict = field(default_factory=lambda: {"applied": [], "refused": [], "kept": []})  # loops closed so far
    trajectory: MapTrajectory = field(default_factory=MapTrajectory.empty)  # the posed frames of every session
    # (none in a version 1 map)
    version: int = VERSION

    def trajectory_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(timestamps, N×4×4 camera-to-world poses) of every posed frame of the sessions that made the map, at the
        keyframes' current poses (every loop applied), in the map's world frame, session after session."""
        return self.trajectory.timestamp.copy(), self.trajectory.poses(self.keyframes)

    @property
    def count(self) -> int:
        """Surfels in the map."""
        return len(self.surfels["position"])

    def make_config(self) -> Config:
        """The config the map was made with (a key this ti-fusion no longer has: one InputError line)."""
        return apply_dict(Config(), self.config, where="the saved map's config")

    def describe(self) -> str:
        """One line: surfels, keyframes, camera."""
        return (f"{self.count} surfels, {len(self.keyframes)} keyframes, {self.frames_fused} frames fused, "
                f"camera {describe_camera(self.intrinsics)}")

    # -- to and from the file layout ---------------------------------------------------------------
    def write(self, folder: str | Path) -> Path:
        """This map written into ``folder`` (created if missing): map.json and map.bin (docs/MAPS.md)."""
        header, arrays = self.to_arrays()
        return write_map_folder(folder, header, arrays)

    def to_arrays(self) -> tuple[dict, dict[str, np.ndarray]]:
        """(header, name → array) as ``write_map_folder`` takes them (docs/MAPS.md lists every one)."""
        header = {
            "camera": _camera_dict(self.intrinsics), "map_level": self.map_level,
            "surfels": self.count, "frames_fused": self.frames_fused, "anchor": self.anchor,
            "last_frame": self.last_frame, "keyframes": [
                {"id": kf.id, "frame": kf.frame, "timestamp": kf.timestamp, "features": len(kf.features),
                 "descriptors": kf.features.descriptors is not None, "intrinsics": _camera_dict(kf.intrinsics),
                 "depth_intrinsics": _camera_dict(kf.depth_intrinsics)} for kf in self.keyframes],
            "places": None if self.places is None else {"trainings": self.places.trainings, "rng": self.places.rng,
                                                        "vocabulary": self.places.vocabulary is not None},
            "graph_edges": [{"i": e.i, "j": e.j, "loop": e.loop, "robust": e.robust,
                             "covariance": e.covariance is not None} for e in self.graph_edges],
            "loops": self.loops, "config": self.config,
            "trajectory": {"frames": len(self.trajectory), "sessions": self.trajectory.sessions},
        }
        arrays = {f"surfels/{name}": self.surfels[name] for name in SURFEL_ATTRIBUTES}
        kfs = self.keyframes
        arrays["keyframes/pose"] = _stack([kf.pose for kf in kfs], (4, 4), np.float64)
        depth_shape = kfs[0].depth.shape if kfs else (0, 0)
        arrays["keyframes/depth"] = _stack([kf.depth for kf in kfs], depth_shape, np.float32)
        feats = [kf.features for kf in kfs]
        arrays["features/keypoints"] = _stack([np.array([(k.pt[0], k.pt[1], k.size, k.angle, k.response)
                                                         for k in f.keypoints], np.float32).reshape(-1, 5)
                                               for f in feats], (5,), np.float32, concat=True)
        arrays["features/keypoint_ids"] = _stack([np.array([(k.octave, k.class_id) for k in f.keypoints],
                                                           np.int32).reshape(-1, 2) for f in feats], (2,), np.int32,
                                                 concat=True)
        arrays["features/descriptors"] = _stack([f.descriptors for f in feats if f.descriptors is not None], (32,),
                                                np.uint8, concat=True)
        arrays["features/pixels"] = _stack([f.pixels for f in feats], (2,), np.float64, concat=True)
        arrays["features/points"] = _stack([f.points for f in feats], (3,), np.float64, concat=True)
        if self.places is not None:
            if self.places.vocabulary is not None:
                arrays["places/vocabulary"] = self.places.vocabulary
            arrays["places/word_counts"] = self.places.word_counts
        arrays["graph/poses"] = _stack(self.graph_poses, (4, 4), np.float64)
        arrays["graph/edge_transforms"] = _stack([e.T for e in self.graph_edges], (4, 4), np.float64)
        arrays["graph/edge_covariances"] = _stack([e.covariance for e in self.graph_edges if e.covariance is not None],
                                                  (6, 6), np.float64)
        t = self.trajectory
        for name, dtype in zip(MapTrajectory.ARRAYS, MapTrajectory.DTYPES):
            arrays[f"trajectory/{name}"] = np.ascontiguousarray(getattr(t, name), dtype=dtype)
        return header, arrays

    @classmethod
    def from_arrays(cls, header: dict, arrays: dict[str, np.ndarray], where: str | Path | None = None) -> "SavedMap":
        """The map ``to_arrays`` gave (read back by ``read_map_folder``); InputError where they disagree."""
        try:
            return cls._from_arrays(header, arrays)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise InputError(where, f"is damaged: its header and arrays disagree ({type(exc).__name__}: "
                                    f"{exc})") from None

    @classmethod
    def _from_arrays(cls, header: dict, arrays: dict[str, np.ndarray]) -> "SavedMap":
        import cv2

        # the arrays are the map's own (read_map_folder reads each into one): taken, not copied again
        surfels = {name: arrays[f"surfels/{name}"] for name in SURFEL_ATTRIBUTES}
        n = int(header["surfels"])
        if any(len(a) != n for a in surfels.values()):
            raise ValueError(f"surfel arrays of another length than the {n} surfels")
        keyframes = []
        k_kp, k_desc = 0, 0
        kp, kp_ids = arrays["features/keypoints"], arrays["features/keypoint_ids"]
        desc, pixels, points = arrays["features/descriptors"], arrays["features/pixels"], arrays["features/points"]
        for index, meta in enumerate(header["keyframes"]):
            m = int(meta["features"])
            if m:
                keypoints = tuple(cv2.KeyPoint(float(x), float(y), float(s), float(a), float(r), int(o), int(c))
                                  for (x, y, s, a, r), (o, c) in zip(kp[k_kp:k_kp + m], kp_ids[k_kp:k_kp + m]))
                descriptors = None
                if meta["descriptors"]:
                    descriptors = desc[k_desc:k_desc + m]
                    k_desc += m
                features = FrameFeatures(keypoints, descriptors, pixels[k_kp:k_kp + m], points[k_kp:k_kp + m])
            else:  # as extract_features leaves a frame without keypoints
                features = FrameFeatures((), None, np.zeros((0, 2)), np.zeros((0, 3)))
            k_kp += m
            depth = arrays["keyframes/depth"][index]
            depth_intrinsics = _camera(meta["depth_intrinsics"])
            keyframes.append(Keyframe(int(meta["id"]), int(meta["frame"]), float(meta["timestamp"]),
                                      arrays["keyframes/pose"][index], features, _camera(meta["intrinsics"]),
                                      depth, depth_intrinsics, grid_points(depth, depth_intrinsics)))
        if k_kp != len(kp) or k_desc != len(desc):
            raise ValueError("feature arrays of another length than the keyframes' features")
        places = None
        if header["places"] is not None:
            p = header["places"]
            places = PlaceState(arrays["places/vocabulary"] if p["vocabulary"] else None,
                                arrays["places/word_counts"], int(p["trainings"]), p["rng"])
        edges, k_cov = [], 0
        covariances = arrays["graph/edge_covariances"]
        for e, T in zip(header["graph_edges"], arrays["graph/edge_transforms"]):
            covariance = None
            if e["covariance"]:
                covariance = covariances[k_cov]
                k_cov += 1
            edges.append(Edge(int(e["i"]), int(e["j"]), T, bool(e["loop"]), covariance, bool(e["robust"])))
        if len(edges) != len(header["graph_edges"]) or k_cov != len(covariances):
            raise ValueError("pose-graph arrays of another length than its edges")
        trajectory = MapTrajectory.empty(sessions=1)  # version 1 kept no trajectory
        if int(header["version"]) >= 2:
            trajectory = MapTrajectory(*(arrays[f"trajectory/{name}"] for name in MapTrajectory.ARRAYS),
                                       sessions=int(header["trajectory"]["sessions"]))
            n = int(header["trajectory"]["frames"])
            if any(len(getattr(trajectory, name)) != n for name in MapTrajectory.ARRAYS) or \
                    trajectory.relative.shape[1:] != (4, 4) or np.any(trajectory.anchor >= len(keyframes)) or \
                    np.any(trajectory.anchor < -1):
                raise ValueError(f"trajectory arrays that are not {n} poses anchored to its keyframes")
        return cls(_camera(header["camera"]), int(header["map_level"]), header["config"], surfels,
                   int(header["frames_fused"]), int(header["anchor"]), int(header["last_frame"]), keyframes, places,
                   list(arrays["graph/poses"]), edges, header["loops"], trajectory,
                   int(header["version"]))


def load_map(path: str | Path) -> SavedMap:
    """The saved map that ``path`` names (a map folder, its map.json, or a run folder holding map/); one
    InputError line for a path that holds none, or a map that is truncated, corrupted or of another version."""
    header, arrays = read_map_folder(path)
    return SavedMap.from_arrays(header, arrays, where=path)


def describe_camera(K: Intrinsics) -> str:
    return f"fx={K.fx:g} fy={K.fy:g} cx={K.cx:g} cy={K.cy:g} at {K.width}x{K.height}"


def check_camera(saved: SavedMap, intrinsics: Intrinsics, where: str | Path | None = None,
                 config: Config | None = None) -> None:
    """InputError naming both cameras when frames of ``intrinsics`` cannot be tracked against ``saved`` (another
    image size or pinhole camera), or, given the new run's ``config``, when its fusion.level puts the map at
    another resolution than the saved one's."""
    a, b = saved.intrinsics, intrinsics
    same = (a.width, a.height) == (b.width, b.height) and all(
        math.isclose(getattr(a, k), getattr(b, k), rel_tol=1e-6, abs_tol=1e-9)
        for k in ("fx", "fy", "cx", "cy", "skew"))
    if not same:
        raise InputError(where, f"a map of camera {describe_camera(a)}; the frames are of camera "
                                f"{describe_camera(b)}: a map is tracked against with the camera (and --downsample) "
                                "it was made with")
    if config is not None and (level := config.fusion.map_level(b.width)) != saved.map_level:
        raise InputError(where, f"a map fused at pyramid level {saved.map_level}; fusion.level = "
                                f"{config.fusion.level} puts this run's map at level {level}")


# -- capture and restore (DenseSLAM.map_state, DenseSLAM.from_map) --------------------------------------
def capture(slam) -> SavedMap:
    """The state of ``slam`` (a DenseSLAM) as a SavedMap: copies, so the run goes on unchanged."""
    carried = slam.loaded_map  # the map this run started from (its loop state kept here when loop closure is off)
    frames = slam.poses.by_frame()
    last = max(frames) if frames else (carried.last_frame if carried is not None else -1)
    saved = SavedMap(slam.intrinsics, slam.map_level, slam.config.to_dict(),
                     slam.mapper.map.to_numpy(SURFEL_ATTRIBUTES), slam._frames_fused, slam.mapper.anchor, last)
    loop = slam.loop
    if loop is not None:
        saved.keyframes = _copied_keyframes(loop.keyframes)
        db = loop.database
        saved.places = PlaceState(None if db.vocabulary is None else db.vocabulary.copy(), db.word_counts.copy(),
                                  db.trainings, db.rng_state())
        saved.graph_poses, saved.graph_edges = _copied_graph(loop.graph.poses, loop.graph.edges)
        saved.loops = {"applied": [list(x) for x in loop.applied], "refused": [list(x) for x in loop.refused],
                       "kept": [list(x) for x in loop.kept]}
    elif carried is not None:  # loop closure off in this run: the loaded map's keyframes stay as they were
        saved.keyframes, saved.places = carried.keyframes, carried.places
        saved.graph_poses, saved.graph_edges, saved.loops = carried.graph_poses, carried.graph_edges, carried.loops
    saved.trajectory = _trajectory(slam)
    return saved


def map_trajectory(slam) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps, N×4×4 camera-to-world poses) of every posed frame of the map ``slam`` holds: the earlier
    sessions' (a loaded map's trajectory) at its keyframes' current poses, then this run's, in the map's frame."""
    carried = slam.loaded_map
    keyframes = slam.loop.keyframes if slam.loop is not None else carried.keyframes if carried is not None else []
    trajectory = _trajectory(slam)
    return trajectory.timestamp.copy(), trajectory.poses(keyframes)


def _trajectory(slam) -> MapTrajectory:
    """The earlier sessions' frames (anchored to the map's keyframes, which this run's loops may have moved), then
    this run's, anchored to the keyframes it made (none without loop closure: in the world frame)."""
    carried = slam.loaded_map
    earlier = carried.trajectory if carried is not None else MapTrajectory.empty()
    return earlier.then(slam.poses.posed(), slam.loop.keyframes if slam.loop is not None else [])


def restore(slam, saved: SavedMap) -> None:
    """Put ``saved`` into a new ``slam`` (DenseSLAM, no frame registered yet): the surfels into its map (grown
    to fit), the map's clock and anchor, and with loop closure on the keyframes, place recognition and the
    pose graph; with it off they are kept aside (``slam.loaded_map``), so that saving again keeps them."""
    if slam.poses:
        raise ValueError("restore into a DenseSLAM that has registered frames")
    slam.mapper.map.from_numpy(saved.surfels)
    slam.mapper.anchor = saved.anchor
    slam.poses.keyframe = saved.anchor
    slam._frames_fused = saved.frames_fused
    # its surfels left out (empty arrays of their own, not views that would keep the loaded ones for the run)
    slam.loaded_map = dataclasses.replace(saved, surfels={name: np.empty((0, *a.shape[1:]), a.dtype)
                                                          for name, a in saved.surfels.items()})
    loop = slam.loop
    if loop is None:
        return
    loop.keyframes = _copied_keyframes(saved.keyframes)
    if saved.places is not None:
        loop.database.restore(loop.keyframes, saved.places.vocabulary, saved.places.word_counts,
                              saved.places.trainings, saved.places.rng)
    else:
        for kf in loop.keyframes:  # a map from a run without place recognition's state: learnt again here
            loop.database.add(kf)
    loop.graph.poses, loop.graph.edges = _copied_graph(saved.graph_poses, saved.graph_edges)
    loop.applied = [tuple(x) for x in saved.loops.get("applied", [])]
    loop.refused = [tuple(x) for x in saved.loops.get("refused", [])]
    loop.kept = [tuple(x) for x in saved.loops.get("kept", [])]


def _copied_keyframes(keyframes: list[Keyframe]) -> list[Keyframe]:
    """The keyframes with poses of their own (loop corrections move them in place); the rest is never written."""
    return [dataclasses.replace(kf, pose=kf.pose.copy()) for kf in keyframes]


def _copied_graph(poses: list[np.ndarray], edges: list[Edge]) -> tuple[list[np.ndarray], list[Edge]]:
    """The pose graph's poses and edges as copies, between a running map and a SavedMap either way."""
    return [p.copy() for p in poses], [dataclasses.replace(e, T=e.T.copy(), covariance=None if e.covariance is None
                                                           else e.covariance.copy()) for e in edges]


def _camera_dict(K: Intrinsics) -> dict:
    d = dataclasses.asdict(K)
    d["distortion"] = list(d["distortion"])
    return d


def _camera(d: dict) -> Intrinsics:
    return Intrinsics(**{**d, "distortion": tuple(d.get("distortion", ()))})


def _stack(items: list, shape: tuple, dtype, concat: bool = False) -> np.ndarray:
    """``items`` stacked (or with ``concat`` concatenated) as ``dtype``; none: an empty array of rows of ``shape``."""
    if not items:
        return np.zeros((0, *shape), dtype)
    return np.ascontiguousarray(np.concatenate(items) if concat else np.stack(items), dtype=dtype)
