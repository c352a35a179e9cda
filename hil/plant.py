"""The plant: the vehicle model integrated with fixed-step RK4, commands in, sensor samples out.

`Plant` is the one stateful object: built ready to use from a vehicle, it advances on an
integer step grid (default 1 ms), holds the last command (a command set at time t applies from
the first step at or after t), and emits sensor samples at their own rates (the first at t = 0),
each delayed by `sensors.delay` (rounded to the step grid). Noise comes from one seeded
generator drawn in a fixed order, so a seed gives the same samples bit for bit.
It owns no clock and no link: the open-loop simulator, the HIL endpoint and the tests drive it.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from onboard import model
from onboard.sensors import (
    ActuatorSample,
    AttitudeSample,
    ImuSample,
    PressureSample,
    TruthSample,
    attitude_sample,
    imu_sample,
    pressure_sample,
    truth_sample,
)
from onboard.vehicle import Vehicle

STREAMS = ("imu", "pressure", "attitude")


@dataclass
class Samples:
    """Sensor samples produced by one `Plant.advance` call, in time order per stream."""

    imu: list = field(default_factory=list)  # ImuSample
    pressure: list = field(default_factory=list)  # PressureSample
    attitude: list = field(default_factory=list)  # AttitudeSample
    truth: list = field(default_factory=list)  # TruthSample at the IMU instants


class Plant:
    """A simulated vehicle: `set_command`, then `advance(t)`; read `state`, `time_s`."""

    def __init__(
        self,
        vehicle: Vehicle,
        dt_s: float = 0.001,
        seed: int = 0,
        depth_m: float = 0.5,
        command=None,
        noise: bool = True,
        state=None,
        rig_stiffness=None,
        rig_anchor=None,
    ):
        self.vehicle = vehicle
        self.dt_s = float(dt_s)
        self.params = model.pack_params(vehicle)
        if rig_stiffness is not None:  # seed 001 spring rig: K (N/m, NED x y z) to an anchor
            self.params[model.P_RIG_K:model.P_RIG_K + 3] = rig_stiffness
            anchor = (0.0, 0.0, vehicle.environment.surface_depth + depth_m) if rig_anchor is None else rig_anchor
            self.params[model.P_RIG_ANCHOR:model.P_RIG_ANCHOR + 3] = anchor
        self.layout = model.StateLayout(vehicle.n_units)
        k = vehicle.n_units
        self.command = np.zeros(3 * k) if command is None else np.asarray(command, float).copy()
        self.state = (
            model.initial_state(vehicle, depth_m, self.command) if state is None
            else np.asarray(state, float).copy()
        )
        self.step_index = 0
        self.rng = np.random.default_rng(seed)
        self.noise = noise
        s = vehicle.sensors
        self._period = {
            "imu": 1.0 / s.imu_rate,
            "pressure": 1.0 / s.pressure_rate,
            "attitude": 1.0 / s.attitude_rate,
        }
        self._count = {name: 0 for name in STREAMS}
        self._delay_steps = int(round(s.delay / self.dt_s))
        self._pending: deque = deque()  # (emit_step, stream, sample) awaiting the sensor delay

    # -- time --------------------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        return self.step_index * self.dt_s

    def _sample_step(self, stream: str, count: int) -> int:
        return int(round(count * self._period[stream] / self.dt_s))

    def set_command(self, command) -> None:
        """Hold this command [n_cmd, alpha_cmd, beta_cmd] from the current step on."""
        c = np.asarray(command, dtype=float)
        if c.shape != self.command.shape or not np.all(np.isfinite(c)):
            raise ValueError(f"command must be {self.command.shape[0]} finite values, got {c!r}")
        self.command = c.copy()

    # -- stepping ----------------------------------------------------------------------------
    def advance(self, t_end_s: float) -> Samples:
        """Integrate up to the last step at or before `t_end_s`, sampling on the way."""
        end_step = int(np.floor(t_end_s / self.dt_s + 1e-9))
        out = Samples()
        while True:
            self._sample_due(out)
            if self.step_index >= end_step:
                break
            # stop where a sample is taken and where a delayed one is due: a delay between two
            # sampling instants is handed out on time, not at the next instant (which made a
            # 52 ms delay at a 100 Hz IMU a 60 ms one)
            nxt = min(
                [self._sample_step(s, self._count[s]) for s in STREAMS] + [end_step]
                + ([self._pending[0][0]] if self._pending else [])
            )
            n = max(nxt - self.step_index, 1)
            self.state = model.rk4_steps(self.state, self.command, self.params, self.dt_s, n)
            self.step_index += n
        return out

    def _sample_due(self, out: Samples) -> None:
        """Take every sample whose instant is now; release delayed samples that are due."""
        due = [s for s in STREAMS if self._sample_step(s, self._count[s]) <= self.step_index]
        if due:
            x = self.state
            xdot = np.zeros_like(x)
            model.derivative(x, self.command, self.params, xdot)  # xdot: the accelerometer's truth
            t = self.time_s
            for stream in due:
                self._count[stream] += 1
                sample = self._measure(stream, t, x, xdot)
                if stream == "imu":
                    out.truth.append(truth_sample(t, x))
                self._pending.append((self.step_index + self._delay_steps, stream, sample))
        while self._pending and self._pending[0][0] <= self.step_index:
            _, stream, sample = self._pending.popleft()
            if self._delay_steps:
                sample = replace(sample, time_s=self.time_s)
            getattr(out, stream).append(sample)

    def _measure(self, stream: str, t: float, x, xdot):
        s = self.vehicle.sensors
        z = self._gauss
        if stream == "imu":
            return imu_sample(t, x, xdot, self.params, self.vehicle, z(3, s.accel_noise), z(3, s.gyro_noise))
        if stream == "pressure":
            return pressure_sample(t, x, self.params, float(z(1, s.pressure_noise)[0]))
        return attitude_sample(t, x, z(3, s.attitude_noise))

    def _gauss(self, n: int, sigma: float) -> np.ndarray:
        draw = self.rng.standard_normal(n)  # always drawn, so noise on/off keeps the sequence
        return draw * sigma if self.noise else np.zeros(n)

    # -- what the actuators are doing ------------------------------------------------------------
    def actuators(self, pwm_us) -> ActuatorSample:
        """Commanded PWM (as given) and measured propeller rpm of each unit, now."""
        n = self.state[self.layout.n]
        return ActuatorSample(self.time_s, tuple(int(c) for c in pwm_us), tuple(float(r) for r in 60.0 * n))


__all__ = [
    "Plant",
    "Samples",
    "ImuSample",
    "PressureSample",
    "AttitudeSample",
    "TruthSample",
    "ActuatorSample",
]
