"""The package's layering: every module imports, no module imports from a layer above it, no cycles, no private names.

Layers, lowest first (``docs/architecture.md``): a module may import from its own layer and the ones below.
Imports inside functions count too: a lazy import that goes upwards is still an upward dependency.
"""

from __future__ import annotations

import ast
import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "roigsf_ros"
LAYERS = ("core", "data", "render", "evaluation", "mapping", "nbv", "policies", "experiments", "nodes", "perf", "cli")


def module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


MODULES = {module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def layer(module: str) -> int | None:
    """Index of the module's layer in LAYERS; None for the package root."""
    parts = module.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 else None


def package_imports(path: Path) -> list[tuple[str, list[str], bool]]:
    """(imported roigsf_ros module, names taken from it, at module level?) for every import in the file."""
    tree = ast.parse(path.read_text())
    top = set(map(id, tree.body))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("roigsf_ros"):
            names = [a.name for a in node.names]
            # ``from roigsf_ros.pkg import mod``: a submodule import, not a name taken from pkg
            subs = [n for n in names if f"{node.module}.{n}" in MODULES]
            for n in subs:
                out.append((f"{node.module}.{n}", [], id(node) in top))
            rest = [n for n in names if n not in subs]
            if rest or not subs:
                out.append((node.module, rest, id(node) in top))
        elif isinstance(node, ast.Import):
            out += [(a.name, [], id(node) in top) for a in node.names if a.name.startswith("roigsf_ros")]
    return out


@pytest.mark.parametrize("module", sorted(m for m in MODULES if not m.endswith("__main__")))
def test_every_module_imports(module: str) -> None:
    importlib.import_module(module)


def test_layers_exist_as_packages_with_public_api() -> None:
    for name in LAYERS:
        init = PKG / name / "__init__.py"
        assert init.is_file(), f"layer {name} has no __init__.py"
        mod = importlib.import_module(f"roigsf_ros.{name}")
        if name not in ("nodes", "perf", "cli"):  # entry points, not a library API
            assert mod.__all__, f"roigsf_ros.{name} exports nothing"
            for attr in mod.__all__:
                assert getattr(mod, attr) is not None, f"roigsf_ros.{name}.{attr}"


def test_no_upward_import() -> None:
    bad = []
    for module, path in MODULES.items():
        here = layer(module)
        for target, _, _ in package_imports(path):
            there = layer(target)
            if here is not None and there is not None and there > here:
                bad.append(f"{module} imports {target} ({LAYERS[here]} -> {LAYERS[there]})")
    assert not bad, "upward imports:\n" + "\n".join(bad)


def test_no_private_name_crosses_a_module() -> None:
    bad = [
        f"{module} imports {name} from {target}"
        for module, path in MODULES.items()
        for target, names, _ in package_imports(path)
        for name in names
        if name.startswith("_") and target != module
    ]
    assert not bad, "\n".join(bad)


def test_no_import_cycle() -> None:
    """Module-level imports between modules form no cycle (package ``__init__`` files resolve lazily)."""
    graph = {
        m: {t for t, _, top in package_imports(p) if top and t in MODULES and t != m and not t.endswith("__init__")}
        for m, p in MODULES.items()
        if p.name != "__init__.py"
    }
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for t in sorted(graph.get(m, ())):
            if state.get(t) == 1:
                return [*stack[stack.index(t) :], t]
            if t not in state and (cycle := visit(t)):
                return cycle
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (cycle := visit(m)):
            pytest.fail("import cycle: " + " -> ".join(cycle))


def test_the_checks_catch_what_they_look_for(tmp_path: Path) -> None:
    """The AST reading sees upward, private and lazy imports (a check that cannot fail is no check)."""
    src = tmp_path / "m.py"
    src.write_text(
        "from roigsf_ros.nbv.scorer import _private, NBVScorer\ndef f():\n    from roigsf_ros.cli import main\n"
    )
    found = package_imports(src)
    assert ("roigsf_ros.nbv.scorer", ["_private", "NBVScorer"], True) in found
    assert ("roigsf_ros.cli", ["main"], False) in found
    assert layer("roigsf_ros.cli.map") > layer("roigsf_ros.nbv.scorer") > layer("roigsf_ros.core.camera")


def test_layer_exports_are_its_modules_public_names() -> None:
    """A layer's ``__all__`` is exactly the union of its modules' ``__all__`` (the reference renderer excepted)."""
    for name in LAYERS[:8]:
        pkg = importlib.import_module(f"roigsf_ros.{name}")
        union: set[str] = set()
        for path in sorted((PKG / name).glob("*.py")):
            if path.name != "__init__.py" and module_name(path) != "roigsf_ros.render.reference":
                union |= set(importlib.import_module(module_name(path)).__all__)
        assert set(pkg.__all__) == union, f"roigsf_ros.{name}: {sorted(set(pkg.__all__) ^ union)}"


def test_dir_and_help_of_a_layer_list_its_lazy_exports() -> None:
    """``dir()`` (tab completion) and ``help()`` of a layer showed only ``__getattr__`` and ``lazy_exports``: the
    exports load on first use, so the package needs a module ``__dir__`` listing them."""
    import pydoc

    for name in LAYERS[:8]:
        pkg = importlib.import_module(f"roigsf_ros.{name}")
        listed = dir(pkg)
        assert set(pkg.__all__) <= set(listed), f"roigsf_ros.{name}: {sorted(set(pkg.__all__) - set(listed))}"
        assert {"__name__", "__doc__", "__all__"} <= set(listed) and listed == sorted(listed)
    nbv = importlib.import_module("roigsf_ros.nbv")
    assert {"NBVConfig", "NBVScorer", "ScoringState"} <= set(dir(nbv))
    assert "class NBVScorer" in pydoc.render_doc(nbv, renderer=pydoc.plaintext)


def test_config_files_name_only_modules_and_objects_that_exist() -> None:
    """The params files' comments point to the code (``roigsf_ros.policies.base.make_policy``,
    ``roigsf_ros/nodes/mapper.py``); keyframe_selector.yaml named ``nbv_policies``, which exists nowhere."""
    import re

    names = []
    for path in sorted((PKG.parent / "config").glob("*.yaml")):
        text = path.read_text()
        assert "nbv_policies" not in text, f"{path.name} names nbv_policies (the policies are roigsf_ros.policies)"
        names += [(path.name, n.rstrip(".")) for n in re.findall(r"roigsf_ros[./][\w./]*", text)]
    assert names
    for file, name in names:
        if "/" in name:
            assert (PKG.parent / name).is_file(), f"{file}: {name}"
            continue
        parts = name.split(".")
        k = max(i for i in range(1, len(parts) + 1) if ".".join(parts[:i]) in MODULES)
        obj = importlib.import_module(".".join(parts[:k]))
        for attr in parts[k:]:
            assert hasattr(obj, attr), f"{file}: {name}"
            obj = getattr(obj, attr)


def test_importing_torch_first_warns_that_openmp_will_spin() -> None:
    """OMP_WAIT_POLICY=PASSIVE only takes effect before torch loads: importing torch first must say so."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    code = "import os, warnings; warnings.simplefilter('error'); {}; import roigsf_ros\n"
    code += "print(os.environ['OMP_WAIT_POLICY'])"
    late = subprocess.run([sys.executable, "-c", code.format("import torch")], env=env, capture_output=True, text=True)
    assert late.returncode != 0 and "import roigsf_ros first" in late.stderr
    first = subprocess.run([sys.executable, "-c", code.format("pass")], env=env, capture_output=True, text=True)
    assert first.returncode == 0 and first.stdout.strip() == "PASSIVE", first.stderr
