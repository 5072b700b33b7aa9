"""The package's foundation: one home per constant, the stable entry points, the error tree."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import yaml

import cwfs_ros
from cwfs_ros import errors, layout
from cwfs_ros.config import config_dir

PACKAGE = Path(cwfs_ros.__file__).resolve().parent


def test_layout_matches_the_sensor_file_and_the_dof_file():
    sensors = yaml.safe_load((config_dir() / "sensors" / "lsst_corners.yaml").read_text())
    assert tuple(sensors["corners"]) == layout.CORNERS
    assert all(set(c) >= set(layout.SIDES) for c in sensors["corners"].values())
    assert layout.NOLL == tuple(range(4, 23)) and layout.N_ZK == 19
    assert layout.N_MEAS == 76 and layout.N_DOF == 50
    assert len(layout.DOF_NAMES) == len(layout.DOF_UNITS) == layout.N_DOF
    dof = yaml.safe_load((config_dir() / "ofc" / "dof.yaml").read_text())["dofs"]
    assert [d["name"] for d in dof] == list(layout.DOF_NAMES)
    assert [d["unit"] for d in dof] == list(layout.DOF_UNITS)
    assert layout.image_topic("R04", "extra") == "aos/wfs/R04/extra/image"
    assert layout.absolute(layout.VECTOR_TOPIC) == "/aos/wfs/wavefront"


def _assignments(tree: ast.AST) -> list[tuple[str, ast.AST]]:
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign):
            out += [(t.id, node.value) for t in node.targets if isinstance(t, ast.Name)]
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            out.append((node.target.id, node.value))
    return out


def test_each_layout_constant_is_defined_once():
    """No module but layout.py assigns a literal to a layout name, a corner tuple or Z4..Z22."""
    names = {"CORNERS", "SIDES", "NOLL", "N_ZK", "N_MEAS", "N_DOF", "DOF_NAMES", "DOF_UNITS",
             "NOLL_MIN", "NOLL_MAX", "CLOCK_RESET_S", "VECTOR_TOPIC", "CORRECTION_TOPIC"}
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.name == "layout.py" and path.parent == PACKAGE:
            continue
        text = path.read_text()
        for name, value in _assignments(ast.parse(text)):
            if name.lstrip("_") in names and isinstance(value, (ast.Constant, ast.Tuple)):
                offenders.append(f"{path.relative_to(PACKAGE)}: {name}")
        if re.search(r"range\(4, 23\)|\(\"R00\", \"R04\", \"R40\", \"R44\"\)", text):
            offenders.append(f"{path.relative_to(PACKAGE)}: a literal Noll range or corner list")
        if re.search(r"[\"']/?aos/(wfs|ofc|sim)/", text):
            offenders.append(f"{path.relative_to(PACKAGE)}: a literal topic name")
    assert offenders == []


def test_stable_entry_points():
    from cwfs_ros.core import estimate_wavefront as from_core
    from cwfs_ros.wfs.estimator import estimate_wavefront

    assert from_core is estimate_wavefront and cwfs_ros.estimate_wavefront is estimate_wavefront


def test_one_error_hierarchy():
    for cls in (errors.ConfigError, errors.ImageError, errors.BagError, errors.LaunchError,
                errors.ToolError, errors.LoopError, errors.CliError, errors.ParamsFileError):
        assert issubclass(cls, errors.CwfsError)
    from cwfs_ros.ros.bag import BagError
    from cwfs_ros.runtime.images import ImageDecodeError

    assert BagError is errors.BagError and issubclass(ImageDecodeError, errors.ImageError)
