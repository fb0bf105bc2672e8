"""Time the Instrument SDF (TSDF init + Adam fit) on rendered keyframes of a procedural instrument.

The instrument is a shaft (capsule) with a box handle and a box jaw, rendered exactly (open3d ray casting) from
`--views` posed cameras at 640x480. Prints the seconds of each step and the symmetric Chamfer distance of the mesh
to the true surface.

    .venv/bin/python benchmarks/sdf_fit.py [--views 24] [--threads 1] [--occluder]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import open3d as o3d
import torch
import trimesh
from scipy.spatial import cKDTree

from surgtrack.config import SDFConfig
from surgtrack.geometry import inv_T, make_T
from surgtrack.registration import InstrumentSDF
from surgtrack.tsdf import View

SHAFT_R, SHAFT_HALF = 0.006, 0.09  # capsule along x
HANDLE = (np.array([0.12, 0.0, 0.0]), np.array([0.035, 0.012, 0.009]))  # centre, half sizes
JAW = (np.array([-0.1, 0.0, 0.004]), np.array([0.012, 0.004, 0.006]))


def instrument_parts() -> list[trimesh.Trimesh]:
    shaft = trimesh.creation.capsule(height=2 * SHAFT_HALF, radius=SHAFT_R, count=[48, 48])
    shaft.apply_transform(make_T(np.array([[0, 0, 1.0], [0, 1.0, 0], [-1.0, 0, 0]]), np.zeros(3)))
    boxes = [trimesh.creation.box(extents=2 * h, transform=make_T(np.eye(3), c)) for c, h in (HANDLE, JAW)]
    return [shaft, *boxes]


def instrument_sdf(p: np.ndarray) -> np.ndarray:
    """Exact signed distance of the union (positive outside)."""
    axis = np.zeros_like(p)
    axis[:, 0] = np.clip(p[:, 0], -SHAFT_HALF, SHAFT_HALF)
    d = np.linalg.norm(p - axis, axis=1) - SHAFT_R
    for c, h in (HANDLE, JAW):
        a = np.abs(p - c) - h
        box = np.linalg.norm(np.maximum(a, 0), axis=1) + np.minimum(a.max(axis=1), 0)
        d = np.minimum(d, box)
    return d


def surface_points(n: int, seed: int = 0) -> np.ndarray:
    """Points on the union's outer surface: samples of each part not inside another."""
    parts = instrument_parts()
    pts = np.concatenate([trimesh.sample.sample_surface(m, n, seed=seed)[0] for m in parts])
    return pts[np.abs(instrument_sdf(pts)) < 2e-4]


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Object-to-camera pose of a camera at `eye` looking at `target` (camera z forward, y down)."""
    z = target - eye
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.95 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    return inv_T(make_T(np.stack([x, np.cross(z, x), z], axis=1), eye))


def render(
    parts: list[trimesh.Trimesh],
    pose: np.ndarray,
    K: np.ndarray,
    w: int,
    h: int,
    occluders_cam: list[trimesh.Trimesh] = (),
) -> View:
    """Exact depth and instrument mask; occluders are given in the camera frame and are not instrument."""
    scene = o3d.t.geometry.RaycastingScene()
    T_co = inv_T(pose)
    ids = []
    for m in parts:
        ids.append(
            scene.add_triangles(
                o3d.core.Tensor(np.asarray(m.vertices, np.float32)), o3d.core.Tensor(np.asarray(m.faces, np.uint32))
            )
        )
    for occ in occluders_cam:
        m = occ.copy()
        m.apply_transform(T_co)
        scene.add_triangles(
            o3d.core.Tensor(np.asarray(m.vertices, np.float32)), o3d.core.Tensor(np.asarray(m.faces, np.uint32))
        )
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((h, w))], axis=-1).reshape(-1, 3)
    d = cam @ T_co[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T_co[:3, 3], d.shape), d], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy()
    gid = hit["geometry_ids"].numpy()
    ok = np.isfinite(t)
    depth = np.where(ok, t, 0.0).reshape(h, w).astype(np.float32)
    mask = (ok & np.isin(gid, ids)).reshape(h, w)
    return View(depth=depth, mask=mask, K=K, pose=pose)


def keyframes(n: int, w: int = 640, h: int = 480, occluder: bool = False) -> list[View]:
    """`n` views on a band of elevations around the instrument at 0.35 m, a background plane 0.25 m behind it."""
    f = 600.0 * w / 640
    K = np.array([[f, 0, w / 2 - 0.5], [0, f, h / 2 - 0.5], [0, 0, 1.0]])
    parts = instrument_parts()
    back = trimesh.creation.box(extents=[2.0, 2.0, 0.01], transform=make_T(np.eye(3), [0, 0, 0.6]))
    occ = []
    if occluder:
        finger = trimesh.creation.capsule(height=0.08, radius=0.009)
        finger.apply_transform(make_T(np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]), [0.0, 0.0, 0.3]))
        occ = [finger]
    views = []
    for i in range(n):
        a = 2 * np.pi * i / n
        e = np.radians(35.0 + 25.0 * np.sin(3 * a))
        eye = 0.35 * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
        views.append(render(parts, look_at(eye, np.zeros(3)), K, w, h, [back, *occ]))
    return views


def chamfer(mesh: trimesh.Trimesh, truth: np.ndarray, n: int = 20000) -> float:
    """Symmetric mean Chamfer distance (m) between mesh samples and true surface points."""
    if len(mesh.faces) == 0:
        return float("inf")
    s = mesh.sample(n, seed=0) if "seed" in mesh.sample.__code__.co_varnames else mesh.sample(n)
    a = cKDTree(truth).query(s)[0].mean()
    b = cKDTree(s).query(truth)[0].mean()
    return float((a + b) / 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (1: see BackgroundFitter)")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--occluder", action="store_true", help="a finger-like capsule in front of every view")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t = time.perf_counter()
    views = keyframes(args.views, occluder=args.occluder)
    t_render = time.perf_counter() - t
    cfg = SDFConfig()
    if args.iterations is not None:
        cfg.iterations = args.iterations
    sdf = InstrumentSDF(cfg, center=np.array([0.02, 0.0, 0.0]), extent=np.array([0.3, 0.06, 0.06]))
    t = time.perf_counter()
    sdf.init_tsdf(views)
    t_init = time.perf_counter() - t
    truth = surface_points(20000)
    cd_init = chamfer(sdf.mesh(), truth)
    report = sdf.fit(views)
    t = time.perf_counter()
    mesh = sdf.mesh()
    t_mesh = time.perf_counter() - t
    cd = chamfer(mesh, truth)
    pts = truth[:4000]
    t = time.perf_counter()
    for _ in range(20):
        psi, _ = sdf.query(pts)
    t_query = (time.perf_counter() - t) / 20
    print(
        f"device {sdf.device}, torch threads {torch.get_num_threads()}, grid {sdf.grid.shape} "
        f"voxel {cfg.voxel_size * 1e3:.1f} mm, {args.views} views 640x480, occluder {args.occluder}"
    )
    print(f"rays: {report['rays'][0]} instrument, {report['rays'][1]} other; iterations {cfg.iterations}")
    print(f"render {t_render:.2f} s (not counted); load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"init_tsdf {t_init:.2f} s, fit {report['seconds']:.2f} s, total {t_init + report['seconds']:.2f} s")
    print(f"mesh {t_mesh:.2f} s, {len(mesh.faces)} faces; query 4000 points {t_query * 1e3:.2f} ms")
    print(
        f"Chamfer to true surface: TSDF init {cd_init * 1e3:.2f} mm, fitted {cd * 1e3:.2f} mm; "
        f"|Psi| at true surface mean {np.abs(psi).mean() * 1e3:.2f} mm; converged {sdf.converged}"
    )
    print("final losses " + ", ".join(f"{k} {v:.4f}" for k, v in report["final"].items()))


if __name__ == "__main__":
    main()
