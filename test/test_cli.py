"""The `roigsf` front door: every subcommand has --help, and bad input is a one-line error, exit 2."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from roigsf_ros.cli import NO_OWN_MESH, build_parser, main

REPO = Path(__file__).resolve().parents[1]


def _subcommand_paths(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    paths = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                paths.append((*prefix, name))
                paths.extend(_subcommand_paths(sub, (*prefix, name)))
    return paths


def test_every_subcommand_has_help(capsys: pytest.CaptureFixture[str]) -> None:
    paths = _subcommand_paths(build_parser())
    expected = {("scene", "synth"), ("scene", "render"), ("bag", "from-replica"), ("bag", "info"), ("perf", "io")}
    assert expected <= set(paths)
    for path in paths:
        with pytest.raises(SystemExit) as exc:
            main([*path, "--help"])
        assert exc.value.code == 0, path
        out = capsys.readouterr().out
        assert out.startswith("usage: roigsf " + " ".join(path)), path


def test_bad_input_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bag", "info", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0] and err[0].startswith("roigsf bag: error:")


def test_module_entry_point_runs() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "roigsf_ros.cli", "--help"], capture_output=True, text=True, cwd=REPO, timeout=120
    )
    assert proc.returncode == 0 and "scene" in proc.stdout and "bag" in proc.stdout


def test_a_closed_output_pipe_is_quiet() -> None:
    """``roigsf bag info BAG | head -1`` where head left first: exit 141 (SIGPIPE, as a shell tool), no traceback.

    Before (session 61): "BrokenPipeError: [Errno 32] Broken pipe" with the whole traceback, exit 1.
    """
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before the command writes: every write fails
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "roigsf_ros.cli", "bag", "info", "bags/synth_room"],
            stdout=write_end, stderr=subprocess.PIPE, text=True, cwd=REPO, timeout=120,
        )  # fmt: skip
    finally:
        os.close(write_end)
    assert (proc.returncode, proc.stderr) == (141, "")


def _no_work(*_args: object, **_kw: object) -> None:
    raise AssertionError("work started before the output folder was checked")


@pytest.fixture
def tiny_scene(tmp_path: Path) -> Path:
    from roigsf_ros.perf.io import make_synthetic_replica

    make_synthetic_replica(tmp_path / "scene", 16, 12, 2, seed=1)
    return tmp_path / "scene"


def _commands(scene: Path, out: Path) -> dict[str, list[str]]:
    return {
        "map": ["map", str(scene), "--out", str(out), "--policy", "every-n", "--no-progress"],
        "bag": ["bag", "from-replica", str(scene), "--out", str(out), "--no-progress"],
        "scene": ["scene", "synth", "--out", str(out), "--frames", "2", "--width", "16", "--height", "12"],
    }


def _stub_work(monkeypatch: pytest.MonkeyPatch) -> None:
    import roigsf_ros.cli.bag
    import roigsf_ros.cli.map
    import roigsf_ros.data.scene

    monkeypatch.setattr(roigsf_ros.cli.map, "run_offline", _no_work)
    monkeypatch.setattr(roigsf_ros.cli.bag, "write_bag", _no_work)
    monkeypatch.setattr(roigsf_ros.data.scene, "render_sequence", _no_work)


@pytest.mark.parametrize("command", ["map", "bag", "scene"])
def test_output_under_a_file_fails_up_front_naming_it(
    command: str, tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    blocker = tmp_path / "a_file"  # a regular file where a folder should be: works as root too
    blocker.write_text("")
    _stub_work(monkeypatch)
    assert main(_commands(tiny_scene, blocker / "sub" / "out")[command]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(blocker) in err[0] and "not a folder" in err[0], err


@pytest.mark.parametrize("command", ["map", "bench"])
def test_a_missing_input_is_said_before_an_output_already_there(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf map /nope --out EXISTING`` answered ``EXISTING: already exists``: the real mistake came only after
    the user had changed ``--out``."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "metrics.json").write_text("{}")
    missing = tmp_path / "nope"
    argv = {
        "map": ["map", str(missing), "--out", str(out)],
        "bench": ["bench", "--scene", str(missing), "--setting", "pool", "--policies", "random", "--out", str(out)],
    }[command]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{missing}: no such bag or scene folder" in err[0], err


NESTED_OUTPUTS = [
    ("map", "metrics.json", "results/bag/metadata.yaml"),
    ("bag", "metadata.yaml", "run/metrics.json"),
    ("scene", "cam_params.json", "sub/cam_params.json"),
]


@pytest.mark.parametrize(("command", "mark", "nested"), NESTED_OUTPUTS)
def test_overwrite_never_deletes_another_output_written_inside_the_earlier_one(
    command: str,
    mark: str,
    nested: str,
    tiny_scene: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A new user wrote a bag and a map run into a scene folder, then ``roigsf scene synth --out ROOM --overwrite``:
    both went with the scene, without a word. An earlier output holding another output (a bag, a run, a scene, a
    bench, a saved map) is refused up front, and everything stays."""
    _stub_work(monkeypatch)
    out = tmp_path / "earlier"
    (out / nested).parent.mkdir(parents=True)
    (out / mark).write_text("{}")
    (out / nested).write_text("{}")
    assert main([*_commands(tiny_scene, out)[command], "--overwrite"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    rel = nested.rsplit("/", 1)[0]
    assert len(err) == 1 and f"{out}: holds {rel}/ ({nested.rsplit('/', 1)[1]}), an output of its own" in err[0], err
    assert (out / nested).read_text() == "{}" and (out / mark).read_text() == "{}"


@pytest.mark.parametrize("command", ["map", "bag", "scene"])
def test_read_only_output_folder_fails_up_front_naming_it(
    command: str, tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import errno
    import tempfile

    def read_only(*_args: object, **_kw: object) -> None:  # what a read-only mount answers, root or not
        raise OSError(errno.EROFS, "Read-only file system")

    _stub_work(monkeypatch)
    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    parent = tmp_path / "ro"
    parent.mkdir()
    assert main(_commands(tiny_scene, parent / "out")[command]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(parent) in err[0] and "Read-only file system" in err[0], err


def test_unwritable_folder_fails_up_front(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import os

    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        if os.access(locked, os.W_OK):
            pytest.skip("running as root: permissions do not stop writes (covered by the tests above)")
        assert main(["scene", "synth", "--out", str(locked / "out"), "--frames", "2"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(locked) in err[0] and "not writable" in err[0], err
    finally:
        locked.chmod(0o755)


@pytest.mark.parametrize(
    ("given", "expected"),
    [(["--width", "160"], (160, 120)), (["--height", "60"], (80, 60)), ([], (320, 240)),
     (["--width", "100", "--height", "20"], (100, 20))],
)  # fmt: skip
def test_scene_synth_derives_the_missing_side_from_the_default_aspect(
    given: list[str], expected: tuple[int, int], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import roigsf_ros.data.scene

    seen = []
    monkeypatch.setattr(roigsf_ros.data.scene, "render_sequence", lambda mesh, poses, intr, *a, **kw: seen.append(intr))
    assert main(["scene", "synth", "--out", str(tmp_path / "s"), "--frames", "2", *given]) == 0
    assert (seen[0].width, seen[0].height) == expected
    assert seen[0].cx == pytest.approx((expected[0] - 1) / 2) and seen[0].cy == pytest.approx((expected[1] - 1) / 2)


def test_every_sized_command_derives_the_missing_side_from_the_source(
    tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from roigsf_ros.data.bags import bag_info
    from roigsf_ros.data.sources import open_frames

    assert main(["bag", "from-replica", str(tiny_scene), "--out", str(tmp_path / "b"), "--width", "8",
                 "--no-progress"]) == 0  # fmt: skip
    assert (bag_info(tmp_path / "b")["width"], bag_info(tmp_path / "b")["height"]) == (8, 6)  # 16x12 source
    src = open_frames(tiny_scene, size=(None, 3))
    assert (src.intrinsics.width, src.intrinsics.height) == (4, 3) and next(iter(src)).depth_m.shape == (3, 4)
    capsys.readouterr()
    assert main(["bag", "from-replica", str(tiny_scene), "--out", str(tmp_path / "c"), "--height", "0"]) == 2
    assert "--height" in capsys.readouterr().err


def test_map_of_a_partial_download_names_the_allow_partial_flag(
    tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A traj.txt with more poses than frames: the error names `--allow-partial`, the flag the user types, and a
    Python caller reads ``allow_partial=True`` (both read "allow_partial=True, on the command line --allow-partial")."""
    from roigsf_ros.core.errors import InputError
    from roigsf_ros.data.replica import ReplicaSequence

    traj = tiny_scene / "traj.txt"
    lines = traj.read_text().splitlines(keepends=True)
    traj.write_text("".join([*lines, lines[0]]))
    _stub_work(monkeypatch)
    assert main(["map", str(tiny_scene), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "traj.txt" in err and "needs --allow-partial)" in err and "allow_partial" not in err, err
    with pytest.raises(InputError) as caught:
        ReplicaSequence(tiny_scene)
    assert str(caught.value).endswith("needs allow_partial=True)"), caught.value
    for cam in (tiny_scene / "cam_params.json", tiny_scene.parent / "cam_params.json"):
        cam.unlink(missing_ok=True)
    assert main(["bag", "from-replica", str(tiny_scene), "--out", str(tmp_path / "bag"), "--allow-partial"]) == 2
    assert "give the camera file (--cam PATH)" in capsys.readouterr().err


def _record_intrinsics(monkeypatch: pytest.MonkeyPatch) -> tuple[list[Any], Callable[..., None]]:
    """``roigsf map``'s mapping stubbed: each run records its source's intrinsics and stops there (exit 2)."""
    import roigsf_ros.cli.map
    from roigsf_ros.core.errors import InputError

    seen: list[Any] = []

    def record(source: object, *_args: object, **_kw: object) -> None:
        seen.append(source.intrinsics)  # type: ignore[attr-defined]
        raise InputError("stub", "the mapping itself is not under test")

    monkeypatch.setattr(roigsf_ros.cli.map, "run_offline", record)
    return seen, record


def test_map_takes_a_replica_folders_camera_file_and_bench_says_the_way_round(
    tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A Replica folder without cam_params.json: `roigsf map` and `roigsf bench` said "give the camera file
    (cam=PATH)", an option neither had. Both have `--cam` now (the bench keeps it for --rescore-ause); a bag given
    `--cam` is refused (its camera_info is its camera)."""
    import roigsf_ros.cli.bench
    import roigsf_ros.cli.map

    cam = tmp_path / "elsewhere.json"
    (tiny_scene / "cam_params.json").rename(cam)
    seen, record = _record_intrinsics(monkeypatch)
    out = str(tmp_path / "out")
    assert main(["map", str(tiny_scene), "--out", out, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "give the camera file (--cam PATH), or a named camera (--cam kinect-v1)" in err and "cam=" not in err, err
    assert main(["map", str(tiny_scene), "--cam", str(cam), "--out", out, "--no-progress"]) == 2
    assert len(seen) == 1 and (seen[0].width, seen[0].height) == (16, 12), seen
    bench = ["bench", "--scene", str(tiny_scene), "--setting", "pool", "--policies", "random", "--out", out]
    capsys.readouterr()
    monkeypatch.setattr(roigsf_ros.cli.bench, "run_bench", lambda cfg, *_a, **_k: record(cfg.source()))
    assert main(bench) == 2
    assert "give the camera file (--cam PATH)" in capsys.readouterr().err
    assert main([*bench, "--cam", str(cam)]) == 2 and len(seen) == 2 and seen[1].width == 16, seen
    seen.pop()
    assert main(["bag", "from-replica", str(tiny_scene), "--cam", str(cam), "--out", str(tmp_path / "bag")]) == 0
    capsys.readouterr()
    assert main(["map", str(tmp_path / "bag"), "--cam", str(cam), "--out", out, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "bag: is a bag: its camera_info gives the camera (--cam PATH is for a Replica folder)" in err, err
    assert len(seen) == 1
    # A folder source with --cam and a bag test scene: the bag reads its own camera_info, as the bench does (it was
    # given --cam, refused it, and the error added a misleading "both bags must be of one layout").
    beside = []

    def record_beside(source: object, *_args: object, eval_source: object, test_source: object, **_kw: object) -> None:
        beside.append(eval_source or test_source)
        record(source)

    monkeypatch.setattr(roigsf_ros.cli.map, "run_offline", record_beside)
    for option in ("--test-scene", "--eval-against"):
        assert main(["map", str(tiny_scene), "--cam", str(cam), option, str(tmp_path / "bag"), "--out", out,
                     "--no-progress"]) == 2, option  # fmt: skip
        err = capsys.readouterr().err
        assert "the mapping itself is not under test" in err and "camera_info gives the camera" not in err, err
    assert [s.intrinsics.width for s in beside] == [16, 16], beside  # type: ignore[attr-defined]


def test_a_named_camera_is_read_by_every_cam_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """`roigsf scene render --cam kinect-v1` took a named camera while `roigsf map --cam kinect-v1` said "camera
    parameters file not found". Every --cam (and the library's cam=) now takes the name (data.sensor.load_camera); a
    name that is neither a file nor a camera lists the names."""
    from roigsf_ros.data.replica import ReplicaSequence
    from roigsf_ros.data.sensor import KINECT_V1_INTRINSICS
    from roigsf_ros.perf.io import make_synthetic_replica

    scene = tmp_path / "kinect"
    make_synthetic_replica(scene, 640, 480, 1, seed=1)
    (scene / "cam_params.json").unlink()
    assert ReplicaSequence(scene, cam="kinect-v1").intrinsics == KINECT_V1_INTRINSICS
    seen, _ = _record_intrinsics(monkeypatch)
    out = str(tmp_path / "out")
    assert main(["map", str(scene), "--cam", "kinect-v1", "--out", out, "--no-progress"]) == 2
    assert seen == [KINECT_V1_INTRINSICS], seen
    capsys.readouterr()
    assert main(["map", str(scene), "--cam", "kinect-v2", "--out", out, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "kinect-v2: camera parameters file not found, nor a named camera (kinect-v1)" in err, err
    assert main(["map", str(scene), "--cam", str(tmp_path / "gone.json"), "--out", out, "--no-progress"]) == 2
    err = capsys.readouterr().err  # a path is a path: no talk of names
    assert err.rstrip().endswith("gone.json: camera parameters file not found"), err


def test_allow_partial_reaches_the_test_scene_and_the_bench_takes_it(
    tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """`roigsf map SRC --test-scene PARTIAL --allow-partial` refused the test scene with "needs --allow-partial", the
    option given (it reached the source only); `roigsf bench` on a partial download said "needs allow_partial=True",
    a Python argument, with no option to pass: it has `--allow-partial` now."""
    import roigsf_ros.cli.bench
    import roigsf_ros.cli.map
    from roigsf_ros.core.errors import InputError

    traj = tiny_scene / "traj.txt"
    lines = traj.read_text().splitlines(keepends=True)
    traj.write_text("".join([*lines, lines[0]]))
    seen = []

    def record(source: object, *_args: object, test_source: object = None, **_kw: object) -> None:
        seen.append(test_source)
        raise InputError("stub", "the mapping itself is not under test")

    monkeypatch.setattr(roigsf_ros.cli.map, "run_offline", record)
    argv = ["map", str(tiny_scene), "--test-scene", str(tiny_scene), "--out", str(tmp_path / "o"), "--no-progress"]
    assert main([*argv, "--allow-partial"]) == 2
    assert len(seen) == 1 and seen[0] is not None and len(seen[0]) == 2, seen  # type: ignore[arg-type]
    capsys.readouterr()
    bench = [
        "bench",
        "--scene",
        str(tiny_scene),
        "--setting",
        "stream",
        "--policies",
        "all",
        "--out",
        str(tmp_path / "b"),
    ]
    assert main(bench) == 2
    err = capsys.readouterr().err
    assert "a partial download needs --allow-partial)" in err, err
    monkeypatch.setattr(
        roigsf_ros.cli.bench, "run_bench", lambda cfg, *_a, **_k: record(cfg.source(), test_source=cfg.source())
    )
    assert main([*bench, "--allow-partial"]) == 2 and len(seen) == 2 and len(seen[1]) == 2, seen  # type: ignore[arg-type]


def test_bag_camera_options_given_to_a_replica_folder_are_refused(
    tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`roigsf map FOLDER --realsense --tf-child-frame camera_link` (and `roigsf bench --scene FOLDER --realsense`)
    ran as if nothing were typed: the options read a bag's topics and were ignored for a folder, without a word."""
    out = str(tmp_path / "o")
    assert main(["map", str(tiny_scene), "--realsense", "--tf-child-frame", "camera_link", "--out", out]) == 2
    err = capsys.readouterr().err
    assert f"--realsense --tf-child-frame: {tiny_scene} is a Replica folder, not a bag" in err, err
    bench = ["bench", "--scene", str(tiny_scene), "--setting", "stream", "--policies", "all", "--out", out]
    assert main([*bench, "--pose-source", "tf"]) == 2
    assert "--pose-source: " in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_map_policy_and_set_errors_name_the_option_and_the_valid_names(
    tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """`--policy` for an unknown policy; `--set` lists the MapperConfig fields (the closest first), as `--pool-set`
    does, and sends a policy parameter to its own option."""
    _stub_work(monkeypatch)
    base = ["map", str(tiny_scene), "--out", str(tmp_path / "out"), "--no-progress"]
    cases = [
        (["--policy", "nosuch"], ["--policy nosuch: unknown keyframe policy; choose one of", "gaus-slam"]),
        (
            ["--set", "lr_mean=1e-4"],
            ["--set lr_mean=1e-4: unknown name 'lr_mean' (did you mean lr_means?)", "iters_per_keyframe"],
        ),  # it said "expected NAME=VALUE", which it was
        (["--set", "tau_k=abc"], ["--set tau_k=abc", "use --tau-k"]),
        (["--set", "nosuch"], ["--set nosuch: expected NAME=VALUE", "iters_per_keyframe"]),
        (["--policy", "every-n", "--every-n", "0"], ["--every-n: must be at least 1, got 0"]),
        (["--policy", "gaus-slam", "--tau-k", "1.5"], ["--tau-k: must be in [0, 1), got 1.5"]),
        # the bench's spec syntax; an option the policy does not take is named as typed (was "takes no parameter(s) n")
        (["--policy", "evry-n:n=2"], ["--policy evry-n:n=2: unknown keyframe policy (did you mean 'every-n'?)"]),
        (["--policy", "every-n:n"], ["--policy every-n:n: expected NAME:KEY=VALUE..., got 'n'"]),
        (["--policy", "every-n:evry_n=2"], ["--policy every-n:evry_n=2: takes no parameter(s) evry_n (did you mean"]),
        (["--policy", "every-n:n=0"], ["n: must be at least 1, got 0"]),
        (["--policy", "gaus-slam", "--every-n", "3"], ["--every-n: policy gaus-slam takes no n (it takes tau_k"]),
        (["--policy", "every-n:n=2", "--every-n", "3"], ["--every-n: n is given in --policy every-n:n=2 too"]),
    ]
    for extra, words in cases:
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert all(w in err for w in words), (extra, err)
    assert not (tmp_path / "out").exists()
    from roigsf_ros.cli.map import policy_from_args

    args = build_parser().parse_args([*base, "--policy", "roi-gsurfisher:window=13:unseen_weight=1"])
    policy = policy_from_args(args)
    assert policy.name == "roi-gsurfisher" and policy.params()["window"] == 13


def test_list_values_of_set_and_pool_set_are_comma_separated(
    tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`4,8` is a list; a `+`-joined one (the `--policies` spec syntax) is refused naming the separator to use."""
    from roigsf_ros.cli.map import parse_overrides
    from roigsf_ros.experiments.pool import PoolConfig
    from roigsf_ros.mapping.mapper import MapperConfig

    pool = {"mesh_checkpoints": PoolConfig().mesh_checkpoints, "mesh_taus_m": PoolConfig().mesh_taus_m}
    assert parse_overrides(["mesh_checkpoints=4,8", "mesh_taus_m=1e-2, 5e-2"], pool, "--pool-set") == {
        "mesh_checkpoints": (4, 8),
        "mesh_taus_m": (0.01, 0.05),
    }
    mapper = {"fisher_params": MapperConfig().fisher_params}
    assert parse_overrides(["fisher_params=means,quats"], mapper, "--set") == {"fisher_params": ("means", "quats")}
    base = [
        "bench",
        "--scene",
        str(tiny_scene),
        "--setting",
        "pool",
        "--policies",
        "random",
        "--out",
        str(tmp_path / "o"),
    ]
    for extra, words in (
        (
            ["--pool-set", "mesh_checkpoints=4+8"],
            ["--pool-set mesh_checkpoints", "separate the items with commas, e.g. 4,8"],
        ),
        (
            ["--set", "fisher_params=means+quats"],
            ["--set fisher_params", "separate the items with commas, e.g. means,quats"],
        ),
        (  # commas already: the hint "e.g. 4,x" repeated the input; the item at fault is named
            ["--pool-set", "mesh_checkpoints=4,x"],
            ["--pool-set mesh_checkpoints: cannot parse 'x' of '4,x' as int"],
        ),
    ):
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert all(w in err for w in words), (extra, err)
    assert not (tmp_path / "o").exists()


def test_map_scores_a_bag_against_the_mesh_beside_it_as_the_demo_does(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf map bags/synth_room`` skipped the mesh metrics (it looked for mesh.ply inside the bag folder only) while
    ``roigsf demo`` scored the same bag against ``bags/synth_room_mesh.ply``: both now find ``NAME_mesh.ply`` beside a
    bag ``NAME`` (and ``mesh.ply`` in its folder), and a bag with neither still gets none, saying so.
    """
    import json
    import shutil

    quick = ["--policy", "every-n", "--no-progress", "--max-frames", "3", "--width", "40", "--iters-per-keyframe",
             "1", "--final-iters", "0", "--no-h-train"]  # fmt: skip
    mesh = REPO / "bags" / "synth_room_mesh.ply"
    assert main(["map", str(REPO / "bags" / "synth_room"), "--out", str(tmp_path / "sample"), *quick]) == 0
    assert f"  mesh metrics against {mesh}\n" in capsys.readouterr().out
    metrics = json.loads((tmp_path / "sample" / "metrics.json").read_text())
    assert metrics["gt_mesh"] == str(mesh) and 0.0 <= metrics["fscore@5cm"] <= 1.0, metrics
    # a copy under another name, without its mesh: none, and the hint; the mesh beside it under its name: taken
    shutil.copytree(REPO / "bags" / "synth_room", tmp_path / "robot")
    assert main(["map", str(tmp_path / "robot"), "--out", str(tmp_path / "none"), *quick]) == 0
    assert f"  no mesh metrics ({NO_OWN_MESH})" in capsys.readouterr().out
    shutil.copy(mesh, tmp_path / "robot_mesh.ply")
    mcap = next((tmp_path / "robot").glob("*.mcap"))  # the .mcap given stands for its folder
    assert main(["map", str(mcap), "--out", str(tmp_path / "beside"), *quick]) == 0
    assert json.loads((tmp_path / "beside" / "metrics.json").read_text())["gt_mesh"] == str(tmp_path / "robot_mesh.ply")


def test_map_empty_gt_mesh_means_none_as_in_demo(
    tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--gt-mesh ''` maps without mesh metrics, even when the source folder has its own mesh.ply (the default)."""
    import json

    import open3d as o3d

    assert o3d.io.write_triangle_mesh(str(tiny_scene / "mesh.ply"), o3d.geometry.TriangleMesh.create_box())
    with pytest.raises(SystemExit):
        main(["map", "--help"])
    assert "'' for none" in " ".join(capsys.readouterr().out.split())
    out = tmp_path / "run"
    argv = ["map", str(tiny_scene), "--out", str(out), "--policy", "every-n", "--no-progress", "--gt-mesh", ""]
    assert main([*argv, "--iters-per-keyframe", "1", "--final-iters", "0", "--no-h-train"]) == 0
    assert "  no mesh metrics (--gt-mesh '')" in capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["gt_mesh"] is None and metrics["no_gt_mesh_reason"] == "--gt-mesh ''" and "fscore@5cm" not in metrics
    # roigsf bench compares the policies' meshes: '' is refused naming the option, not read as the folder "."
    with pytest.raises(SystemExit):
        main(["bench", str(tiny_scene), "--gt-mesh", ""])
    assert "argument --gt-mesh: '' (no mesh) is not taken here" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["render", "--repeats", "0"], "--repeats"),  # was: StatisticsError after the whole benchmark ran
        (["render", "--threads", "0"], "--threads"),  # was: RuntimeError from torch.set_num_threads
        (["render", "--threads", "-2"], "--threads"),
        (["render", "--torch-threads", "0"], "--torch-threads"),  # was: 0 silently meant --threads
        (["nbv", "--repeats", "0"], "--repeats"),
        (["nbv", "--voxel-size", "nan"], "--voxel-size"),
        (["nbv", "--voxel-size", "inf"], "--voxel-size"),  # was: refused late, naming voxel_size_m
        (["io", "--messages", "1"], "--messages"),  # was: one message naming three options
        (["novelty", "--hash-capacity", "0", "--bag", "no_such_bag"], "--hash-capacity"),  # was: hash_capacity
        (["novelty", "--lookahead", "-1", "--bag", "no_such_bag"], "--lookahead"),  # was: after reading the bag
    ],
)
def test_perf_refuses_bad_numbers_up_front_naming_the_option(
    argv: list[str], option: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "perf.json"
    assert main(["perf", *argv, "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith(f"roigsf perf: error: {option}: must be") and captured.err.count("\n") == 1
    assert captured.out == "" and not out.exists()  # nothing timed, nothing written


def _raises_inside_numba(interrupt: KeyboardInterrupt, link: str) -> Callable[[argparse.Namespace], int]:
    """A command whose Ctrl-C lands inside a numba dispatch: numba re-raises it wrapped in a SystemError."""

    def command(_args: argparse.Namespace) -> int:
        try:
            raise interrupt
        except KeyboardInterrupt as exc:
            numba = "CPUDispatcher(<function _k_forward>)" if link == "cause" else "<function _numba_unpickle>"
            wrapped = SystemError(f"{numba} returned a result with an exception set")
            if link == "cause":
                raise wrapped from exc
            raise wrapped  # noqa: B904 - numba leaves the interrupt as __context__ only

    return command


@pytest.mark.parametrize(
    ("interrupt", "link", "rc"),
    [(KeyboardInterrupt(), "context", 130), ("SIGINT", "cause", 130), ("SIGTERM", "context", 143)],
)
def test_an_interrupt_wrapped_in_another_exception_is_the_interrupt(
    interrupt: KeyboardInterrupt | str,
    link: str,
    rc: int,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import signal

    import roigsf_ros.cli.scene
    from roigsf_ros.cli import _Interrupted

    if isinstance(interrupt, str):
        interrupt = _Interrupted(getattr(signal, interrupt))
    monkeypatch.setattr(roigsf_ros.cli.scene, "_synth", _raises_inside_numba(interrupt, link))
    assert main(["scene", "synth", "--out", str(tmp_path / "s")]) == rc
    assert capsys.readouterr().err == "roigsf scene: interrupted\n"  # one line, no traceback


def test_other_errors_still_raise_and_memory_errors_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import roigsf_ros.cli.scene

    def fails(exc: Exception) -> Callable[[argparse.Namespace], int]:
        def command(_args: argparse.Namespace) -> int:
            raise exc

        return command

    argv = ["scene", "synth", "--out", str(tmp_path / "s")]
    monkeypatch.setattr(roigsf_ros.cli.scene, "_synth", fails(SystemError("a bug, not an interrupt")))
    with pytest.raises(SystemError, match="a bug"):
        main(argv)
    too_big = MemoryError("Unable to allocate 168. GiB for an array with shape (75000, 100000, 3)")
    monkeypatch.setattr(roigsf_ros.cli.scene, "_synth", fails(too_big))
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("roigsf scene: error: not enough memory for this command (Unable to allocate 168. GiB")
    assert err.count("\n") == 1 and "--width/--height" in err


def test_image_sizes_beyond_8192_px_a_side_are_refused_up_front(
    tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from roigsf_ros.core.camera import derive_size

    _stub_work(monkeypatch)
    render = ["scene", "render", "--mesh", str(tmp_path / "no_mesh_read.ply"), "--traj", str(tiny_scene / "traj.txt"),
              "--cam", str(tiny_scene / "cam_params.json"), "--out", str(tmp_path / "r")]  # fmt: skip
    for argv, option, size in [
        ([*render, "--width", "100000"], "--width", "100000x75000"),  # was: numpy's 168 GiB _ArrayMemoryError
        ([*render, "--width", "9000", "--height", "10"], "--width/--height", "9000x10"),
        (["scene", "synth", "--out", str(tmp_path / "s"), "--height", "8192"], "--height", "10923x8192"),
        (["map", str(tiny_scene), "--out", str(tmp_path / "m"), "--width", "8193"], "--width", "8193x6145"),
    ]:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert f"error: {option}: image size {size} is above 8192 px a side" in err and err.count("\n") == 1, err
    assert not any(tmp_path.glob("[rsm]"))
    assert derive_size(8192, None, (640, 480)) == (8192, 6144)  # the limit itself is allowed


def test_options_are_taken_only_as_spelt(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """argparse took any unique prefix of an option: ``roigsf map --cam FILE`` (before ``map`` had ``--cam``) was read
    as ``--camera-info-topic`` and silently ignored for a scene folder."""
    scene, o, b = str(tmp_path), str(tmp_path / "o"), str(tmp_path / "b")
    for bad, args in (("--camera", ["map", scene, "--camera", "cam.json", "--out", o]),
                      ("--polic", ["bench", "--scene", scene, "--polic", "random", "--out", b])):  # fmt: skip
        with pytest.raises(SystemExit) as exc:
            main(args)
        assert exc.value.code == 2
        assert f"unrecognized arguments: {bad}" in capsys.readouterr().err
    assert not (tmp_path / "o").exists() and not (tmp_path / "b").exists()


def test_ctrl_c_while_the_commands_import_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ctrl-C in the first seconds of a command, while its modules import (torch, open3d), printed a traceback."""
    import roigsf_ros.cli as cli

    def interrupted_import() -> argparse.ArgumentParser:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted_import)
    assert main(["map", "x", "--out", "y"]) == 130
    assert capsys.readouterr().err == "roigsf map: interrupted\n"  # the command typed, as once it runs
    for argv in (["--help"], ["mapp", "x"], []):  # no command named: the program's name alone
        assert main(argv) == 130
        assert capsys.readouterr().err == "roigsf: interrupted\n"


def test_a_runs_table_says_what_recall_counts_and_why_psnr_is_missing(capsys: pytest.CaptureFixture[str]) -> None:
    """A 4-frame office0 run printed recall @5cm 0.998 (of the GT its poses see, 20% of the room) with nothing to say
    so, and a run whose every frame became a keyframe dropped its PSNR rows without a word."""
    from roigsf_ros.cli import metric_notes
    from roigsf_ros.cli.demo import format_table
    from roigsf_ros.cli.map import print_summary

    culled = "GT samples culled to those seen (in image, in range, unoccluded) from the poses of all frames"
    metrics = {"n_frames": 4, "n_eval_frames": 0, "recall@5cm": 0.998, "gt_observed_fraction": 0.2}
    metrics["gt_culling"] = culled
    print_summary(metrics)
    out = capsys.readouterr().out
    assert "recall and completion count the GT in view of the run's poses: 20% of the GT mesh" in out
    assert "no PSNR/SSIM: every frame was a keyframe" in out
    assert "20% of the GT mesh" in format_table(metrics)
    whole = {"gt_culling": "none: recall/completion against the whole GT mesh", "gt_observed_fraction": 1.0}
    assert metric_notes(whole | {"n_eval_frames": 3}) == []


def test_a_map_run_says_what_it_mapped_and_how(
    tiny_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf map``'s metrics.json named neither the bag or scene it mapped nor the options (only the GT mesh
    hinted at it), unlike the demo's and a bench's: now the source, the image size and the command line."""
    out = tmp_path / "run dir"
    argv = ["map", str(tiny_scene), "--out", str(out), "--policy", "every-n", "--no-progress", "--width", "16"]
    monkeypatch.setattr(sys, "argv", ["roigsf", *argv])
    assert main(argv) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["source"] == str(tiny_scene) and metrics["image_size"] == [16, 12]
    assert metrics["command"] == f"roigsf map {tiny_scene} --out '{out}' --policy every-n --no-progress --width 16"


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--policy", "roi-gsurfisher:window=abc"], "--policy roi-gsurfisher:window=abc: window: must be a whole"),
        (["--policy", "roi-gsurfisher", "--window", "0"], "--window: must be a positive integer, got 0"),
    ],
)
def test_a_bad_policy_value_names_where_it_was_typed(
    extra: list[str], words: str, tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--policy roi-gsurfisher:window=abc`` was blamed on ``--window``, an option the user had not typed."""
    assert main(["map", str(tiny_scene), "--out", str(tmp_path / "out"), *extra]) == 2
    err = capsys.readouterr().err
    assert f"roigsf map: error: {words}" in err, err


def test_bag_info_says_no_message_rather_than_none() -> None:
    """A bag without a depth message on the topic read printed ``depth None``."""
    from roigsf_ros.cli.bag import format_info

    info = {"path": "b", "gt_mesh": None, "topics": {}, "message_count": 0, "start_ns": None, "width": 4, "height": 3,
            "color_encoding": "rgb8", "depth_encoding": None, "pose_source": "pose topic", "frame_count": 0,
            "incomplete_stamps": 0}  # fmt: skip
    line = next(line for line in format_info(info).splitlines() if line.startswith("images:"))
    assert line.endswith("colour rgb8, depth no message, pose from pose topic"), line


@pytest.mark.parametrize(
    "argv",
    [["scene", "synth", "--out", "x"], ["scene", "render", "--mesh", "m", "--traj", "t", "--cam", "c", "--out", "x"],
     ["bag", "from-replica", "s", "--out", "x"], ["bag", "to-robot", "b", "--out", "x"], ["map", "s", "--out", "x"],
     ["demo"]],
)  # fmt: skip
def test_every_command_that_shows_progress_takes_no_progress(argv: list[str]) -> None:
    """``roigsf scene synth --no-progress`` was "unrecognized arguments" while every other writer took it."""
    assert build_parser().parse_args([*argv, "--no-progress"]).no_progress is True


def test_progress_bars_are_drawn_on_a_terminal_only(
    tiny_scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A walk: `roigsf bag from-replica`, `bag to-robot` and `roigsf map` wrote their tqdm bars into a log file or a
    pipe (carriage-return lines), while `roigsf scene --help` says bars are shown on a terminal only. Every command
    now asks the same question (``show_progress``): not --no-progress, and stderr a terminal."""
    import sys

    import roigsf_ros.cli.bag
    import roigsf_ros.cli.map
    from roigsf_ros.core.errors import InputError

    asked = []

    def record(*_args: object, progress: bool, **_kw: object) -> None:
        asked.append(progress)
        raise InputError("stub", "the work itself is not under test")

    monkeypatch.setattr(roigsf_ros.cli.map, "run_offline", record)
    monkeypatch.setattr(roigsf_ros.cli.bag, "write_bag", record)
    commands = (["map", str(tiny_scene), "--out", str(tmp_path / "m")],
                ["bag", "from-replica", str(tiny_scene), "--out", str(tmp_path / "b")])  # fmt: skip
    for tty in (False, True):
        monkeypatch.setattr(sys.stderr, "isatty", lambda tty=tty: tty)
        for argv in commands:
            assert main(argv) == 2 and main([*argv, "--no-progress"]) == 2
    assert asked == [False, False, False, False, True, False, True, False], asked


def test_bag_from_replica_warns_of_a_wrong_depth_scale_before_writing(
    tiny_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A walk: a Replica folder whose cam_params.json had the wrong depth 'scale' was converted without a word; every
    reader of the bag then masked most of its depth (F@5cm 0.000). The conversion still writes what the camera file
    says, but says so first; a right scale says nothing."""
    assert main(["bag", "from-replica", str(tiny_scene), "--out", str(tmp_path / "right"), "--no-progress"]) == 0
    assert "depth scale" not in capsys.readouterr().err
    cam_file = tiny_scene / "cam_params.json"
    cam = json.loads(cam_file.read_text())
    cam["camera"]["scale"] = cam["camera"]["scale"] / 100.0  # every depth 100x too far
    cam_file.write_text(json.dumps(cam))
    assert main(["bag", "from-replica", str(tiny_scene), "--out", str(tmp_path / "wrong"), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "of frame 0's depth values are outside 0.1-10 m (the mapper's default min_depth_m..max_depth_m)" in err, err
    assert f"read at depth scale {cam['camera']['scale']:g}" in err and "a wrong depth scale?" in err, err
    assert (tmp_path / "wrong" / "metadata.yaml").is_file()  # written all the same
