"""`DaqBoundary` on NI-DAQmx through the `nidaqmx` Python package (imported lazily).

Synchronisation: the AO task runs on the device's onboard sample clock in finite mode with
regeneration off; the AI task is clocked by `/<device>/ao/SampleClock`, and is started
first so it is armed and takes exactly one conversion per AO update. AO sample k and AI
sample k therefore share a clock edge with no trigger latency or drift, which is what a
local scan and the raster pixel binning rely on. Static holds use a second AO task on the
same channels with on-demand timing; only one of the two holds the channels' reservation at
a time, and the outputs keep their last level when a task stops.

Construction checks package, driver and device and raises `DaqUnavailable` naming what is
missing, so a driver node started without hardware fails at start-up with that message.
"""

from __future__ import annotations

import math

import numpy as np

from afm_core.daq.boundary import DaqUnavailable


def _driver_error(error: Exception) -> DaqUnavailable:
    kind = type(error).__name__
    if kind == "DaqNotSupportedError":
        return DaqUnavailable(f"NI-DAQmx is not supported on this platform: {error}")
    if kind == "DaqNotFoundError" or isinstance(error, OSError):
        return DaqUnavailable(
            "NI-DAQmx driver/runtime not found: the 'nidaqmx' Python package is installed but the "
            "NI-DAQmx driver is not "
            "(install it from NI; on Linux `python -m nidaqmx installdriver`). "
            f"Driver said: {error}"
        )
    return DaqUnavailable(f"NI-DAQmx could not list the local devices: {kind}: {error}")


class NidaqmxBoundary:
    """The DAQ card `device` (NI MAX name, e.g. "Dev1") driven through NI-DAQmx.

    Channel names given to `configure` may be device-relative ("ao0") or full ("Dev1/ao0").
    `terminal_config` names a nidaqmx.constants.TerminalConfiguration member for the AI
    channels ("DEFAULT", "RSE", "NRSE", "DIFF"): how the controller's monitor BNCs are wired.
    """

    def __init__(
        self, device: str = "Dev1", terminal_config: str = "DEFAULT", timeout_margin: float = 5.0
    ):
        try:
            import nidaqmx
            import nidaqmx.system
        except ImportError as e:
            raise DaqUnavailable(
                "NI-DAQmx unavailable: the Python package 'nidaqmx' is not installed "
                f"(pip install nidaqmx; it also needs the NI-DAQmx driver) [{e}]"
            ) from e
        try:
            names = list(nidaqmx.system.System.local().devices.device_names)
        except Exception as e:  # the driver is loaded on this first call
            raise _driver_error(e) from e
        if device not in names:
            raise DaqUnavailable(
                f'DAQ device "{device}" not present; NI-DAQmx sees: '
                f"{', '.join(names) if names else 'no devices'}"
            )
        self._nidaqmx = nidaqmx
        self.device = device
        self.terminal_config = terminal_config
        self.timeout_margin = timeout_margin
        self.sample_rate = 0.0
        self._ao = self._ai = self._static = None
        self._writer = self._reader = None
        self._n_ai = 0

    def _physical(self, channel: str) -> str:
        return channel if "/" in channel else f"{self.device}/{channel}"

    def configure(
        self,
        ao_channels: list[str],
        ai_channels: list[str],
        sample_rate: float,
        ao_range: tuple[float, float],
        ai_range: tuple[float, float],
    ) -> None:
        self._close_tasks()
        try:
            self._configure(ao_channels, ai_channels, sample_rate, ao_range, ai_range)
            self._verify_rate(float(sample_rate))
        except Exception as exc:
            self._close_tasks()
            if isinstance(exc, DaqUnavailable):
                raise
            # At start-up, so the node stops naming the set-up instead of a driver traceback.
            raise DaqUnavailable(
                f"NI-DAQmx refused the set-up on {self.device} (AO {list(ao_channels)} in "
                f"{tuple(ao_range)} V, AI {list(ai_channels)} in {tuple(ai_range)} V, "
                f"{float(sample_rate):g} Hz): {type(exc).__name__}: {exc}"
            ) from exc

    def _configure(self, ao_channels, ai_channels, sample_rate, ao_range, ai_range) -> None:
        from nidaqmx.constants import RegenerationMode, TerminalConfiguration
        from nidaqmx.stream_readers import AnalogMultiChannelReader
        from nidaqmx.stream_writers import AnalogMultiChannelWriter

        Task = self._nidaqmx.Task
        # One at a time: a failure leaves the ones made so far for _close_tasks to free.
        self._ao = Task("afm_ao_ramp")
        self._ai = Task("afm_ai")
        self._static = Task("afm_ao_static")
        terminal = TerminalConfiguration[self.terminal_config]
        for channel in ao_channels:
            for task in (self._ao, self._static):
                task.ao_channels.add_ao_voltage_chan(
                    self._physical(channel), min_val=ao_range[0], max_val=ao_range[1]
                )
        for channel in ai_channels:
            self._ai.ai_channels.add_ai_voltage_chan(
                self._physical(channel),
                terminal_config=terminal,
                min_val=ai_range[0],
                max_val=ai_range[1],
            )
        # Never replay stale samples: a late write must fail, not repeat a ramp.
        self._ao.out_stream.regen_mode = RegenerationMode.DONT_ALLOW_REGENERATION
        self._writer = AnalogMultiChannelWriter(self._ao.out_stream, auto_start=False)
        self._reader = AnalogMultiChannelReader(self._ai.in_stream)
        self._n_ai = len(ai_channels)
        self.sample_rate = float(sample_rate)

    def _clock(self, n: int) -> None:
        """Both tasks finite, n samples, AI on the AO sample clock."""
        from nidaqmx.constants import AcquisitionType

        self._ao.timing.cfg_samp_clk_timing(
            self.sample_rate, sample_mode=AcquisitionType.FINITE, samps_per_chan=n
        )
        self._ai.timing.cfg_samp_clk_timing(
            self.sample_rate,
            source=f"/{self.device}/ao/SampleClock",
            sample_mode=AcquisitionType.FINITE,
            samps_per_chan=n,
        )

    def _verify_rate(self, sample_rate: float) -> None:
        """Make the driver check the timing now, at start-up, not at the first scan; and refuse
        a rate the card would silently coerce (its clock divides a timebase), since every
        speed and time above assumes `sample_rate` exactly."""
        from nidaqmx.constants import TaskMode

        self._clock(2)
        for task in (self._ao, self._ai):
            task.control(TaskMode.TASK_VERIFY)
        actual = float(self._ao.timing.samp_clk_rate)
        if not math.isclose(actual, sample_rate, rel_tol=1e-9):
            raise DaqUnavailable(
                f"sample_rate={sample_rate:g} Hz: {self.device}'s sample clock cannot run at "
                f"that rate and would run at {actual:.10g} Hz; set sample_rate to {actual:.10g}"
                " (or a rate its timebase divides exactly)"
            )

    def write_read(self, ao_samples: np.ndarray) -> np.ndarray:
        if self._ao is None:
            raise RuntimeError("NidaqmxBoundary: write_read before configure")
        data = np.ascontiguousarray(ao_samples, dtype=np.float64)
        n = data.shape[1]
        self._clock(n)
        self._writer.write_many_sample(data)
        readings = np.zeros((self._n_ai, n))
        timeout = n / self.sample_rate + self.timeout_margin
        self._ai.start()  # armed: waits for the AO sample clock
        try:
            self._ao.start()
            try:
                self._reader.read_many_sample(
                    readings, number_of_samples_per_channel=n, timeout=timeout
                )
                self._ao.wait_until_done(timeout=self.timeout_margin)
            finally:
                self._ao.stop()
        finally:
            self._ai.stop()
        return readings

    def write_static(self, volts: np.ndarray) -> None:
        from nidaqmx.constants import TaskMode

        if self._static is None:
            raise RuntimeError("NidaqmxBoundary: write_static before configure")
        # A ramp task that had samples written may stay committed after stop: release its
        # channels explicitly so the on-demand task can take them.
        self._ao.control(TaskMode.TASK_UNRESERVE)
        self._static.start()
        try:
            self._static.write([float(v) for v in np.ravel(volts)])
        finally:
            self._static.stop()
            self._static.control(TaskMode.TASK_UNRESERVE)  # free for the next ramp; levels hold

    def _close_tasks(self) -> None:
        for task in (self._ao, self._ai, self._static):
            if task is not None:
                task.close()
        self._ao = self._ai = self._static = None

    def close(self) -> None:
        self._close_tasks()
