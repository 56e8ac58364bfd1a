"""The measurement scripts in scripts/ as a user meets them: ``--help`` answers without measuring, a wrong call is
refused with the usage, and a failed run leaves no result file (a fresh-clone walk of the documented figures found
each of these wrong)."""

from __future__ import annotations

import runpy
import subprocess
from pathlib import Path
from typing import Any

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def _script(name: str) -> dict[str, Any]:
    """The script's module namespace (its imports run; its ``__main__`` block does not)."""
    return runpy.run_path(str(SCRIPTS / name), run_name=f"script_{name.removesuffix('.py')}")


def test_measure_nbv_stalls_answers_help_and_refuses_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    """It read no arguments: ``--help`` ran the whole measurement (109 s beside another job) and printed figures."""
    main = _script("measure_nbv_stalls.py")["main"]
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    out = capsys.readouterr().out
    assert exc.value.code == 0 and "block-map growth" in out and "1-min load" not in out, out
    with pytest.raises(SystemExit) as exc:
        main(["--runs", "3"])
    assert exc.value.code == 2 and "unrecognized arguments: --runs 3" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("name", "usage"),
    [
        ("unseen_spread.py", "--out JSON -- <roigsf bench arguments>"),
        ("late_handover.py", "--after H --log JSON -- <roigsf bench arguments>"),
        ("carve_from_captured.py", "--out JSON -- --scene DIR <roigsf bench arguments>"),
    ],
)
def test_bench_wrapping_scripts_answer_help(name: str, usage: str, capsys: pytest.CaptureFixture[str]) -> None:
    """They answered ``--help`` with a one-line usage and exit 2; now argparse's help (options described), and a
    call without the bench's arguments after ``--`` is refused with the usage."""
    main = _script(name)["main"]
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    out = capsys.readouterr().out
    assert exc.value.code == 0 and usage in out and "JSON file" in out, out
    with pytest.raises(SystemExit) as exc:
        main(["--after", "2", "--log", "y.json"] if name == "late_handover.py" else ["--out", "x.json"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "give the wrapped command's arguments after --" in err and usage in err, err


def test_carve_from_captured_needs_the_benchs_scene(capsys: pytest.CaptureFixture[str]) -> None:
    main = _script("carve_from_captured.py")["main"]
    with pytest.raises(SystemExit) as exc:
        main(["--out", "x.json", "--", "--setting", "pool"])
    assert exc.value.code == 2 and "must give --scene DIR" in capsys.readouterr().err


def test_close_front_spread_stops_at_a_failed_bench_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """It went on after both benches failed and ended in a traceback, or, with its folder there, wrote a spread.json
    that read like a result ("fusions": 0)."""
    import roigsf_ros.nbv.scorer as scorer_module

    fuse = scorer_module.fuse_scores
    out = tmp_path / "spread"
    out.mkdir()
    rc = _script("close_front_spread.py")["main"](["--scene", str(tmp_path / "nope"), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and "no such bag or scene folder" in err and "a bench failed (exit 2)" in err, err
    assert err.count("roigsf bench: error") == 1  # the stream bench was not tried after the pool bench failed
    assert not (out / "spread.json").exists() and scorer_module.fuse_scores is fuse  # the scorer restored


FIGURE_SCRIPTS = [*sorted(p.name for p in SCRIPTS.glob("figure_*.sh")), "make_sample_bag.sh"]


def _bash(name: str, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    import os

    base = {k: v for k, v in os.environ.items() if not k.startswith("ROIGSF_")}
    return subprocess.run(["bash", str(SCRIPTS / name), *args], env={**base, **env}, capture_output=True, text=True,
                          timeout=30, cwd="/")  # fmt: skip


@pytest.mark.parametrize("name", FIGURE_SCRIPTS)
def test_figure_scripts_answer_help_and_refuse_arguments_before_any_work(name: str) -> None:
    """A walk of the figure scripts: every one ignored its arguments, so ``--help`` or a typo ran the whole job (set-up,
    renders, benches written over earlier results), and make_sample_bag.sh rewrote the shipped bag. Now ``--help``
    prints the header and an unknown argument is refused, both before set-up."""
    helped = _bash(name, "--help")
    assert helped.returncode == 0 and "[setup]" not in helped.stderr + helped.stdout, helped.stderr
    assert helped.stdout.strip() and not helped.stdout.startswith("#!"), helped.stdout
    refused = _bash(name, "--chek")
    assert refused.returncode == 2 and f"{name}: unknown argument(s): --chek (see {name} --help" in refused.stderr
    assert "[setup]" not in refused.stderr


@pytest.mark.parametrize(
    ("name", "env", "said"),
    [
        ("figure_nbv_stream_synth.sh", {"BENCHES": "nope"}, "BENCHES: unknown name 'nope' (one of: gaus-slam"),
        ("figure_nbv_stream_synth.sh", {"WINDOW": "abc"}, "WINDOW=abc: must be a whole number >= 1"),
        (
            "figure_nbv_stream_office0.sh",
            {"ROWS": "paper nope", "ROIGSF_SHARED_DATA": "/nonexistent"},
            "ROWS: unknown name 'nope' (one of: unseen gaus-slam random paper",
        ),
        ("figure_hindsight_bounds.sh", {"PARTS": "nope"}, "PARTS: unknown name 'nope' (one of: pool suite)"),
        ("figure_nbv_pool.sh", {"SCALE": "1.5"}, "SCALE=1.5: must be a whole number >= 1"),
        ("figure_nbv_pool.sh", {"SCENES": "synth nope"}, "SCENES: unknown scene nope"),
        (
            "figure_office0_mapping.sh",
            {"ROIGSF_SHARED_DATA": "/nonexistent"},
            "set ROIGSF_SHARED_DATA to the folder holding replica_office0",
        ),
        ("figure_f3.sh", {"ROIGSF_SHARED_DATA": "/nonexistent"}, "Replica office0 sample not found at /nonexistent"),
        ("figure_f3.sh", {"TAG": "a b"}, "TAG=a b: letters, digits"),
    ],
)
def test_figure_scripts_check_their_settings_before_any_work(name: str, env: dict[str, str], said: str) -> None:
    """A selector naming nothing (``BENCHES=nope``) ran nothing and exited 0; a bad number or an unknown scene failed
    only after minutes of work, or without naming the setting; a missing Replica sample was found after set-up, or
    after the synthetic scenes' benches (10-13 min). Now each is refused first, naming the setting."""
    res = _bash(name, **env)
    assert res.returncode == 2 and said in res.stderr and "[setup]" not in res.stderr, res.stderr


def test_compare_bags_fails_on_a_content_difference(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``make_sample_bag.sh --check`` runs it: it exited 0 whatever the images or poses held (only the topics and
    counts were checked), so the check could not fail. Two bags of one seed compare equal; of two seeds, they differ."""
    from roigsf_ros.data.bags import write_bag
    from roigsf_ros.data.replica import ReplicaSequence
    from roigsf_ros.perf.io import make_synthetic_replica

    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        make_synthetic_replica(tmp_path / f"scene_{name}", 16, 12, 2, seed=seed)
        write_bag(ReplicaSequence(tmp_path / f"scene_{name}"), tmp_path / name, progress=False)
    main = _script("compare_bags.py")["main"]
    assert main([str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    assert main([str(tmp_path / "a"), str(tmp_path / "c")]) == 1
    out = capsys.readouterr().out
    assert "/camera/color/image_raw: 2 messages, 2 differ" in out and "the bags differ on " in out, out
