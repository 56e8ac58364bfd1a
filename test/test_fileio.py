"""Atomic outputs: replacing leaves nothing but the new output, whatever stood at the target before."""

from __future__ import annotations

from pathlib import Path

import pytest

from roigsf_ros.core.fileio import atomic_dir, atomic_path


def _write_dir(final: Path, overwrite: bool = True) -> None:
    with atomic_dir(final, overwrite=overwrite) as tmp:
        (tmp / "map.ply").write_text("new")


@pytest.mark.parametrize("old", ["file", "folder", "symlink"])
def test_overwrite_leaves_only_the_new_folder(tmp_path: Path, old: str) -> None:
    final = tmp_path / "map"
    if old == "file":  # e.g. save_map with overwrite onto a regular file
        final.write_text("old")
    elif old == "folder":
        final.mkdir()
        (final / "stale.json").write_text("{}")
    else:
        (tmp_path / "elsewhere").mkdir()
        final.symlink_to(tmp_path / "elsewhere")
    _write_dir(final)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != "elsewhere") == ["map"]  # no hidden .old
    assert final.is_dir() and not final.is_symlink() and [p.name for p in final.iterdir()] == ["map.ply"]
    if old == "symlink":
        assert (tmp_path / "elsewhere").is_dir()  # the link's target is not ours to delete


def test_failure_leaves_the_old_output_and_no_temporaries(tmp_path: Path) -> None:
    final = tmp_path / "map"
    final.write_text("old")
    with pytest.raises(RuntimeError), atomic_dir(final, overwrite=True):
        raise RuntimeError("half-way")
    assert final.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["map"]
    with pytest.raises(FileExistsError):
        _write_dir(final, overwrite=False)
    with pytest.raises(RuntimeError), atomic_path(tmp_path / "x.json"):
        raise RuntimeError("half-way")
    assert [p.name for p in tmp_path.iterdir()] == ["map"]
