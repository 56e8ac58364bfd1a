"""The code base stays ruff-clean (the project's lint configuration lives in pyproject.toml)."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_ruff_clean() -> None:
    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    if not Path(ruff).exists():
        pytest.skip("ruff is not installed (scripts/setup.sh installs it)")
    proc = subprocess.run([ruff, "check", "--no-cache", str(REPO)], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_package_metadata_consistent() -> None:
    """package.xml, setup.py and the ament marker agree on the package name and version."""
    import xml.etree.ElementTree as ET

    root = ET.parse(REPO / "package.xml").getroot()
    assert root.get("format") == "3"
    assert root.findtext("name") == "roigsf_ros"
    setup_text = (REPO / "setup.py").read_text()
    assert f'version="{root.findtext("version")}"' in setup_text
    assert (REPO / "resource" / "roigsf_ros").is_file()
    assert "install_scripts=$base/lib/roigsf_ros" in (REPO / "setup.cfg").read_text()


@pytest.mark.parametrize(
    "script", sorted(str(p.relative_to(REPO)) for p in [*(REPO / "scripts").glob("*.sh"), REPO / ".ci" / "run"])
)
def test_shell_script_parses(script: str) -> None:
    """Every shell script (the figure scripts run for minutes before reaching their last lines) is valid bash."""
    proc = subprocess.run(["bash", "-n", script], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
