from glob import glob

from setuptools import setup

package_name = "afm_imaging"

setup(
    name=package_name,
    version="0.1.0",
    packages=[package_name],
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="AFM nano-manipulation maintainers",
    maintainer_email="maintainers@afm-nanorobotics.org",
    description="Image reconstruction: thermal-drift compensation, blind tip estimation, "
    "landmark extraction.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "imaging = afm_imaging.imaging_node:main",
        ],
    },
)
