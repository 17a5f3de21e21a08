from glob import glob

from setuptools import setup

package_name = "afm_manipulation"

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
    description="Virtual nano-hand executor: push actions with feedback and cancel.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "nano_hand = afm_manipulation.nano_hand_node:main",
            "teleop = afm_manipulation.teleop_node:main",
        ],
    },
)
