"""ObservedSpace: the grid of unknown / free / occupied cells the carved unseen term reads (issue 10)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.core.errors import InputError
from roigsf_ros.mapping import observed_space as osp
from roigsf_ros.mapping.observed_space import FREE, OCCUPIED, UNKNOWN, ObservedSpace

INTR = Intrinsics(width=80, height=60, fx=60.0, fy=60.0, cx=39.5, cy=29.5)
LO, HI = np.array([-2.0, -2.0, 0.5]), np.array([2.0, 2.0, 3.0])
"""A box from z = 0.5 to 3 in front of a camera at the origin looking down +z."""


def pose(x: float = 0.0, z: float = 0.0, back: bool = False) -> np.ndarray:
    """Camera at (x, 0, z) looking down +z, or down -z with ``back`` (x flipped to keep a right-handed frame)."""
    T = np.eye(4)
    if back:
        T[:3, :3] = np.diag([-1.0, 1.0, -1.0])
    T[0, 3], T[2, 3] = x, z
    return T


def wall(z: float = 2.0) -> np.ndarray:
    """One depth map [1, H, W]: every pixel sees a wall at camera depth ``z``."""
    return np.full((1, INTR.height, INTR.width), z)


def test_a_wall_seen_from_the_front_is_seen_and_its_back_is_unseen() -> None:
    """The keyframe's own view reaches the wall through carved free space (no unseen pixel); from behind the wall
    every ray meets unknown space, which ends where the wall's occupied band (the cell at 2-2.05 m) starts."""
    space = ObservedSpace.carve(LO, HI, 0.05, [pose()], wall(), INTR)
    counts = space.counts()
    assert counts["free"] > 0 and counts["occupied"] > 0 and sum(counts.values()) == space.state.size
    enter, leave = space.unseen_depths(pose(), INTR, 0.1, 10.0)
    assert not enter.any() and not leave.any()
    enter, leave = space.unseen_depths(pose(z=2.8, back=True), INTR, 0.1, 10.0)
    c = (INTR.height // 2, INTR.width // 2)
    assert (enter > 0).all() and enter[c] == pytest.approx(0.1)
    assert leave[c] == pytest.approx(2.8 - 2.05, abs=0.03)  # steps of half a cell
    i, j, k = np.floor((np.array([0.0, 0.0, 2.02]) - LO) / 0.05).astype(int)
    assert space.state[i, j, k] == OCCUPIED and space.state[i, j, k - 4] == FREE
    assert space.state[i, j, k + 5] == UNKNOWN  # behind the wall: never observed


def test_unknown_space_crossed_before_observed_free_space_does_not_count() -> None:
    """A camera 1 m to the side sees the wall through space the keyframe never looked through (outside its cone
    near the camera) and then through space it carved: its centre ray is seen. The same ray from a grid that nothing
    carved is unseen from the box's entry on."""
    space = ObservedSpace.carve(LO, HI, 0.05, [pose()], wall(), INTR)
    side = pose(x=1.0)
    enter, _ = space.unseen_depths(side, INTR, 0.1, 10.0)
    c = (INTR.height // 2, INTR.width // 2)
    assert enter[c] == 0.0  # x = 1 enters the keyframe's cone (half-width 2/3 z) at z = 1.5, before the wall
    empty = ObservedSpace.carve(LO, HI, 0.05, np.zeros((0, 4, 4)), np.zeros((0, INTR.height, INTR.width)), INTR)
    e2, l2 = empty.unseen_depths(side, INTR, 0.1, 10.0)
    assert e2[c] == pytest.approx(0.5) and l2[c] == pytest.approx(3.0)  # the box's near and far faces
    assert empty.counts()["unknown"] == empty.state.size


def test_rays_that_met_nothing_carve_free_space_up_to_far() -> None:
    """A keyframe depth of inf (the map renders nothing there) carves free space up to ``far_m`` and marks nothing
    occupied; 0 and nan carve nothing. So a later view through that space reaches the box's side through free
    space (seen), and beyond ``far_m`` the space stays unknown."""
    miss = np.full((1, INTR.height, INTR.width), np.inf)
    space = ObservedSpace.carve(LO, HI, 0.05, [pose()], miss, INTR, far_m=2.0)
    assert space.counts()["occupied"] == 0
    enter, _ = space.unseen_depths(pose(), INTR, 0.1, 1.9)
    assert not enter.any()
    enter, _ = space.unseen_depths(pose(), INTR, 0.1, 10.0)
    assert enter[INTR.height // 2, INTR.width // 2] == pytest.approx(2.05, abs=0.03)  # past far's cell: unknown
    none = np.zeros((1, INTR.height, INTR.width))
    none[0, :10] = np.nan
    nothing = ObservedSpace.carve(LO, HI, 0.05, [pose()], none, INTR)
    assert nothing.counts()["unknown"] == nothing.state.size


def test_the_frontier_count_is_the_boundary_a_view_looks_at_each_cell_once() -> None:
    """A keyframe whose rays met nothing carves free space up to 2 m; beyond lies unknown space. From the keyframe's
    pose and from 1 m nearer, every pixel is unseen (the pixel fractions tie), but the nearer view looks at a quarter
    of the frontier: the cell count (``NBVConfig.unseen_measure="cells"``) is the frontier's area over the cell's
    (a staircase of cells, a little more than the plane's), and with 4x the pixels it grows by under 10 %."""
    miss = np.full((1, INTR.height, INTR.width), np.inf)
    space = ObservedSpace.carve(LO, HI, 0.05, [pose()], miss, INTR, far_m=2.0)
    enter_far, far = space.unseen_frontier(pose(), INTR, 0.1, 10.0)
    enter_near, near = space.unseen_frontier(pose(z=1.0), INTR, 0.1, 10.0)
    assert (enter_far > 0).all() and (enter_near > 0).all()
    width, height = 2.0 * INTR.width / INTR.fx, 2.0 * INTR.height / INTR.fy  # the frustum at the frontier, 2 m
    assert len(far) == pytest.approx(width * height / 0.05**2, rel=0.15)
    assert 3.0 < len(far) / len(near) < 5.0
    fine = Intrinsics(width=160, height=120, fx=120.0, fy=120.0, cx=79.5, cy=59.5)
    _, far_fine = space.unseen_frontier(pose(), fine, 0.1, 10.0)
    assert len(far) <= len(far_fine) < 1.1 * len(far)
    assert np.isin(far, far_fine).mean() > 0.95


def test_the_ray_measure_weighs_each_unseen_pixel_by_the_unknown_space_it_crosses() -> None:
    """``NBVConfig.unseen_measure="rays"`` (the volumetric gain's unknown voxels per ray): two views of a wall's
    back, from 0.25 m and 0.85 m behind it, are all unseen (the pixel fractions tie at 1), but past ``near_m`` (0.1 m)
    the far one's rays cross about 0.75 m of unknown space and the near one's 0.15 m: the ray measure is that length
    in cells."""
    from roigsf_ros.nbv.config import NBVConfig
    from roigsf_ros.nbv.unseen import UnseenTerm

    space = ObservedSpace.carve(LO, HI, 0.05, [pose()], wall(), INTR)
    cfg = NBVConfig(unseen_weight=1.0, unseen_source="carved", unseen_voxel_m=0.05, near_m=0.1)
    measured = {}
    for kind in ("pixels", "rays"):
        term = UnseenTerm(replace(cfg, unseen_measure=kind), (LO, HI), None, None, space, None)
        measured[kind] = [term.measure(None, pose(z=2.05 + d, back=True), 0, INTR) for d in (0.25, 0.85)]
    assert measured["pixels"] == pytest.approx([1.0, 1.0])
    near, far = measured["rays"]
    assert near == pytest.approx((0.25 - 0.1) / 0.05, abs=1.0) and far == pytest.approx((0.85 - 0.1) / 0.05, abs=1.0)


def test_numba_kernels_match_the_plain_python_ones() -> None:
    """The compiled carve and query give exactly what the same loops give interpreted, on two keyframes with holes
    and a tilted wall, so the numba path is checked against a plain reference (as every fast path here)."""
    rng = np.random.default_rng(3)
    small = Intrinsics(width=24, height=18, fx=18.0, fy=18.0, cx=11.5, cy=8.5)
    depth = 1.5 + 0.5 * rng.random((2, 18, 24))
    depth[0, :3] = 0.0
    depth[1, 5:7] = np.inf
    poses = np.stack([pose(), pose(x=0.4)])
    fast = ObservedSpace.carve(LO, HI, 0.1, poses, depth, small, far_m=2.5)
    ref = np.zeros_like(fast.state)
    for occupied in (False, True):
        osp._k_carve(ref, poses, depth, LO, 0.1, small.fx, small.fy, small.cx, small.cy, 2.5, occupied)
    np.testing.assert_array_equal(fast.state, ref)
    assert len(np.unique(ref)) == 3
    enter, leave = fast.unseen_depths(pose(x=-0.7), small, 0.1, 10.0)
    e_ref, l_ref = np.zeros_like(enter), np.zeros_like(leave)
    c_ref = np.zeros(enter.shape, dtype=np.int64)
    osp._k_unseen(ref, pose(x=-0.7), LO, 0.1, small.fx, small.fy, small.cx, small.cy, 0.1, 10.0, e_ref, l_ref, c_ref)
    np.testing.assert_array_equal(enter, e_ref)
    np.testing.assert_array_equal(leave, l_ref)
    assert 0 < (enter > 0).mean() < 1
    _, cells = fast.unseen_frontier(pose(x=-0.7), small, 0.1, 10.0)
    np.testing.assert_array_equal(cells, np.unique(c_ref[c_ref >= 0]))
    assert ((c_ref >= 0) == (enter > 0)).all() and 0 < len(cells) < (enter > 0).sum()


def test_carving_in_parts_gives_the_grid_carving_at_once_gives() -> None:
    """A cell ends occupied where any ray ended, else free where any passed, so carving keyframes one part at a time
    (a planner adding each new keyframe) gives, cell for cell, the grid carving them all at once gives, in any order
    of the parts: walls at several depths from several places, with holes (0), nan and misses (inf)."""
    rng = np.random.default_rng(3)
    poses = np.stack([pose(x=x, z=z, back=b) for x, z, b in ((0.0, 0.0, False), (0.6, 0.2, False),
                                                             (-0.5, 2.9, True), (0.3, 0.4, False))])  # fmt: skip
    depth = np.concatenate([wall(z) for z in (2.0, 1.2, 1.5, 2.3)]) + rng.uniform(-0.1, 0.1, (4, 60, 80))
    depth[0, :5] = 0.0
    depth[1, 10:20, 30:40] = np.inf
    depth[2, :, :7] = np.nan
    whole = ObservedSpace.carve(LO, HI, 0.05, poses, depth, INTR, far_m=2.5)
    assert min(whole.counts().values()) > 0
    for parts in ([0, 1], [2], [3]), ([3], [1, 2], [0]), ([2, 0, 1, 3],):
        space = ObservedSpace.empty(LO, HI, 0.05)
        for part in parts:
            space.carve_more(poses[part], depth[part], INTR, far_m=2.5)
        np.testing.assert_array_equal(space.state, whole.state)
    with pytest.raises(InputError, match="depth_m"):
        space.carve_more(poses[:2], depth[:1], INTR)


def test_bad_grids_are_refused_naming_the_field() -> None:
    with pytest.raises(InputError, match="voxel_m"):
        ObservedSpace.carve(LO, HI, 0.0, [pose()], wall(), INTR)
    with pytest.raises(InputError, match="box"):
        ObservedSpace.carve(HI, LO, 0.05, [pose()], wall(), INTR)
    with pytest.raises(InputError, match="voxel_m"):
        ObservedSpace.carve(LO, HI, 1e-4, [pose()], wall(), INTR)  # 4e10 cells
    with pytest.raises(InputError, match="depth_m"):
        ObservedSpace.carve(LO, HI, 0.05, [pose(), pose()], wall(), INTR)


def test_a_slot_no_keyframe_looked_into_is_unseen_only_with_cells_under_half_its_width() -> None:
    """A wall at 2 m with a 6 cm slot no keyframe looked into (depth 0 there). With 5 cm cells the cells the slot
    falls in also hold the wall's edges, so they are occupied and a ray down the slot stops there, seen: the slot
    hides. With 2.5 cm cells (the default, ``NBVConfig.unseen_voxel_m``) the slot's cells hold no wall, and the rays
    down it meet unknown space up to the box's far side. The cluttered objects' gaps of 8 cm are the case."""
    from roigsf_ros.nbv.config import NBVConfig

    intr = Intrinsics(width=200, height=20, fx=600.0, fy=600.0, cx=99.5, cy=9.5)
    x_at_wall = (np.arange(intr.width) - intr.cx) / intr.fx * 2.0
    slot = np.abs(x_at_wall) < 0.03
    depth = np.broadcast_to(np.where(slot, 0.0, 2.0), (1, intr.height, intr.width))
    r = intr.height // 2
    coarse = ObservedSpace.carve(LO, HI, 0.05, [pose()], depth, intr)
    enter, _ = coarse.unseen_depths(pose(), intr, 0.1, 10.0)
    assert not enter[r].any()
    cell = NBVConfig().unseen_voxel_m
    assert cell <= 0.025
    fine = ObservedSpace.carve(LO, HI, cell, [pose()], depth, intr)
    enter, leave = fine.unseen_depths(pose(), intr, 0.1, 10.0)
    centre = slot & (np.abs(x_at_wall) < 0.02)  # rays whose cells lie wholly inside the slot
    assert (enter[r, centre] > 0).all() and (enter[r, centre] < 2.0).all()
    np.testing.assert_allclose(leave[r, centre], 3.0)  # the box's far face
    assert not enter[r, ~slot].any()  # the wall itself stays seen
