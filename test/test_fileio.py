"""Atomic outputs: replacing leaves nothing but the new output, whatever stood at the target before; JSON reads."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import (
    atomic_dir,
    atomic_path,
    check_replaceable,
    check_run_output,
    check_writable,
    deferred_interrupts,
    read_json,
    write_json,
)


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


def test_overwrite_never_deletes_an_input_or_a_folder_of_other_things(tmp_path: Path) -> None:
    """``roigsf bench --scene X --out X --overwrite`` deleted the scene it had benchmarked, and ``--overwrite`` on a
    mistyped ``--out`` any folder: with ``inputs`` an output holding one is refused, and with ``marks`` only an earlier
    output of the same kind (or an empty folder) is replaced; whatever stood there stays as it was."""
    scene = tmp_path / "work" / "scene"
    scene.mkdir(parents=True)
    (scene / "traj.txt").write_text("poses")
    (tmp_path / "work" / "notes.txt").write_text("mine")
    for out in (scene, tmp_path / "work"):  # the input itself, and a folder above it
        with (
            pytest.raises(InputError, match="which this command reads: writing there would delete it"),
            atomic_dir(out, overwrite=True, marks=("results.json",), what="a bench's output", inputs=[scene]),
        ):
            pass
    with (
        pytest.raises(InputError, match=r"is a folder without results.json, not a bench's output: only a bench's"),
        atomic_dir(tmp_path / "work", overwrite=True, marks=("results.json",), what="a bench's output"),
    ):
        pass
    assert (scene / "traj.txt").read_text() == "poses" and (tmp_path / "work" / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["work"]  # no temporary left beside it
    earlier = tmp_path / "bench"
    earlier.mkdir()
    (earlier / "results.json").write_text("{}")
    (tmp_path / "empty").mkdir()
    for out in (earlier, tmp_path / "empty"):  # an earlier output, or an empty folder: replaced as before
        with atomic_dir(out, overwrite=True, marks=("results.json",), what="a bench's output", inputs=[scene]) as tmp:
            (tmp / "results.json").write_text("new")
        assert (out / "results.json").read_text() == "new"
    check_replaceable(tmp_path / "nothing-yet", ("results.json",), "a bench's output", [tmp_path / "gone"])  # no-op


def test_a_run_checks_its_output_before_its_work_and_writes_it_the_same_way(tmp_path: Path) -> None:
    """``check_run_output`` (run_offline's and run_pool's check before hours of mapping): an existing folder without
    overwrite, a folder holding an input (None: an input not given) or other things are refused; what it returns
    makes ``atomic_dir`` write by the same rule, so an earlier output is replaced."""
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "traj.txt").write_text("poses")
    earlier = tmp_path / "run"
    earlier.mkdir()
    (earlier / "metrics.json").write_text("{}")
    with pytest.raises(FileExistsError, match=r"run: already exists \(overwrite=True replaces it"):
        check_run_output(earlier, False, "a map's output", (scene, None), ("metrics.json",))
    with pytest.raises(InputError, match="which this command reads"):
        check_run_output(tmp_path, True, "a map's output", (scene, None), ("metrics.json",))
    with pytest.raises(InputError, match=r"is a folder without metrics\.json, not a map's output"):
        check_run_output(scene, True, "a map's output", (None,), ("metrics.json",))
    keep = check_run_output(earlier, True, "a map's output", (scene, None), ("metrics.json",))
    with atomic_dir(earlier, True, **keep) as tmp:
        (tmp / "metrics.json").write_text("new")
    assert (earlier / "metrics.json").read_text() == "new" and scene.is_dir()
    assert check_run_output(tmp_path / "new", False, "a map's output", (scene,), ("metrics.json",))["marks"] == ()


def test_overwrite_replaces_a_bench_with_its_own_runs_but_never_another_output_inside(tmp_path: Path) -> None:
    """A bench's runs (``runs/<label>/seed<k>/metrics.json``) are its own and go with it (``own``); a map run or a bag
    that a user put into the bench folder is another output, and refuses the replacement (it would be deleted)."""
    bench = tmp_path / "bench"
    (bench / "runs" / "random" / "seed0").mkdir(parents=True)
    (bench / "results.json").write_text("{}")
    (bench / "runs" / "random" / "seed0" / "metrics.json").write_text("{}")
    kind = {"marks": ("results.json",), "what": "a bench's output", "own": ("runs/*/*",)}
    with atomic_dir(bench, overwrite=True, **kind) as tmp:
        (tmp / "results.json").write_text("new")
    assert sorted(p.name for p in bench.iterdir()) == ["results.json"]
    for inside in ("maps/run1/metrics.json", "runs/bag/metadata.yaml", "keep/map/keyframes.json"):
        (bench / inside).parent.mkdir(parents=True, exist_ok=True)
        (bench / inside).write_text("{}")
        rel, mark = inside.rsplit("/", 1)
        with (
            pytest.raises(InputError, match=rf"holds {rel}/ \({mark}\), an output of its own: replacing a bench's"),
            atomic_dir(bench, overwrite=True, **kind),
        ):
            pass
        assert (bench / inside).read_text() == "{}"
        shutil.rmtree(bench / inside.split("/")[0]) if not inside.startswith("runs/") else (bench / inside).unlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bench"]  # no temporary left beside it


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


def test_read_json_names_the_file_and_what_is_wrong(tmp_path: Path) -> None:
    """A written object reads back; a missing file (or a folder) says the caller's hint, a file cut short says it is
    not valid JSON, a list is not an object; every error names the file."""
    ok = tmp_path / "results.json"
    write_json(ok, {"a": [1, 2]})
    assert read_json(ok) == {"a": [1, 2]}
    cut = tmp_path / "cut.json"
    cut.write_text(ok.read_text()[:-4])
    listed = tmp_path / "list.json"
    listed.write_text("[1, 2]")
    cases = (
        (tmp_path / "none.json", "none.json: give a bench folder"),
        (tmp_path, ": give a bench folder"),
        (cut, "cut.json: not valid JSON"),
        (listed, "list.json: not a JSON object (a list)"),
    )
    for path, words in cases:
        with pytest.raises(InputError) as err:
            read_json(path, "give a bench folder")
        assert words in str(err.value)


def test_an_existing_folder_error_says_how_the_caller_overwrites(tmp_path: Path) -> None:
    """The command line's `--overwrite` by default; a service names its request field (`overwrite: true`)."""
    final = tmp_path / "map"
    final.mkdir()
    with pytest.raises(FileExistsError, match=r"already exists \(pass --overwrite to replace it\)"):
        _write_dir(final, overwrite=False)
    hint = "set overwrite: true in the request"
    want = r"already exists \(set overwrite: true in the request to replace it\)"
    with pytest.raises(FileExistsError, match=want), atomic_dir(final, overwrite_hint=hint) as tmp:
        (tmp / "map.ply").write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map"] and not any(final.iterdir())


def test_deferred_interrupts_raise_a_ctrl_c_once_the_block_is_done() -> None:
    """A Ctrl-C inside the block (the swap of an old output for a new one) is raised only once the block is done."""
    handler = signal.getsignal(signal.SIGINT)
    done = []
    with pytest.raises(KeyboardInterrupt), deferred_interrupts():
        signal.raise_signal(signal.SIGINT)
        done.append(1)
    assert done == [1] and signal.getsignal(signal.SIGINT) is handler


@pytest.mark.parametrize("name", [".", "..", "sub/..", "/"])
def test_an_output_naming_no_entry_of_its_own_is_refused_before_anything_is_made(
    name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``roigsf map BAG --out . --overwrite`` mapped the whole bag, then failed in the rename with a traceback
    (``PosixPath('.') has an empty name``) and left a complete-looking ``..tmp-*`` map; ``--out ..`` left
    ``....tmp-*`` (EBUSY). Refused first, naming the path; the working folder given by its full name too."""
    monkeypatch.chdir(tmp_path)
    for out in (name, str(tmp_path)):
        for check in (lambda o: check_writable(o), lambda o: atomic_dir(o, overwrite=True).__enter__()):
            with pytest.raises(InputError) as caught:
                check(out)
            assert str(caught.value).startswith(f"{out}: "), str(caught.value)
            assert "names no folder or file of its own" in str(caught.value) or "working folder" in str(caught.value)
    assert list(tmp_path.iterdir()) == []


def test_a_failed_final_rename_removes_the_temporary_and_restores_the_old_output(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The final renames were outside the clean-up: a rename that failed left the finished temporary folder beside
    the output (looking complete) and, when replacing, the old output renamed away."""
    final = tmp_path / "run"
    final.mkdir()
    (final / "old.txt").write_text("old")
    real_rename = Path.rename

    def failing_rename(self: Path, target: Path) -> Path:
        if self.name.startswith(".run.tmp-"):
            raise OSError(16, "Device or resource busy")
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", failing_rename)
    with pytest.raises(OSError, match="busy"), atomic_dir(final, overwrite=True) as tmp:
        (tmp / "new.txt").write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    assert [p.name for p in final.iterdir()] == ["old.txt"]


def test_a_killed_writers_temporaries_are_removed_by_the_next_write(tmp_path: Path) -> None:
    """A mapper killed with SIGKILL during an autosave left ``.autosave.tmp-*`` beside the map for good (session 60's
    walk). Temporaries name their writer's process; the next write of that output removes those of a process that is
    gone, and leaves a running writer's, an older unnamed one and an interrupted replacement's old copy alone."""
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead = int(gone.stdout)  # that process has exited
    alive = os.getpid()
    for name in (f".auto.tmp-{dead}-k1", f".auto.tmp-{alive}-k2", ".auto.tmp-abc12", f".auto.old-{dead}"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "keyframes.json").write_text("{}")
    (tmp_path / f".metrics.tmp-{dead}-z9.json").write_text("{")
    with atomic_dir(tmp_path / "auto") as tmp:
        assert tmp.name.startswith(f".auto.tmp-{alive}-")
        (tmp / "keyframes.json").write_text("{}")
    write_json(tmp_path / "metrics.json", {"a": 1})
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([f".auto.old-{dead}", ".auto.tmp-abc12", f".auto.tmp-{alive}-k2", "auto", "metrics.json"])


def test_a_folder_that_refuses_files_says_the_system_refused_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--out /proc/x`` read "output folder is not writable (No such file or directory)" about a folder that is
    there (/proc gives ENOENT for a new file): the OS's reason is now said as the system's refusal of a new file."""
    import errno
    import tempfile

    def refuse(*args: object, **kwargs: object) -> tuple[int, str]:
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(InputError) as caught:
        check_writable(tmp_path / "x" / "run")
    assert str(caught.value) == (
        f"{tmp_path}: output folder is not writable: the system refused a new file in it (No such file or "
        f"directory); {tmp_path / 'x' / 'run'} cannot be written there; choose another one"
    )
