"""Posture graph optimisation (paper eqs. 8-11) on synthetic RGB-D views of analytic shapes."""

from __future__ import annotations

import cv2
import numpy as np

from surgtrack.config import GraphConfig
from surgtrack.geometry import inv_T, make_T, rotation_angle_deg, so3_exp, transform
from surgtrack.posture_graph import Coverage, FeatureEdge, FreeSpace, GraphNode, MaskView, default_pairs, optimize_graph
from surgtrack.preprocess import MaskEdge

HALF = np.array([0.04, 0.025, 0.015])  # half-extents of the box object, m
K = np.array([[150.0, 0.0, 79.5], [0.0, 150.0, 59.5], [0.0, 0.0, 1.0]])  # 640x480 intrinsics downscaled x4
HW = (120, 160)


def _rot_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    return so3_exp(axis / np.linalg.norm(axis) * np.arccos(np.clip(a @ b, -1, 1)))


# Object rotation that shows three faces of the box to a camera looking down +z.
R0 = _rot_between(np.ones(3), np.array([0.0, 0.0, -1.0]))


def view_poses(n: int) -> list[np.ndarray]:
    """n object-to-camera poses around a corner view, 0.3 m away, up to ~20 degrees apart."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        w = 0.18 * np.array([np.cos(a), np.sin(a), 0.5 * np.sin(2 * a)])
        out.append(make_T(so3_exp(w) @ R0, np.array([0.005 * np.cos(a), 0.004 * np.sin(a), 0.3])))
    return out


def _rays(K: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    v, u = np.mgrid[0 : hw[0], 0 : hw[1]]
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1).reshape(-1, 3)


def _finish(d, s, hit, n_cam, hw, noise, rng):
    """Grids from ray parameters s (depth, since d_z = 1), with grazing views and misses removed."""
    cosv = -(n_cam * d).sum(1) / np.linalg.norm(d, axis=1)
    keep = hit & (cosv > np.cos(np.radians(80.0)))
    depth = np.where(keep, s, 0.0)
    if noise > 0:
        depth[keep] += rng.normal(0.0, noise, keep.sum())
    xyz = d * depth[:, None]
    n_cam = np.where(keep[:, None], n_cam, 0.0)
    return xyz.reshape(*hw, 3), n_cam.reshape(*hw, 3)


def render_box(pose: np.ndarray, noise: float = 0.0, rng: np.random.Generator | None = None):
    """Camera-frame xyz and normal grids of the box by ray casting (slab method)."""
    d = _rays(K, HW)
    C = inv_T(pose)
    o, dd = C[:3, 3], d @ C[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-HALF - o) / dd, (HALF - o) / dd
    tlo = np.minimum(t1, t2)
    tmin, tmax = tlo.max(1), np.maximum(t1, t2).min(1)
    hit = (tmax >= tmin) & (tmin > 0)
    axis = np.argmax(tlo, 1)
    n_obj = np.zeros_like(d)
    n_obj[np.arange(len(d)), axis] = -np.sign(dd[np.arange(len(d)), axis])
    return _finish(d, np.where(hit, tmin, 0.0), hit, n_obj @ pose[:3, :3].T, HW, noise, rng)


def render_sphere(pose: np.ndarray, radius: float):
    """Camera-frame xyz and normal grids of a sphere centred on the object origin."""
    d = _rays(K, HW)
    c = pose[:3, 3]
    a = (d * d).sum(1)
    b = -2 * d @ c
    disc = b * b - 4 * a * (c @ c - radius**2)
    hit = disc > 0
    s = np.where(hit, (-b - np.sqrt(np.where(hit, disc, 0.0))) / (2 * a), 0.0)
    hit &= s > 0
    n_cam = d * s[:, None] - c
    n_cam /= np.linalg.norm(n_cam, axis=1, keepdims=True)
    return _finish(d, s, hit, n_cam, HW, 0.0, None)


def box_surface_points(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Uniform points on the box faces with their outward normals (object frame)."""
    areas = np.array([HALF[1] * HALF[2], HALF[0] * HALF[2], HALF[0] * HALF[1]]).repeat(2)
    face = rng.choice(6, size=n, p=areas / areas.sum())
    axis, sign = face // 2, np.where(face % 2 == 0, -1.0, 1.0)
    p = rng.uniform(-1, 1, (n, 3)) * HALF
    p[np.arange(n), axis] = sign * HALF[axis]
    nrm = np.zeros((n, 3))
    nrm[np.arange(n), axis] = sign
    return p, nrm


def feature_edge(rng, gt, i, j, m=60, noise=0.001, outlier_frac=0.0) -> FeatureEdge:
    """m matches between nodes i and j on faces both cameras see, with noise and a share of wrong matches."""
    p, nrm = box_surface_points(rng, 30 * m)
    ci, cj = inv_T(gt[i])[:3, 3], inv_T(gt[j])[:3, 3]
    both = ((nrm * (ci - p)).sum(1) > 0.01) & ((nrm * (cj - p)).sum(1) > 0.01)
    p = p[both][:m]
    p_i = transform(gt[i], p) + rng.normal(0, noise, p.shape)
    p_j = transform(gt[j], p) + rng.normal(0, noise, p.shape)
    k = int(round(outlier_frac * len(p)))
    if k:
        p_j[:k] = transform(gt[j], box_surface_points(rng, k)[0])
    return FeatureEdge(i, j, p_i, p_j)


def perturb(rng: np.random.Generator, T: np.ndarray, deg: float, trans: float) -> np.ndarray:
    ax, dt = rng.normal(size=3), rng.normal(size=3)
    w = np.radians(deg) * ax / np.linalg.norm(ax)
    return make_T(so3_exp(w), trans * dt / np.linalg.norm(dt)) @ T


def pose_error(T: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """Rotation error (degrees) and translation error (m) of an object-to-camera pose."""
    return rotation_angle_deg(T[:3, :3] @ T_gt[:3, :3].T), float(np.linalg.norm(T[:3, 3] - T_gt[:3, 3]))


def make_graph(rng, n, perturb_deg=(2.0, 5.0), perturb_m=(0.01, 0.02), depth_noise=0.0005, fixed=(0,)):
    gt = view_poses(n)
    nodes = []
    for k in range(n):
        xyz, nrm = render_box(gt[k], depth_noise, rng)
        pose = gt[k] if k in fixed else perturb(rng, gt[k], rng.uniform(*perturb_deg), rng.uniform(*perturb_m))
        nodes.append(GraphNode(pose=pose, xyz=xyz, normals=nrm, K=K.copy(), fixed=k in fixed))
    return gt, nodes


def max_errors(poses, gt, skip=()) -> tuple[float, float]:
    errs = [pose_error(T, G) for k, (T, G) in enumerate(zip(poses, gt, strict=True)) if k not in skip]
    return max(e[0] for e in errs), max(e[1] for e in errs)


def test_box_views_are_usable():
    gt = view_poses(6)
    for T in gt:
        xyz, nrm = render_box(T)
        valid = xyz[..., 2] > 0
        assert 800 < valid.sum() < 6000
        # Three faces in view: three distinct normal directions in the object frame.
        n_obj = np.round(nrm[valid] @ T[:3, :3], 3)
        assert len(np.unique(n_obj, axis=0)) == 3


def test_graph_recovers_perturbed_poses():
    rng = np.random.default_rng(0)
    n = 8
    gt, nodes = make_graph(rng, n)
    edges = [feature_edge(rng, gt, 0, j) for j in range(1, n)]
    edges += [feature_edge(rng, gt, j, j + 1) for j in range(1, n - 1)]
    rot0, trans0 = max_errors([nd.pose for nd in nodes], gt, skip=(0,))
    assert rot0 > 3.0 and trans0 > 0.015
    out = optimize_graph(nodes, edges, GraphConfig())
    rot, trans = max_errors(out, gt)
    assert rot < 0.3
    assert trans < 0.001


def test_fixed_nodes_are_returned_unchanged():
    rng = np.random.default_rng(1)
    n = 5
    gt, nodes = make_graph(rng, n, fixed=(0, 3))
    nodes[3].pose = perturb(rng, gt[3], 1.0, 0.003)  # a fixed node keeps even a wrong pose
    edges = [feature_edge(rng, gt, 0, j) for j in range(1, n)]
    out = optimize_graph(nodes, edges, GraphConfig())
    assert np.array_equal(out[0], nodes[0].pose)
    assert np.array_equal(out[3], nodes[3].pose)
    assert out[3] is not nodes[3].pose
    assert not np.allclose(out[1], nodes[1].pose)


def test_projective_term_alone_converges():
    rng = np.random.default_rng(2)
    n = 6
    gt, nodes = make_graph(rng, n, perturb_deg=(1.0, 2.0), perturb_m=(0.003, 0.006))
    rot0, trans0 = max_errors([nd.pose for nd in nodes], gt)
    assert rot0 > 1.0 and trans0 > 0.003
    out = optimize_graph(nodes, [], GraphConfig())
    rot, trans = max_errors(out, gt)
    assert rot < 0.3
    assert trans < 0.001


def test_ground_truth_is_a_fixed_point():
    rng = np.random.default_rng(3)
    n = 5
    gt, nodes = make_graph(rng, n, perturb_deg=(0.0, 0.0), perturb_m=(0.0, 0.0), depth_noise=0.0)
    edges = [feature_edge(rng, gt, 0, j, noise=0.0) for j in range(1, n)]
    out = optimize_graph(nodes, edges, GraphConfig())
    rot, trans = max_errors(out, gt)
    assert rot < 0.05
    assert trans < 1e-4


def test_sdf_term_pulls_pose_onto_sphere():
    radius = 0.05
    T_gt = make_T(np.eye(3), np.array([0.01, -0.005, 0.3]))
    xyz, nrm = render_sphere(T_gt, radius)
    assert (xyz[..., 2] > 0).sum() > 500
    T0 = make_T(np.eye(3), T_gt[:3, 3] + np.array([0.008, -0.006, 0.01]))
    node = GraphNode(pose=T0, xyz=xyz, normals=nrm, K=K.copy())

    def sphere_sdf(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.linalg.norm(p, axis=1)
        return r - radius, p / r[:, None]

    without = optimize_graph([node], [], GraphConfig())
    assert np.allclose(without[0], T0)
    out = optimize_graph([node], [], GraphConfig(), sdf=sphere_sdf, sdf_nodes=[0])
    assert np.linalg.norm(out[0][:3, 3] - T_gt[:3, 3]) < 2e-4
    pts = transform(inv_T(out[0]), xyz[xyz[..., 2] > 0])
    assert np.abs(sphere_sdf(pts)[0]).max() < 5e-4


def test_sdf_term_leaves_out_points_the_field_has_no_value_for():
    """Points beyond the field's box (NaN) neither move the pose nor spoil it."""
    radius = 0.05
    T_gt = make_T(np.eye(3), np.array([0.01, -0.005, 0.3]))
    xyz, nrm = render_sphere(T_gt, radius)
    T0 = make_T(np.eye(3), T_gt[:3, 3] + np.array([0.008, -0.006, 0.01]))
    node = GraphNode(pose=T0, xyz=xyz, normals=nrm, K=K.copy())

    def half_known(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.linalg.norm(p, axis=1)
        psi, grad = r - radius, p / r[:, None]
        psi[p[:, 0] > 0], grad[p[:, 0] > 0] = np.nan, np.nan
        return psi, grad

    out = optimize_graph([node], [], GraphConfig(), sdf=half_known, sdf_nodes=[0])
    assert np.isfinite(out[0]).all()
    assert np.linalg.norm(out[0][:3, 3] - T_gt[:3, 3]) < 1e-3


def graph_with_wrong_matches(seed: int, frac: float = 0.2):
    rng = np.random.default_rng(seed)
    n = 6
    gt, nodes = make_graph(rng, n)
    edges = [feature_edge(rng, gt, 0, j, m=100, outlier_frac=frac) for j in range(1, n)]
    edges += [feature_edge(rng, gt, j, j + 1, m=100, outlier_frac=frac) for j in range(1, n - 1)]
    return gt, nodes, edges


def test_graph_converges_with_wrong_matches():
    gt, nodes, edges = graph_with_wrong_matches(4)
    rot, trans = max_errors(optimize_graph(nodes, edges, GraphConfig()), gt)
    assert rot < 0.3
    assert trans < 0.001


def test_huber_downweights_wrong_matches():
    gt, nodes, edges = graph_with_wrong_matches(5)
    # L_3D alone: with 20 % wrong matches the robust solution stays near the 1 mm noise floor of the features,
    # the quadratic one (delta far above every residual) does not.
    rot, trans = max_errors(optimize_graph(nodes, edges, GraphConfig(w_p=0.0)), gt)
    assert rot < 1.5 and trans < 0.001
    rot_q, trans_q = max_errors(optimize_graph(nodes, edges, GraphConfig(w_p=0.0, huber_delta=10.0)), gt)
    assert rot_q > 3.0 and trans_q > 0.003


def test_default_pairs():
    e = [FeatureEdge(0, 2, np.zeros((1, 3)), np.zeros((1, 3))), FeatureEdge(2, 0, np.zeros((1, 3)), np.zeros((1, 3)))]
    assert default_pairs(3, e) == [(0, 2), (2, 0)]
    assert default_pairs(3, []) == [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)]


def test_motion_prior_is_weak_next_to_the_data():
    radius = 0.05
    T_gt = make_T(np.eye(3), np.array([0.01, -0.005, 0.3]))
    xyz, nrm = render_sphere(T_gt, radius)
    T0 = make_T(so3_exp(np.array([0.0, 0.3, 0.0])), T_gt[:3, 3] + np.array([0.008, -0.006, 0.01]))
    node = GraphNode(pose=T0, xyz=xyz, normals=nrm, K=K.copy())

    def sphere_sdf(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.linalg.norm(p, axis=1)
        return r - radius, p / r[:, None]

    out = optimize_graph([node], [], GraphConfig(), sdf=sphere_sdf, sdf_nodes=[0], priors=[(0, T0)])
    # The data pin the centre (the prior costs a fraction of a millimetre); the sphere's rotation, which the data
    # leave free, stays where the prior holds it.
    assert np.linalg.norm(out[0][:3, 3] - T_gt[:3, 3]) < 5e-4
    assert rotation_angle_deg(out[0][:3, :3].T @ T0[:3, :3]) < 0.01


def test_motion_prior_alone_gives_the_prior():
    T0 = make_T(np.eye(3), np.array([0.0, 0.0, 0.3]))
    T1 = make_T(so3_exp(np.array([0.02, -0.01, 0.03])), np.array([0.004, -0.002, 0.303]))
    empty = GraphNode(pose=T0, xyz=np.zeros(HW + (3,)), normals=np.zeros(HW + (3,)), K=K.copy())
    out = optimize_graph([empty], [], GraphConfig(), priors=[(0, T1)])
    assert np.allclose(out[0], T1, atol=1e-6)
    assert np.allclose(optimize_graph([empty], [], GraphConfig(w_m=0.0), priors=[(0, T1)])[0], T0)


def test_the_directions_the_data_leave_free_are_reported_unmeasured():
    """A sphere's rotation is free (three turns, its centre measured); a box seen at a corner leaves nothing free."""
    radius = 0.05
    T_gt = make_T(np.eye(3), np.array([0.01, -0.005, 0.3]))
    xyz, nrm = render_sphere(T_gt, radius)
    node = GraphNode(pose=T_gt, xyz=xyz, normals=nrm, K=K.copy())

    def sphere_sdf(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = np.linalg.norm(p, axis=1)
        return r - radius, p / r[:, None]

    free: dict = {}
    optimize_graph([node], [], GraphConfig(), sdf=sphere_sdf, sdf_nodes=[0], priors=[(0, T_gt)], unmeasured=free)
    assert [u.kind for u in free[0]] == ["turn"] * 3
    axes = np.stack([u.axis for u in free[0]])
    assert np.allclose(axes @ axes.T, np.eye(3), atol=1e-6)  # every axis of rotation

    rng = np.random.default_rng(3)
    _, nodes = make_graph(rng, 3)
    free = {}
    optimize_graph(nodes, [], GraphConfig(), priors=[(1, nodes[1].pose)], unmeasured=free)
    assert free == {1: []}
    # The report does not depend on the prior's weight; without the argument nothing is reported or changed.
    free_w0: dict = {}
    out = optimize_graph(nodes, [], GraphConfig(w_m=0.0), priors=[(1, nodes[1].pose)], unmeasured=free_w0)
    assert free_w0 == {1: []}
    assert all(np.allclose(a, b) for a, b in zip(out, optimize_graph(nodes, [], GraphConfig(w_m=0.0)), strict=True))


def face_on_free_space(occluded: bool) -> tuple[np.ndarray, list[GraphNode], FreeSpace]:
    """The box seen face-on (only its -z face shows: L_2D leaves a slide within that face free), a node slid 1 cm
    along the box's long side against a fixed node at the truth, and the frame's free space at 640x480: the face's
    rectangle as mask, background 0.5 m behind. With ``occluded``, something 0.2 m from the camera covers the
    pixels the slid box's end would reach."""
    truth = make_T(np.eye(3), np.array([0.005, -0.004, 0.3]))
    xyz, nrm = render_box(truth)
    slid = truth @ make_T(np.eye(3), np.array([0.01, 0.0, 0.0]))
    nodes = [GraphNode(slid, xyz, nrm, K.copy()), GraphNode(truth, xyz, nrm, K.copy(), fixed=True)]
    Kf = np.array([[600.0, 0.0, 319.5], [0.0, 600.0, 239.5], [0.0, 0.0, 1.0]])
    z = truth[2, 3] - HALF[2]
    v, u = np.mgrid[0:480, 0:640]
    x, y = (u - Kf[0, 2]) * z / Kf[0, 0] - truth[0, 3], (v - Kf[1, 2]) * z / Kf[1, 1] - truth[1, 3]
    mask = (np.abs(x) <= HALF[0]) & (np.abs(y) <= HALF[1])
    depth = np.where(mask, z, 0.5).astype(np.float32)
    if occluded:
        depth[(x > HALF[0]) & (x < HALF[0] + 0.02)] = 0.2
    points = box_surface_points(np.random.default_rng(8), 3000)[0]
    return truth, nodes, FreeSpace.of(points, MaskEdge.of(mask), depth, Kf, 1500)


def test_mask_edge_gives_the_exact_distance_to_the_mask_and_its_gradient():
    """Off the mask, the distance to the nearest edge pixel is the exact Euclidean distance to the mask (the
    precise distance transform), and its gradient is that distance's slope; with no mask every distance is
    infinite."""
    v, u = np.mgrid[0:120, 0:160]
    mask = (((u - 50) / 30.0) ** 2 + ((v - 60) / 12.0) ** 2 <= 1) | ((u > 90) & (u < 140) & (np.abs(v - u + 40) < 4))
    edge = MaskEdge.of(mask)
    exact = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    off = ~mask
    dist, _, _ = edge.distance(u[off].astype(float), v[off].astype(float))
    assert len(edge.uv) < mask.sum() / 3  # the edge, not the whole mask
    assert np.abs(dist - exact[off]).max() < 1e-3
    rng = np.random.default_rng(3)
    pu, pv = rng.uniform(0, 160, 300), rng.uniform(0, 120, 300)
    d, gu, gv = edge.distance(pu, pv)
    far = d > 3  # away from the mask, where the nearest pixel does not change within the step
    h = 1e-4
    assert np.allclose(gu[far], (edge.distance(pu + h, pv)[0] - edge.distance(pu - h, pv)[0])[far] / (2 * h), atol=1e-4)
    assert np.allclose(gv[far], (edge.distance(pu, pv + h)[0] - edge.distance(pu, pv - h)[0])[far] / (2 * h), atol=1e-4)
    assert np.all(np.isinf(MaskEdge.of(np.zeros((8, 8), bool)).distance(pu, pv)[0]))


def test_free_space_pulls_a_slid_pose_back_into_the_mask():
    """A slide along a flat face moves none of its points off the other frame's surface (L_2D is blind to it),
    but it moves the box's end over background the frame saw: L_FS pulls it back."""
    truth, nodes, fs = face_on_free_space(occluded=False)
    r, _ = fs.residuals(inv_T(truth), GraphConfig())
    assert np.all(r == 0)  # at the truth every model point lies within the mask
    assert np.count_nonzero(fs.residuals(inv_T(nodes[0].pose), GraphConfig())[0]) > 100
    blind = optimize_graph(nodes, [], GraphConfig(w_fs=0.0), free_space=(0, fs))
    assert np.linalg.norm(blind[0][:3, 3] - truth[:3, 3]) > 0.008
    out = optimize_graph(nodes, [], GraphConfig(w_fs=1.0, iterations=15), free_space=(0, fs))
    rot, trans = pose_error(out[0], truth)
    assert trans < 0.0015 and rot < 0.3


def test_free_space_is_not_what_an_occluder_hides():
    """Where the frame's depth lies in front of the model point (an occluder, a hand), the camera did not see past
    it: L_FS leaves the slid pose where it is."""
    truth, nodes, fs = face_on_free_space(occluded=True)
    assert np.count_nonzero(fs.residuals(inv_T(nodes[0].pose), GraphConfig())[0]) == 0
    out = optimize_graph(nodes, [], GraphConfig(w_fs=1.0, iterations=15), free_space=(0, fs))
    assert np.linalg.norm(out[0][:3, 3] - truth[:3, 3]) > 0.008


def test_coverage_pulls_a_slid_pose_back_into_what_the_keyframe_saw():
    """The counterpart of L_FS: the frame's own points, at a pose slid along the face, stand where a keyframe at
    the truth saw the background beyond the box's end; L_CV pulls them back. Where the keyframe's depth lies in
    front of them (an occluder) it saw nothing past them, and the pose stays."""
    truth, nodes, fs = face_on_free_space(occluded=False)
    xyz = nodes[0].xyz
    frame_points = xyz[xyz[..., 2] > 0]
    cv = Coverage.of(frame_points, fs.view, inv_T(truth), 1000)
    assert len(cv.points) <= 1000
    assert len(cv.residuals(inv_T(truth), GraphConfig())[0]) == 0  # at the truth every point lies in the mask
    r, J = cv.residuals(inv_T(nodes[0].pose), GraphConfig())
    assert len(r) > 20 and np.all(r > 0) and J.shape == (6, len(r))
    blind = optimize_graph(nodes, [], GraphConfig(w_fs=0.0, w_cv=0.0), coverage=(0, cv))
    assert np.linalg.norm(blind[0][:3, 3] - truth[:3, 3]) > 0.008
    out = optimize_graph(nodes, [], GraphConfig(w_fs=0.0, w_cv=1.0, iterations=15), coverage=(0, cv))
    rot, trans = pose_error(out[0], truth)
    # The frame's points lie on its grid, 4 px apart at 640 px (2 mm here): the outermost stops within the margin.
    assert trans < 0.0035 and rot < 0.3
    hidden = MaskView(fs.view.edge, np.where(fs.view.edge.mask, fs.view.depth, 0.2).astype(np.float32), fs.view.K)
    cv = Coverage.of(frame_points, hidden, inv_T(truth), 1000)
    kept = optimize_graph(nodes, [], GraphConfig(w_fs=0.0, w_cv=1.0, iterations=15), coverage=(0, cv))
    assert np.linalg.norm(kept[0][:3, 3] - truth[:3, 3]) > 0.008
