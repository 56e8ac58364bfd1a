"""scripts/clutter_missed.py: where a policy's mesh of the clutter scene misses the ground truth (issue 10)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import open3d as o3d

from roigsf_ros.cli.scene import synth_intrinsics
from roigsf_ros.data.scene import dome_trajectory, render_sequence, synth_clutter
from roigsf_ros.evaluation.metrics import sample_surface

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "clutter_missed.py"
_spec = importlib.util.spec_from_file_location("clutter_missed", SCRIPT)
assert _spec is not None and _spec.loader is not None
cm = importlib.util.module_from_spec(_spec)
sys.modules["clutter_missed"] = cm
_spec.loader.exec_module(cm)


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
