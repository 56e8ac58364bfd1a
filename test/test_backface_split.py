"""scripts/backface_split.py: where the back-face test fires on a map, and what the keyframe test spares (issue 10)."""

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
from roigsf_ros.mapping.mapper import Mapper, MapperConfig

bs = load_script("backface_split")

INTR = Intrinsics(48, 36, 40.0, 40.0, 23.5, 17.5)
UP = np.array([0.0, 0.0, 1.0])


def test_a_thin_panel_seen_from_behind_is_at_the_surface_and_spared_once_a_keyframe_saw_it(tmp_path: Path) -> None:
    """A 2 cm panel, mapped from its front (which sees all of it): from behind, the map renders the front's surfels
    2 cm behind the true back face (within the 5 cm margin), so its back pixels lie "at the surface". The mapper seeds
    nothing from a keyframe behind it (within its densify margin), and that keyframe's render confirms them: spared
    with it, not without it. A folder that is no bench is refused with a one-line error naming it."""
    panel = o3d.geometry.TriangleMesh.create_box(0.02, 1.6, 1.2).translate((1.99, -0.8, 0.4))
    front = look_at(np.array([0.0, 0.0, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    back = look_at(np.array([3.2, 0.1, 1.0]), np.array([2.0, 0.0, 1.0]), UP)
    scene = tmp_path / "panel"
    render_sequence(panel, np.stack([front, back]), INTR, scene, progress=False)
    frames = list(open_frames(scene))
    bench = tmp_path / "bench"
    for name, views in (("front-only", frames[:1]), ("front-and-back", frames)):
        mapper = Mapper(INTR, MapperConfig())
        counts = []
        for f in views:
            assert mapper.add_keyframe(f, optimise=False)
            counts.append(mapper.n_surfels)
        assert counts[-1] == counts[0] > 0  # the view from behind seeded nothing
        mapper.save(bench / "runs" / name / "seed0")
    out = tmp_path / "split.json"
    assert bs.main(["--scene", str(scene), "--every", "1", "--out", str(out), str(bench)]) == 0
    table = json.loads(out.read_text())["policies"]
    for name in ("front-only", "front-and-back"):
        row = table[name]
        assert row["back"] > 0.3 and row["at_surface"] > 0.95 and row["behind"] == 0.0, row
    assert table["front-only"]["spared_at_surface"] == 0.0
    assert table["front-and-back"]["spared_at_surface"] > 0.95
    with pytest.raises(SystemExit, match="no such folder"):
        bs.main(["--scene", str(scene), str(tmp_path)])
