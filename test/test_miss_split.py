"""scripts/miss_split.py: a pool bench's recall misses, split by part of the ground-truth scene (issue 10)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from conftest import load_script

from roigsf_ros.core.camera import Intrinsics
from roigsf_ros.data.scene import look_at, render_sequence
from roigsf_ros.data.sources import open_frames
from roigsf_ros.evaluation import gt_visible_mask, mesh_metrics

ms = load_script("miss_split")

INTR = Intrinsics(48, 36, 40.0, 40.0, 23.5, 17.5)
UP = np.array([0.0, 0.0, 1.0])
SAMPLES = 4000


def _bench(tmp_path: Path) -> tuple[Path, dict[str, float]]:
    """A floor plate (the largest part) with a box on it, seen from two poses; a bench with two runs: one whose
    mesh is the whole scene, one whose mesh is the box alone. Their recalls as the bench computes them."""
    floor = o3d.geometry.TriangleMesh.create_box(1.6, 1.6, 0.02).translate((-0.8, -0.8, -0.02))
    box = o3d.geometry.TriangleMesh.create_box(0.3, 0.3, 0.3).translate((-0.15, -0.15, 0.0))
    gt = floor + box
    scene = tmp_path / "scene"
    poses = np.stack([look_at(np.array([1.5, -1.2, 1.2]), np.zeros(3), UP),
                      look_at(np.array([-1.4, 1.3, 1.1]), np.zeros(3), UP)])  # fmt: skip
    render_sequence(gt, poses, INTR, scene, progress=False)
    o3d.io.write_triangle_mesh(str(scene / "mesh.ply"), gt)
    src = open_frames(scene)
    seen = np.stack([f.T_wc for f in src])
    bench = tmp_path / "bench"
    runs, recalls = [], {}
    for label, mesh in (("whole", gt), ("box-only", box)):
        d = bench / "runs" / label / "seed3"
        d.mkdir(parents=True)
        o3d.io.write_triangle_mesh(str(d / "mesh.ply"), mesh)
        observed = lambda p: gt_visible_mask(p, scene / "mesh.ply", seen, src.intrinsics)  # noqa: E731
        m = mesh_metrics(mesh, scene / "mesh.ply", n_samples=SAMPLES, seed=3, gt_point_filter=observed)
        recalls[label] = m["recall@5cm"]
        cfg = {"mesh_samples": SAMPLES, "cull_gt_to_observed": True}
        runs.append({"label": label, "seed": 3, "dir": f"runs/{label}/seed3", "metrics": {**m, "pool_config": cfg}})
    res = {"setting": "pool", "scene": str(scene), "gt_mesh": str(scene / "mesh.ply"), "size": None, "runs": runs}
    (bench / "results.json").write_text(json.dumps(res))
    return bench, recalls


def test_the_misses_of_a_mesh_without_its_floor_are_all_on_the_floor_away_from_the_box(tmp_path: Path) -> None:
    """The box-only mesh misses exactly the floor samples beyond 5 cm of the box: all on component c0 (the floor,
    the largest part), their median radius well out from the centre (the box reaches 0.21 m); the recall the split
    adds up to is the bench's; the whole mesh misses nothing.
    """
    bench, recalls = _bench(tmp_path)
    assert 0.05 < recalls["box-only"] < 0.8 and recalls["whole"] == 1.0
    out = tmp_path / "split.json"
    assert ms.main(["--out", str(out), str(bench)]) == 0
    got = json.loads(out.read_text())
    comps = got["benches"][0]["components"]
    assert comps[0]["bbox_min_m"][:2] == [-0.8, -0.8] and comps[0]["area_m2"] > comps[1]["area_m2"]
    rows = got["policies"]
    assert rows["whole"]["recall"] == 1.0 and rows["whole"]["c0"] == 0.0
    box_only = rows["box-only"]
    assert box_only["recall"] == pytest.approx(recalls["box-only"], abs=1e-9)
    assert box_only["c0"] == pytest.approx(1.0 - recalls["box-only"], abs=1e-9) and box_only["other"] == 0.0
    assert box_only["c0_radius_m"] > 0.4


def test_bad_benches_are_refused_naming_the_file(tmp_path: Path) -> None:
    """A recall that the meshes do not reproduce, a stream bench, a run without its folder, a truncated results.json
    and a folder without one are refused with one line naming the file.
    """
    bench, _ = _bench(tmp_path)
    res_path = bench / "results.json"
    res = json.loads(res_path.read_text())
    res["runs"][1]["metrics"]["recall@5cm"] += 0.01
    res_path.write_text(json.dumps(res))
    with pytest.raises(SystemExit, match=r"box-only/seed3/mesh.ply: recomputed recall"):
        ms.main([str(bench)])
    res_path.write_text(json.dumps({**res, "setting": "stream"}))
    with pytest.raises(SystemExit, match=r"results.json: setting is 'stream'"):
        ms.main([str(bench)])
    del res["runs"][0]["dir"]
    res_path.write_text(json.dumps(res))
    with pytest.raises(SystemExit, match=r"results.json: runs\[0\] has no field 'dir'"):
        ms.main([str(bench)])
    res_path.write_text(json.dumps(res)[:-20])
    with pytest.raises(SystemExit, match=r"results.json: not valid JSON"):
        ms.main([str(bench)])
    with pytest.raises(SystemExit, match=r"results\.json: not found"):
        ms.main([str(tmp_path)])
