"""ROS-free core of the AFM nano-manipulation stack.

Everything here is plain numpy/scipy and importable without a ROS runtime; the ROS nodes
in afm_* packages are thin adapters over it.
"""
