#!/bin/bash
# Entrypoint of the afm image: ROS 2 Jazzy and the built workspace, then the given command.
set -e
# The setup scripts read unset variables, so no `set -u` here.
source /opt/ros/jazzy/setup.bash
source /ws/install/setup.bash
exec "$@"
