"""Graph launcher, MCAP recorder and replay, the afm CLI and a Python API for scripts."""
