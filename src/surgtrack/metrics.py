"""Pose and shape accuracy: ADD, ADD-S, their AUC and the Chamfer distance (DESIGN.md section 4).

The protocol is BundleSDF's HO3D protocol:

1. Align the arbitrary predicted object frame on the first frame: pred_t' = pred_t @ inv(pred_0) @ gt_0.
2. Draw 10,000 model points (fixed seed) from the ground-truth surface the video shows (``gt_visible_points``),
   else from the whole ground-truth model; whole-model figures are reported too when a model exists.
3. ADD = mean ||T_pred p - T_gt p||; ADD-S = mean over ground-truth-posed points of the distance to the nearest
   prediction-posed point. A frame without a prediction has an infinite error.
4. AUC of the accuracy-threshold curve from 0 to 0.1 m, VOC style (YCB-Video / PoseCNN), in percent.
5. Chamfer distance in cm between the reconstructed mesh, moved into the ground-truth object frame with
   inv(gt_0) @ pred_0 and refined by point-to-point ICP (2 cm), and the seen ground-truth surface.

If frame 0 has no prediction (or no ground truth), the alignment anchor is the first frame, in sequence order, that has
both; frame 0 is then still scored as missing. The anchor's id is reported as ``anchor``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from .geometry import inv_T, kabsch, transform
from .io import Sequence as RGBDSequence
from .io import SequenceError, load_mesh, read_poses

N_MODEL_POINTS = 10_000  # protocol step 2
SEED = 0
AUC_MAX_ERR = 0.1  # m, protocol step 4
ICP_MAX_DIST = 0.02  # m, protocol step 5
WRONG_ERR = 0.05  # m, ADD-S above which a frame given a pose counts as wrong (not lost: the tracker gave a pose)
N_MESH_SAMPLES = 50_000  # dense sampling of the reconstructed mesh for the Chamfer distance
N_ICP_POINTS = 10_000  # of those samples, the ones ICP aligns
MAX_SURFACE_POINTS = 200_000  # ground-truth surface points kept for the Chamfer distance


# ------------------------------------------------------------------------------------------------ poses


def is_rigid(T: np.ndarray, tol: float = 1e-3) -> bool:
    """True when T is a 4x4 rigid transform (orthonormal rotation, det +1, last row 0 0 0 1)."""
    R = T[:3, :3]
    return (
        bool(np.allclose(R.T @ R, np.eye(3), atol=tol))
        and np.linalg.det(R) > 0
        and bool(np.allclose(T[3], [0, 0, 0, 1], atol=tol))
    )


def alignment_anchor(pred: Mapping[str, np.ndarray], gt: Mapping[str, np.ndarray], ids: Sequence[str]) -> str | None:
    """Frame whose poses fix the predicted object frame (step 1): frame 0, else the first frame with both poses."""
    for i in ids:
        if i in pred and i in gt:
            return i
    return None


def align_first_frame(pred: Mapping[str, np.ndarray], pred_a: np.ndarray, gt_a: np.ndarray) -> dict[str, np.ndarray]:
    """Protocol step 1: pred_t' = pred_t @ inv(pred_a) @ gt_a, with a the anchor frame (frame 0 normally)."""
    offset = inv_T(pred_a) @ gt_a
    return {k: T @ offset for k, T in pred.items()}


def add_errors(pred: Sequence[np.ndarray | None], gt: Sequence[np.ndarray], pts: np.ndarray) -> np.ndarray:
    """Protocol step 3, ADD per frame: mean ||T_pred p - T_gt p|| over model points; inf where pred is None."""
    out = np.full(len(gt), np.inf)
    for k, (P, G) in enumerate(zip(pred, gt, strict=True)):
        if P is not None:
            out[k] = float(np.linalg.norm(transform(P, pts) - transform(G, pts), axis=1).mean())
    return out


def adds_errors(pred: Sequence[np.ndarray | None], gt: Sequence[np.ndarray], pts: np.ndarray) -> np.ndarray:
    """Protocol step 3, ADD-S per frame: mean distance of each gt-posed point to the nearest pred-posed point.

    Distances are rigid-invariant, so the query runs in the model frame: ||G p - P q|| = ||inv(P) G p - q||,
    against one KD-tree of the model points.
    """
    tree = cKDTree(pts)
    out = np.full(len(gt), np.inf)
    for k, (P, G) in enumerate(zip(pred, gt, strict=True)):
        if P is not None:
            d, _ = tree.query(transform(inv_T(P) @ G, pts))
            out[k] = float(d.mean())
    return out


def auc(errors: Sequence[float] | np.ndarray, max_err: float = AUC_MAX_ERR) -> float:
    """Protocol step 4: VOC-style area under the accuracy-threshold curve on [0, max_err], percent.

    Sort the n errors, accuracy a_j = j / n for the j-th smallest, keep errors < max_err (k of them),
    x = [0, e_1..e_k, max_err], y = [0, a_1..a_k, a_k]; AUC = sum of (x_i - x_(i-1)) * y_i over the i where x
    changes, divided by max_err. Infinite (missing) errors count in n and are never kept.
    """
    e = np.sort(np.asarray(errors, dtype=np.float64))
    n = len(e)
    if n == 0:
        return 0.0
    acc = np.arange(1, n + 1) / n
    keep = e < max_err
    if not keep.any():
        return 0.0
    x = np.concatenate([[0.0], e[keep], [max_err]])
    y = np.concatenate([[0.0], acc[keep], [acc[keep][-1]]])
    i = np.nonzero(x[1:] != x[:-1])[0] + 1
    return float(np.sum((x[i] - x[i - 1]) * y[i]) / max_err * 100.0)


# ------------------------------------------------------------------------------------------------ surfaces


def sample_mesh(mesh: trimesh.Trimesh, n: int, seed: int = SEED) -> np.ndarray:
    """n points drawn uniformly by area from a mesh surface, reproducibly."""
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts, dtype=np.float64)


def subsample(pts: np.ndarray, n: int, seed: int = SEED) -> np.ndarray:
    """At most n of the points, drawn without replacement with a fixed seed (all of them when there are fewer)."""
    if len(pts) <= n:
        return np.asarray(pts, dtype=np.float64)
    idx = np.random.default_rng(seed).choice(len(pts), n, replace=False)
    return np.asarray(pts[np.sort(idx)], dtype=np.float64)


def model_points(
    visible: np.ndarray | None, model: trimesh.Trimesh | None, n: int = N_MODEL_POINTS, seed: int = SEED
) -> np.ndarray | None:
    """Protocol step 2: n points of the seen surface when known, else of the whole model; None when neither."""
    if visible is not None and len(visible):
        return subsample(visible, n, seed)
    if model is not None:
        return sample_mesh(model, n, seed)
    return None


def icp_point_to_point(
    src: np.ndarray, dst: np.ndarray, max_dist: float = ICP_MAX_DIST, iterations: int = 30, tol: float = 1e-6
) -> np.ndarray:
    """Protocol step 5 refinement: rigid T with dst ~ T @ src by point-to-point ICP, pairs within max_dist."""
    tree = cKDTree(dst)
    T = np.eye(4)
    for _ in range(iterations):
        cur = transform(T, src)
        d, j = tree.query(cur, distance_upper_bound=max_dist)
        ok = np.isfinite(d)
        if ok.sum() < 3:
            break
        dT = kabsch(cur[ok], dst[j[ok]])
        T = dT @ T
        if np.abs(dT - np.eye(4)).max() < tol:
            break
    return T


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance 0.5 * (mean nearest distance a->b + mean nearest distance b->a), same units."""
    da, _ = cKDTree(b).query(a)
    db, _ = cKDTree(a).query(b)
    return 0.5 * (float(da.mean()) + float(db.mean()))


def chamfer_cm(
    mesh: trimesh.Trimesh,
    mesh_to_gt: np.ndarray,
    gt_surface: np.ndarray,
    icp: bool = True,
    n_samples: int = N_MESH_SAMPLES,
    seed: int = SEED,
) -> float:
    """Protocol step 5: CD in cm of a reconstructed mesh against the seen gt surface (object frame, metres).

    ``mesh_to_gt`` moves the mesh into the ground-truth object frame (inv(gt_0) @ pred_0); the dense samples are
    then refined onto the surface by point-to-point ICP with a 2 cm correspondence gate.
    """
    src = transform(mesh_to_gt, sample_mesh(mesh, n_samples, seed))
    dst = subsample(gt_surface, MAX_SURFACE_POINTS, seed)
    if icp:
        src = transform(icp_point_to_point(subsample(src, N_ICP_POINTS, seed), dst), src)
    return chamfer(src, dst) * 100.0


# ------------------------------------------------------------------------------------------------ evaluation


def _json_errors(ids: Sequence[str], errors: np.ndarray) -> dict[str, float | None]:
    return {i: (float(e) if np.isfinite(e) else None) for i, e in zip(ids, errors, strict=True)}


def evaluate(out_dir: Path | str, seq: RGBDSequence) -> dict:
    """Score a tracking result folder against a sequence's ground truth (DESIGN.md section 4, steps 1-5).

    Returns a JSON-serialisable dict: ``add_s_auc``, ``add_auc`` (percent, over the seen-surface model points),
    ``add_s_auc_full``, ``add_auc_full`` (whole model; None without one), ``cd_cm`` (None without OUT/mesh.ply),
    ``frames`` (frames with ground truth), ``missing`` (those without a prediction: lost), ``missing_ids``,
    ``wrong`` (frames given a pose that is more than WRONG_ERR off in ADD-S: a lost instrument not reported lost),
    ``anchor`` and ``errors``: per-frame ADD / ADD-S in metres keyed by frame id (None for a missing frame).
    Raises SequenceError when the result or the ground truth cannot be scored.
    """
    out = Path(out_dir)
    if not out.is_dir():
        raise SequenceError(out, "result folder does not exist")
    pose_dir = out / "ob_in_cam"
    pred = read_poses(pose_dir) if pose_dir.is_dir() else {}
    if not pred:
        raise SequenceError(pose_dir, "no predicted poses (expected ob_in_cam/000000.txt ...)")
    gt_all = seq.gt_poses()
    if not gt_all:
        raise SequenceError(seq.root, "sequence has no ground-truth poses; nothing to evaluate against")
    for k, T in pred.items():
        if not is_rigid(T):
            raise SequenceError(pose_dir / f"{k}.txt", "not a rigid transform (rotation not orthonormal)")
    ids = [i for i in seq.ids if i in gt_all]
    anchor = alignment_anchor(pred, gt_all, ids)
    if anchor is None:
        raise SequenceError(pose_dir, f"no predicted pose matches a ground-truth frame id (e.g. {ids[0]}.txt)")
    model = seq.gt_model()
    visible = seq.gt_visible_points()
    pts = model_points(visible, model)
    if pts is None:
        raise SequenceError(seq.root, "no ground-truth surface (gt/visible_points.ply or gt/model.ply) to score")

    aligned = align_first_frame(pred, pred[anchor], gt_all[anchor])
    P = [aligned.get(i) for i in ids]
    G = [gt_all[i] for i in ids]
    add, adds = add_errors(P, G, pts), adds_errors(P, G, pts)
    result: dict = {
        "sequence": str(seq.root),
        "result": str(out),
        "frames": len(ids),
        "missing": int(sum(p is None for p in P)),
        "missing_ids": [i for i, p in zip(ids, P, strict=True) if p is None],
        "wrong": int(np.sum(np.isfinite(adds) & (adds > WRONG_ERR))),
        "anchor": anchor,
        "model_points": "visible_points" if visible is not None and len(visible) else "model",
        "add_s_auc": auc(adds),
        "add_auc": auc(add),
        "add_s_auc_full": None,
        "add_auc_full": None,
        "cd_cm": None,
        "errors": {"add": _json_errors(ids, add), "add_s": _json_errors(ids, adds)},
    }
    if model is not None:
        full = sample_mesh(model, N_MODEL_POINTS)
        add_f, adds_f = add_errors(P, G, full), adds_errors(P, G, full)
        result["add_s_auc_full"] = auc(adds_f)
        result["add_auc_full"] = auc(add_f)
        result["errors"]["add_full"] = _json_errors(ids, add_f)
        result["errors"]["add_s_full"] = _json_errors(ids, adds_f)
    mesh_path = out / "mesh.ply"
    if mesh_path.is_file():
        surface = visible if visible is not None and len(visible) else sample_mesh(model, N_MESH_SAMPLES, SEED + 1)
        mesh_to_gt = inv_T(gt_all[anchor]) @ pred[anchor]
        mesh = load_mesh(mesh_path)
        if len(mesh.faces) == 0:
            raise SequenceError(mesh_path, "mesh has no faces")
        result["cd_cm"] = chamfer_cm(mesh, mesh_to_gt, surface)
    return result
