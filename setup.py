"""setuptools build for the cwfs_ros ROS 2 (ament_python) package.

Works with ``pip install -e .`` in the project venv (see tools/bootstrap.sh)
and with ``colcon build`` in a full ROS 2 Jazzy install.
"""

import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE_NAME = "cwfs_ros"
HERE = os.path.dirname(os.path.abspath(__file__))


def config_data_files():
    """Install config/** into share/cwfs_ros/config, keeping sub-directories."""
    out = {}
    config_root = os.path.join(HERE, "config")
    for path in sorted(glob(os.path.join(config_root, "**", "*"), recursive=True)):
        if not os.path.isfile(path):
            continue
        rel_dir = os.path.relpath(os.path.dirname(path), HERE)
        dest = os.path.join("share", PACKAGE_NAME, rel_dir)
        out.setdefault(dest, []).append(os.path.relpath(path, HERE))
    return sorted(out.items())


setup(
    name=PACKAGE_NAME,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={"cwfs_ros.sim": ["data/bending/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE_NAME}"]),
        (f"share/{PACKAGE_NAME}", ["package.xml"]),
        *config_data_files(),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="cwfs_ros maintainers",
    maintainer_email="cwfs-ros@example.org",
    description="Curvature wavefront sensing for Rubin/LSST as ROS 2 nodes",
    license="GPL-3.0-or-later",
    python_requires=">=3.11,<3.14",
    entry_points={
        "console_scripts": [
            "cwfs-ros = cwfs_ros.cli:main",
            "wavefront_node = cwfs_ros.ros.wavefront_node:main",
            "ofc_node = cwfs_ros.ros.ofc_node:main",
            "camera_sim_node = cwfs_ros.ros.camera_sim_node:main",
        ],
    },
)
