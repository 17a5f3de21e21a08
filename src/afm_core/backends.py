"""The instrument behind a backend name: what the driver node serves and what offline tools
(`afm calibrate`) run against, so both open the same instrument the same way."""

from __future__ import annotations

BACKENDS = ("sim", "daq", "replay")


def open_instrument(
    backend: str,
    sim_config: str = "",
    seed: int = -1,
    daq_device: str = "",
    daq_calibration: str = "",
    replay_input: str = "",
):
    """sim: SimulatedAfm from a config file (empty: the defaults), `seed` >= 0 overrides its
    seed; daq: the NI DAQ scanner; replay: a recorded session. ValueError naming what is
    wrong (unknown backend, missing file, missing hardware)."""
    if backend == "sim":
        from afm_core.sim.config import load_config, merge
        from afm_core.sim.instrument import SimulatedAfm

        config = load_config(sim_config or None)
        if seed >= 0:
            config = merge(config, {"seed": seed})
        return SimulatedAfm(config)
    if backend == "daq":
        from afm_core.daq import open_daq_instrument

        return open_daq_instrument(daq_device, daq_calibration or None)
    if backend == "replay":
        from afm_core.recording import RecordingError
        from afm_core.replay_instrument import ReplayInstrument

        if not replay_input:
            raise ValueError("replay_input: required with backend 'replay' (a .mcap recording)")
        try:
            return ReplayInstrument(replay_input)
        except RecordingError as exc:  # missing, not MCAP, damaged
            raise ValueError(f"replay_input={replay_input!r}: {exc}") from exc
    raise ValueError(f"backend={backend!r}: expected one of {BACKENDS}")
