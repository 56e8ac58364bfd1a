"""scripts/clutter_missed.py: where a policy's mesh of the clutter scene misses the ground truth (issue 10)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch
from conftest import load_script

from roigsf_ros.cli.scene import synth_intrinsics
from roigsf_ros.data.scene import dome_trajectory, render_sequence, synth_clutter
from roigsf_ros.data.sources import open_frames
from roigsf_ros.evaluation.metrics import sample_surface
from roigsf_ros.render.surfels import surfels_from_rgbd

cm = load_script("clutter_missed")


def test_the_parts_cover_the_four_cabinet_insides_and_the_box_block() -> None:
    """Every part holds samples; the insides are found in all four cabinets and lie inside the 0.8 m disc."""
    pts = sample_surface(synth_clutter(0), 40_000, 0)
    part = cm.regions(pts)
    assert set(part) == set(cm.REGIONS)
    inside = pts[part == "cabinet inside"]
    for axis, sign in ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)):  # one cabinet each way
        assert np.any(sign * inside[:, axis] > 0.47)
    assert np.all(np.linalg.norm(inside[:, :2], axis=1) < 0.8) and np.all(inside[:, 2] < 0.28)


def test_a_perfect_mesh_misses_nothing_and_the_disc_alone_misses_the_cabinets_and_boxes(tmp_path: Path) -> None:
    """Against the scene's own mesh nothing is missed; against the bare disc the walls and boxes are."""
    scene = tmp_path / "clutter"
    render_sequence(synth_clutter(0), dome_trajectory(12), synth_intrinsics(48, 36), scene, progress=False)
    bench = tmp_path / "bench"
    for name, mesh in (("perfect", synth_clutter(0)), ("disc", o3d.geometry.TriangleMesh.create_cylinder(0.8, 0.04))):
        (bench / "runs" / name / "seed0").mkdir(parents=True)
        o3d.io.write_triangle_mesh(str(bench / "runs" / name / "seed0" / "mesh.ply"), mesh)
    out = tmp_path / "missed.json"
    assert cm.main(["--scene", str(scene), "--samples", "5000", "--out", str(out), str(bench)]) == 0
    table = json.loads(out.read_text())["policies"]
    assert table["perfect"]["all"] == 0.0
    disc = table["disc"]  # the disc alone: it holds the cabinets' floors, not their walls, nor the boxes
    assert disc["cabinet inside"] > 0.5 and disc["box block"] > 0.8 and disc["other"] < 0.1, disc


def test_render_check_reports_fractions_and_names_a_missing_map(tmp_path: Path) -> None:
    """--render-check renders each run's map.ply: a map made from one view yields fractions in [0, 1]; a run without
    its map.ply, or a folder that is no bench, is refused with a one-line error naming the path."""
    scene = tmp_path / "clutter"
    render_sequence(synth_clutter(0), dome_trajectory(12), synth_intrinsics(48, 36), scene, progress=False)
    source = open_frames(scene)
    frame = next(iter(source))
    run = tmp_path / "bench" / "runs" / "one-view" / "seed0"
    run.mkdir(parents=True)
    o3d.io.write_triangle_mesh(str(run / "mesh.ply"), synth_clutter(0))
    with pytest.raises(SystemExit, match=r"map\.ply: no such file"):
        cm.main(["--scene", str(scene), "--samples", "2000", "--render-check", str(tmp_path / "bench")])
    with pytest.raises(SystemExit, match="no such folder"):
        cm.main(["--scene", str(scene), str(tmp_path)])
    surfel_map = surfels_from_rgbd(frame.rgb, frame.depth_m, frame.T_wc, source.intrinsics, dtype=torch.float32)
    surfel_map.save_ply(run / "map.ply")
    out = tmp_path / "missed.json"
    args = ["--scene", str(scene), "--samples", "2000", "--render-check", "--out", str(out), str(tmp_path / "bench")]
    assert cm.main(args) == 0
    row = json.loads(out.read_text())["policies"]["one-view"]
    assert 0.0 <= row["inside_alpha_below_half"] <= 1.0 and 0.0 <= row["inside_seen_through"] <= 1.0
