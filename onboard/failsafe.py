"""Failsafe: a pure state machine over arming, IMU freshness and estimator health.

States (`Mode`): DISARMED (outputs safe), ARMED (the controller drives the jets) and FAILSAFE
(outputs safe, latched with its reason). Each transition is a pure function of a frozen
`FailsafeState` and an event, returning the next state; the loop owns the clock and the link.

    DISARMED --arm, IMU fresh, estimator healthy---------> ARMED
    DISARMED --arm, otherwise (incl. an IMU fault)---------> DISARMED (reason: why refused)
    ARMED    --tick, no IMU for imu_timeout_s (0.3 s)-------> FAILSAFE (reason)
    ARMED    --tick, estimator diverged--------------------> FAILSAFE (reason)
    ARMED    --tick, IMU fault (frozen: samples that never change)-> FAILSAFE (reason)
    ARMED    --disarm----------------------------------------> DISARMED
    FAILSAFE --anything but disarm/reset (IMU back, arm)----> FAILSAFE (recovery is not automatic)
    FAILSAFE --disarm or reset (explicit operator action)---> DISARMED, then arm again

The safe output (`safe_command`) is zero propeller speed with every joint at neutral: the
vehicle is positively buoyant (about 1.5 N on the reference vehicle), so it ascends slowly and
stays upright on its righting moment. A frozen IMU (onboard.monitor: identical samples) is treated
as a lost one: its samples do not refresh `last_imu_s`, and `imu_fault` trips the failsafe at once
rather than after the timeout. The loop should also `Estimator.reset()` on recovery,
since arming is refused while the estimator still reports divergence.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import Enum

import numpy as np

IMU_TIMEOUT_S = 0.3
_EPS_S = 1e-9  # timestamps are sums of steps: 1.3 - 1.0 must count as 0.3, not as 0.30000000000000004


class Mode(Enum):
    DISARMED = "disarmed"
    ARMED = "armed"
    FAILSAFE = "failsafe"


@dataclass(frozen=True)
class FailsafeState:
    mode: Mode = Mode.DISARMED
    reason: str = ""  # why the last transition (or refusal) happened
    since_s: float = 0.0  # time the current mode was entered
    last_imu_s: float | None = None  # time of the last IMU sample received
    imu_timeout_s: float = IMU_TIMEOUT_S

    @property
    def outputs_enabled(self) -> bool:
        """True only when ARMED: otherwise the jets get `safe_command`."""
        return self.mode is Mode.ARMED

    def imu_age_s(self, time_s: float) -> float:
        """Seconds since the last IMU sample (inf if none yet)."""
        return math.inf if self.last_imu_s is None else time_s - self.last_imu_s


def _time(name: str, time_s) -> float:
    try:
        t = float(time_s)
    except (TypeError, ValueError):
        raise ValueError(f"failsafe.{name}: time_s must be a finite number of seconds, got {time_s!r}") from None
    if not math.isfinite(t):
        raise ValueError(f"failsafe.{name}: time_s must be a finite number of seconds, got {time_s!r}")
    return t


def _go(state: FailsafeState, mode: Mode, reason: str, time_s: float) -> FailsafeState:
    return replace(state, mode=mode, reason=reason, since_s=time_s)


def on_imu(state: FailsafeState, time_s: float) -> FailsafeState:
    """An IMU sample arrived at time_s (the loop's clock). Never leaves FAILSAFE by itself."""
    t = _time("on_imu", time_s)
    last = state.last_imu_s
    return replace(state, last_imu_s=t if last is None else max(last, t))


def on_tick(state: FailsafeState, time_s: float, estimator_diverged: bool = False,
            estimator_reason: str = "", imu_fault: str = "") -> FailsafeState:
    """Check the conditions at time_s: IMU older than the timeout, an IMU fault (e.g. "frozen",
    from onboard.monitor: its samples are not fresh ones), or estimator divergence."""
    t = _time("on_tick", time_s)
    if state.mode is not Mode.ARMED:
        return state
    age = state.imu_age_s(t)
    if age > state.imu_timeout_s + _EPS_S:
        return _go(state, Mode.FAILSAFE, f"no IMU for {age:.2f} s (limit {state.imu_timeout_s:.2f} s)", t)
    if imu_fault:
        return _go(state, Mode.FAILSAFE, f"IMU {imu_fault}", t)
    if estimator_diverged:
        return _go(state, Mode.FAILSAFE, f"estimator diverged: {estimator_reason or 'unspecified'}", t)
    return state


def on_arm(state: FailsafeState, time_s: float, estimator_diverged: bool = False,
           imu_fault: str = "") -> FailsafeState:
    """Arm request: granted from DISARMED when the IMU is fresh (and not faulty) and the estimator healthy."""
    t = _time("on_arm", time_s)
    if state.mode is Mode.ARMED:
        return state
    if state.mode is Mode.FAILSAFE:
        return replace(state, reason=f"{state.reason}; arm refused: disarm (or reset) first")
    age = state.imu_age_s(t)
    if age > state.imu_timeout_s + _EPS_S:
        why = "no IMU yet" if state.last_imu_s is None else f"no IMU for {age:.2f} s"
        return replace(state, reason=f"arm refused: {why}")
    if imu_fault:
        return replace(state, reason=f"arm refused: IMU {imu_fault}")
    if estimator_diverged:
        return replace(state, reason="arm refused: estimator diverged (reset it)")
    return _go(state, Mode.ARMED, "armed", t)


def on_disarm(state: FailsafeState, time_s: float) -> FailsafeState:
    """Disarm: the explicit recovery from FAILSAFE, and the normal way out of ARMED."""
    t = _time("on_disarm", time_s)
    if state.mode is Mode.DISARMED:
        return state
    why = f"disarmed after failsafe ({state.reason})" if state.mode is Mode.FAILSAFE else "disarmed"
    return _go(state, Mode.DISARMED, why, t)


def on_reset(state: FailsafeState, time_s: float) -> FailsafeState:
    """Operator acknowledges a failsafe: FAILSAFE -> DISARMED (same as disarm, named for logs)."""
    t = _time("on_reset", time_s)
    if state.mode is not Mode.FAILSAFE:
        return state
    return _go(state, Mode.DISARMED, f"failsafe reset ({state.reason})", t)


def safe_command(n_units: int) -> np.ndarray:
    """u = [n_cmd = 0 x k, alpha_cmd = 0 x k, beta_cmd = 0 x k]: no thrust, joints neutral."""
    if int(n_units) != n_units or n_units < 1:
        raise ValueError(f"safe_command: n_units must be a positive integer, got {n_units!r}")
    return np.zeros(3 * int(n_units))


__all__ = [
    "IMU_TIMEOUT_S",
    "FailsafeState",
    "Mode",
    "on_arm",
    "on_disarm",
    "on_imu",
    "on_reset",
    "on_tick",
    "safe_command",
]
