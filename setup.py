"""Which packages the qnav distribution ships (the metadata is in pyproject.toml).

The three programs' packages are found as usual; the top-level `policies/`
folder, the source of truth for the shipped policies, is shipped as the
package `qnav_policies` so an installed qnav finds them without a checkout
(`firmware_py.shipped_policies`). pyproject.toml's `[tool.setuptools]`
cannot combine `packages.find` with a renamed package, hence this file.
"""

from setuptools import find_packages, setup

PACKAGES = find_packages(include=["firmware_py*", "ground_station*", "sim_bridge*"])
DATA_PACKAGES = ["ground_station.maps_data", "qnav_policies", "firmware_py.profiles", "firmware_py.deploy"]  # folders of data, named so setuptools ships them

setup(
    packages=PACKAGES + DATA_PACKAGES,
    package_dir={"qnav_policies": "policies"},
    package_data={
        "firmware_py": ["*.dbc"],
        "firmware_py.mavlink": ["*.xml"],
        "firmware_py.profiles": ["*.toml"],
        "firmware_py.deploy": ["*.service"],  # the systemd unit (docs/deploy.md)  # an example robot profile per backend (docs/robot-profile.md)  # extra.xml: messages pymavlink lacks (mavlink/extra.py)
        "ground_station.logs": ["*.json"],  # the Foxglove layout (docs/monitor.md)
        "ground_station.maps_data": ["*"],
        "qnav_policies": ["*.qtab", "*.json", "README.md"],
    },
)
