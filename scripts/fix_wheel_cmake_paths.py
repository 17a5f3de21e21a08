"""Rewrite the build machine's Python paths baked into the ROS wheels' CMake exports.

The ros-jazzy wheels were built under /opt/python/cp311-cp311 and their exported CMake
targets name that interpreter's include dir and numpy's include dir; CMake refuses targets
whose include paths do not exist ("Imported target ... includes non-existent path").
Running this twice is harmless: after the first run the old prefixes are gone.
"""

import pathlib
import sys
import sysconfig

import numpy

BUILD_MACHINE_PYTHON_INCLUDE = "/opt/python/cp311-cp311/include/python3.11"
BUILD_MACHINE_NUMPY_INCLUDE = (
    "/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include"
)


def main(venv: pathlib.Path) -> int:
    replacements = {
        BUILD_MACHINE_NUMPY_INCLUDE: numpy.get_include(),
        BUILD_MACHINE_PYTHON_INCLUDE: sysconfig.get_paths()["include"],
    }
    fixed = 0
    for cmake_file in (venv / "share").glob("**/cmake/*.cmake"):
        text = cmake_file.read_text()
        new_text = text
        for old, new in replacements.items():
            new_text = new_text.replace(old, new)
        if new_text != text:
            cmake_file.write_text(new_text)
            fixed += 1
    print(f"fix_wheel_cmake_paths: rewrote {fixed} CMake file(s) under {venv}/share")
    return 0


if __name__ == "__main__":
    sys.exit(main(pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else sys.prefix)))
