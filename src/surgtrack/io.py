"""Sequence input and result output (DESIGN.md section 2).

Readers are lazy: a frame is read from disk when it is indexed, so a long video is never held in memory.
Three layouts are read: the BundleSDF / YCBInEOAT folder (``rgb/ depth/ masks/ cam_K.txt gt/``), a BOP scene
(``scene_camera.json scene_gt.json rgb/ depth/ mask_visib/``) and an APC vision-toolbox scene (real RealSense
frames, ``frame-NNNNNN.color.png``). Every problem with the input raises :class:`SequenceError` with one line that
names the file and what is wrong.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np
import trimesh

DEPTH_SCALE_MM = 0.001  # metres per depth unit of the DESIGN layout
INVERTED_MASK_SHARE = 0.5  # a first mask over more of the image than this, three corners or more, is inverted
T = TypeVar("T")


class SequenceError(ValueError):
    """Bad input; the message is one line naming the file and the problem."""

    def __init__(self, path: Path | str, problem: str):
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)
        self.problem = problem

    def __reduce__(self) -> tuple:
        return (SequenceError, (self.path, self.problem))  # picklable across processes (bench runs methods apart)


@dataclass
class Frame:
    """One RGB-D frame: rgb (H, W, 3) uint8, depth (H, W) float32 metres with 0 = invalid, optional mask."""

    index: int
    id: str
    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    mask: np.ndarray | None = None


# ------------------------------------------------------------------------------------------------ reading


def read_image(path: Path, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    """Read an image file or raise SequenceError naming it."""
    if not path.is_file():
        raise SequenceError(path, "missing file")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise SequenceError(path, "unreadable image (corrupt or not an image)")
    return img


def read_rgb(path: Path) -> np.ndarray:
    img = read_image(path, cv2.IMREAD_COLOR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: Path, depth_scale: float) -> np.ndarray:
    """Read a uint16 depth PNG and convert it to float32 metres; reject other types and NaN."""
    d = read_image(path)
    if d.ndim != 2:
        raise SequenceError(path, f"depth must be a single-channel image, got {d.shape[2]} channels")
    if d.dtype != np.uint16:
        raise SequenceError(path, f"depth must be uint16 (got {d.dtype}); expected depth units x {depth_scale} m")
    return d.astype(np.float32) * np.float32(depth_scale)


def read_mask(path: Path) -> np.ndarray:
    m = read_image(path, cv2.IMREAD_UNCHANGED)
    if m.ndim == 3:
        m = m[..., 0]
    return m > 0


def check_first_mask(path: Path, mask: np.ndarray) -> None:
    """A first-frame mask must mark the instrument: not nothing, and not the view around it (a mask saved
    inverted, or all 255), which would make the whole scene the instrument."""
    if not mask.any():
        raise SequenceError(path, "first-frame mask is empty")
    share = float(mask.mean())
    if share > INVERTED_MASK_SHARE and mask[[0, 0, -1, -1], [0, -1, 0, -1]].sum() >= 3:
        raise SequenceError(path, f"first-frame mask covers {share:.0%} of the image and its corners: inverted? "
                                  "(instrument pixels must be > 0, the rest 0)")


def make_folder(path: Path) -> Path:
    """``path`` as a folder, made with its parents when missing; a file there or above it raises SequenceError."""
    if path.exists() and not path.is_dir():
        raise SequenceError(path, "is a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise SequenceError(path, f"cannot make the folder ({e.strerror})") from None
    return path


def read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """Read a whitespace-separated matrix of the given shape (e.g. cam_K.txt, a 4x4 pose)."""
    if not path.is_file():
        raise SequenceError(path, "missing file")
    try:
        M = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise SequenceError(path, f"not a numeric matrix ({e})") from None
    if M.shape != shape:
        raise SequenceError(path, f"expected a {shape[0]}x{shape[1]} matrix, got {M.shape[0]}x{M.shape[1]}")
    if not np.all(np.isfinite(M)):
        raise SequenceError(path, "contains NaN or infinite values")
    return M


def check_intrinsics(path: Path, K: np.ndarray, where: str = "") -> np.ndarray:
    """``K`` when it is a pinhole camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 (a
    transposed one puts cx, cy in its last row); ``where`` names the entry in a file of several."""
    if not (K[0, 0] > 0 and K[1, 1] > 0 and abs(K[1, 0]) <= 1e-6 * K[1, 1] and np.allclose(K[2], [0.0, 0.0, 1.0])):
        raise SequenceError(path, f"{where}not a camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 "
                                  f"(fx {K[0, 0]:g}, fy {K[1, 1]:g}, last row {' '.join(f'{v:g}' for v in K[2])})")
    return K


def check_depth_units(path: Path, depth: np.ndarray, depth_scale: float) -> None:
    """Catch depth in the wrong units: a median under 10 raw units means metres were written as integers."""
    valid = depth[depth > 0]
    if valid.size and np.median(valid) / depth_scale < 10:
        raise SequenceError(
            path,
            f"median depth is {np.median(valid) / depth_scale:.2f} units of {depth_scale} m: depth looks saved in "
            f"metres; save it as uint16 millimetres (or finer units, with --depth-scale)",
        )


class Sequence:
    """A lazily read RGB-D sequence. Subclasses set ``root``, ``K``, ``ids`` and implement ``_read``."""

    root: Path
    K: np.ndarray
    ids: list[str]

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i: int) -> Frame:
        if not 0 <= i < len(self.ids):
            raise IndexError(i)
        return self._read(i)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def read_ahead(self, start: int = 0, ahead: int = 2,
                   prepare: Callable[[Frame], T] | None = None) -> Iterator[tuple[Frame, T | None]]:
        """The frames from ``start`` on, in order, each read and decoded in a background thread while the caller
        works on the ones before (up to ``ahead`` frames early), with what ``prepare`` made of it in that thread
        (None without ``prepare``). Image decoding releases the GIL, so a tracker on the main thread does not wait
        for files. An unreadable frame raises its SequenceError when its turn comes."""

        def read(i: int) -> tuple[Frame, T | None]:
            frame = self[i]
            return frame, None if prepare is None else prepare(frame)

        with ThreadPoolExecutor(1, thread_name_prefix="frame-reader") as reader:
            pending = deque(reader.submit(read, i) for i in range(start, min(start + ahead, len(self))))
            following = start + len(pending)
            try:
                while pending:
                    item = pending.popleft().result()
                    if following < len(self):
                        pending.append(reader.submit(read, following))
                        following += 1
                    yield item
            finally:
                for future in pending:  # the caller stopped early: read no further
                    future.cancel()

    def _read(self, i: int) -> Frame:
        raise NotImplementedError

    def gt_poses(self) -> dict[str, np.ndarray]:
        """Ground-truth object-to-camera poses by frame id (empty when the sequence has none)."""
        return {}

    def gt_model(self) -> trimesh.Trimesh | None:
        """Ground-truth mesh in the object frame, metres, or None."""
        return None

    def gt_visible_points(self) -> np.ndarray | None:
        """Ground-truth surface the video shows (object frame, metres), or None."""
        return None

    def _check_frame(self, frame: Frame, paths: dict[str, Path]) -> Frame:
        h, w = frame.depth.shape
        if frame.rgb.shape[:2] != (h, w):
            raise SequenceError(paths["rgb"], f"size {frame.rgb.shape[1]}x{frame.rgb.shape[0]} != depth size {w}x{h}")
        if frame.mask is not None and frame.mask.shape != (h, w):
            mh, mw = frame.mask.shape
            raise SequenceError(paths["mask"], f"size {mw}x{mh} != depth size {w}x{h}")
        return frame

    def _check_first(self, f0: Frame | None = None) -> None:
        """Up-front validation: the first frame reads, has sane units and a mask that marks the instrument."""
        f0 = self[0] if f0 is None else f0
        if f0.mask is None:
            raise SequenceError(self.mask_path(0), "missing first-frame mask (the first frame needs one)")
        check_first_mask(self.mask_path(0), f0.mask)

    def mask_path(self, i: int) -> Path:
        raise NotImplementedError


def _numbered(folder: Path, pattern: str) -> dict[int, Path]:
    rx = re.compile(pattern)
    out: dict[int, Path] = {}
    for p in folder.iterdir() if folder.is_dir() else []:
        m = rx.fullmatch(p.name)
        if m:
            out[int(m.group(1))] = p
    return out


def _check_consecutive(folder: Path, numbers: list[int]) -> None:
    for a, b in zip(numbers, numbers[1:], strict=False):
        if b != a + 1:
            raise SequenceError(folder, f"frame numbering gap: {a:06d} is followed by {b:06d}")


class FolderSequence(Sequence):
    """The DESIGN.md layout: rgb/, depth/, masks/ (first frame required), cam_K.txt, optional gt/."""

    def __init__(self, root: Path | str, depth_scale: float = DEPTH_SCALE_MM):
        self.root = Path(root)
        if not self.root.is_dir():
            raise SequenceError(self.root, "sequence folder does not exist")
        self.depth_scale = depth_scale
        self.K = check_intrinsics(self.root / "cam_K.txt", read_matrix(self.root / "cam_K.txt", (3, 3)))
        rgb = _numbered(self.root / "rgb", r"(\d+)\.(?:png|jpg)")
        if not rgb:
            raise SequenceError(self.root / "rgb", "no frames (expected rgb/000000.png ...)")
        numbers = sorted(rgb)
        _check_consecutive(self.root / "rgb", numbers)
        width = len(rgb[numbers[0]].stem)
        self.ids = [f"{n:0{width}d}" for n in numbers]
        self._rgb = [rgb[n] for n in numbers]
        depth = _numbered(self.root / "depth", r"(\d+)\.png")
        for n in numbers:
            if n not in depth:
                raise SequenceError(self.root / "depth" / f"{n:0{width}d}.png", "missing depth frame")
        self._depth = [depth[n] for n in numbers]
        self._masks = _numbered(self.root / "masks", r"(\d+)\.png")
        self._numbers = numbers
        f0 = self[0]
        check_depth_units(self._depth[0], f0.depth, depth_scale)
        self._check_first(f0)

    def mask_path(self, i: int) -> Path:
        return self._masks.get(self._numbers[i], self.root / "masks" / f"{self.ids[i]}.png")

    def _read(self, i: int) -> Frame:
        paths = {"rgb": self._rgb[i], "depth": self._depth[i], "mask": self.mask_path(i)}
        mask = read_mask(paths["mask"]) if self._numbers[i] in self._masks else None
        depth = read_depth(paths["depth"], self.depth_scale)
        frame = Frame(i, self.ids[i], read_rgb(paths["rgb"]), depth, self.K, mask)
        return self._check_frame(frame, paths)

    def gt_poses(self) -> dict[str, np.ndarray]:
        folder = self.root / "gt" / "ob_in_cam"
        return {p.stem: read_matrix(p, (4, 4)) for p in sorted(folder.glob("*.txt"))} if folder.is_dir() else {}

    def gt_model(self) -> trimesh.Trimesh | None:
        p = self.root / "gt" / "model.ply"
        return load_mesh(p) if p.is_file() else None

    def gt_visible_points(self) -> np.ndarray | None:
        p = self.root / "gt" / "visible_points.ply"
        return load_points(p) if p.is_file() else None


class BopScene(Sequence):
    """A BOP scene folder; poses from scene_gt.json (mm), depth scaled by each frame's ``depth_scale``."""

    def __init__(self, root: Path | str, obj_id: int | None = None):
        self.root = Path(root)
        cams = _load_json(self.root / "scene_camera.json")
        gts = _load_json(self.root / "scene_gt.json") if (self.root / "scene_gt.json").is_file() else {}
        numbers = sorted(int(k) for k in cams)
        if not numbers:
            raise SequenceError(self.root / "scene_camera.json", "no frames listed")
        self.ids = [f"{n:06d}" for n in numbers]
        self._cams = [cams[str(n)] for n in numbers]
        for n, cam in zip(numbers, self._cams, strict=True):
            if np.asarray(cam.get("cam_K", []), dtype=np.float64).size != 9:
                raise SequenceError(self.root / "scene_camera.json", f"frame {n}: cam_K missing or not 3x3")
            check_intrinsics(self.root / "scene_camera.json", np.asarray(cam["cam_K"], np.float64).reshape(3, 3),
                             f"frame {n}: cam_K ")
        self.K = np.asarray(self._cams[0]["cam_K"], dtype=np.float64).reshape(3, 3)
        self._gts = [gts.get(str(n), []) for n in numbers]
        if obj_id is None and self._gts[0]:
            obj_id = int(self._gts[0][0]["obj_id"])
        self.obj_id = obj_id
        self._numbers = numbers
        self._check_first()

    def _slot(self, i: int) -> int | None:
        for k, g in enumerate(self._gts[i]):
            if int(g["obj_id"]) == self.obj_id:
                return k
        return None

    def mask_path(self, i: int) -> Path:
        k = self._slot(i)
        return self.root / "mask_visib" / f"{self._numbers[i]:06d}_{(k or 0):06d}.png"

    def _read(self, i: int) -> Frame:
        n = self._numbers[i]
        rgb_path = self.root / "rgb" / f"{n:06d}.png"
        if not rgb_path.exists():
            rgb_path = rgb_path.with_suffix(".jpg")
        scale = float(self._cams[i].get("depth_scale", 1.0)) * 1e-3
        paths = {"rgb": rgb_path, "depth": self.root / "depth" / f"{n:06d}.png", "mask": self.mask_path(i)}
        mask = read_mask(paths["mask"]) if self._slot(i) is not None and paths["mask"].exists() else None
        K = np.asarray(self._cams[i]["cam_K"], dtype=np.float64).reshape(3, 3)
        frame = Frame(i, self.ids[i], read_rgb(rgb_path), read_depth(paths["depth"], scale), K, mask)
        return self._check_frame(frame, paths)

    def gt_poses(self) -> dict[str, np.ndarray]:
        out = {}
        for i in range(len(self)):
            k = self._slot(i)
            if k is not None:
                g = self._gts[i][k]
                R = np.asarray(g["cam_R_m2c"], dtype=np.float64).reshape(3, 3)
                t = np.asarray(g["cam_t_m2c"], dtype=np.float64) * 1e-3
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = R, t
                out[self.ids[i]] = T
        return out

    def gt_model(self) -> trimesh.Trimesh | None:
        p = self.root.parent.parent / "models" / f"obj_{self.obj_id:06d}.ply"
        if not p.is_file():
            return None
        mesh = load_mesh(p)
        mesh.apply_scale(1e-3)  # BOP models are in millimetres
        return mesh


class ApcScene(Sequence):
    """An APC vision-toolbox scene: real RealSense frames of static objects seen from known camera poses.

    The object frame is the world frame, so the ground-truth object-to-camera pose of frame t is
    inv(T_world_cam(t)); the seen surface is the union of every frame's masked depth in that frame.
    """

    def __init__(self, root: Path | str, obj: str = "creativity_chenille_stems"):
        self.root = Path(root)
        info = self.root / "cam.info.txt"
        if not info.is_file():
            raise SequenceError(info, "missing file")
        blocks = _apc_blocks(info.read_text())
        self.K = blocks["Color camera intrinsic matrix"]
        frames = _numbered(self.root, r"frame-(\d+)\.color\.png")
        numbers = sorted(frames)
        _check_consecutive(self.root, numbers)
        self._numbers = numbers
        self.ids = [f"{n:06d}" for n in numbers]
        key = "Camera-to-world extrinsic matrix (camera pose) for frame-{:06d}"
        self._poses = {f"{n:06d}": blocks[key.format(n)] for n in numbers}
        self.obj = obj
        thresh = self.root / "masks" / f"{obj}.thresh.txt"
        self._thresh = float(thresh.read_text().split()[0]) if thresh.is_file() else 0.5
        self._check_first()

    def mask_path(self, i: int) -> Path:
        return self.root / "masks" / f"frame-{self._numbers[i]:06d}.{self.obj}.mask.png"

    def _read(self, i: int) -> Frame:
        n = self._numbers[i]
        paths = {
            "rgb": self.root / f"frame-{n:06d}.color.png",
            "depth": self.root / f"frame-{n:06d}.depth.png",
            "mask": self.mask_path(i),
        }
        raw = read_image(paths["depth"])
        if raw.dtype != np.uint16:
            raise SequenceError(paths["depth"], f"depth must be uint16, got {raw.dtype}")
        depth = ((raw << 13) | (raw >> 3)).astype(np.float32) / 10000.0  # circular bit shift, 0.1 mm units
        prob = read_image(paths["mask"]) if paths["mask"].exists() else None
        mask = None if prob is None else prob.astype(np.float64) / np.iinfo(prob.dtype).max > self._thresh
        frame = Frame(i, self.ids[i], read_rgb(paths["rgb"]), depth, self.K, mask)
        return self._check_frame(frame, paths)

    def gt_poses(self) -> dict[str, np.ndarray]:
        return {k: np.linalg.inv(T) for k, T in self._poses.items()}

    def gt_visible_points(self) -> np.ndarray | None:
        from .geometry import backproject, transform

        pts = []
        for i, f in enumerate(self):
            if f.mask is None:
                continue
            p, _ = backproject(f.depth, f.K, f.mask)
            pts.append(transform(self._poses[self.ids[i]], p))
        if not pts:
            return None
        # The toolbox's later masks are noisy segmentations that also cover shelf and neighbours: keep the points
        # near the first (clean) mask's object.
        centre = np.median(pts[0], axis=0) if len(pts[0]) else np.median(np.concatenate(pts), axis=0)
        allp = np.concatenate(pts)
        return allp[np.linalg.norm(allp - centre, axis=1) < 0.15]


def _apc_blocks(text: str) -> dict[str, np.ndarray]:
    blocks: dict[str, list[list[float]]] = {}
    name = None
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("#"):
            name = line.lstrip("# ").strip()
            blocks[name] = []
        elif line and name is not None:
            try:
                blocks[name].append([float(x) for x in line.split()])
            except ValueError:
                continue
    return {k: np.array(v) for k, v in blocks.items() if v}


def sequence_digest(root: Path | str) -> str:
    """SHA-256 of a sequence folder: every file's path (relative, sorted) and bytes. Two folders with the same
    digest hold the same frames, whichever machine rendered or recorded them; benchmark figures compare only then."""
    root = Path(root)
    h = hashlib.sha256()
    for path in sorted((p for p in root.rglob("*") if p.is_file()), key=lambda p: p.relative_to(root).as_posix()):
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        h.update(path.read_bytes())
    return h.hexdigest()


def _load_json(path: Path) -> dict:
    if not path.is_file():
        raise SequenceError(path, "missing file")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise SequenceError(path, f"invalid JSON ({e.msg} at line {e.lineno})") from None


def open_sequence(path: Path | str, depth_scale: float = DEPTH_SCALE_MM, obj_id: int | None = None) -> Sequence:
    """Open a sequence folder in any supported layout (detected from its files)."""
    root = Path(path)
    if not root.is_dir():
        raise SequenceError(root, "sequence folder does not exist")
    if (root / "scene_camera.json").exists():
        return BopScene(root, obj_id)
    if (root / "cam.info.txt").exists():
        return ApcScene(root)
    return FolderSequence(root, depth_scale)


def load_mesh(path: Path) -> trimesh.Trimesh:
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types for bad files
        raise SequenceError(path, f"unreadable mesh ({e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) == 0:
        raise SequenceError(path, "mesh has no vertices")
    return mesh


def load_points(path: Path) -> np.ndarray:
    try:
        obj = trimesh.load(path, process=False)
    except Exception as e:
        raise SequenceError(path, f"unreadable point cloud ({e})") from None
    pts = np.asarray(getattr(obj, "vertices", []), dtype=np.float64)
    if pts.size == 0:
        raise SequenceError(path, "point cloud is empty")
    return pts


# ------------------------------------------------------------------------------------------------ writing


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file: a run stopped mid-write leaves the old file whole."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def format_pose(T: np.ndarray) -> str:
    return "\n".join(" ".join(f"{x:.9g}" for x in row) for row in T) + "\n"


def write_pose(path: Path, T: np.ndarray) -> None:
    """Write a 4x4 pose atomically: a crash never leaves a half-written file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, format_pose(T))


def read_poses(folder: Path | str) -> dict[str, np.ndarray]:
    """All ``NNNNNN.txt`` 4x4 poses in a folder, by frame id."""
    folder = Path(folder)
    return {p.stem: read_matrix(p, (4, 4)) for p in sorted(folder.glob("*.txt"))}


def read_track_log(out: Path | str) -> list[dict]:
    """OUT/track.jsonl as `ResultWriter` writes it: one dict a frame, in order (frame, status, confidence, ms...)."""
    path = Path(out) / "track.jsonl"
    if not path.is_file():
        raise SequenceError(path, "missing file")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            raise SequenceError(path, f"line {n} is not JSON") from None
    return rows


class ResultWriter:
    """Writes OUT/config.json (the run's ``config``, when given) at the start, OUT/ob_in_cam/NNNNNN.txt as each
    frame is tracked, OUT/track.jsonl and OUT/mesh.ply."""

    def __init__(self, out: Path | str, config: dict | None = None):
        self.out = make_folder(Path(out))
        (self.out / "ob_in_cam").mkdir(exist_ok=True)
        # A new run replaces an earlier run's result in the same folder, so no stale pose or mesh mixes in.
        for stale in [*(self.out / "ob_in_cam").glob("*.txt"), self.out / "mesh.ply"]:
            stale.unlink(missing_ok=True)
        if config is not None:
            write_text_atomic(self.out / "config.json", json.dumps(config, indent=2))
        self._log = open(self.out / "track.jsonl", "w")

    def write(self, frame_id: str, T: np.ndarray | None, record: dict) -> None:
        """Record one frame; a lost frame (T is None) gets a log line but no pose file."""
        if T is not None:
            write_pose(self.out / "ob_in_cam" / f"{frame_id}.txt", T)
        self._log.write(json.dumps({"frame": frame_id, **record}) + "\n")
        self._log.flush()

    def write_mesh(self, mesh: trimesh.Trimesh) -> None:
        tmp = self.out / "mesh.tmp.ply"
        mesh.export(tmp)
        os.replace(tmp, self.out / "mesh.ply")

    def close(self) -> None:
        self._log.close()

    def __enter__(self) -> ResultWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SequenceWriter:
    """Writes a sequence in the DESIGN.md layout (used by the synthesiser and converters)."""

    def __init__(self, root: Path | str, K: np.ndarray):
        self.root = make_folder(Path(root))
        for sub in ("rgb", "depth", "masks", "gt/ob_in_cam"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        np.savetxt(self.root / "cam_K.txt", K, fmt="%.10g")

    def write_frame(
        self,
        i: int,
        rgb: np.ndarray,
        depth_m: np.ndarray,
        mask: np.ndarray | None = None,
        gt_pose: np.ndarray | None = None,
    ) -> None:
        name = f"{i:06d}"
        cv2.imwrite(str(self.root / "rgb" / f"{name}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        mm = np.clip(np.round(np.nan_to_num(depth_m) / DEPTH_SCALE_MM), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(self.root / "depth" / f"{name}.png"), mm)
        if mask is not None:
            cv2.imwrite(str(self.root / "masks" / f"{name}.png"), mask.astype(np.uint8) * 255)
        if gt_pose is not None:
            write_pose(self.root / "gt" / "ob_in_cam" / f"{name}.txt", gt_pose)

    def write_model(self, mesh: trimesh.Trimesh, visible_points: np.ndarray | None = None) -> None:
        mesh.export(self.root / "gt" / "model.ply")
        if visible_points is not None:
            trimesh.PointCloud(visible_points).export(self.root / "gt" / "visible_points.ply")
