"""Single-file outputs and ``roigsf perf``: a folder or a path under a file is refused before any work, no temporary
file is left behind, the player's ROS domain follows ``--domain-id`` / ``ROS_DOMAIN_ID``, the novelty benchmark says
where its default bag is, and ``perf nbv`` refuses images too small to fuse a TSDF."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any

import pytest

from roigsf_ros.cli import main
from roigsf_ros.core import package_files
from roigsf_ros.core.errors import InputError
from roigsf_ros.core.fileio import atomic_path, check_writable, write_json

# The work each benchmark does first, once its options are checked: replaced here by a function that fails the test.
FIRST_WORK = {
    "render": ("roigsf_ros.perf.render", "bench_case"),
    "nbv": ("roigsf_ros.perf.nbv", "build_state"),
    "novelty": ("roigsf_ros.perf.novelty", "read_bag_frames"),
    "io": ("roigsf_ros.perf.io", "bench_conversion"),
}


REPO = Path(__file__).resolve().parents[1]


def _no_work(*_args: Any, **_kwargs: Any) -> Any:
    raise AssertionError("the benchmark ran before --out was checked")


def test_atomic_path_refuses_a_folder_up_front_and_leaves_no_temporary(tmp_path: Path) -> None:
    """A folder at the target was a raw IsADirectoryError from the rename, after the work, with the temporary left."""
    final = tmp_path / "results.json"
    final.mkdir()
    (final / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match=r"results\.json: is a folder; give a file name"):
        write_json(final, {"a": 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]  # no .results.tmp-* beside it
    assert (final / "keep.txt").read_text() == "mine"


def test_atomic_path_removes_its_temporary_when_the_rename_fails(tmp_path: Path) -> None:
    """A folder made at the target while the file was being written: the rename fails, the temporary goes."""
    final = tmp_path / "results.json"
    with pytest.raises(InputError, match="is a folder"), atomic_path(final) as tmp:
        tmp.write_text("{}")
        final.mkdir()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"] and final.is_dir()


def test_atomic_path_under_a_regular_file_names_that_file(tmp_path: Path) -> None:
    """Was a bare ``[Errno 17] File exists``."""
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(InputError) as err:
        write_json(afile / "sub" / "x.json", {})
    assert str(err.value).startswith(f"{afile}: is not a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"] and afile.read_text() == "x"


def test_check_writable_refuses_a_folder_only_for_a_file_output(tmp_path: Path) -> None:
    """``file=True``: the caller writes one file there; the default (a folder output, replaced) still takes it."""
    folder = tmp_path / "out"
    folder.mkdir()
    check_writable(folder)
    with pytest.raises(InputError, match=r"out: is a folder; give a file name"):
        check_writable(folder, file=True)
    check_writable(tmp_path / "new.json", file=True)
    (tmp_path / "old.json").write_text("{}")
    check_writable(tmp_path / "old.json", file=True)  # an existing file is replaced


@pytest.mark.parametrize("benchmark", sorted(FIRST_WORK))
@pytest.mark.parametrize("where", ["folder", "under a file"])
def test_perf_checks_out_before_any_work(
    benchmark: str, where: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Was: the whole benchmark ran, then a traceback (folder) or ``[Errno 17] File exists`` (under a file)."""
    module, name = FIRST_WORK[benchmark]
    monkeypatch.setattr(f"{module}.{name}", _no_work)
    if where == "folder":
        out = tmp_path / "results"
        out.mkdir()
        words = f"{out}: is a folder; give a file name"
    else:
        (tmp_path / "afile").write_text("x")
        out = tmp_path / "afile" / "x.json"
        words = f"{tmp_path / 'afile'}: is not a folder"
    assert main(["perf", benchmark, "--repeats", "1", "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith(f"roigsf perf: error: {words}")
    assert captured.err.count("\n") == 1 and captured.out == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name if where == "folder" else "afile"]


@pytest.mark.parametrize("benchmark", sorted(FIRST_WORK))
def test_perf_never_writes_over_a_file_that_is_not_its_earlier_result(
    benchmark: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf perf io --out bags/synth_room/metadata.yaml`` wrote its JSON over the shipped bag's metadata (and
    ``--out SCENE/traj.txt`` over a trajectory): an existing file is replaced only when it is an earlier result of
    the same benchmark; anything else is refused before any work and stays as it was."""
    module, name = FIRST_WORK[benchmark]
    monkeypatch.setattr(f"{module}.{name}", _no_work)
    meta = tmp_path / "metadata.yaml"
    meta.write_text("rosbag2_bagfile_information:\n  version: 5\n")
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"benchmark": "not-" + benchmark}))
    for out in (meta, other):
        assert main(["perf", benchmark, "--repeats", "1", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"roigsf perf: error: {out}: exists and is not an earlier `roigsf perf {benchmark}` "
                              "result (a JSON object with benchmark: "), err  # fmt: skip
    assert meta.read_text() == "rosbag2_bagfile_information:\n  version: 5\n"
    assert json.loads(other.read_text()) == {"benchmark": "not-" + benchmark}


def test_perf_io_says_where_it_ran_and_replaces_its_earlier_result(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every ``roigsf perf`` JSON carries one ``environment`` block (the CPU model, not only ``x86_64``; the load; the
    versions; the commit): the io benchmark's had none, and each benchmark named the machine differently. A second
    run with the same ``--out`` replaces the first one's result, and says where it wrote."""
    from roigsf_ros.perf import cpu_model

    monkeypatch.setattr("roigsf_ros.perf.io.bench_conversion", lambda *_a: {})
    out = tmp_path / "io.json"
    for _ in range(2):
        assert main(["perf", "io", "--repeats", "1", "--skip-player", "--out", str(out)]) == 0
        assert capsys.readouterr().out.rstrip().endswith(f"wrote {out}")
    env = json.loads(out.read_text())["environment"]
    assert env["cpu"] == cpu_model() and env["cpu_count"] >= 1 and len(env["load_average_1min"]) == 2
    assert env["versions"]["torch"] is not None and env["finished_utc"].endswith("+00:00")


def test_perf_render_prints_its_footer_and_writes_its_json(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf perf render`` printed its table, then died on ``KeyError: 'load_average_1min'`` (the load moved into
    the environment block): no units line, no JSON, on every run, and in ``scripts/device_check.sh`` too. The cases'
    timings are faked here; the table, the footer and the file are what is checked."""

    def case(width: int, height: int, n: int, *_a: Any) -> dict[str, Any]:
        return {"width": width, "height": height, "surfels": n, "visible_surfels": n // 4,
                "mean_contributors_per_pixel": 3.0, "forward_ms": 1.0, "forward_nograd_ms": 0.5,
                "forward_backward_ms": 2.0}  # fmt: skip

    monkeypatch.setattr("roigsf_ros.perf.render.bench_case", case)
    out = tmp_path / "render.json"
    assert main(["perf", "render", "--repeats", "1", "--threads", "1", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "wall-clock milliseconds, medians" in text and "1-min load average" in text and f"wrote {out}" in text
    result = json.loads(out.read_text())
    assert result["benchmark"] == "render" and len(result["cases"]) == 4
    assert len(result["environment"]["load_average_1min"]) == 2


def test_the_perf_tables_say_the_threads_numba_took_where_fewer_than_asked() -> None:
    """``perf nbv --threads 64`` on 2 cores printed "backend numba, 64 threads" (JSON "threads": 64) while numba,
    which has at most one thread per CPU, ran its kernels on 2."""
    from roigsf_ros.perf import threads_text

    cpus = os.cpu_count() or 1
    assert threads_text(1, 1) == "1 thread" and threads_text(1, None) == "1 thread"
    over = f", more than the {cpus} CPUs: slower"
    assert (
        threads_text(cpus + 62, cpus)
        == f"torch {cpus + 62}, numba {cpus} threads ({cpus + 62} asked: numba's most here){over}"
    )
    assert threads_text(1, 1, cpus + 1) == f"torch {cpus + 1}, numba 1 threads{over}"  # perf render --torch-threads


def _fake_player(seen: list[int]) -> Any:
    """A ``_play_and_listen`` that records the domain id and returns two pose arrivals 0.1 s apart."""

    def play(_bag: Path, _rate: float, domain_id: int) -> dict[str, Any]:
        seen.append(domain_id)
        return {"arrivals": {"/camera/pose": [0.0, 0.1]}, "expected": 2, "lost": 0, "summary": {}}

    return play


@pytest.mark.parametrize(("argv", "env", "want"), [(["--domain-id", "7"], "150", 7), ([], "150", 150)])
def test_perf_io_player_runs_on_the_domain_given(
    argv: list[str], env: str, want: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``--domain-id``, else ROS_DOMAIN_ID (was: always a random id of 1..99, no option)."""
    seen: list[int] = []
    monkeypatch.setenv("ROS_DOMAIN_ID", env)
    monkeypatch.setattr("roigsf_ros.perf.io.bench_conversion", lambda *_a: {})
    monkeypatch.setattr("roigsf_ros.perf.io._play_and_listen", _fake_player(seen))
    out = tmp_path / "io.json"
    argv = ["perf", "io", "--repeats", "1", "--messages", "2", "--out", str(out), *argv]
    assert main(argv) == 0
    assert seen == [want, want] and json.loads(out.read_text())["player"]["domain_id"] == want


def test_choose_domain_id_order_and_range() -> None:
    """The option over the environment; random 1..99 without either; a bad id names where it came from."""
    from roigsf_ros.perf.io import choose_domain_id

    assert choose_domain_id(0, {"ROS_DOMAIN_ID": "42"}) == 0
    assert choose_domain_id(None, {"ROS_DOMAIN_ID": " 42 "}) == 42
    assert all(1 <= choose_domain_id(None, {"ROS_DOMAIN_ID": ""}) <= 99 for _ in range(20))
    for given, env, words in ((233, {}, "--domain-id: must be"), (None, {"ROS_DOMAIN_ID": "x"}, "ROS_DOMAIN_ID: not")):
        with pytest.raises(InputError, match=words):
            choose_domain_id(given, env)


def test_perf_io_refuses_a_bad_domain_id_before_any_work(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr("roigsf_ros.perf.io.bench_conversion", _no_work)
    assert main(["perf", "io", "--domain-id", "-1"]) == 2
    assert capsys.readouterr().err.startswith("roigsf perf: error: --domain-id: must be a ROS domain id in 0..232")


def test_perf_io_help_states_the_minimum_frames(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["perf", "io", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "frames converted per run (default 20, at least 2)" in help_text
    assert "--domain-id N" in help_text


def test_perf_novelty_reads_the_installed_sample_bag_from_another_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Was: ``bags/synth_room: bag not found`` from any folder but the repository root. The default is now the
    shipped sample found as the params files are (the checkout's, else the installed share folder's); only where
    neither has it the error says where it looked."""
    read: list[Path] = []

    def record(bag: Path, _topics: Any = None) -> Any:
        read.append(bag)
        raise InputError(bag, "read")

    monkeypatch.setattr("roigsf_ros.perf.novelty.read_bag_frames", record)
    monkeypatch.chdir(tmp_path)
    assert main(["perf", "novelty"]) == 2
    assert read == [REPO / "bags" / "synth_room"], read  # the checkout's, from another folder
    monkeypatch.setattr(package_files, "CHECKOUT_ROOT", tmp_path / "installed")
    monkeypatch.setattr(package_files, "share_folders", lambda: [])
    assert main(["perf", "novelty"]) == 2
    err = capsys.readouterr().err
    assert f"bags/synth_room: the package's sample is not installed (looked in {sys.prefix}/share/roigsf_ros/" in err
    with pytest.raises(SystemExit):
        main(["perf", "novelty", "--help"])
    assert "the shipped sample, bags/synth_room of the checkout, else of" in " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize(("width", "height", "option"), [(1, 1, "--width"), (7, 6, "--width"), (8, 5, "--height")])
def test_perf_nbv_refuses_images_too_small_up_front(
    width: int, height: int, option: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Was: an Open3D traceback ``No block is touched in TSDF volume`` from the TSDF fusion in build_state."""
    monkeypatch.setattr("roigsf_ros.perf.nbv.build_state", _no_work)
    assert main(["perf", "nbv", "--width", str(width), "--height", str(height)]) == 2
    least = 8 if option == "--width" else 6
    got = width if option == "--width" else height
    assert capsys.readouterr().err == f"roigsf perf: error: {option}: must be at least {least}, got {got}\n"


def test_perf_nbv_build_state_names_the_options_when_nothing_is_seen() -> None:
    """Two surfels at 8x6: the training views see no surface; an InputError, not Open3D's RuntimeError."""
    from roigsf_ros.nbv.scorer import NBVScorer
    from roigsf_ros.perf.nbv import build_state

    with pytest.raises(InputError, match=r"--surfels: the training views at 8x6 with 2 surfels saw too little"):
        build_state(2, 8, 6, 2, 0.02, NBVScorer())


@pytest.mark.parametrize(
    "argv",
    [
        ["render", "--threads", "99999999999"],
        ["render", "--torch-threads", "99999999999"],
        ["nbv", "--threads", "99999999999"],
        ["nbv", "--voxel-size", "99999999999"],
    ],
)
def test_perf_refuses_huge_thread_counts_and_voxels_naming_the_option(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """A typo's 99999999999 threads overflowed inside torch, and a 1e11 m voxel failed in numpy, both with a traceback
    (session 60's second walk): refused before any work, naming the option."""
    assert main(["perf", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"roigsf perf: error: {argv[1]}: must be at most ") and len(err.splitlines()) == 1, err


def test_a_novelty_hash_set_that_cannot_be_allocated_is_a_memory_error(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """open3d reports a failed allocation as RuntimeError("CPU malloc failed"), which went out as a traceback from
    ``roigsf perf novelty --hash-capacity 9999999999``; it is now the MemoryError that the CLI reports in one line."""
    import open3d as o3d

    from roigsf_ros.nbv.novelty import ObservedSurface

    def failing(*args: Any, **kwargs: Any) -> Any:
        raise RuntimeError("[Open3D Error] CPU malloc failed")

    monkeypatch.setattr(o3d.core, "HashSet", failing)
    with pytest.raises(MemoryError, match="hash_capacity 9999999999"):
        ObservedSurface(hash_capacity=9999999999)
    assert main(["perf", "novelty", "--hash-capacity", "9999999999", "--repeats", "1"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("roigsf perf: error: not enough memory for this command (a hash set of hash_capacity"), err
