"""The measurement scripts in scripts/ as a user meets them: ``--help`` answers without measuring, a wrong call is
refused with the usage, and a failed run leaves no result file (a fresh-clone walk of the documented figures found
each of these wrong)."""

from __future__ import annotations

import runpy
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
