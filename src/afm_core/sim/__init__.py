"""The simulated AFM instrument: the sample it generates, its tip, scanner, drift, noise and
imaging pipeline, on the physical models it shares with the planners and estimators
(afm_core.physics: the sample's objects, pushing, tip-surface morphology).

`SimulatedAfm` (instrument.py) is the entry point; `load_config` (config.py) reads the one
documented parameter file, default_config.yaml.
"""
