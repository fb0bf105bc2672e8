"""The registered instrument model: what `surgtrack register` writes and `surgtrack track --model` reads.

A model is one file, by convention ``NAME.stm``: a zip archive (deflate-compressed members) holding ``meta.json``
and arrays in NumPy's ``.npy`` format (read without pickle). Format version 2:

    meta.json                          {"format": "surgtrack-model", "version": 2, "created_by": "surgtrack X.Y.Z",
                                        "created": ISO 8601 time, "info": {...} (source sequence, frames, ...),
                                        "config": TrackerConfig.to_dict() of the scan, "K": 3x3 intrinsics,
                                        "units": "metres", "depth_unit_m": 0.001,
                                        "sdf": null | {"origin", "rotation", "voxel", "shape", "fitted",
                                                       "converged", "config"},
                                        "mesh": {"vertices": V, "faces": F},
                                        "keyframes": [{"id", "pose" (4x4 object-to-camera), "K", "K_grid",
                                                       "image_size" [H, W], "grid_size" [h, w], "features" N,
                                                       "image" true when image.npy is there}, ...]}
    sdf/psi.npy                        float16 (nx, ny, nz): Psi / truncation on the grid nodes, node (i, j, k) at
                                       R^T (origin + voxel (i, j, k)) in the object frame, R the 3x3 "rotation"
                                       (the box's axes as rows; version 1 files have none: identity) (truncation in the
                                       sdf config); relative rounding below 2^-11, 5 um at twice the truncation
    sdf/weight.npy                     float32 (nx, ny, nz): TSDF fusion weights (sdf/ is absent when sdf is null)
    mesh/vertices.npy                  float32 (V, 3), object frame, metres (marching cubes of Psi, kept to the
                                       surface the scan saw, as OUT/mesh.ply)
    mesh/faces.npy                     int32 (F, 3)
    keyframes/NNN/features_uv.npy      float32 (N, 2) pixel coordinates
    keyframes/NNN/features_desc.npy    (N, D) descriptors, float32 (SIFT, XFeat) or uint8 (ORB)
    keyframes/NNN/features_xyz.npy     float32 (N, 3) camera frame of the keyframe
    keyframes/NNN/features_normals.npy float32 (N, 3)
    keyframes/NNN/grid_xyz.npy         float32 (h, w, 3) downscaled point grid (z = 0 off the instrument)
    keyframes/NNN/grid_normals.npy     float32 (h, w, 3)
    keyframes/NNN/depth.npy            uint16 (H, W) full depth in units of depth_unit_m, 0 = invalid
    keyframes/NNN/mask.npy             uint8 (ceil(H * W / 8),) instrument mask, np.packbits of the row-major bits
    keyframes/NNN/image.npy            uint8 (H, W) intensity, for re-localisation's appearance check (optional:
                                       files written before it have none, and that check then skips the keyframe)

Poses and intrinsics live in meta.json (JSON floats round-trip exactly). The object frame is the scan's (the first
frame of the registration video). Keyframe ids are the scan's frame ids prefixed with ``model:`` so that they never
collide with the frame ids of a video tracked against the model. A reader refuses a file of a newer format version.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
import zipfile
import zlib
from dataclasses import asdict, dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from .config import SDFConfig
from .features import Features
from .geometry import is_rotation
from .io import SequenceError
from .memory_pool import Keyframe
from .registration import InstrumentSDF

FORMAT = "surgtrack-model"
VERSION = 2
DEPTH_UNIT_M = 0.001
ID_PREFIX = "model:"


@dataclass
class InstrumentModel:
    """Keyframes with features and poses, the Instrument SDF, and the settings they were made with."""

    keyframes: list[Keyframe]
    sdf: InstrumentSDF | None
    K: np.ndarray
    config: dict = field(default_factory=dict)
    mesh: trimesh.Trimesh | None = None  # marching cubes of the SDF, object frame, metres
    info: dict = field(default_factory=dict)  # provenance (source sequence, frames, ...); read_meta has the writer

    @classmethod
    def from_tracker(cls, tracker: Any, info: dict | None = None) -> InstrumentModel:
        """The model a tracker has built: its memory pool, its SDF and that SDF's mesh of what the scan saw.

        Call it after ``tracker.mesh()`` (``track_sequence`` does): the SDF is then the tracker's final fit on every
        keyframe; before, it is the newest completed background fit. Keyframe ids get the ``model:`` prefix (once).
        """
        keyframes = [kf if kf.frame_id.startswith(ID_PREFIX) else replace(kf, frame_id=ID_PREFIX + kf.frame_id)
                     for kf in tracker.pool.keyframes]
        if not keyframes:
            raise ValueError("the tracker has no keyframes: register a first frame and track before saving a model")
        sdf = tracker.fitted_field()
        mesh = tracker.surface(sdf) if sdf is not None else None
        return cls(keyframes, sdf, np.array(keyframes[0].K, dtype=np.float64), tracker.cfg.to_dict(), mesh,
                   dict(info or {}))

    @property
    def features(self) -> str | None:
        """The keypoint detector the keyframes' descriptors come from (sift, orb, xfeat), when recorded."""
        return self.config.get("ransac", {}).get("features")

    def check_compatible(self, config: Any) -> None:
        """Raise ValueError when a tracker with this config cannot match the model's keyframe descriptors."""
        wanted = config.ransac.features
        if self.features is not None and wanted != self.features:
            raise ValueError(f"the model's keyframes have {self.features} features, the tracker is set to {wanted}")


# ------------------------------------------------------------------------------------------------------- writing


def save_model(model: InstrumentModel, path: str | Path) -> Path:
    """Write the model to one file (format above), atomically: a temporary file beside it, then os.replace."""
    from . import __version__

    path = Path(path)
    arrays: dict[str, np.ndarray] = {}
    sdf_meta = None
    if model.sdf is not None:
        state = model.sdf.state_dict()
        arrays["sdf/psi.npy"] = np.clip(state["psi"] / model.sdf.cfg.truncation, -6e4, 6e4).astype(np.float16)
        arrays["sdf/weight.npy"] = np.asarray(state["weight"], np.float32)
        sdf_meta = {"origin": [float(x) for x in state["origin"]], "rotation": _list(state["rotation"]),
                    "voxel": float(state["voxel"]),
                    "shape": list(arrays["sdf/psi.npy"].shape), "fitted": bool(model.sdf.fitted),
                    "converged": bool(model.sdf.converged), "config": asdict(model.sdf.cfg)}
    mesh = model.mesh if model.mesh is not None else (model.sdf.mesh() if model.sdf is not None else None)
    arrays["mesh/vertices.npy"] = np.asarray(mesh.vertices if mesh is not None else np.zeros((0, 3)), np.float32)
    arrays["mesh/faces.npy"] = np.asarray(mesh.faces if mesh is not None else np.zeros((0, 3)), np.int32)
    kf_meta = []
    for i, kf in enumerate(model.keyframes):
        pre = f"keyframes/{i:03d}/"
        f = kf.features
        arrays[pre + "features_uv.npy"] = np.asarray(f.uv, np.float32)
        arrays[pre + "features_desc.npy"] = np.asarray(f.desc)
        arrays[pre + "features_xyz.npy"] = np.asarray(f.xyz, np.float32)
        arrays[pre + "features_normals.npy"] = np.asarray(f.normals, np.float32)
        arrays[pre + "grid_xyz.npy"] = np.asarray(kf.xyz, np.float32)
        arrays[pre + "grid_normals.npy"] = np.asarray(kf.normals, np.float32)
        units = np.round(np.nan_to_num(np.asarray(kf.depth, np.float64)) / DEPTH_UNIT_M)
        arrays[pre + "depth.npy"] = np.where((units > 0) & (units <= 65535), units, 0).astype(np.uint16)
        arrays[pre + "mask.npy"] = np.packbits(np.asarray(kf.mask, bool).reshape(-1))
        if kf.image is not None:
            arrays[pre + "image.npy"] = np.asarray(kf.image, np.uint8)
        kf_meta.append({"id": kf.frame_id, "pose": _list(kf.pose), "K": _list(kf.K), "K_grid": _list(kf.K_grid),
                        "image_size": list(kf.depth.shape[:2]), "grid_size": list(kf.xyz.shape[:2]),
                        "features": len(f), "image": kf.image is not None})
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "created_by": f"surgtrack {__version__}",
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "info": model.info,
        "config": model.config,
        "K": _list(model.K),
        "units": "metres",
        "depth_unit_m": DEPTH_UNIT_M,
        "sdf": sdf_meta,
        "mesh": {"vertices": len(arrays["mesh/vertices.npy"]), "faces": len(arrays["mesh/faces.npy"])},
        "keyframes": kf_meta,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            with zipfile.ZipFile(fh, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6) as zf:
                zf.writestr("meta.json", json.dumps(meta, indent=1))
                for name, arr in arrays.items():
                    buf = io.BytesIO()
                    np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
                    zf.writestr(name, buf.getvalue())
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _list(a: np.ndarray) -> list:
    return np.asarray(a, dtype=np.float64).tolist()


# ------------------------------------------------------------------------------------------------------- reading


class _Reader:
    """Array and meta access to an open model archive; every problem becomes a one-line SequenceError."""

    def __init__(self, path: Path, zf: zipfile.ZipFile):
        self.path, self.zf = path, zf
        self.names = set(zf.namelist())

    def fail(self, problem: str) -> SequenceError:
        return SequenceError(self.path, problem)

    def array(self, name: str, shape: tuple[int | None, ...], dtypes: tuple[str, ...] | None = None) -> np.ndarray:
        """Read ``name`` and check its shape (None: any length) and dtype kind."""
        if name not in self.names:
            raise self.fail(f"corrupt surgtrack model: {name} is missing")
        try:
            with self.zf.open(name) as fh:
                arr = np.lib.format.read_array(io.BytesIO(fh.read()), allow_pickle=False)
        except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError) as e:
            raise self.fail(f"corrupt surgtrack model: cannot read {name} ({_short(e)})") from None
        if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape, strict=True)):
            want = "x".join("N" if s is None else str(s) for s in shape)
            got = "x".join(str(n) for n in arr.shape)
            raise self.fail(f"corrupt surgtrack model: {name} has shape {got or 'scalar'}, expected {want}")
        if dtypes is not None and arr.dtype.name not in dtypes:
            raise self.fail(f"corrupt surgtrack model: {name} has dtype {arr.dtype}, expected {' or '.join(dtypes)}")
        return arr


def _short(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


def _matrix(reader: _Reader, value: Any, shape: tuple[int, int], what: str) -> np.ndarray:
    try:
        m = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape != shape or not np.all(np.isfinite(m)):
        raise reader.fail(f"corrupt surgtrack model: {what} is not a finite {shape[0]}x{shape[1]} matrix")
    return m


def read_meta(path: str | Path) -> dict:
    """The model file's meta.json, after the format and version checks (cheap: no arrays are read)."""
    path = Path(path)
    with _open(path) as zf:
        return _meta(_Reader(path, zf))


def _open(path: Path) -> zipfile.ZipFile:
    if not path.exists():
        raise SequenceError(path, "no such model file")
    if path.is_dir():
        raise SequenceError(path, "is a folder, not a surgtrack model file")
    try:
        return zipfile.ZipFile(path)
    except zipfile.BadZipFile:
        raise SequenceError(path, "not a surgtrack model (not a zip archive, or a truncated file)") from None
    except OSError as e:
        raise SequenceError(path, f"cannot read the model ({_short(e)})") from None


def _meta(reader: _Reader) -> dict:
    if "meta.json" not in reader.names:
        raise reader.fail("not a surgtrack model (no meta.json in the archive)")
    try:
        meta = json.loads(reader.zf.read("meta.json"))
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise reader.fail(f"corrupt surgtrack model: meta.json is unreadable ({_short(e)})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise reader.fail(f"not a surgtrack model (meta.json format is not {FORMAT!r})")
    version = meta.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise reader.fail(f"corrupt surgtrack model: bad format version {version!r}")
    if version > VERSION:
        raise reader.fail(f"written by a newer surgtrack: format version {version} > {VERSION}; upgrade surgtrack")
    for key, kind in (("keyframes", list), ("config", dict), ("K", list)):
        if not isinstance(meta.get(key), kind):
            raise reader.fail(f"corrupt surgtrack model: meta.json has no valid {key!r}")
    return meta


def load_model(path: str | Path, device: str | None = None) -> InstrumentModel:
    """Read a model file; raises SequenceError (path: problem, one line) for anything that is not a valid model."""
    path = Path(path)
    with _open(path) as zf:
        r = _Reader(path, zf)
        meta = _meta(r)
        try:
            return _build(r, meta, device)
        except SequenceError:
            raise
        except (KeyError, TypeError, ValueError) as e:
            raise r.fail(f"corrupt surgtrack model: bad meta.json entry ({_short(e)})") from None


def _build(r: _Reader, meta: dict, device: str | None) -> InstrumentModel:
    unit = float(meta.get("depth_unit_m", DEPTH_UNIT_M))
    keyframes = []
    for i, km in enumerate(meta["keyframes"]):
        pre = f"keyframes/{i:03d}/"
        h_img, w_img = (int(x) for x in km["image_size"])
        h, w = (int(x) for x in km["grid_size"])
        n = int(km["features"])
        desc = r.array(pre + "features_desc.npy", (n, None), ("float32", "uint8"))
        feats = Features(
            r.array(pre + "features_uv.npy", (n, 2), ("float32",)),
            desc,
            r.array(pre + "features_xyz.npy", (n, 3), ("float32",)),
            r.array(pre + "features_normals.npy", (n, 3), ("float32",)),
        )
        depth = r.array(pre + "depth.npy", (h_img, w_img), ("uint16",))
        bits = r.array(pre + "mask.npy", (-(-h_img * w_img // 8),), ("uint8",))
        mask = np.unpackbits(bits, count=h_img * w_img).reshape(h_img, w_img).astype(bool)
        keyframes.append(Keyframe(
            frame_id=str(km["id"]),
            pose=_matrix(r, km["pose"], (4, 4), f"keyframe {i} pose"),
            features=feats,
            xyz=r.array(pre + "grid_xyz.npy", (h, w, 3), ("float32",)),
            normals=r.array(pre + "grid_normals.npy", (h, w, 3), ("float32",)),
            K_grid=_matrix(r, km["K_grid"], (3, 3), f"keyframe {i} K_grid"),
            depth=(depth * unit).astype(np.float32),
            mask=mask,
            K=_matrix(r, km["K"], (3, 3), f"keyframe {i} K"),
            image=r.array(pre + "image.npy", (h_img, w_img), ("uint8",)) if km.get("image") else None,
        ))
    descs = {kf.features.desc.shape[1:] + (kf.features.desc.dtype.name,) for kf in keyframes if len(kf.features)}
    if len(descs) > 1:
        raise r.fail("corrupt surgtrack model: the keyframes' descriptors differ in size or type")
    sdf = None
    sm = meta.get("sdf")
    if sm is not None:
        shape = tuple(int(x) for x in sm["shape"])
        if len(shape) != 3 or min(shape) < 2:
            raise r.fail(f"corrupt surgtrack model: bad SDF grid shape {list(shape)}")
        cfg = SDFConfig(**sm["config"])
        state = {
            "psi": r.array("sdf/psi.npy", shape, ("float16",)).astype(np.float32) * np.float32(cfg.truncation),
            "weight": r.array("sdf/weight.npy", shape, ("float32",)),
            "origin": _vector(r, sm["origin"]),
            "rotation": (_matrix(r, sm.get("rotation"), (3, 3), "SDF rotation") if meta["version"] >= 2
                         else np.eye(3)),  # version 1: an axis-aligned box
            "voxel": np.float64(sm["voxel"]),
            "flags": np.array([bool(sm["fitted"]), bool(sm["converged"])]),
            "cfg": np.array(json.dumps(asdict(cfg))),
        }
        if not state["voxel"] > 0:
            raise r.fail(f"corrupt surgtrack model: SDF voxel size {sm['voxel']} is not positive")
        if not is_rotation(state["rotation"]):
            raise r.fail("corrupt surgtrack model: SDF rotation is not a rotation matrix")
        sdf = InstrumentSDF.from_state_dict(state, device=device)
    mm = meta.get("mesh") or {"vertices": 0, "faces": 0}
    verts = r.array("mesh/vertices.npy", (int(mm["vertices"]), 3), ("float32",))
    faces = r.array("mesh/faces.npy", (int(mm["faces"]), 3), ("int32",))
    if len(faces) and (faces.min() < 0 or faces.max() >= len(verts)):
        raise r.fail("corrupt surgtrack model: mesh faces index missing vertices")
    mesh = trimesh.Trimesh(verts.astype(np.float64), faces, process=False) if len(faces) else None
    info = meta.get("info") or {}
    if not isinstance(info, dict):
        raise r.fail("corrupt surgtrack model: meta.json 'info' is not an object")
    K = _matrix(r, meta["K"], (3, 3), "K")
    return InstrumentModel(keyframes, sdf, K, meta["config"], mesh, dict(info))


def _vector(reader: _Reader, value: Any) -> np.ndarray:
    v = np.array(value, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise reader.fail("corrupt surgtrack model: SDF origin is not a finite 3-vector")
    return v
