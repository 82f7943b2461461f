"""What `pip install .` puts into site-packages: hmdrt and its dist-info only. The repository's drivers/ and replay/
folders install as hmdrt.drivers and hmdrt.replay, never as top-level packages that another project may also name."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_wheel_holds_only_hmdrt(tmp_path: Path) -> None:
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "--wheel-dir", str(tmp_path), str(ROOT)],
        check=True,
        timeout=300,
    )
    (wheel,) = tmp_path.glob("hmdrt-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {name.split("/")[0] for name in names}
    assert {t for t in top if not t.endswith(".dist-info")} == {"hmdrt"}, sorted(top)
    assert len([t for t in top if t.endswith(".dist-info")]) == 1, sorted(top)
    # the drivers, their emulators and protocols, and the trace readers come along under hmdrt
    for module in ("drivers/base.py", "drivers/emulators/base.py", "drivers/protocols/smi.py", "replay/__init__.py"):
        assert f"hmdrt/{module}" in names, module
    assert "hmdrt/configs/default.toml" in names


def test_version_has_one_source() -> None:
    """The package and its metadata agree: pyproject.toml reads the version from hmdrt.version."""
    from importlib.metadata import version

    from hmdrt import __version__

    assert version("hmdrt") == __version__
