from setuptools import setup

package_name = "afm_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=[package_name],
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="AFM nano-manipulation maintainers",
    maintainer_email="maintainers@afm-nanorobotics.org",
    description="ROS glue the nodes share: topics, QoS, conversions, parameters, action client, "
    "the driver's actions as a core Instrument, the node main loop.",
    license="Apache-2.0",
)
