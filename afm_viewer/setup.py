from glob import glob

from setuptools import setup

package_name = "afm_viewer"

setup(
    name=package_name,
    version="0.1.0",
    packages=[package_name],
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/foxglove", glob("foxglove/*.json")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="AFM nano-manipulation maintainers",
    maintainer_email="maintainers@afm-nanorobotics.org",
    description="Live view of the graph in Foxglove (Foxglove SDK WebSocket server).",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "viewer = afm_viewer.viewer_node:main",
        ],
    },
)
