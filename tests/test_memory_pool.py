"""Posture memory pool: the keyframe add rule, the cap and its retention policy, view-overlap selection."""

from __future__ import annotations

import numpy as np

from surgtrack.config import PoolConfig
from surgtrack.features import Features
from surgtrack.geometry import make_T, so3_exp
from surgtrack.memory_pool import Keyframe, MemoryPool


def keyframe(name: str, axis: np.ndarray, deg: float) -> Keyframe:
    pose = make_T(so3_exp(np.asarray(axis, float) / np.linalg.norm(axis) * np.radians(deg)), [0, 0, 0.4])
    empty = Features(np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros((0, 3)), np.zeros((0, 3)))
    grid = np.zeros((4, 4, 3))
    return Keyframe(name, pose, empty, grid, grid, np.eye(3), np.zeros((8, 8)), np.zeros((8, 8), bool), np.eye(3))


def test_keyframe_added_only_when_rotation_differs_enough():
    pool = MemoryPool(PoolConfig(keyframe_rot_deg=5.0))
    pool.add(keyframe("0", [0, 1, 0], 0))
    assert not pool.should_add(keyframe("1", [0, 1, 0], 4.0).pose)  # 4 deg from the only keyframe
    assert pool.should_add(keyframe("1", [0, 1, 0], 6.0).pose)
    pool.add(keyframe("1", [0, 1, 0], 6.0))
    assert not pool.should_add(keyframe("2", [0, 1, 0], 9.0).pose)  # 3 deg from keyframe 1
    assert pool.should_add(keyframe("2", [1, 0, 0], 5.5).pose)  # 5.5 deg from 0, more from 1


def test_cap_drops_most_redundant_view_and_keeps_first():
    pool = MemoryPool(PoolConfig(max_size=4))
    for i, deg in enumerate([0, 30, 60, 61, 90]):
        pool.add(keyframe(str(i), [0, 1, 0], deg))
    names = [k.frame_id for k in pool.keyframes]
    assert len(names) == 4
    assert names[0] == "0"
    assert ("2" in names) != ("3" in names)  # one of the two near-identical views went


def test_select_prefers_overlapping_views_within_limit():
    pool = MemoryPool(PoolConfig(overlap_normal_deg=70.0))
    for i, deg in enumerate([0, 20, 50, 100, 170]):
        pool.add(keyframe(str(i), [0, 1, 0], deg))
    current = keyframe("c", [0, 1, 0], 45).pose
    chosen = [k.frame_id for k in pool.select(current, 3)]
    assert chosen == ["2", "1", "0"]  # nearest viewing direction first
    assert [k.frame_id for k in pool.select(current, 10)] == ["2", "1", "0", "3"]
