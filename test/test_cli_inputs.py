"""Bad or surprising input to the ``roigsf`` command line (found by a fresh-clone walk): the demo's default mesh,
params files and numbers, domain ids, ``targets`` margins, ``bag info`` on a robot bag read with the wrong namespace,
``map``'s --realsense hint, Ctrl-C.
"""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from roigsf_ros.cli import NO_OWN_MESH, main
from roigsf_ros.core.errors import InputError
from roigsf_ros.data import bags
from roigsf_ros.data.replica import ReplicaSequence
from roigsf_ros.perf.io import make_synthetic_replica

REPO = Path(__file__).resolve().parents[1]


def _bag(root: Path, frames: int, width: int, height: int, seed: int) -> Path:
    """A small synthetic camera bag (the package's default topics, pose on /camera/pose, 10 Hz)."""
    make_synthetic_replica(root / "scene", width, height, frames, seed=seed)
    bags.write_bag(ReplicaSequence(root / "scene"), root / "bag", progress=False)
    return root / "bag"


def _robot_bag(root: Path, frames: int, seed: int) -> Path:
    """A small bag as a robot records it (RealSense names under /camera, pose only on TF, compressed images)."""
    from roigsf_ros.data.robot_bag import write_robot_bag

    assert write_robot_bag(_bag(root, frames, 32, 24, seed=seed), root / "robot") == frames
    return root / "robot"


def _no_call(*args: Any, **kwargs: Any) -> Any:
    """Stands in for the demo's expensive steps where an option must be refused before them."""
    raise AssertionError("called: the option should have been refused before any work")


def _fake_run_demo(used: dict[str, Any]) -> Callable[..., dict[str, Any]]:
    """A ``run_demo`` that records its mesh arguments and returns a run where every frame arrived."""

    def run_demo(bag: Path, out: Path, **kwargs: Any) -> dict[str, Any]:
        used.update(bag=bag, gt_mesh=kwargs["gt_mesh"], why=kwargs.get("no_gt_mesh_reason"))
        return {"policy": "every-n", "frames_received": 4, "fallbacks": 0, "keyframes_not_mapped": 0}

    return run_demo


# ------------------------------------------------------------------------------------ 1. demo: the default mesh
def test_demo_scores_mesh_metrics_against_a_bags_own_mesh_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf demo --bag OTHER`` scored the mesh metrics against the shipped sample's mesh; now a bag is scored
    against its own mesh only (as ``roigsf map`` finds it), else none unless ``--gt-mesh`` is given, and the start line
    and the table say which mesh, or none and why.
    """
    pytest.importorskip("rclpy")
    from roigsf_ros.cli import demo

    used: dict[str, Any] = {}
    monkeypatch.setattr(demo, "run_demo", _fake_run_demo(used))
    bag = _bag(tmp_path, 4, 32, 24, seed=1)
    args = ["demo", "--bag", str(bag), "--out", str(tmp_path / "run"), "--rate", "0", "--no-progress"]
    assert main(args) == 0
    assert used["gt_mesh"] is None and used["why"] == NO_OWN_MESH, used
    out = capsys.readouterr().out
    first = out.splitlines()[0]
    assert first.endswith(f"; no mesh metrics ({NO_OWN_MESH})"), first
    table = f"\n  keyframes not mapped       0\n  no mesh metrics ({NO_OWN_MESH})\n"
    assert table in out, out
    mesh = REPO / "bags" / "synth_room_mesh.ply"
    assert main([*args, "--gt-mesh", str(mesh)]) == 0  # given: taken, for any bag
    assert used["gt_mesh"] == mesh
    assert f"; mesh metrics against {mesh}" in capsys.readouterr().out
    assert main([*args, "--gt-mesh", str(tmp_path / "none.ply")]) == 2  # refused now, not after the replay
    assert "none.ply: ground-truth mesh not found (--gt-mesh)" in capsys.readouterr().err
    # the sample bag however spelt (here through a symlink): its mesh by default
    (tmp_path / "link").symlink_to(REPO / "bags")
    sample = ["demo", "--bag", str(tmp_path / "link" / "synth_room"), "--out", str(tmp_path / "run"), "--no-progress"]
    monkeypatch.setattr(demo, "bag_info", lambda *a, **k: {"frame_count": 4, "width": 32, "height": 24,
                                                           "depth_encoding": "32FC1", "pose_source": "topic",
                                                           "duration_s": 0.3})  # fmt: skip
    assert main(sample) == 0
    beside = tmp_path / "link" / "synth_room_mesh.ply"  # the sample's mesh, found beside the bag as it was named
    assert used["gt_mesh"] == beside and beside.resolve() == REPO / "bags" / "synth_room_mesh.ply", used
    assert f"mesh metrics against {beside}" in capsys.readouterr().out
    assert main([*sample, "--gt-mesh", ""]) == 0
    assert used["gt_mesh"] is None and used["why"] == "--gt-mesh ''"
    # a copy of the sample without its mesh is one more bag (one rule with roigsf map: it used to take the sample's
    # mesh for a byte-identical copy); with the mesh put beside it under its name, or into it, it has its own
    shutil.copytree(REPO / "bags" / "synth_room", tmp_path / "copy")
    sample[2] = str(tmp_path / "copy")
    assert main(sample) == 0
    assert used["gt_mesh"] is None and used["why"] == NO_OWN_MESH, used
    shutil.copy(REPO / "bags" / "synth_room_mesh.ply", tmp_path / "copy" / "mesh.ply")
    assert main([*sample[:2], str(tmp_path / "copy" / "synth_room.mcap"), *sample[3:]]) == 0  # a .mcap: its folder's
    assert used["gt_mesh"] == tmp_path / "copy" / "mesh.ply", used


# ------------------------------------------------------------------------------------ 2. demo: params files
def test_demo_warns_of_a_misspelt_section_and_names_the_params_file_of_a_bad_value(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    """``roigsf demo --params-file F`` says what ``active_mapping --ros-args --params-file F`` says: a warning for a
    misspelt section (``mappr:``) and "(set in F)" after a bad value. Before, the demo's context had no note of its
    params files: no warning, and the error did not name the file.
    """
    pytest.importorskip("rclpy")
    import roigsf_ros.nodes.bag_player

    class NoPlayer:  # the nodes are built (and have warned) once the player is made: stop there
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            raise InputError("test", "no playback in this test")

    monkeypatch.setattr(roigsf_ros.nodes.bag_player, "BagPlayer", NoPlayer)
    bag = _bag(tmp_path, 3, 32, 24, seed=2)
    typo = tmp_path / "typo.yaml"
    typo.write_text("mappr:\n  ros__parameters:\n    iters_per_keyframe: 3\n")
    args = ["demo", "--bag", str(bag), "--out", str(tmp_path / "run"), "--gt-mesh", "", "--no-progress"]
    assert main([*args, "--params-file", str(typo)]) == 2
    err = capfd.readouterr().err
    assert f"section 'mappr' in {typo} looks like a misspelling of 'mapper'" in err, err
    assert "no playback in this test" in err
    bad = tmp_path / "bad.yaml"
    bad.write_text("mapper:\n  ros__parameters:\n    iters_per_keyframe: -1\n")
    assert main([*args, "--params-file", str(bad)]) == 2
    err = capfd.readouterr().err
    assert f"parameter 'mapper.iters_per_keyframe': must be >= 0, got -1 (set in {bad})" in err, err
    camera = tmp_path / "camera.yaml"  # a camera parameter: refused by the demo's own probe, before the nodes
    camera.write_text("keyframe_selector:\n  ros__parameters:\n    pose_source: gps\n")
    assert main([*args, "--params-file", str(camera)]) == 2
    err = capfd.readouterr().err
    assert f"parameter 'keyframe_selector.pose_source': 'gps' is not one of topic, tf (set in {camera})" in err, err


# ------------------------------------------------------------------------------------ 3. demo: numbers
@pytest.mark.parametrize(
    ("option", "value", "words"),
    [
        ("--final-iters", "-1", "--final-iters: must be >= 0, got -1"),
        ("--rate", "nan", "--rate: must be a finite number"),
        ("--rate", "inf", "--rate: must be a finite number"),
        # a misspelt policy was refused by the selector, once the nodes had started and warmed up
        ("--policy", "evry-n", "--policy: unknown policy 'evry-n' (did you mean 'every-n'?); choose one of roi-gsur"),
        ("--set", "keyframe_selector.policy=evry-n", "--set keyframe_selector.policy: unknown policy 'evry-n' (did"),
    ],
)
def test_demo_refuses_nonsense_numbers_before_any_work(
    option: str,
    value: str,
    words: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--final-iters -1`` was accepted (and ``--rate nan`` reached the player after the nodes' warm-up); a negative
    rate stays meaningful (lockstep).
    """
    from roigsf_ros.cli import demo

    monkeypatch.setattr(demo, "demo_camera", _no_call)
    monkeypatch.setattr(demo, "run_demo", _no_call)
    bag = _bag(tmp_path, 2, 16, 12, seed=3)
    assert main(["demo", "--bag", str(bag), "--out", str(tmp_path / "run"), option, value]) == 2
    err = capsys.readouterr().err
    assert f"roigsf demo: error: {words}" in err and err.count("\n") == 1, err


# ------------------------------------------------------------------------------------ 4. --domain-id
def test_every_domain_id_option_refuses_an_id_whose_dds_ports_do_not_fit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf demo --domain-id 999`` failed in Fast DDS ("port number is too high", exit 1) after leaving files in
    /dev/shm; every command with ``--domain-id`` now refuses it up front through one check, naming the option (or
    ROS_DOMAIN_ID when the id came from there).
    """
    from roigsf_ros.cli import demo
    from roigsf_ros.core.ros_domain import MAX_DOMAIN_ID, check_domain_id, domain_id_from_env

    assert MAX_DOMAIN_ID == 232 and check_domain_id(0) == 0 and check_domain_id(232) == 232
    with pytest.raises(InputError, match=r"--domain-id: must be a ROS domain id in 0\.\.232, got 233"):
        check_domain_id(233)
    assert domain_id_from_env({}) is None and domain_id_from_env({"ROS_DOMAIN_ID": " 7 "}) == 7
    monkeypatch.setattr(demo, "demo_camera", _no_call)
    monkeypatch.setattr(demo, "run_demo", _no_call)
    monkeypatch.setattr("roigsf_ros.perf.io.bench_conversion", _no_call)
    bag = _bag(tmp_path, 2, 16, 12, seed=4)
    for argv in (
        ["demo", "--bag", str(bag), "--out", str(tmp_path / "run"), "--domain-id", "999"],
        ["demo", "--bag", str(bag), "--out", str(tmp_path / "run"), "--domain-id", "-1"],
        ["perf", "io", "--skip-player", "--domain-id", "999"],
    ):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert f"error: --domain-id: must be a ROS domain id in 0..232, got {argv[-1]}" in err, err
    monkeypatch.setenv("ROS_DOMAIN_ID", "400")
    assert main(["demo", "--bag", str(bag), "--out", str(tmp_path / "run")]) == 2
    assert "error: ROS_DOMAIN_ID: must be a ROS domain id in 0..232, got 400" in capsys.readouterr().err


# ------------------------------------------------------------------------------------ 5. targets: margins
def _stream_bench(folder: Path, policies: dict[str, dict[str, tuple[float, float]]]) -> Path:
    """A stream results.json as ``roigsf bench`` writes it, with (mean, std) per policy and metric."""
    res = {"setting": "stream", "scene": "runs/s", "size": [240, 180], "stride": 1, "max_frames": None,
           "n_frames": 96, "seeds": [0, 1, 2], "mapper_config": {"seed": 0}, "pool_config": None, "runs": [],
           "summary": {label: {k: {"mean": m, "std": s, "n": 3} for k, (m, s) in metrics.items()}
                       for label, metrics in policies.items()}}  # fmt: skip
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps(res))
    return folder


@pytest.mark.parametrize(
    ("option", "value", "words"),
    [
        ("--max-keyframe-ratio", "nan", "must be a finite number > 0, got nan"),
        ("--max-keyframe-ratio", "inf", "must be a finite number > 0, got inf"),
        ("--max-keyframe-ratio", "0", "must be a finite number > 0, got 0.0"),
        ("--recall-margin", "-0.01", "must be a finite number >= 0, got -0.01"),
        ("--recall-margin", "inf", "must be a finite number >= 0, got inf"),
        ("--psnr-margin-db", "nan", "must be a finite number >= 0, got nan"),
        ("--psnr-margin-db", "-1", "must be a finite number >= 0, got -1.0"),
    ],
)
def test_targets_refuses_nonsense_margins_naming_the_option(
    option: str, value: str, words: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--max-keyframe-ratio nan`` printed "at most nan%", ``inf`` made every check "met", a negative
    ``--recall-margin`` was taken: refused before the benches are read, naming the option.
    """
    metrics = {"n_keyframes": (30.0, 1.0), "recall@5cm": (0.9, 0.01), "psnr": (30.0, 0.1)}
    bench = _stream_bench(tmp_path / "b", {"cand": metrics, "gaus-slam": {**metrics, "n_keyframes": (160.0, 2.0)}})
    argv = ["targets", f"{bench}#cand", "--against", f"{bench}#gaus-slam", option, value]
    assert main(argv) == 2
    out = capsys.readouterr()
    assert out.err == f"roigsf targets: error: {option}: {words}\n" and out.out == "", out
    assert main(argv[:4]) == 0  # the defaults: a table
    assert "keyframes, at most 20% of the reference's" in capsys.readouterr().out


def test_the_target_functions_refuse_nonsense_margins_too(tmp_path: Path) -> None:
    """A script calling ``stream_target`` / ``pool_target`` gets the same refusal, naming the argument."""
    from roigsf_ros.experiments.targets import load_policy, pool_target, stream_target

    metrics = {"n_keyframes": (30.0, 1.0), "recall@5cm": (0.9, 0.01), "psnr": (30.0, 0.1)}
    bench = _stream_bench(tmp_path / "b", {"cand": metrics, "ref": {**metrics, "n_keyframes": (160.0, 2.0)}})
    cand, ref = load_policy(f"{bench}#cand"), load_policy(f"{bench}#ref")
    bad: list[tuple[dict[str, float], str]] = [
        ({"max_keyframe_ratio": math.inf}, "max_keyframe_ratio"),
        ({"recall_margin": -0.5}, "recall_margin"),
        ({"psnr_margin_db": math.nan}, "psnr_margin_db"),
    ]
    for kwargs, name in bad:
        with pytest.raises(InputError, match=f"^{name}: must be a finite number"):
            stream_target(cand, ref, **kwargs)
    with pytest.raises(InputError, match=r"^psnr_margin_db: must be a finite number >= 0, got inf"):
        pool_target(cand, [ref], psnr_margin_db=math.inf)


# ------------------------------------------------------------------------------------ 6. bag info: TF is no frame
def test_bag_info_counts_no_tf_message_as_an_incomplete_frame(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf bag info ROBOT_BAG --realsense /cam`` (a namespace the bag lacks) said "166 incomplete stamps" of a
    150-frame bag: with none of the camera topics present, rosbags read every topic, /tf's TFMessages (no header)
    included. Here 6 frames: 0 incomplete stamps (before: 8), and the hint names /camera.
    """
    bag = _robot_bag(tmp_path, 6, seed=5)
    assert main(["bag", "info", str(bag), "--realsense", "/cam", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["frame_count"], info["incomplete_stamps"]) == (0, 0), info
    assert info["realsense_namespace"] == "/camera" and info["hint"].endswith("try --realsense /camera"), info
    assert main(["bag", "info", str(bag), "--realsense", "/cam"]) == 0
    assert ", 0 refused, 0 incomplete stamps\n" in capsys.readouterr().out
    # the default topics: the one camera topic present (colour, compressed) counts its 6 stamps, TF still not
    assert main(["bag", "info", str(bag), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["incomplete_stamps"] == 6


# ------------------------------------------------------------------------------------ 7. map: the --realsense hint
def test_map_on_a_robot_bag_without_realsense_says_try_realsense(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf map`` on a robot bag failed on the missing default topic without the hint ``roigsf demo`` and
    ``roigsf bag info`` give; now it gives it (naming options that would override the RealSense names).
    """
    bag = _robot_bag(tmp_path, 3, seed=6)
    out = tmp_path / "run"
    assert main(["map", str(bag), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"roigsf map: error: {bag}: ") and "is missing" in err, err
    assert err.endswith("; the bag has a RealSense camera's topics under /camera: try --realsense\n"), err
    assert main(["map", str(bag), "--out", str(out), "--realsense", "/cam", "--depth-transport", "raw"]) == 2
    err = capsys.readouterr().err
    assert (
        err.endswith("under /camera: try --realsense /camera without --depth-transport\n") and err.count("\n") == 1
    ), err
    assert not out.exists()
    scene = tmp_path / "scene"  # a scene folder's error: no hint, as before
    (scene / "results").mkdir(parents=True, exist_ok=True)
    (scene / "results" / "frame000000.jpg").unlink()
    assert main(["map", str(scene), "--out", str(out)]) == 2
    assert "--realsense" not in capsys.readouterr().err


# ------------------------------------------------------------------------------------ 8. Ctrl-C anywhere
def test_ctrl_c_inside_a_commands_import_is_one_line_and_130(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roigsf map BAG --out OUT`` stopped at ~0.5 s, while Open3D imports: its pybind11 init turned the Ctrl-C
    into "ImportError: initialization failed" (a KeyboardInterrupt traceback, exit 1). Now: one line, 130, also for
    a Ctrl-C inside the subcommand itself, bare or wrapped.
    """
    import roigsf_ros.cli.map

    def import_interrupted(_sub: Any) -> None:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise ImportError("initialization failed") from exc

    argv = ["map", str(tmp_path / "bag"), "--out", str(tmp_path / "run")]
    with monkeypatch.context() as m:
        m.setattr(roigsf_ros.cli.map, "register", import_interrupted)
        assert main(argv) == 130
    assert capsys.readouterr().err == "roigsf map: interrupted\n"

    def interrupted(_args: Any) -> int:
        raise KeyboardInterrupt

    def interrupted_import(_args: Any) -> int:
        import_interrupted(None)
        return 0

    for command in (interrupted, interrupted_import):
        monkeypatch.setattr(roigsf_ros.cli.map, "run", command)
        assert main(argv) == 130
        assert capsys.readouterr().err == "roigsf map: interrupted\n"
    assert not (tmp_path / "run").exists()
    monkeypatch.setattr(roigsf_ros.cli.map, "register", lambda _sub: (_ for _ in ()).throw(ImportError("no o3d")))
    with pytest.raises(ImportError, match="no o3d"):  # an import error that is no interrupt: as it was
        main(argv)


def test_map_of_frames_without_valid_depth_is_one_line_not_a_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Every frame without valid depth (a sensor model that drops it all): every keyframe was skipped, then the empty
    mesh's write failed with a traceback (session 60's second walk). Now one line naming the source and why."""
    import cv2

    scene = tmp_path / "scene"
    make_synthetic_replica(scene, 32, 24, 3, seed=4)
    for depth in (scene / "results").glob("depth*.png"):
        cv2.imwrite(str(depth), np.zeros((24, 32), np.uint16))
    argv = ["map", str(scene), "--out", str(tmp_path / "run"), "--no-progress", "--gt-mesh", "", "--policy", "all"]
    assert main([*argv, "--final-iters", "0", "--no-h-train"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("no keyframe could be mapped from 3 frame(s): 3 keyframe(s) had no valid depth"), err
    assert len(err.splitlines()) == 1 and not (tmp_path / "run").exists()


def test_a_test_scene_of_another_camera_names_both_cameras(tmp_path: Path) -> None:
    """``--test-scene`` of another image size said only "its camera differs" (session 60's second walk)."""
    from roigsf_ros.data.sources import open_frames
    from roigsf_ros.experiments.offline import run_offline
    from roigsf_ros.policies import make_policy

    make_synthetic_replica(tmp_path / "a", 32, 24, 2, seed=1)
    make_synthetic_replica(tmp_path / "b", 48, 36, 2, seed=1)
    with pytest.raises(InputError) as caught:
        run_offline(
            open_frames(tmp_path / "a"),
            make_policy("all"),
            None,
            tmp_path / "run",
            test_source=open_frames(tmp_path / "b"),
        )
    text = str(caught.value)
    assert "its camera differs from the mapped sequence's (48x36 px, fx " in text and ", against 32x24 px, fx" in text
    assert not (tmp_path / "run").exists()
