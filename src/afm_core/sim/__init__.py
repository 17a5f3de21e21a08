"""The simulated AFM instrument: sample world, tip, scanner, drift, imaging, pushing.

`SimulatedAfm` (instrument.py) is the entry point; `load_config` (config.py) reads the one
documented parameter file, default_config.yaml.
"""
