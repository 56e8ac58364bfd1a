"""Observed novelty (stream setting, beyond the paper): the hash-set count against a k-d tree, and its meaning."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from roigsf_ros.core.camera import Intrinsics, depth_points_w
from roigsf_ros.core.errors import InputError
from roigsf_ros.nbv.novelty import ObservedSurface, unique_voxels, unreached_by_each, unreached_by_each_plain

INTR = Intrinsics(width=64, height=48, fx=160.0, fy=160.0, cx=31.5, cy=23.5)  # 1.3 cm pixels at 2 m


def reference_new_voxels(added: list[np.ndarray], query: np.ndarray, voxel_m: float, radius_m: float) -> int:
    """Distinct voxels of ``query`` whose centre is farther than radius + voxel / 2 from every added voxel's centre."""
    q = np.unique(np.floor(query / voxel_m).astype(np.int64), axis=0)
    if not added:
        return len(q)
    a = np.unique(np.floor(np.concatenate(added) / voxel_m).astype(np.int64), axis=0)
    dist, _ = cKDTree(a.astype(np.float64)).query(q.astype(np.float64), k=1)
    return int(np.count_nonzero(dist > (radius_m + 0.5 * voxel_m) / voxel_m + 1e-9))


@pytest.mark.parametrize(("voxel_m", "radius_m"), [(0.025, 0.05), (0.05, 0.05), (0.1, 0.0), (0.03, 0.1)])
def test_new_voxels_equal_a_kd_tree_reference(voxel_m: float, radius_m: float) -> None:
    rng = np.random.default_rng(5)
    clouds = [c + rng.normal(0.0, 0.15, (800, 3)) for c in rng.uniform(-1.0, 1.0, (4, 3))]
    surface = ObservedSurface(voxel_m, radius_m)
    assert surface.new_voxels(clouds[3]) == reference_new_voxels([], clouds[3], voxel_m, radius_m)  # nothing added
    for k in range(3):
        surface.add_points(clouds[k])
        for q in (clouds[3], clouds[k] + 0.04, rng.uniform(-1.5, 1.5, (500, 3))):
            assert surface.new_voxels(q) == reference_new_voxels(clouds[: k + 1], q, voxel_m, radius_m)
    assert surface.n_added == 3
    assert surface.new_voxels(clouds[1]) == 0  # what was added is not new
    q = np.concatenate([clouds[3], clouds[3][:100]])  # points, not voxels: repeats count
    a = np.unique(np.floor(np.concatenate(clouds[:3]) / voxel_m), axis=0)
    dist, _ = cKDTree(a).query(np.floor(q / voxel_m), k=1)
    assert surface.unreached_points(q) == np.count_nonzero(dist > (radius_m + 0.5 * voxel_m) / voxel_m + 1e-9)


def test_the_hash_set_in_small_chunks_holds_and_finds_the_same() -> None:
    """Inserts and lookups go into open3d's hash set in chunks (each call holds Python's lock), from a capacity large
    enough not to rehash: chunks of 97 rows from a small set that grows give the k-d tree reference's counts too."""
    rng = np.random.default_rng(8)
    clouds = [c + rng.normal(0.0, 0.15, (800, 3)) for c in rng.uniform(-1.0, 1.0, (3, 3))]
    counts = []
    for kwargs in ({}, {"hash_capacity": 64, "hash_chunk_rows": 97}):
        surface = ObservedSurface(0.025, 0.05, **kwargs)
        surface.add_points(clouds[0])
        surface.add_points(clouds[1])
        counts.append((surface.new_voxels(clouds[2]), surface.unreached_points(clouds[2])))
    assert counts[0] == counts[1] and counts[0][0] == reference_new_voxels(clouds[:2], clouds[2], 0.025, 0.05)
    with pytest.raises(InputError, match="hash_chunk_rows"):
        ObservedSurface(hash_chunk_rows=0)


@pytest.mark.parametrize(("voxel_m", "radius_m"), [(0.025, 0.05), (0.1, 0.0), (0.03, 0.1)])
def test_lookahead_new_voxels_equal_a_kd_tree_reference(voxel_m: float, radius_m: float) -> None:
    """Each candidate's new voxels plus the most one frame ahead still adds after it, against the k-d tree count."""
    rng = np.random.default_rng(8)
    centres = rng.uniform(-0.6, 0.6, (7, 3))
    clouds = [c + rng.normal(0.0, 0.2, (600, 3)) for c in centres]
    surface = ObservedSurface(voxel_m, radius_m)
    surface.add_points(clouds[0])
    cands, ahead = [clouds[1], clouds[2], clouds[3], np.zeros((0, 3))], [clouds[4], clouds[5], clouds[1] + 0.02]
    got = surface.lookahead_new_voxels(cands, ahead)
    ref = [reference_new_voxels(clouds[:1], c, voxel_m, radius_m)
           + max(reference_new_voxels([clouds[0], c], g, voxel_m, radius_m) for g in ahead) for c in cands]  # fmt: skip
    np.testing.assert_array_equal(got, ref)
    plain = [surface.new_voxels(c) for c in cands]
    np.testing.assert_array_equal(surface.lookahead_new_voxels(cands, []), plain)  # nothing ahead: the novelty
    assert np.all(got >= plain)


def test_unreached_by_each_equals_the_plain_k_d_tree_path() -> None:
    """The bit-mask pass counts, for every candidate and frame ahead, what a k-d tree per candidate counts: across a
    64-candidate chunk boundary, with an empty candidate, an empty frame ahead, a candidate outside the box of the
    frames ahead, and for a box too large to pack (the plain path then)."""
    rng = np.random.default_rng(11)
    reach = ObservedSurface(0.025, 0.05)._offsets  # the lattice ball of radius 2.5 voxels
    blob = lambda c, n: unique_voxels(np.rint(c + rng.normal(0.0, 4.0, (n, 3))).astype(np.int32))  # noqa: E731
    centres = rng.integers(-20, 20, (8, 3))
    cand = [blob(centres[k % 8], 150) for k in range(69)]
    cand[3] = np.zeros((0, 3), np.int32)
    cand[5] = blob(np.array([500, 500, 500]), 100)  # reaches nothing ahead
    ahead = [blob(centres[k], 200) for k in (0, 2, 7)] + [np.zeros((0, 3), np.int32), blob(centres[1] + 3, 200)]
    got = unreached_by_each(cand, ahead, reach)
    want = unreached_by_each_plain(cand, ahead, reach)
    np.testing.assert_array_equal(got, want)
    assert got.shape == (69, 5) and got[3].tolist() == [len(a) for a in ahead] == got[5].tolist()
    assert got.min() < got.max()  # some candidates reach some voxels ahead, not all
    big = 1 << 29
    far = [np.array([[big, big, big], [big + 2, big, big]]), np.array([[-big, -big, -big]])]  # 2^90 voxels: unpacked
    mixed = [*ahead[:1], *far]
    plain = unreached_by_each_plain(cand[:4], mixed, reach)
    np.testing.assert_array_equal(unreached_by_each(cand[:4], mixed, reach), plain)
    np.testing.assert_array_equal(unreached_by_each([far[0][:1]], far, reach), [[0, 1]])


def test_unique_voxels_are_numpys_distinct_rows() -> None:
    rng = np.random.default_rng(4)
    shifted = rng.integers(-3, 3, (200, 3)) + np.array([10**8, -(10**8), 5])
    huge = np.array([[2**30 - 1, -(2**30), 0], [-(2**30), 2**30 - 1, 7]] * 3)  # a box too large to pack
    for ijk in (rng.integers(-30, 30, (500, 3)), shifted, np.zeros((0, 3), np.int64), huge):
        got = unique_voxels(ijk)
        assert got.dtype == np.int32
        np.testing.assert_array_equal(got, np.unique(np.asarray(ijk).reshape(-1, 3), axis=0))


def test_lookahead_leaves_surface_a_later_frame_shows_to_it() -> None:
    """Two walls: the larger one a later frame also shows, the smaller one only this window shows."""

    def patch(x0: float, x1: float) -> np.ndarray:
        x, z = np.meshgrid(np.arange(x0, x1, 0.01), np.arange(0.0, 1.0, 0.01))
        return np.stack([x.ravel(), np.full(x.size, 2.0), z.ravel()], axis=1)

    surface = ObservedSurface(0.025, 0.05)
    seen_later, only_now = patch(0.0, 1.0), patch(3.0, 3.8)
    later = patch(0.0, 1.5)
    plain = surface.lookahead_new_voxels([seen_later, only_now], [])
    assert np.argmax(plain) == 0  # the larger wall has more new surface
    with_ahead = surface.lookahead_new_voxels([seen_later, only_now], [later])
    assert np.argmax(with_ahead) == 1  # but the pair (small wall, later frame) shows more
    assert with_ahead[1] == plain[1] + surface.new_voxels(later)


def reference_held_pixels(added: list[np.ndarray], cands: list[np.ndarray], ahead: list[np.ndarray], voxel_m: float,
                          radius_m: float) -> list[int]:  # fmt: skip
    """Pixel by pixel: a held pixel is uncovered when its voxel is out of reach of every added voxel; a frame covers
    it when one of the frame's voxels is within reach; each candidate's count with the best frame ahead."""
    reach = (radius_m + 0.5 * voxel_m) / voxel_m + 1e-9

    def within(pix: np.ndarray, frames: list[np.ndarray]) -> np.ndarray:
        out = np.zeros(len(pix), dtype=bool)
        for f in frames:
            if len(f):
                d, _ = cKDTree(np.floor(f / voxel_m)).query(pix, k=1)
                out |= d <= reach
        return out

    pix = np.floor(np.concatenate([*cands, *ahead]) / voxel_m)
    pix = pix[~within(pix, added)]
    return [int(within(pix, [c]).sum()) + max([int((within(pix, [g]) & ~within(pix, [c])).sum()) for g in ahead],
                                              default=0) for c in cands]  # fmt: skip


@pytest.mark.parametrize(("voxel_m", "radius_m"), [(0.025, 0.05), (0.1, 0.0), (0.03, 0.1)])
def test_held_pixels_covered_equal_a_pixel_by_pixel_reference(voxel_m: float, radius_m: float) -> None:
    rng = np.random.default_rng(9)
    clouds = [c + rng.normal(0.0, 0.2, (500, 3)) for c in rng.uniform(-0.6, 0.6, (6, 3))]
    clouds[4] = np.concatenate([clouds[4], np.repeat(clouds[4][:50], 3, axis=0)])  # pixels sharing voxels count each
    surface = ObservedSurface(voxel_m, radius_m, measure="pixels")
    cands, ahead = [clouds[1], clouds[2], np.zeros((0, 3))], [clouds[3], clouds[4], clouds[1] + 0.02]
    np.testing.assert_array_equal(surface.held_pixels_covered(cands, ahead),
                                  reference_held_pixels([], cands, ahead, voxel_m, radius_m))  # fmt: skip
    added = [clouds[0], clouds[5]]
    for c in added:
        surface.add_points(c)
    np.testing.assert_array_equal(surface.held_pixels_covered(cands, ahead),
                                  reference_held_pixels(added, cands, ahead, voxel_m, radius_m))  # fmt: skip
    np.testing.assert_array_equal(surface.held_pixels_covered(cands, []),
                                  reference_held_pixels(added, cands, [], voxel_m, radius_m))  # fmt: skip


def test_held_pixels_weigh_surface_the_held_frames_look_at() -> None:
    """Two new walls of equal area: the one the other held frames also look at wins by pixels, ties by area."""

    def patch(x0: float, x1: float, step: float = 0.01) -> np.ndarray:
        x, z = np.meshgrid(np.arange(x0, x1, step), np.arange(0.0, 1.0, step))
        return np.stack([x.ravel(), np.full(x.size, 2.0), z.ravel()], axis=1)

    looked_at, glimpsed = patch(0.0, 1.0), patch(3.0, 4.0)
    others = [patch(0.0, 1.0, 0.005), patch(0.2, 0.8, 0.005)]  # two more held frames, nearer: more pixels there
    area = ObservedSurface(0.025, 0.05).lookahead_new_voxels([looked_at, glimpsed], [])
    assert area[0] == area[1]
    pixels = ObservedSurface(0.025, 0.05, measure="pixels").held_pixels_covered([looked_at, glimpsed, *others], [])
    assert pixels[0] > 4 * pixels[1]  # the wall the held frames look at: its pixels in three frames, not one
    assert pixels[1] == len(glimpsed)


def plane_depth(z_m: float) -> np.ndarray:
    return np.full((INTR.height, INTR.width), z_m, dtype=np.float32)


def test_novelty_is_the_area_of_surface_no_keyframe_observed() -> None:
    """A fronto-parallel wall: its area before any keyframe, none once seen, about half after a half-view pan."""
    z = 2.0125  # mid-voxel, so the wall is one voxel thick
    valid = np.ones((INTR.height, INTR.width), dtype=bool)
    T0 = np.eye(4)
    area = (INTR.width / INTR.fx * z) * (INTR.height / INTR.fy * z)  # 0.80 x 0.60 m
    surface = ObservedSurface(0.025, 0.05)
    assert surface.new_area_m2(plane_depth(z), T0, INTR, valid) == pytest.approx(area, rel=0.05)
    surface.add(plane_depth(z), T0, INTR, valid)
    assert surface.new_area_m2(plane_depth(z), T0, INTR, valid) == 0.0
    assert surface.new_area_m2(plane_depth(z + 0.03), T0, INTR, valid) == 0.0  # within 5 cm: observed
    assert surface.new_area_m2(plane_depth(z + 0.2), T0, INTR, valid) == pytest.approx(
        area * ((z + 0.2) / z) ** 2, rel=0.05
    )
    T1 = np.eye(4)
    T1[0, 3] = 0.5 * INTR.width / INTR.fx * z  # pan by half the wall: new, the half less the 6.25 cm reached
    new_half = (0.5 * INTR.width / INTR.fx * z - 0.0625) * (INTR.height / INTR.fy * z)
    assert surface.new_area_m2(plane_depth(z), T1, INTR, valid) == pytest.approx(new_half, rel=0.1)
    half = valid.copy()
    half[:, : INTR.width // 2] = False  # only the valid pixels count
    assert surface.new_area_m2(plane_depth(z), T1, INTR, half) == pytest.approx(new_half, rel=0.1)
    assert surface.new_area_m2(plane_depth(z), T1, INTR, ~half) == pytest.approx(0.0, abs=0.02 * area)


def test_depth_points_are_the_back_projected_valid_pixels() -> None:
    T = np.eye(4)
    T[:3, 3] = (1.0, -2.0, 0.5)
    depth = plane_depth(1.5)
    valid = np.zeros(depth.shape, dtype=bool)
    valid[10, 20] = valid[47, 0] = True
    pts = depth_points_w(depth, T, INTR, valid)
    expected = [[(20 - INTR.cx) / INTR.fx * 1.5, (10 - INTR.cy) / INTR.fy * 1.5, 1.5],
                [(0 - INTR.cx) / INTR.fx * 1.5, (47 - INTR.cy) / INTR.fy * 1.5, 1.5]]  # fmt: skip
    np.testing.assert_allclose(pts, np.array(expected) + T[:3, 3], atol=1e-12)


def test_bad_input_names_the_field() -> None:
    with pytest.raises(InputError, match="novelty_voxel_m"):
        ObservedSurface(0.0)
    with pytest.raises(InputError, match="novelty_radius_m"):
        ObservedSurface(0.025, float("nan"))
    with pytest.raises(InputError, match=r"novelty_measure.*area, pixels"):
        ObservedSurface(measure="volume")
    surface = ObservedSurface()
    with pytest.raises(InputError, match="points_w"):
        surface.add_points(np.array([[0.0, np.inf, 0.0]]))
    with pytest.raises(InputError, match=r"points_w.*from the origin"):
        surface.new_voxels(np.array([[3.0e7, 0.0, 0.0]]))
    with pytest.raises(InputError, match="depth_m"):
        surface.new_area_m2(np.ones((4, 4)), np.eye(4), INTR, np.ones((4, 4), dtype=bool))
    with pytest.raises(InputError, match="T_wc"):
        surface.add(plane_depth(1.0), np.zeros((4, 4)), INTR, np.ones((INTR.height, INTR.width), dtype=bool))
    assert surface.n_added == 0 and surface.new_voxels(np.zeros((0, 3))) == 0


def test_perf_novelty_finds_the_fast_counts_equal_on_the_shipped_bag(tmp_path, capsys) -> None:
    """``roigsf perf novelty`` on real frames: a window of 66 candidates (two bit-mask chunks) with 20 frames ahead,
    the fast counts equal to the plain ones, and the JSON written; too few frames is a one-line error."""
    import json
    from pathlib import Path

    from roigsf_ros.cli import main

    bag = Path(__file__).resolve().parents[1] / "bags" / "synth_room"
    out = tmp_path / "novelty.json"
    args = ["perf", "novelty", "--bag", str(bag), "--repeats", "1"]
    assert main([*args, "--window", "66", "--lookahead", "20", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert [w["first_frame"] for w in data["windows"]] == [1] and data["summary"]["all_equal"]
    assert data["windows"][0]["fast_s"] > 0 and data["windows"][0]["plain_s"] > 0
    capsys.readouterr()
    assert main([*args, "--window", "100", "--lookahead", "100"]) == 2
    err = capsys.readouterr().err  # it blamed --bag for the window's size
    assert "--window/--lookahead: need 201 frames (1 + window 100 + lookahead 100), the bag has 150" in err, err
    assert main([*args, "--window", "0"]) == 2
    assert "--window: must be at least 1, got 0" in capsys.readouterr().err
