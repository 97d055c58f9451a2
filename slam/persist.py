"""SLAM map persistence: one file per map, written atomically, verified on load (issue 7).

File layout: an uncompressed numpy ``.npz`` (zip of ``.npy`` arrays, no pickles) holding

* ``header``: UTF-8 JSON (as a uint8 array): ``format`` ("terraslam-slam-map"), ``version``, the
  camera it was built with (size, K, distortion), ``map_id`` and ``reset_counter`` (the identity
  downstream alignments are keyed on), the id counters, ``created_wall_s`` (time.time()) and
  ``created_mono_s`` (time.monotonic()) of the snapshot, counts, ``attachments`` (caller JSON, e.g.
  the alignment that maps this map to the world) and ``content_sha256``;
* keyframes: ``kf_id``, ``kf_t_s``, ``kf_seq``, ``kf_T_cam_slam`` (K,4,4) and the features needed to
  relocalise and to keep mapping: ``feat_offsets`` (K+1), ``feat_uv_px`` (F,2), ``feat_desc`` (F,32)
  uint8, ``feat_point_id`` (F,) (-1: no map point);
* map points: ``pt_id``, ``pt_p_slam`` (P,3), ``pt_desc`` (P,32), ``pt_first_kf``, and observations
  ``obs_offsets`` (P+1), ``obs_kf_id``, ``obs_feat``; their reference patches (slam.patches), so a
  loaded point's new observations are aligned to sub-pixel from the first keyframe on:
  ``pt_patch`` (P,13,13) uint8 and ``pt_patch_octave`` (P,) (its pyramid level; -1: no patch, the
  rows are zeros). The two are optional: a file without them (written before they existed) loads
  with no patches, and a build that does not know them reads the file and ignores them.

``content_sha256`` covers the header's other fields and every array (name, dtype, shape, bytes), so
a truncated or altered file is refused. Writes go to a temporary file in the same folder, are
fsynced, then ``os.replace``d over the target (and the folder fsynced): a ``kill -9`` or power cut
mid-write leaves either the previous file or the new one, never a torn one.

Times: keyframe ``t_s`` are the saving process's monotonic seconds. ``LoadedMap.rebase_times``
moves them onto this process's monotonic clock with the wall-clock time elapsed since the save.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import secrets
import tempfile
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slam.map import Keyframe, MapPoint, SlamMap
from slam.patches import N_LEVELS, STORED_PX
from slam.types import CameraModel

FORMAT = "terraslam-slam-map"
VERSION = 1
DESC_BYTES = 32
_K_RTOL = 1e-6


class MapFileError(ValueError):
    """A saved map cannot be used: names the file and the problem (caller starts a fresh map)."""

    def __init__(self, path: Path | str, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"SLAM map file {self.path}: {problem}")


def new_map_id() -> int:
    """A random 62-bit id for a new map (unique across processes and restarts)."""
    return secrets.randbits(62)


@dataclass(frozen=True)
class MapSnapshot:
    """A consistent copy of a SlamMap (taken under its lock), ready to write without the lock."""

    arrays: dict[str, np.ndarray]
    next_kf_id: int
    next_point_id: int

    @property
    def n_keyframes(self) -> int:
        return len(self.arrays["kf_id"])

    @property
    def n_points(self) -> int:
        return len(self.arrays["pt_id"])


@dataclass(frozen=True)
class MapHeader:
    map_id: int
    reset_counter: int
    created_wall_s: float
    created_mono_s: float
    n_keyframes: int
    n_points: int
    attachments: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SavedMap:
    path: Path
    sha256: str
    n_bytes: int
    n_keyframes: int
    n_points: int
    snapshot_ms: float  # time the map lock was held for the copy
    write_ms: float


@dataclass
class LoadedMap:
    slam_map: SlamMap
    header: MapHeader
    path: Path
    sha256: str

    def rebase_times(self, offset_s: float) -> None:
        """Add ``offset_s`` to every keyframe time (e.g. ``clock_offset_s(header)``)."""
        for kf in self.slam_map.keyframes.values():
            kf.t_s = kf.t_s + offset_s


def clock_offset_s(header: MapHeader, mono_now_s: float | None = None, wall_now_s: float | None = None) -> float:
    """Offset from the saving process's monotonic clock to this one's, assuming the wall clock ran
    on in between: a time t saved is ``t + offset`` now (monotonic clocks restart at boot)."""
    mono = time.monotonic() if mono_now_s is None else mono_now_s
    wall = time.time() if wall_now_s is None else wall_now_s
    return (mono - wall) - (header.created_mono_s - header.created_wall_s)


def camera_json(camera: CameraModel) -> dict:
    return {"width_px": int(camera.width_px), "height_px": int(camera.height_px),
            "K": np.asarray(camera.K, float).tolist(), "dist": np.asarray(camera.dist, float).ravel().tolist()}


# --- snapshot (under the lock) -------------------------------------------------------------------
def snapshot_map(m: SlamMap) -> MapSnapshot:
    """Copy the map's content under its lock. Only array copies happen while it is held (the
    mapping thread waits for them; the tracking thread never takes this lock while tracking)."""
    with m.lock:
        kfs = [m.keyframes[k] for k in sorted(m.keyframes)]
        pts = [m.points[p] for p in sorted(m.points)]
        kf_rows = [(kf.kf_id, kf.t_s, kf.seq, kf.T_cam_slam.copy(), kf.uv_px.copy(), kf.desc.copy(), kf.point_ids.copy())
                   for kf in kfs]
        pt_rows = [(p.point_id, p.p_slam.copy(), p.desc.copy(), p.first_kf, list(p.obs.items()),
                    None if p.patch is None else p.patch.copy(), p.patch_octave) for p in pts]
        next_kf, next_pt = m._next_kf, m._next_pt
    return MapSnapshot(_pack(kf_rows, pt_rows), int(next_kf), int(next_pt))


def _pack(kf_rows: list, pt_rows: list) -> dict[str, np.ndarray]:
    n_feat = [len(r[4]) for r in kf_rows]
    obs = [r[4] for r in pt_rows]
    n_obs = [len(o) for o in obs]
    return {
        "kf_id": np.array([r[0] for r in kf_rows], np.int64),
        "kf_t_s": np.array([r[1] for r in kf_rows], np.float64),
        "kf_seq": np.array([r[2] for r in kf_rows], np.int64),
        "kf_T_cam_slam": np.array([r[3] for r in kf_rows], np.float64).reshape(-1, 4, 4),
        "feat_offsets": np.concatenate([[0], np.cumsum(n_feat)]).astype(np.int64),
        "feat_uv_px": np.concatenate([np.asarray(r[4], np.float64).reshape(-1, 2) for r in kf_rows] or [np.zeros((0, 2))]),
        "feat_desc": np.concatenate([np.asarray(r[5], np.uint8).reshape(-1, DESC_BYTES) for r in kf_rows]
                                    or [np.zeros((0, DESC_BYTES), np.uint8)]),
        "feat_point_id": np.concatenate([np.asarray(r[6], np.int64) for r in kf_rows] or [np.zeros(0, np.int64)]),
        "pt_id": np.array([r[0] for r in pt_rows], np.int64),
        "pt_p_slam": np.array([r[1] for r in pt_rows], np.float64).reshape(-1, 3),
        "pt_desc": np.array([r[2] for r in pt_rows], np.uint8).reshape(-1, DESC_BYTES),
        "pt_first_kf": np.array([r[3] for r in pt_rows], np.int64),
        "obs_offsets": np.concatenate([[0], np.cumsum(n_obs)]).astype(np.int64),
        "obs_kf_id": np.array([k for o in obs for k, _ in o], np.int64),
        "obs_feat": np.array([i for o in obs for _, i in o], np.int64),
        "pt_patch": np.array([np.zeros((STORED_PX, STORED_PX), np.uint8) if r[5] is None else r[5] for r in pt_rows],
                             np.uint8).reshape(-1, STORED_PX, STORED_PX),
        "pt_patch_octave": np.array([-1 if r[5] is None else r[6] for r in pt_rows], np.int64),
    }


# --- write ---------------------------------------------------------------------------------------
def _content_hash(header_fields: dict, arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256(json.dumps(header_fields, sort_keys=True).encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def save_map_file(path: Path | str, snap: MapSnapshot, camera: CameraModel, map_id: int, reset_counter: int,
                  attachments: dict | None = None, snapshot_ms: float = 0.0) -> SavedMap:
    """Write ``snap`` to ``path`` atomically (tmp file + fsync + os.replace + folder fsync)."""
    path = Path(path)
    t0 = time.perf_counter()
    fields = {
        "format": FORMAT, "version": VERSION, "camera": camera_json(camera),
        "map_id": int(map_id), "reset_counter": int(reset_counter),
        "next_kf_id": snap.next_kf_id, "next_point_id": snap.next_point_id,
        "created_wall_s": time.time(), "created_mono_s": time.monotonic(),
        "n_keyframes": snap.n_keyframes, "n_points": snap.n_points,
        "attachments": attachments or {},
    }
    sha = _content_hash(fields, snap.arrays)
    header = np.frombuffer(json.dumps({**fields, "content_sha256": sha}).encode(), np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, header=header, **snap.arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dfd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)
    return SavedMap(path, sha, path.stat().st_size, snap.n_keyframes, snap.n_points, snapshot_ms,
                    (time.perf_counter() - t0) * 1e3)


# --- read ----------------------------------------------------------------------------------------
_ARRAYS = {  # name: (dtype kind, trailing shape)
    "kf_id": ("i", ()), "kf_t_s": ("f", ()), "kf_seq": ("i", ()), "kf_T_cam_slam": ("f", (4, 4)),
    "feat_offsets": ("i", ()), "feat_uv_px": ("f", (2,)), "feat_desc": ("u", (DESC_BYTES,)),
    "feat_point_id": ("i", ()), "pt_id": ("i", ()), "pt_p_slam": ("f", (3,)), "pt_desc": ("u", (DESC_BYTES,)),
    "pt_first_kf": ("i", ()), "obs_offsets": ("i", ()), "obs_kf_id": ("i", ()), "obs_feat": ("i", ()),
}
_OPTIONAL_ARRAYS = {"pt_patch": ("u", (STORED_PX, STORED_PX)), "pt_patch_octave": ("i", ())}  # both or neither


def _read_npz(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    try:
        data = path.read_bytes()
    except OSError as e:
        raise MapFileError(path, f"cannot read: {e.strerror or e}") from None
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            arrays = {name: z[name] for name in z.files}
    except (zipfile.BadZipFile, EOFError, ValueError, OSError, KeyError) as e:
        raise MapFileError(path, f"not a readable map archive (truncated or corrupt: {e})") from None
    if "header" not in arrays:
        raise MapFileError(path, "no header (not a TerraSLAM map file)")
    try:
        header = json.loads(arrays.pop("header").tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise MapFileError(path, f"header is not valid JSON ({e})") from None
    if not isinstance(header, dict):
        raise MapFileError(path, "header is not a JSON object")
    return header, arrays


def _check_header(path: Path, header: dict, camera: CameraModel) -> None:
    if header.get("format") != FORMAT:
        raise MapFileError(path, f"format {header.get('format')!r}, expected {FORMAT!r}")
    if header.get("version") != VERSION:
        raise MapFileError(path, f"format version {header.get('version')!r}, this build reads version {VERSION}")
    cam = header.get("camera") or {}
    mine = camera_json(camera)
    if (cam.get("width_px"), cam.get("height_px")) != (mine["width_px"], mine["height_px"]):
        raise MapFileError(path, f"built for a {cam.get('width_px')}x{cam.get('height_px')} px camera, this camera is "
                                 f"{mine['width_px']}x{mine['height_px']} px")
    K = np.asarray(cam.get("K", np.zeros((3, 3))), float)
    if K.shape != (3, 3) or not np.allclose(K, mine["K"], rtol=_K_RTOL, atol=1e-9):
        raise MapFileError(path, f"built with camera K {K.tolist()}, this camera has K {mine['K']} (recalibrated?)")


def _check_arrays(path: Path, arrays: dict[str, np.ndarray]) -> None:
    optional = [name for name in _OPTIONAL_ARRAYS if name in arrays]
    if optional and len(optional) != len(_OPTIONAL_ARRAYS):
        raise MapFileError(path, f"array {optional[0]!r} without {sorted(set(_OPTIONAL_ARRAYS) - set(optional))}")
    for name, (kind, tail) in {**_ARRAYS, **{k: _OPTIONAL_ARRAYS[k] for k in optional}}.items():
        a = arrays.get(name)
        if a is None:
            raise MapFileError(path, f"array {name!r} is missing")
        if a.dtype.kind != kind or a.shape[1:] != tail:
            raise MapFileError(path, f"array {name!r} has dtype {a.dtype} shape {a.shape}, expected kind {kind!r} (..., {tail})")
    K, P = len(arrays["kf_id"]), len(arrays["pt_id"])
    fo, oo = arrays["feat_offsets"], arrays["obs_offsets"]
    bad = (len(arrays["kf_t_s"]) != K or len(arrays["kf_seq"]) != K or len(arrays["kf_T_cam_slam"]) != K
           or len(fo) != K + 1 or fo[0] != 0 or np.any(np.diff(fo) < 0) or fo[-1] != len(arrays["feat_uv_px"])
           or len(arrays["feat_desc"]) != fo[-1] or len(arrays["feat_point_id"]) != fo[-1]
           or len(arrays["pt_p_slam"]) != P or len(arrays["pt_desc"]) != P or len(arrays["pt_first_kf"]) != P
           or len(oo) != P + 1 or oo[0] != 0 or np.any(np.diff(oo) < 0) or oo[-1] != len(arrays["obs_kf_id"])
           or len(arrays["obs_feat"]) != oo[-1]
           or any(len(arrays[name]) != P for name in optional))
    if bad:
        raise MapFileError(path, "array sizes are inconsistent")
    if not (np.isfinite(arrays["kf_T_cam_slam"]).all() and np.isfinite(arrays["pt_p_slam"]).all()):
        raise MapFileError(path, "non-finite poses or point positions")
    if optional and not np.all((arrays["pt_patch_octave"] >= -1) & (arrays["pt_patch_octave"] < N_LEVELS)):
        raise MapFileError(path, f"a point's patch level is outside -1..{N_LEVELS - 1}")


def read_map_header(path: Path | str) -> MapHeader:
    """The verified header of a map file (format, version, content hash) without unpacking the map
    or checking the camera: what a caller needs before it has a camera (e.g. the saved alignment's
    GIS site). Raises MapFileError as ``load_map_file``."""
    path = Path(path)
    header, arrays = _read_npz(path)
    if header.get("format") != FORMAT or header.get("version") != VERSION:
        raise MapFileError(path, f"format {header.get('format')!r} version {header.get('version')!r}, "
                                 f"this build reads {FORMAT!r} version {VERSION}")
    sha = header.pop("content_sha256", None)
    if sha != _content_hash(header, arrays):
        raise MapFileError(path, "content does not match its SHA-256 (corrupted)")
    try:
        return _map_header(header)
    except (KeyError, TypeError, ValueError) as e:
        raise MapFileError(path, f"inconsistent header ({type(e).__name__}: {e})") from None


def _map_header(header: dict) -> MapHeader:
    return MapHeader(int(header["map_id"]), int(header["reset_counter"]), float(header["created_wall_s"]),
                     float(header["created_mono_s"]), int(header["n_keyframes"]), int(header["n_points"]),
                     dict(header.get("attachments") or {}))


def load_map_file(path: Path | str, camera: CameraModel) -> LoadedMap:
    """Read and verify a map file written by ``save_map_file`` for ``camera``.

    Raises MapFileError (naming the file and the problem) for a missing/unreadable file, a
    truncated or corrupt archive, another format or version, another camera (size or K), a
    content hash mismatch or inconsistent arrays."""
    path = Path(path)
    header, arrays = _read_npz(path)
    _check_header(path, header, camera)
    sha = header.pop("content_sha256", None)
    if sha != _content_hash(header, arrays):
        raise MapFileError(path, "content does not match its SHA-256 (corrupted)")
    _check_arrays(path, arrays)
    try:
        slam_map = _unpack(arrays, int(header["next_kf_id"]), int(header["next_point_id"]))
        hdr = _map_header(header)
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise MapFileError(path, f"inconsistent content ({type(e).__name__}: {e})") from None
    if (hdr.n_keyframes, hdr.n_points) != (len(slam_map.keyframes), len(slam_map.points)):
        raise MapFileError(path, "header counts do not match the arrays")
    return LoadedMap(slam_map, hdr, path, sha)


def _unpack(a: dict[str, np.ndarray], next_kf_id: int, next_point_id: int) -> SlamMap:
    m = SlamMap()
    fo, oo = a["feat_offsets"], a["obs_offsets"]
    octave = a.get("pt_patch_octave", np.full(len(a["pt_id"]), -1))
    for j, kf_id in enumerate(a["kf_id"].tolist()):
        s, e = int(fo[j]), int(fo[j + 1])
        m.keyframes[kf_id] = Keyframe(kf_id, float(a["kf_t_s"][j]), int(a["kf_seq"][j]), a["kf_T_cam_slam"][j].copy(),
                                      a["feat_uv_px"][s:e].copy(), a["feat_desc"][s:e].copy(),
                                      a["feat_point_id"][s:e].copy())
    for j, pid in enumerate(a["pt_id"].tolist()):
        s, e = int(oo[j]), int(oo[j + 1])
        obs = dict(zip(a["obs_kf_id"][s:e].tolist(), a["obs_feat"][s:e].tolist()))
        for kf_id, i in obs.items():
            if kf_id not in m.keyframes or not 0 <= i < len(m.keyframes[kf_id].point_ids):
                raise ValueError(f"point {pid} observed by keyframe {kf_id} feature {i}, which does not exist")
        m.points[pid] = MapPoint(pid, a["pt_p_slam"][j].copy(), a["pt_desc"][j].copy(), obs, int(a["pt_first_kf"][j]))
        if octave[j] >= 0:
            m.points[pid].set_patch(a["pt_patch"][j], octave[j])
    for kf in m.keyframes.values():  # a feature whose point is gone carries no point
        if len(kf.point_ids):
            kf.point_ids[np.array([p >= 0 and p not in m.points for p in kf.point_ids.tolist()])] = -1
    if m.keyframes and max(m.keyframes) >= next_kf_id or m.points and max(m.points) >= next_point_id:
        raise ValueError("id counters below the stored ids")
    m._next_kf, m._next_pt = next_kf_id, next_point_id
    return m
