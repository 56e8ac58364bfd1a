"""The console scripts (``ros2 run roigsf_ros <program>``): the command line is checked before the node loads.

A node's module imports torch, open3d and rosbags, 4-5 s on a 2-core machine before a word was printed;
``--help`` and a mistyped option need none of it. They are answered here, with the module's docstring read
from its source (not imported), exactly as the node's own ``main`` answers them; anything else goes on to
that ``main``.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import sys
from pathlib import Path

from roigsf_ros.nodes.node_process import script_args

PROGRAMS = {
    "bag_player": "roigsf_ros.nodes.bag_player",
    "mapper": "roigsf_ros.nodes.mapper",
    "nbv_planner": "roigsf_ros.nodes.nbv_planner",
    "keyframe_selector": "roigsf_ros.nodes.keyframe_selector",
    "active_mapping": "roigsf_ros.nodes.active_mapping",
}
"""Console script name -> the module whose ``main(args)`` runs it."""


def module_doc(module: str) -> str:
    """The docstring of ``module`` as its ``__doc__`` would be, read from the source without importing it."""
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        raise ModuleNotFoundError(module)
    return ast.get_docstring(ast.parse(Path(spec.origin).read_text(encoding="utf-8")), clean=False) or ""


def run(program: str, args: list[str] | None = None) -> int:
    """Run console script ``program``: ``--help`` (exit 0) and bad plain arguments (exit 2) before its module loads.

    A Ctrl-C while the module imports (torch, open3d: seconds), before the node handles signals, is one line and
    exit 130, not an import traceback.
    """
    module = PROGRAMS[program]
    script_args(program, module_doc(module), args, bag=program == "bag_player")  # may exit
    try:
        main = importlib.import_module(module).main
    except KeyboardInterrupt:
        print(f"{program}: interrupted", file=sys.stderr)
        return 130
    return int(main(args))


def bag_player() -> int:
    """Console script ``bag_player``."""
    return run("bag_player")


def mapper() -> int:
    """Console script ``mapper``."""
    return run("mapper")


def nbv_planner() -> int:
    """Console script ``nbv_planner``."""
    return run("nbv_planner")


def keyframe_selector() -> int:
    """Console script ``keyframe_selector``."""
    return run("keyframe_selector")


def active_mapping() -> int:
    """Console script ``active_mapping``."""
    return run("active_mapping")


def main(argv: list[str] | None = None) -> int:
    """``python -m roigsf_ros.nodes.console PROGRAM [ARGS]``: what the console script ``PROGRAM`` runs."""
    argv = list(sys.argv if argv is None else argv)
    if len(argv) < 2 or argv[1] not in PROGRAMS:
        print(f"usage: python -m roigsf_ros.nodes.console {{{','.join(PROGRAMS)}}} [ARGS]", file=sys.stderr)
        return 2
    return run(argv[1], [argv[1], *argv[2:]])


__all__ = [
    "PROGRAMS",
    "active_mapping",
    "bag_player",
    "keyframe_selector",
    "main",
    "mapper",
    "module_doc",
    "nbv_planner",
    "run",
]


if __name__ == "__main__":
    sys.exit(main())
