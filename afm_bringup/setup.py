from glob import glob

from setuptools import setup

package_name = "afm_bringup"

setup(
    name=package_name,
    version="0.1.0",
    packages=[package_name],
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/foxglove", glob("foxglove/*.json")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="AFM nano-manipulation maintainers",
    maintainer_email="maintainers@afm-nanorobotics.org",
    description="Graph launcher, MCAP recorder and replay, the afm CLI "
    "and a Python API for scripts.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "recorder = afm_bringup.recorder_node:main",
            "replay = afm_bringup.replay_node:main",
            "sim2real = afm_bringup.sim2real_node:main",
            "afm = afm_bringup.cli:main",
        ],
    },
)
