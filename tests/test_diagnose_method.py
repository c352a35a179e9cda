"""The diagnosis method (issue 18): estimate with the model, decide with calibrated odds, say what
cannot be tested; checked against hand-computed forces, the plant's true state, scipy's Wilson
interval, and the recordings of the issue's repros."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import types
import warnings

import numpy as np
import pytest
from scipy.stats import binomtest, chi2

from conftest import ARDUSUB, shared_file
from ground import prove
from ground.cli import main
from ground.diagnose import candidates, core, decide, estimate, locate, null, replay
from ground.diagnose.candidates import Evaluator
from ground.diagnose.report import no_finding_text, write_json
from ground.recording import read_recording
from hil.plant import Plant
from onboard import model
from onboard.vehicle import load_vehicle

V = load_vehicle()


def _session(tmp_path_factory, name, truth, mocap, seed=4, noise=True, duration=60.0):
    path = tmp_path_factory.mktemp("rec") / f"{name}.tlog"
    prove.record_session(truth, path, duration, seed=seed, mocap=mocap, noise=noise)
    return read_recording(path)


def _true_states(traj, vehicle):
    """The plant re-flown under the recording's held commands (noise does not touch the dynamics),
    started as `prove.record_session` starts it."""
    plant = Plant(vehicle, noise=False, depth_m=0.5)
    out = []
    for k, t in enumerate(traj.time_s):
        plant.set_command(traj.command[k])
        out.append(plant.state.copy())
        plant.advance(t + traj.dt_s)
    return np.array(out)


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """60 s pool session, reference vehicle, no motion capture."""
    return _session(tmp_path_factory, "plain", V, mocap=False)


def test_estimator_follows_the_true_state_without_motion_capture(plain):
    """Horizontal velocity from the dynamics and the sensors together: within a few cm/s of the
    plant's, and the smoother's own sd says so (normalised errors of order one)."""
    traj = Evaluator(plain, V).traj0
    X = _true_states(traj, V)
    est = traj.estimate
    inner = slice(300, -300)
    err = est.x[inner, 6:9] - X[inner, 7:10]
    assert np.sqrt(np.mean(err[:, :2] ** 2)) < 0.06  # m/s, surge and sway: never measured
    assert np.sqrt(np.mean(err[:, 2] ** 2)) < 0.02  # heave: depth is measured
    z = err / est.std[inner, 6:9]
    assert 0.2 < np.sqrt(np.mean(z ** 2)) < 2.0
    eul = np.array([model.quat_to_euler(q) for q in X[inner, 3:7]])
    assert np.abs(est.x[inner, 3:5] - eul[:, :2]).max() < 0.01  # rad
    # the right model: no disturbance beyond its own uncertainty on average
    d, s = est.disturbance[inner], est.disturbance_std[inner]
    assert np.all(np.abs(d.mean(axis=0)) < 3 * np.median(s, axis=0))


@pytest.mark.parametrize("mocap", [True, False])
def test_disturbance_is_the_missing_buoyancy_force(tmp_path_factory, mocap):
    """1 % more volume than the file says: the heave disturbance is -rho g dV (up is -z), hand
    computed: 1000 * 9.81 * 0.0000665 = 0.652 N."""
    rec = _session(tmp_path_factory, "buoy", V.with_values({"body.volume": V.body.volume * 1.01}), mocap=mocap)
    est = Evaluator(rec, V).traj0.estimate
    force = -1000.0 * 9.81 * V.body.volume * 0.01
    assert force == pytest.approx(-0.652, abs=1e-3)
    inner = slice(500, -500)
    assert np.mean(est.disturbance[inner, 2]) == pytest.approx(force, rel=0.1)
    assert abs(np.mean(est.x[inner, estimate.I_BA + 2])) < 0.02  # not taken for an accelerometer bias


def test_held_commands_are_the_recorded_commands_averaged_over_each_grid_step(plain):
    """Hand computed: servo outputs every 10 ms on a 20 ms grid; each grid step holds the mean of
    the two commands inside it (not the first), before the first record the first command."""
    from ground.recording import ServoStream

    ts = plain.servo.time_s[:6]
    rec = dataclasses.replace(plain, servo=ServoStream(ts, plain.servo.pwm_us[:6]))
    cmd = replay.flown_commands(rec, V)
    d = float(ts[1] - ts[0])
    got = replay.held_commands(rec, V, np.array([ts[0] - 2 * d, ts[0], ts[2]]))
    np.testing.assert_allclose(got[0], cmd[0], atol=1e-12)
    np.testing.assert_allclose(got[1], 0.5 * (cmd[0] + cmd[1]), atol=1e-9)
    np.testing.assert_allclose(got[2], 0.5 * (cmd[2] + cmd[3]), atol=1e-9)


def _smoother_inputs(rec, seconds: float):
    """(grid, params, commands, actuator run, measurements, initial state) of the smoother over
    the first `seconds` of a recording."""
    rec = rec.between(rec.t_start_s, rec.t_start_s + seconds)
    t, dt = replay.grid_for(rec)
    p = model.pack_params(V)
    cmd = replay.held_commands(rec, V, t)
    act = replay.actuator_run_commands(cmd, dt, p, 4)
    meas = estimate.measurements(rec, V, t)
    return t, p, cmd, act, meas, estimate.initial_state(meas, 0.0)


def test_chunked_smoother_equals_one_pass(plain, monkeypatch):
    """Memory bounded by the chunk, not the recording: the chunked RTS gives the same answer."""
    t, p, cmd, act, meas, x0 = _smoother_inputs(plain, 12.0)
    one = estimate.smooth(meas, act, cmd, p, x0)
    monkeypatch.setattr(estimate, "CHUNK", 173)
    chunked = estimate.smooth(meas, act, cmd, p, x0)
    np.testing.assert_allclose(chunked.x, one.x, atol=1e-9)
    np.testing.assert_allclose(chunked.std, one.std, atol=1e-9)


def test_samples_go_on_the_grid_interpolated_to_each_row_s_time():
    """Hand computed, a 50 Hz grid from 0: a 100 Hz stream y = 3 t + 1 (its 5 ms-late samples
    used to land on every other row as they were: 15 ms-off values) gives each row 3 t_row + 1
    exactly (row 0, before the first sample, holds it); a 12.5 Hz stream fills only its samples' nearest rows (0, 4 and 8: 0.08 s is 4
    rows); a NaN sample is no sample; an angle column is interpolated across +-pi."""
    grid = np.arange(11) * 0.02
    t_fast = 0.005 + np.arange(21) * 0.01
    y, ok = estimate._on_grid(grid, t_fast, 3.0 * t_fast + 1.0)
    assert ok.all()
    np.testing.assert_allclose(y[1:, 0], 3.0 * grid[1:] + 1.0, atol=1e-12)
    assert y[0, 0] == pytest.approx(1.015)  # before the first sample: held, not extrapolated
    t_slow = np.array([0.0, 0.08, 0.16, 0.24])
    vals = np.column_stack([t_slow, np.array([3.10, -3.12, -3.05, np.nan])])
    y, ok = estimate._on_grid(grid, t_slow, vals, angles=(1,))
    assert np.flatnonzero(ok).tolist() == [0, 4, 8]
    np.testing.assert_allclose(y[ok, 0], [0.0, 0.08, 0.16], atol=1e-12)
    np.testing.assert_allclose(y[ok, 1], [3.10, -3.12, -3.05], atol=1e-12)
    y, ok = estimate._on_grid(grid, np.array([0.03, 0.05]), np.array([[3.13], [-3.13]]), angles=(0,))
    # both samples round to row 2 (0.04 s, halfway between them across the wrap: +-pi, not 0)
    assert np.flatnonzero(ok).tolist() == [2] and abs(abs(y[2, 0]) - np.pi) < 1e-9


def test_a_perfect_model_shows_no_delay_and_no_added_mass_in_the_linear_scores(tmp_path_factory):
    """Noise-free, the nominal model the truth: 50 Hz IMU and a 15 ms sensor delay, so the
    (undelayed) motion capture sits 5 ms off the IMU's grid. The linear steps of the delay and of
    the added mass stay at the nominal values. Before the samples were interpolated to their
    rows (estimate._on_grid) and the filter moved the actuators along each step (estimate._step),
    this read as a -6 ms delay and an added-mass statistic of 100 (dev case 1134: every null
    draw did, and set their thresholds 10-20x the other families')."""
    truth = V.with_values({"sensors.imu_rate": 50.0, "sensors.delay": 0.015})
    rec = _session(tmp_path_factory, "late", truth, mocap=True, noise=False, duration=30.0)
    ev = Evaluator(rec, truth)
    res0 = ev.residual(ev.base)
    split = locate.make_split(ev.traj0, locate.noise_realisation(ev, res0))
    cands = [c for c in candidates.candidates_for(truth)
             if c.effect in ("sensor_delay", "added_mass", "thruster_fault")]
    got = {s.effect: s for s in decide.linear_scores(ev, cands, split, res0, truth)}
    # the thruster fault is tested one unit at a time: a part per unit, each freeing its own
    units = got["thruster_fault"].parts
    assert [q.keep for q in units] == [(j,) for j in range(truth.n_jets)]
    np.testing.assert_allclose([q.theta[0] for q in units], 1.0, atol=0.05)
    # 1.9 ms remain (6.5 before): a delay that is not a whole number of IMU samples leaves a
    # bias of a few ms in the perfect model's own linear step (3.5 ms with 15 ms at 100 Hz, 3.8
    # with 5 ms; none with 10 or 20 ms); the null draws carry it too, unexplained
    assert got["sensor_delay"].theta[0] == pytest.approx(0.015, abs=0.003)
    np.testing.assert_allclose(got["added_mass"].theta[:3], truth.hydro.added_mass[:3], rtol=0.03)


def test_a_candidate_that_changes_nothing_but_rounding_has_no_evidence(plain):
    """The plain session's 5-35 s stay 0.5 m or more below the surface (the effect acts above
    R = 0.16 m), with a servo lag missing from the model. Switching the surface proximity on
    changes the residual by 1e-14 along the added mass's force, and the scale-free score made a
    full statistic of it (S 135, held-out drop 84, ranked and fitted; eval 4077 counted a case
    never near the surface as testable). Now it carries no evidence, and the report says why."""
    w = plain.between(5.0, 35.0)
    nominal = V.with_effects(servo_lag=False, surface_proximity=False)
    ev = Evaluator(w, nominal)
    assert ev.traj0.pos_ned_m[:, 2].min() > 2 * V.body.radius
    res0 = ev.residual(ev.base)
    split = locate.make_split(ev.traj0, locate.noise_realisation(ev, res0))
    cands = [c for c in candidates.candidates_for(nominal) if c.effect in ("surface_proximity", "servo_lag")]
    got = {s.effect: s for s in decide.linear_scores(ev, cands, split, res0, nominal)}
    assert got["servo_lag"].statistic > 100  # the model error the rounding followed
    assert got["surface_proximity"].statistic == 0.0 and got["surface_proximity"].holdout_drop == 0.0
    cal = decide.calibrate([], ["surface_proximity"], [got["surface_proximity"]])
    assert not decide.testable(got["surface_proximity"], cal)
    reason = core.untestable_reason("surface_proximity", got["surface_proximity"], cal, ev.traj0, nominal, w)
    # the rule on the motion (1.5 R of the surface), then the Cramer-Rao verdict of a column of zeros
    assert reason == (f"never within {1.5 * V.body.radius:.2f} m of the surface; "
                      "the recording carries no information on it")


def test_the_held_out_blocks_move_to_cover_the_only_surfacing():
    """A 90 s flight at 10 Hz that surfaces once, at 76-83 s (eval 5580): with the fixed phase the
    blocks 76-80 s and 80-84 s (indices 19 and 20) are both training, and the surface effect
    could not be shown held out. Phase 2 holds out block 20 (3 of the 7 s: balance 0.82), phase
    3 block 19 (4 of 7: 0.61, too little left to fit); the better balance wins. A boundary whose
    samples are already split, or one no phase can split (one block), keeps phase 0, as does a
    flight that never comes near. Only the samples the fits use count: EDGE_S in from each end
    of each fitting window."""
    t = np.arange(0.0, 90.0, 0.1)
    none = np.zeros_like(t, bool)
    whole = [(0.0, 90.0)]
    near = np.column_stack([(t >= 76.0) & (t < 83.0), none])
    assert locate.block_shift(t, near, whole) == 2
    long = np.column_stack([t < 40.0, none])  # ten blocks, three held out at phase 0
    assert locate.block_shift(t, long, whole) == 0
    one = np.column_stack([(t >= 8.0) & (t < 12.0), none])  # one block: held out or fitted, whole
    assert locate.block_shift(t, one, whole) == 0
    assert locate.block_shift(t, np.column_stack([none, none]), whole) == 0
    # windows: the surfacing outside them does not count, nor their first and last second
    assert locate.block_shift(t, near, [(0.0, 40.0), (60.0, 90.0)]) == 2
    assert locate.block_shift(t, near, [(0.0, 40.0)]) == 0
    assert locate.block_shift(t, near, [(70.0, 80.0)]) == 0  # 76-79 s: block 19 alone
    assert locate.block_shift(t, near, [(70.0, 80.0), (80.0, 90.0)]) == 2  # 76-79 and 81-83 s
    # the floor counts as the surface does: 12-20 s (blocks 3 and 4) are both training at phase
    # 0, phase 1 holds out the second
    floor = np.column_stack([none, (t >= 12.0) & (t < 20.0)])
    assert locate.block_shift(t, floor, whole) == 1
    both = np.column_stack([near[:, 0], floor[:, 1]])  # the worse-balanced of the two decides
    assert locate.block_shift(t, both, whole) == 2


def test_the_fitting_windows_and_the_whole_recording_hold_out_the_same_blocks():
    """The fits train on the windows' training blocks and the held-out shooting shows the whole
    recording's held-out blocks: at any phase they must be the same blocks of time, or a finding
    is shown on what it was fitted on (a review's find: each split had picked its own phase, and
    the windows counted their blocks from the first window's start)."""
    dt = 0.02
    t = np.arange(0.0, 200.0, dt)
    traj = types.SimpleNamespace(time_s=t, dt_s=dt, has_mocap=False)
    spans = [(30.0, 40.0), (70.0, 80.0), (150.0, 160.0)]  # the first window is not at the start
    wins = [types.SimpleNamespace(time_s=t[(t >= a) & (t < b)], dt_s=dt, has_mocap=False) for a, b in spans]
    noise = lambda n: np.random.default_rng(0).normal(size=(n, 12))  # noqa: E731
    for shift in (0, 3, 7):
        whole = locate.make_split([traj], [noise(len(t))], shift)
        fit = locate.make_split(wins, [noise(len(w.time_s)) for w in wins], shift, origin=t[0])
        in_wins = np.concatenate([w.time_s for w in wins])
        np.testing.assert_array_equal(fit.holdout_mask, whole.holdout_mask[np.searchsorted(t, in_wins)])
        assert 0.0 < fit.holdout_mask.mean() < 1.0


def test_rounding_is_judged_per_channel_against_its_size_not_one_wild_sample():
    rng = np.random.default_rng(0)
    r0 = np.column_stack([rng.normal(0, 1.0, 1000), rng.normal(0, 1e-3, 1000), np.full(1000, np.nan)])
    r0[10, 0] = 1e9  # a wild sample does not raise channel 0's floor
    r0[[11, 12], 0] = np.inf  # nor do infinite ones
    floor = decide.rounding_floor(r0)
    assert floor[0] == pytest.approx(1e-9 * np.percentile(np.abs(r0[np.isfinite(r0[:, 0]), 0]), 99))
    # by hand: the 99th percentile of |N(0, s)| is 2.576 s (the two-sided 1 % point), so the
    # floors are about 2.6e-9 and 2.6e-12; an all-NaN channel has none
    assert 2e-9 < floor[0] < 4e-9 and 2e-12 < floor[1] < 4e-12 and floor[2] == 0.0
    step = np.zeros_like(r0)
    step[:, 0], step[:, 1] = 1e-12, 1e-13  # rounding in both channels
    step[5, 0], step[6, 1] = 1e-7, 1e-10  # a real change in each
    d = decide._moved(r0 + step, r0, floor)
    assert d[5, 0] == pytest.approx(1e-7) and d[6, 1] == pytest.approx(1e-10)
    assert np.count_nonzero(np.nan_to_num(d)) == 2


def test_the_delay_probe_delays_the_commands_through_the_lead_in(plain):
    """CorrectedModel.command_delay_s (the sensor delay's linear score): two grid steps later,
    the lead-in's last two commands open the window and its first command is held twice before
    it; with no lead-in the window's first command is held; the measurements stay as they were."""
    full = Evaluator(plain, V).traj0
    win = plain.between(20.0, 25.0)
    t_w, dt = replay.grid_for(win)
    lead = replay.LeadIn(full.command[full.time_s < t_w[0] - 1e-9][-50:])
    ev = Evaluator(win, V, lead)
    probe = dataclasses.replace(ev.base, command_delay_s=2 * dt)
    cmd, lead2 = ev.timed(ev.traj0, probe)
    np.testing.assert_array_equal(cmd[:2], lead.command[-2:])
    np.testing.assert_array_equal(cmd[2:], ev.traj0.command[:-2])
    np.testing.assert_array_equal(lead2.command, np.vstack([lead.command[:1]] * 2 + [lead.command[:-2]]))
    bare = Evaluator(win, V)
    cmd, none = bare.timed(bare.traj0, probe)
    assert none is None
    np.testing.assert_array_equal(cmd, np.vstack([bare.traj0.command[:1]] * 2 + [bare.traj0.command[:-2]]))
    assert ev.trajectory(probe.correction) is ev.traj0  # nothing re-timed but the commands


def test_null_draw_from_the_true_state_is_the_plant(tmp_path_factory):
    """A null draw with zero noise started from the plant's true state (and the actuators run from
    the commands before the window) reproduces the plant's own samples: one model, two integrators."""
    rec = _session(tmp_path_factory, "quiet", V, mocap=True, noise=False)
    full = Evaluator(rec, V).traj0
    X = _true_states(full, V)
    win = rec.between(20.0, 30.0)
    t_w, dt = replay.grid_for(win)
    before = full.time_s < t_w[0] - 1e-9
    ev = Evaluator(win, V, replay.LeadIn(full.command[before]))
    traj = ev.traj0
    act = ev.actuators(traj, model.pack_params(V), ev.base)
    i = int(np.searchsorted(full.time_s, t_w[0] - 1e-9))
    np.testing.assert_allclose(act[0], X[i, 13:], atol=2e-3)
    xe = np.zeros(estimate.NX)
    xe[0:3], xe[3:6], xe[6:12] = X[i, 0:3], model.quat_to_euler(X[i, 3:7]), X[i, 7:13]
    zero = {"gyro_rad_s": 0.0, "accel_m_s2": 0.0, "pressure_pa": 0.0, "attitude_rad": 0.0, "mocap_m": 0.0, "mocap_quat": 0.0}
    draw = null.simulate_window(win, traj, act, V, zero, np.random.default_rng(0), start=(xe, np.zeros(estimate.NX)))
    assert np.array_equal(draw.imu.time_s, win.imu.time_s)
    inside = win.imu.time_s <= traj.time_s[-1] + 1e-9  # (a sample after the grid's end is held)
    np.testing.assert_allclose(draw.imu.gyro_frd_rad_s[inside], win.imu.gyro_frd_rad_s[inside], atol=2e-3)
    np.testing.assert_allclose(draw.imu.accel_frd_m_s2[inside], win.imu.accel_frd_m_s2[inside], atol=2e-2)
    np.testing.assert_allclose(draw.pressure.press_abs_pa, win.pressure.press_abs_pa, atol=5.0)  # 0.5 mm


def test_lead_seconds_is_five_of_the_slowest_actuator_time_constants():
    """asr4's axial-loss filter f1x has the factor s^2 + 9.88 s + 1 (seed 004 Table 1): its slow
    root is (-9.88 + sqrt(9.88^2 - 4)) / 2 = -0.10228 rad/s, tau = 9.778 s, so 48.89 s of lead."""
    assert core.lead_seconds(V) == pytest.approx(5 * 2 / (9.88 - np.sqrt(9.88 ** 2 - 4)), abs=1e-6)
    assert core.lead_seconds(V) == pytest.approx(48.889, abs=1e-3)
    # the same with the transient off: a candidate switches it on in the same windows (a 2 s lead
    # had fitted the missing transient's gain 10-44 % high on five dev cases)
    assert core.lead_seconds(V.with_effects(azimuth_transient=False)) == core.lead_seconds(V)


def test_a_filter_pole_at_the_edge_of_zero_waits_the_cap_without_overflow():
    """A vehicle file may hold subnormal filter coefficients (finite, within range): the slow
    root is then ~1e-320 rad/s, and 1 / rate overflowed (a RuntimeWarning on stderr, a hostile
    review's find). The lead-in is the cap, quietly."""
    f1x = list(V.effects.azimuth_transient.f1x)
    f1x[3], f1x[4] = 2e-320, 1e-320
    odd = V.with_effects(azimuth_transient=False).with_values({"effects.azimuth_transient.f1x": f1x})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert core.lead_seconds(odd) == core.LEAD_MAX_S


@pytest.mark.slow
def test_lead_in_brings_a_window_s_actuators_to_their_state_in_the_whole_flight(tmp_path_factory):
    """A window's modelled acceleration, with its actuators run from the diagnosis's own lead-in,
    is the one the whole flight's actuator run gives (which starts at rest, as the plant does;
    test_null_draw_from_the_true_state_is_the_plant checks that run against the plant). A 2 s
    lead-in left asr4's slow f1x state short: under a joystick pilot a steady heave acceleration
    of about 0.01 m/s^2 (0.1 N), which every window showed as a force (README 'Diagnose')."""
    path = tmp_path_factory.mktemp("rec") / "lead.tlog"
    prove.record_session(V, path, 45.0, seed=4, mocap=False, noise=False, pilot="joystick")
    rec = read_recording(path)
    ev_full = Evaluator(rec, V)
    full, p = ev_full.traj0, model.pack_params(V)
    A = ev_full.actuators(full, p, ev_full.base)
    win = rec.between(32.0, 42.0)
    gaps = {}
    for label, taus in (("old", 0.0), ("now", core.LEAD_TAUS)):
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(core, "LEAD_TAUS", taus)
            ev = Evaluator(win, V, core._lead_in(rec, full, win, V))
        act = ev.actuators(ev.traj0, p, ev.base)
        i = int(np.searchsorted(full.time_s, ev.traj0.time_s[0] - 1e-9))
        n = len(ev.traj0.time_s)
        gap = replay.model_acceleration(ev.traj0, act, p) - replay.model_acceleration(ev.traj0, A[i:i + n], p)
        gaps[label] = float(abs(gap[:, 2].mean()))
    assert gaps["old"] > 3e-3  # the test sees the fault it guards against
    assert gaps["now"] < 1e-4


def test_calibration_recovers_the_scale_of_chi_square_draws():
    """Null statistics c * chi2(p): the scale comes back; the threshold is c chi2^-1(1 - a), or the
    largest null statistic when that is higher (a tail heavier than the scaled chi-square)."""
    rng = np.random.default_rng(3)
    fams = [("a", 1), ("b", 3), ("c", 6)]
    draws = [[decide.Score(f, p, float(2.0 * rng.chisquare(p)), 0.0, np.zeros(p), np.ones(p)) for f, p in fams]
             for _ in range(400)]
    cal = decide.calibrate(draws, [f for f, _ in fams])
    assert cal.alpha_family == pytest.approx(0.01)  # min(1 %, 5 % / 3)
    for f, p in fams:
        assert cal.scale[f] == pytest.approx(2.0, rel=0.15)
        largest = max(s.statistic for draw in draws for s in draw if s.effect == f)
        assert cal.null_max[f] == largest
        assert cal.threshold[f] == pytest.approx(max(cal.scale[f] * chi2.ppf(0.99, p), largest))


def test_a_probed_family_is_calibrated_per_direction():
    """The delay's two directions (secant, command probe) with null scales 20 and 1 (a chi2(1)
    each): each direction its own scale; the recording's statistic is the larger S_k / c_k,
    stated in the picked direction's units against c_k chi2_1^-1(1 - a / 2), never below the
    null draws' largest normalised statistic. One scale for both (the secant's, the mean of the
    max) had held a true 33 ms delay below its threshold (eval 2238)."""
    rng = np.random.default_rng(5)

    def delay(s_sec, s_probe, th_sec=0.01, th_probe=0.03, sd=(1.0, 1.0)):
        parts = tuple(decide.Score("d", 1, float(v), 0.0, np.array([th]), np.array([e]), np.array([0.02]))
                      for v, th, e in ((s_sec, th_sec, sd[0]), (s_probe, th_probe, sd[1])))
        return dataclasses.replace(max(parts, key=lambda q: q.statistic), parts=parts)

    fams = ["d"] + [f"f{i}" for i in range(4)]
    draws = [[delay(20.0 * rng.chisquare(1), rng.chisquare(1), rng.normal(0, 0.02), rng.normal(0, 0.001))]
             + [decide.Score(f, 1, float(rng.chisquare(1)), 0.0, np.zeros(1), np.ones(1)) for f in fams[1:]]
             for _ in range(2000)]
    observed = [delay(60.0, 45.0)]  # 60 / 20 = 3 in the secant's units, 45 in the probe's
    cal = decide.calibrate(draws, fams, observed)
    assert cal.part["d"] == 1 and cal.looks["d"] == 2
    assert cal.scale["d"] == pytest.approx(1.0, rel=0.1)
    c = np.mean([[q.statistic for q in d[0].parts] for d in draws], axis=0)
    largest = max(max(q.statistic / ck for q, ck in zip(d[0].parts, np.maximum(c, cal.pooled_scale))) for d in draws)
    assert cal.threshold["d"] == pytest.approx(max(cal.scale["d"] * chi2.ppf(1 - cal.alpha_family / 2, 1),
                                                   cal.scale["d"] * largest))
    picked = decide.pick_part(observed[0], cal)
    assert picked.statistic == 45.0 and picked.theta[0] == 0.03 and picked.parts == observed[0].parts
    # the bootstrap sd is the picked direction's own spread over the draws (not the winners' mix)
    probe_th = [d[0].parts[1].theta[0] for d in draws]
    assert cal.theta_sd["d"][0] == pytest.approx(np.std(probe_th, ddof=1), rel=1e-12)
    assert cal.theta_sd["d"][0] == pytest.approx(0.001, rel=0.1)
    # testability: the best-determined direction, each on its own scale and spread, whichever
    # direction a control's noise picks (a review's find: the secant's sd alone said untestable)
    quiet = delay(25.0, 0.1, sd=(0.01, 0.002))  # the secant wins the pick: 25/20 > 0.1/1
    cq = decide.calibrate(draws, fams, [quiet])
    q = decide.pick_part(quiet, cq)
    assert cq.part["d"] == 0 and q.statistic < cq.threshold["d"]
    assert not decide.determined(decide.calibrated_sd(q, cq), q.reference).any()  # the secant's sd
    assert decide.testable(q, cq)  # ... but the probe's 0.002 (x1) is under half of 0.02
    assert decide.best_sd(q, cq)[0] == pytest.approx(max(0.002 * math.sqrt(max(cq.part_scale["d"][1], 1.0)),
                                                         np.std(probe_th, ddof=1)))
    # a non-finite null statistic is left out, not a NaN threshold
    bad = [[dataclasses.replace(delay(1.0, 1.0), statistic=math.nan)] + draws[0][1:]] + draws[:50]
    cb = decide.calibrate(bad, fams, observed)
    assert math.isfinite(cb.threshold["d"]) and math.isfinite(cb.scale["d"])
    assert picked.statistic > cal.threshold["d"]  # the max of the raw statistics (60) would have
    assert 60.0 < max(s.statistic for d in draws for s in d if s.effect == "d")  # ... sat under its null
    # an unprobed Score passes through; the confidence counts the two looks
    assert decide.pick_part(draws[0][1], cal) is draws[0][1]
    pv = chi2.sf(45.0 / cal.scale["d"], 1)
    assert decide.confidence(picked, cal, 5) == pytest.approx(max(0.0, 1 - 5 * 2 * pv))


def test_a_one_at_a_time_family_is_calibrated_per_unit():
    """The thruster fault's four units, unit 3 barely driven (sd 0.5 against 0.01): each unit is
    its own part. The family's statistic is the most likely unit's S (the largest), calibrated
    on the null draws' same largest; a 25 % loss on unit 0 gets unit 0's own bootstrap spread
    (before, the draws that unit 3 won set it: 0.3, and the fault, 41x its threshold, was
    dropped as within its noise), and a quiet recording is testable whichever unit its noise
    picks (a review's find)."""
    rng = np.random.default_rng(1)
    sd_unit = np.array([0.01, 0.01, 0.01, 0.5])

    def fault(z, louder=(1.0, 1.0, 1.0, 1.0)):
        parts = tuple(decide.Score("tf", 1, float(v * v * f), 1.0, np.array([1.0 + v * e]), np.array([e]),
                                   np.array([0.2]), None, (j,)) for j, (v, e, f) in enumerate(zip(z, sd_unit, louder)))
        return dataclasses.replace(max(parts, key=lambda q: q.statistic), parts=parts)

    fams = ["tf"] + [f"f{i}" for i in range(5)]
    others = [[decide.Score(f, 1, float(rng.chisquare(1)), 0.0, np.zeros(1), np.ones(1)) for f in fams[1:]]
              for _ in range(400)]
    zs = rng.standard_normal((400, 4))
    draws = [[fault(z)] + o for z, o in zip(zs, others)]
    loss = fault(np.array([-25.0, 0.3, -0.2, 0.1]))  # unit 0 at 0.75
    cal = decide.calibrate(draws, fams, [loss])
    got = decide.pick_part(loss, cal)
    assert cal.part["tf"] == 0 and got.keep == (0,) and "tf" not in cal.looks
    largest = [d[0].statistic for d in draws]  # each draw's largest unit
    assert cal.scale["tf"] == pytest.approx(max(np.mean(largest), cal.pooled_scale))
    assert cal.threshold["tf"] == pytest.approx(max(cal.scale["tf"] * chi2.ppf(1 - cal.alpha_family, 1), max(largest)))
    unit0 = [d[0].parts[0].theta[0] for d in draws]
    assert cal.theta_sd["tf"][0] == pytest.approx(np.std(unit0, ddof=1), rel=1e-12)
    assert decide.calibrated_sd(got, cal)[0] == pytest.approx(0.01 * math.sqrt(cal.scale["tf"]), rel=0.15)
    assert not decide.within_noise(types.SimpleNamespace(switch_on=False, n_params=1, x0=(1.0,)), got.theta,
                                   decide.calibrated_sd(got, cal))
    # a quiet recording whose noise picks the barely driven unit: its sd is 2.5x the reference,
    # yet units 0-2 are determined, so the absence of a fault is concluded (testable)
    quiet = fault(np.array([0.1, 0.05, 0.05, 0.2]))
    cq = decide.calibrate(draws, fams, [quiet])
    q = decide.pick_part(quiet, cq)
    assert cq.part["tf"] == 3 and q.statistic < cq.threshold["tf"]
    assert not decide.determined(decide.calibrated_sd(q, cq), q.reference).any()
    assert decide.testable(q, cq)
    # alternative models are picked by likelihood (the largest S), not by S / c_k as the delay's
    # directions are: unit 0 with a null scale 4x the others' and S 50 (12.5 in its units) over
    # unit 1's 40 (dev 2463: the normalised pick went to a quieter unit, added mass was named)
    louder = (4.0, 1.0, 1.0, 1.0)
    noisy = [[fault(z, louder)] + o for z, o in zip(zs, others)]
    two = fault(np.array([-math.sqrt(50.0), math.sqrt(40.0), 0.1, 0.1]))
    c2 = decide.calibrate(noisy, fams, [two])
    assert c2.part["tf"] == 0 and decide.pick_part(two, c2).statistic == pytest.approx(50.0)
    # one scale per unit for testability and the reported sd: the family's (a review's find:
    # testability on each unit's own c_k, the report on the family's, disagreed for one unit)
    assert np.allclose(c2.part_scale["tf"], c2.scale["tf"])
    p2 = decide.pick_part(two, c2)
    assert np.array_equal(decide.part_sds(p2, c2)[0], decide.calibrated_sd(p2, c2))
    # any unit's reported sd is its own (a second pass may score another unit than the picked one)
    for j in range(4):
        assert np.array_equal(decide.calibrated_sd(two.parts[j], c2), decide.part_sds(p2, c2)[j])
    # a unit never driven is listed untestable by name, the family's other units tested
    cand = types.SimpleNamespace(n_params=4, public="thruster_fault", kind="misestimated",
                                 parameter_name=lambda j: f"unit[{j}]")
    idle = core._partly_untestable(cand, q, cq)
    assert idle["parameters"] == ["unit[3]"] and "other parameters are tested" in idle["reason"]
    assert core._partly_untestable(cand, got, cal) is None  # significant: a finding, not a list
    # a null draw whose estimate is not finite is left out of the spread (before: a NaN sd, and
    # within_noise dropped the 25 % loss)
    nan_draw = [[dataclasses.replace(d[0], parts=tuple(dataclasses.replace(q_, theta=np.array([math.nan]))
                                                        for q_ in d[0].parts))] + d[1:] for d in draws[:3]]
    cn = decide.calibrate(nan_draw + draws, fams, [loss])
    gn = decide.pick_part(loss, cn)
    assert np.isfinite(decide.calibrated_sd(gn, cn)).all()
    assert cn.theta_sd["tf"][0] == pytest.approx(cal.theta_sd["tf"][0], rel=1e-12)
    assert not decide.within_noise(types.SimpleNamespace(switch_on=False, n_params=1, x0=(1.0,)), gn.theta,
                                   decide.calibrated_sd(gn, cn))


def test_the_most_likely_part_is_nan_safe():
    """A part the model could not evaluate (statistic NaN) never hides a unit that scores."""
    parts = [decide.Score("tf", 1, v, 0.0, np.zeros(1), np.ones(1)) for v in (math.nan, 3.0, 7.0, math.nan)]
    assert decide.most_likely(parts).statistic == 7.0
    assert decide.most_likely(parts[:1]) is parts[0]  # nothing finite: the first, no error
    strongest = decide.Score("tf", 1, math.inf, 0.0, np.zeros(1), np.ones(1))
    assert decide.most_likely(parts + [strongest]) is strongest  # +inf is the strongest evidence, not none


def test_confidence_is_the_recording_level_probability():
    """At the threshold of 13 families (a = 5 % / 13) the confidence is 1 - 13 a = 0.95."""
    fams = [f"f{i}" for i in range(13)]
    draws = [[decide.Score(f, 1, 1.0, 0.0, np.zeros(1), np.ones(1)) for f in fams]]
    cal = decide.calibrate(draws, fams)
    assert cal.alpha_family == pytest.approx(0.05 / 13)
    s = decide.Score("f0", 1, cal.threshold["f0"], 0.0, np.zeros(1), np.ones(1))
    assert decide.confidence(s, cal, 13) == pytest.approx(0.95, abs=1e-9)


def test_untestable_when_the_bound_is_wide_unless_significant():
    cal = decide.Calibration(8, 1.0, {"x": 4.0}, {"x": 10.0}, 0.01, {"x": 5.0})
    wide = decide.Score("x", 1, 2.0, 0.0, np.zeros(1), np.array([1.0]), np.array([1.0]))  # sd 2 (x sqrt 4) > 0.5
    assert not decide.testable(wide, cal)
    assert decide.testable(decide.Score("x", 1, 11.0, 0.0, np.zeros(1), np.array([1.0]), np.array([1.0])), cal)
    assert decide.testable(decide.Score("x", 1, 2.0, 0.0, np.zeros(1), np.array([0.2]), np.array([1.0])), cal)


@pytest.mark.parametrize("k,n", [(0, 10), (9, 10), (27, 30), (300, 300), (151, 312)])
def test_wilson_interval_equals_scipy(k, n):
    lo, hi = prove.wilson(k, n)
    ref = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    assert lo == pytest.approx(ref.low, abs=2e-4) and hi == pytest.approx(ref.high, abs=2e-4)


def test_wilson_hand_computed():
    # 9/10, z = 1.96: centre (0.9 + z^2/20) / (1 + z^2/10) = 0.78898, half-width
    # z sqrt(0.009 + z^2/400) / (1 + z^2/10) = 0.19314: (0.5958, 0.9821)
    lo, hi = prove.wilson(9, 10)
    assert (lo, hi) == pytest.approx((0.5958, 0.9821), abs=1e-4)


def test_benchmark_family_is_seeded_split_and_varied():
    a = [prove.family_case("dev", i) for i in range(200)]
    b = [prove.family_case("dev", i) for i in range(200)]
    assert [c.name for c, _, _ in a] == [c.name for c, _, _ in b]
    assert all(f.pilot != prove.HIDDEN_PILOT for _, f, _ in a)
    ev = [prove.family_case("eval", i) for i in range(200)]
    assert prove.HIDDEN_PILOT in {f.pilot for _, f, _ in ev}
    assert {c.name for c, _, _ in a}.isdisjoint({c.name for c, _, _ in ev})
    for cases in (a, ev):
        controls = sum(1 for c, _, _ in cases if not c.expect)
        assert 0.28 <= controls / len(cases) <= 0.45
        assert {f.sensors for _, f, _ in cases} == set(prove.SENSOR_SETS)
        assert {f.duration_s for _, f, _ in cases} >= {60.0, 600.0}
        mags = [m for c, _, m in cases if c.expect]
        assert min(mags) >= 1.0 and max(mags) <= 5.0
        assert any(len(c.expect) == 2 for c, _, _ in cases)  # masking pairs
    names = {c.expect[0] for c, _, _ in a + ev if c.expect}
    assert len(names) == len(prove._effect_family())


@pytest.mark.slow
def test_repro_perfect_model_gives_no_finding(tmp_path):
    """Issue 18 repro 1: commands replayed through the reference vehicle, diagnosed against it."""
    rec = tmp_path / "replay.tlog"
    cmds = shared_demo_commands()
    assert main(["sim", "--commands", str(cmds), "--out", str(rec), "--depth", "0", "--seed", "3"]) == 0
    assert main(["diagnose", str(rec), "--json", str(tmp_path / "r.json"), "--quiet"]) == 0
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["findings"] == []
    assert rep["calibration"]["null_draws"] >= 4


def shared_demo_commands():
    from pathlib import Path

    import onboard

    return Path(onboard.__file__).with_name("data") / "demo_commands.csv"


@pytest.mark.slow
def test_repro_buoyancy_without_motion_capture_is_buoyancy(tmp_path):
    """Issue 18 repro 2: the buoyancy proof case without ATT_POS_MOCAP names buoyancy, with a
    parameter within 15 % and within 3 sd of the truth."""
    truth = V.with_values({"body.volume": V.body.volume * 1.005})
    prove.record_session(truth, tmp_path / "b.tlog", 120.0, seed=1, mocap=False)
    assert main(["diagnose", str(tmp_path / "b.tlog"), "--json", str(tmp_path / "r.json"), "--quiet"]) == 0
    rep = json.loads((tmp_path / "r.json").read_text())
    f = rep["findings"][0]
    assert f["effect"] == "buoyancy"
    got, sd = f["parameters"]["body.volume"], f["std"]["body.volume"]
    assert got == pytest.approx(truth.body.volume, rel=0.15)
    assert abs(got - truth.body.volume) < 3 * sd
    assert rep["fit"]["holdout"]["after"]["total"] < rep["fit"]["holdout"]["before"]["total"]
    cur = next(u for u in rep["untestable"] if u["effect"] == "current")  # no position measured
    assert cur["reason"].startswith("horizontal: no position or velocity over ground measured")
    assert cur["parameters"][:2] == ["environment.current[0]", "environment.current[1]"]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["small.tlog", "small.BIN", "2023-04-18_11-03-34.tlog"])
def test_real_ardusub_logs_give_a_report(name, tmp_path, capsys):
    """Real BlueROV2 logs at 2-25 Hz read with asr4: a report, weak and honest, never a traceback.
    One that names nothing while candidates stand above their thresholds must not say "within its
    noise" (2023-04-18 did, buoyancy 10x its threshold: fits that were worse held out or too small
    were dropped silently; an adversary's find)."""
    from ground.diagnose.cli import summary_text

    code = main(["diagnose", str(shared_file(ARDUSUB / name)), "--json", str(tmp_path / "r.json"), "--quiet"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "Traceback" not in captured.err
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["untestable"], "a 2-25 Hz log cannot test every candidate"
    assert all(u["reason"] for u in rep["untestable"])
    if not rep["findings"] and any(c["testable"] and c["statistic"] > c["threshold"] for c in rep["candidates"]):
        assert "within its noise" not in summary_text(rep)
        assert rep["rejected"] or rep["negligible"]


@pytest.mark.parametrize("effect, says", [
    ("linear_damping", "linear and quadratic damping inseparable"),
    ("thrust_inflow", "too little inflow to change the jets' thrust"),
    ("current", "a drift and the damping it meets are inseparable"),
    ("wall_proximity", "no heave motion within 0.3 m of the floor"),
    ("sensor_delay", "IMU at 10 Hz"),
])
def test_untestable_reason_names_the_effect_s_own_limit(effect, says):
    """A slow, deep recording at 10 Hz: each candidate's reason is its own, with its bound."""
    from types import SimpleNamespace

    n = 100
    traj = SimpleNamespace(pos_ned_m=np.tile([0.0, 0.0, 1.0], (n, 1)), nu=np.full((n, 6), 0.01), dt_s=0.1)
    score = decide.Score(effect, 1, 0.0, 0.0, np.zeros(1), np.array([0.4]), np.array([0.1]), None)
    cal = decide.Calibration(8, 1.0, {}, {effect: 10.0}, 0.01, {})
    why = core.untestable_reason(effect, score, cal, traj, V, None)
    assert says in why and "Cramer-Rao sd 4x the smallest error worth finding" in why


def test_a_steady_horizontal_current_leaves_imu_attitude_and_depth_unchanged():
    """Why the current is vertical-only without motion capture (candidates_for): the plant
    flown in a 0.15 m/s current, started moving with the water, gives the same IMU, attitude and
    pressure samples as in still water under the same commands, turning included."""
    vc = np.array([0.15, -0.10, 0.0])
    wet = V.with_values({"environment.current": list(vc)})
    cmds = [np.r_[[40.0, 10.0, 40.0, 10.0], [0.3, -0.2, 0.1, 0.0], [0.0, 0.2, -0.1, 0.1]],
            np.r_[[10.0, 50.0, 20.0, 50.0], [-0.4, 0.3, 0.0, 0.2], [0.2, 0.0, 0.1, -0.2]]]
    still = Plant(V, noise=False, command=cmds[0])
    state = still.state.copy()
    state[7:10] = vc  # at rest in the water: ground velocity = R^T v_c, level and heading north
    moving = Plant(wet, noise=False, command=cmds[0], state=state)
    a, b = [], []
    for k in range(8):
        for p in (still, moving):
            p.set_command(cmds[k % 2])
        a.append(still.advance(2.5 * (k + 1)))
        b.append(moving.advance(2.5 * (k + 1)))
    assert abs(moving.state[2] - still.state[2]) < 1e-9  # the same depth
    assert np.hypot(*(moving.state[:2] - still.state[:2])) > 0.15 * 20 * 0.9  # carried away 3 m
    assert abs(model.quat_to_euler(still.state[3:7])[2]) > 0.5  # it turned
    from dataclasses import astuple

    compared = {"imu": 0, "pressure": 0, "attitude": 0}
    for sa, sb in zip(a, b):
        for name in compared:
            xs, ys = getattr(sa, name), getattr(sb, name)
            assert len(xs) == len(ys)
            for x, y in zip(xs, ys):
                np.testing.assert_allclose(np.hstack(astuple(y)), np.hstack(astuple(x)), rtol=1e-10, atol=1e-8, err_msg=name)
                compared[name] += 1
    assert min(compared.values()) > 100


def test_without_motion_capture_the_current_candidate_is_vertical_only():
    full = next(c for c in core.candidates_for(V) if c.effect == "current")
    vert = next(c for c in core.candidates_for(V, over_ground=False) if c.effect == "current")
    assert full.keys == tuple(("environment.current", i) for i in range(3))
    assert vert.keys == (("environment.current", 2),)
    assert decide.reference_magnitude(vert, V).shape == (1,)


@pytest.mark.slow
def test_a_missing_current_is_scored(tmp_path_factory):
    """A nominal vehicle with the current switched off: its candidate starts at zero, where the
    secant of a missing effect divided by zero and the family scored 0 on any recording. Now
    the current of the recording (motion capture on) stands far above chance with the right
    signs."""
    vc = [0.10, -0.08, 0.0]
    rec = _session(tmp_path_factory, "cur", V.with_values({"environment.current": vc}), mocap=True, duration=40.0)
    nominal = V.with_effects(current=False)
    cand = next(c for c in core.candidates_for(nominal) if c.effect == "current")
    assert cand.kind == "missing" and cand.x0 == (0.0, 0.0, 0.0)
    ev = Evaluator(rec, nominal)
    res0 = ev.residual(ev.base)
    split = locate.make_split(ev.traj0, locate.noise_realisation(ev, res0))
    (score,) = decide.linear_scores(ev, [cand], split, res0, nominal)
    assert score.statistic > chi2.ppf(1 - 1e-6, 3)
    assert score.theta[0] > 0.03 and score.theta[1] < -0.02


def test_correction_size_in_units_of_the_smallest_error_worth_finding():
    """Hand computed: 0.25 % more volume is half of the 0.5 % worth finding; a 0.03 m/s current
    0.6 of 0.05 m/s; a missing effect switched on is the correction itself."""
    cands = {c.effect: c for c in core.candidates_for(V)}
    vol = V.body.volume
    assert decide.correction_size(cands["buoyancy"], [vol * 1.0025], V) == pytest.approx(0.5)
    assert decide.correction_size(cands["current"], [0.0, -0.03, 0.01], V) == pytest.approx(0.6)
    tm = V.thruster.motor_time_constant
    assert decide.correction_size(cands["motor_lag"], [tm * 1.01], V) == pytest.approx(0.05)
    missing = next(c for c in core.candidates_for(V.with_effects(motor_lag=False)) if c.effect == "motor_lag")
    assert missing.switch_on and decide.correction_size(missing, [0.001], V) == math.inf


def test_an_imu_bias_is_named_only_when_an_axis_stands_out_of_its_noise_and_may_be_worth_finding():
    """Hand computed against one count of MAVLink's SCALED_IMU (1 mrad/s, 1 mG; half: 0.5 mrad/s,
    4.9 mG). The two false biases of fresh block 8332-8631 as reported (controls 8360, 8610):
    their gyro axes stand out (2.6 and 2.5 sd) but at most 0.12 and 0.25 mrad/s with 2 sd; the
    accelerometer's 1.5 mG is 0.55 sd, no evidence either way (its 6.9 mG with 2 sd would have
    carried the bias over the size rule alone). The smallest concealed benchmark bias (4 mrad/s)
    is named; so is an accel bias of 10 mG at 4 sd."""
    def worth(gyro, accel, sd_g, sd_a):
        score = decide.Score("imu_bias", 6, 10.0, math.nan, np.array(gyro + accel), None, decide.IMU_BIAS_WORTH)
        return not decide.bias_too_small(score, np.zeros(6), np.array([sd_g] * 3 + [sd_a] * 3))
    assert not worth([1.93e-05, -8.113e-06, 6.672e-05], [1.437e-4, -1.085e-4, -6.825e-05], 2.7e-5, 1.9e-3)  # 8360
    assert not worth([1.508e-05, 1.358e-4, 2.414e-05], [-5.026e-4, 1.488e-3, 4.166e-4], 5.5e-5, 2.7e-3)  # 8610
    assert worth([0.004, 0.0, 0.0], [0.0, 0.0, 0.0], 5e-5, 2e-3)
    assert worth([0.0, 0.0, 0.0], [0.01, 0.0, 0.0], 5e-5, 2.5e-3)
    # the edge, at 0.1 mrad/s sd: 0.31 mrad/s reaches 0.51 with 2 sd, 0.29 only 0.49
    assert worth([3.1e-4, 0, 0], [0, 0, 0], 1e-4, 1e-3) and not worth([2.9e-4, 0, 0], [0, 0, 0], 1e-4, 1e-3)
    # 0.4 mrad/s at 0.25 mrad/s sd reaches it (0.9) but is within 2 sd: no evidence of a bias
    assert not worth([4e-4, 0, 0], [0, 0, 0], 2.5e-4, 1e-3)
    # a nominal bias in the file: the correction is measured from it
    score = decide.Score("imu_bias", 6, 10.0, math.nan, np.array([0.0101, 0, 0, 0, 0, 0]), None, decide.IMU_BIAS_WORTH)
    assert decide.bias_too_small(score, np.array([0.01, 0, 0, 0, 0, 0]), np.full(6, 1e-5)).startswith(
        "the axes over 2 sd of their noise reach 0.12 of")


def test_sandwich_sd_hand_computed_for_white_residuals():
    """Lag 0, the mean of r (J = -1 on one channel): A = T (+ the prior), B = sum r^2, so the sd
    is sqrt(sum r^2) / (T + prior), the textbook standard error of a mean."""
    r = np.array([0.5, -1.0, 2.0, 0.0, 1.5])
    J = -np.ones((5, 1, 1))
    assert candidates.sandwich_sd(J, r[:, None], np.zeros(1), 0)[0] == pytest.approx(math.sqrt(7.5) / 5)
    assert candidates.sandwich_sd(J, r[:, None], np.array([3.0]), 0)[0] == pytest.approx(math.sqrt(7.5) / 8)
    # a sample the model could not evaluate (inf, NaN) counts as nothing, not as a NaN sd: the
    # same as leaving it at zero
    Jbad, rbad = J.copy(), r[:, None].copy()
    Jbad[3, 0, 0], rbad[3, 0] = np.inf, np.nan
    J0 = J.copy()
    J0[3, 0, 0] = 0.0
    assert candidates.sandwich_sd(Jbad, rbad, np.zeros(1), 1)[0] == pytest.approx(
        candidates.sandwich_sd(J0, r[:, None], np.zeros(1), 1)[0])
    # ... and a residual the model could not evaluate drops its sample from the bread as well
    # (a reviewer's find: zeroed alone, the sd came out too small)
    assert candidates.sandwich_sd(J, rbad, np.zeros(1), 1)[0] == pytest.approx(
        candidates.sandwich_sd(J0, r[:, None], np.zeros(1), 1)[0])


def test_sandwich_sd_matches_the_spread_of_estimates_under_coloured_residuals():
    """A second, independent route: the mean of AR(1) residuals (rho 0.8) estimated 300 times.
    The spread of the estimates is sqrt((1 + rho) / (1 - rho)) = 3x the white-noise bound; the
    sandwich with a 50-sample lag window agrees with the spread within 15 %, the white bound
    (lag 0) is a third of it."""
    rng = np.random.default_rng(7)
    T, rho, reps = 2000, 0.8, 300
    e = rng.normal(size=(reps, T))
    for t in range(1, T):
        e[:, t] += rho * e[:, t - 1]
    means = e.mean(axis=1)
    J = -np.ones((T, 1, 1))
    hac = [candidates.sandwich_sd(J, (x - x.mean())[:, None], np.zeros(1), 50)[0] for x in e[:40]]
    white = [candidates.sandwich_sd(J, (x - x.mean())[:, None], np.zeros(1), 0)[0] for x in e[:40]]
    spread = float(np.std(means, ddof=1))
    assert np.mean(hac) == pytest.approx(spread, rel=0.15)
    assert np.mean(white) < 0.45 * spread


def test_a_pair_with_a_delay_keeps_the_delay_s_resolution():
    """A delay's residual is piecewise linear between samples: least squares must not take a
    difference step below 10 ms on it, alone or in a pair (a reviewer's find: `combine` dropped
    it, so a pair fitted the delay with a 0.5 ms step); the other parameters keep the default."""
    cands = {c.effect: c for c in core.candidates_for(V)}
    pair = candidates.combine(cands["sensor_delay"], cands["buoyancy"])
    assert pair.resolution == (0.01, None)
    assert candidates.combine(cands["buoyancy"], cands["sensor_delay"]).resolution == (None, 0.01)
    assert cands["current"].subset([1]).resolution == ()


def test_a_scanned_parameter_is_refined_between_its_scan_points():
    """candidates._scan_fit on a known training chi-square: least at 55 ms, piecewise linear
    between 10 ms samples (what a re-timed sampled stream gives); the scan brackets it between
    40 and 70 ms and the bounded search lands within SCAN_TOL."""
    truth = 0.055
    grid = np.arange(0.0, 0.51, 0.01)
    f = lambda th: float(np.interp(th[0], grid, (grid - truth) ** 2 * 1e4 + 50.0))  # noqa: E731
    lo, hi = np.array([0.0]), np.array([0.5])
    got = candidates._scan_fit(f, np.array([0.0]), lo, hi, (0.0, 0.01, 0.02, 0.04, 0.07, 0.1, 0.2))[0]
    assert abs(got - truth) <= candidates.SCAN_TOL + 0.005  # the interpolated minimum is 50 or 60 ms
    smooth = lambda th: float((th[0] - truth) ** 2)  # noqa: E731
    assert candidates._scan_fit(smooth, np.array([0.0]), lo, hi, (0.0, 0.04, 0.07))[0] == pytest.approx(
        truth, abs=candidates.SCAN_TOL)
    # a point where the model diverged (NaN) is no minimum (argmin took the first NaN: 0 s)
    broken = lambda th: float("nan") if th[0] == 0.0 else smooth(th)  # noqa: E731
    assert candidates._scan_fit(broken, np.array([0.0]), lo, hi, (0.0, 0.04, 0.07))[0] == pytest.approx(
        truth, abs=candidates.SCAN_TOL)


def test_a_correction_within_one_sd_of_the_nominal_is_within_noise():
    """Hand computed: a wall gain 0.165 +- 1.66 against 0.375 (z 0.13) is within noise; 0.165
    +- 0.1 (z 2.1) is not; a current is not while any component stands 1 sd clear; a missing
    effect switched on has no start value to compare with."""
    V_wall = V.with_values({"effects.wall_proximity.k_wall": 0.375})
    cands = {c.effect: c for c in core.candidates_for(V_wall)}
    wall = cands["wall_proximity"]
    assert wall.x0 == (0.375,)
    assert decide.within_noise(wall, [0.165], [1.66])
    assert not decide.within_noise(wall, [0.165], [0.1])
    assert not decide.within_noise(cands["current"], [0.0, 0.03, 0.0], [0.1, 0.02, 0.1])
    assert decide.within_noise(cands["current"], [0.01, 0.01, 0.0], [0.02, 0.02, 0.02])
    missing = next(c for c in core.candidates_for(V.with_effects(motor_lag=False)) if c.effect == "motor_lag")
    assert not decide.within_noise(missing, [0.05], [1.0])


def test_the_untestable_current_names_the_parameters_it_covers():
    """Horizontal only while the vertical current was tested; all three, with both reasons, when
    the recording could not test the vertical one either; other entries kept."""
    vert = next(c for c in core.candidates_for(V, over_ground=False) if c.effect == "current")
    other = {"effect": "wall_proximity", "kind": "misestimated", "reason": "no heave motion"}
    one = core._horizontal_current_untestable([other], vert)
    assert one[0] == other and one[1]["parameters"] == ["environment.current[0]", "environment.current[1]"]
    assert one[1]["reason"].startswith("horizontal: no position or velocity over ground")
    both = core._horizontal_current_untestable(
        [{"effect": "current", "kind": vert.kind, "reason": "Cramer-Rao sd 3x"}, other], vert)
    assert [u["effect"] for u in both] == ["wall_proximity", "current"]
    assert both[1]["parameters"] == [f"environment.current[{i}]" for i in range(3)]
    assert both[1]["reason"].endswith("; vertical: Cramer-Rao sd 3x")


def test_a_few_seconds_of_motion_capture_do_not_cover_the_recording():
    """Motion capture for 3 s of 60 would be held over the other 57 s as a vehicle standing
    still: it counts only where it covers 90 % of the grid (replay.mocap_covers)."""
    import dataclasses

    from ground.recording import MocapStream

    t = np.arange(0.0, 60.0, 0.01)
    tm = np.arange(0.0, 60.0, 0.01)
    full = MocapStream(tm, quat_wxyz=np.tile([1.0, 0.0, 0.0, 0.0], (len(tm), 1)), pos_ned_m=np.zeros((len(tm), 3)))

    class Rec:
        mocap = full

    assert replay.mocap_covers(Rec, t)
    few = tm < 3.0
    Rec.mocap = dataclasses.replace(full, time_s=tm[few], pos_ned_m=full.pos_ned_m[few], quat_wxyz=full.quat_wxyz[few])
    assert not replay.mocap_covers(Rec, t)
    gappy = (tm % 10.0) < 9.5  # 0.5 s dropouts every 10 s: 95 % covered (a 0.05 s hold on each side)
    Rec.mocap = dataclasses.replace(full, time_s=tm[gappy], pos_ned_m=full.pos_ned_m[gappy], quat_wxyz=full.quat_wxyz[gappy])
    assert replay.mocap_covers(Rec, t)
    Rec.mocap = None
    assert not replay.mocap_covers(Rec, t)


def test_a_well_determined_correction_is_not_cut_by_its_point_estimate():
    """0.41 of the 0.05 m/s worth finding, sd 0.003 m/s: with 2 sd it may be 0.53 (kept); the
    same estimate with no sd given stays 0.41 (cut)."""
    vert = next(c for c in core.candidates_for(V, over_ground=False) if c.effect == "current")
    assert decide.correction_size(vert, [0.0205], V) == pytest.approx(0.41)
    assert decide.correction_size(vert, [0.0205], V, np.array([0.003])) == pytest.approx(0.53)


def test_an_unexcited_axis_does_not_carry_a_correction_over_the_cut():
    """Added mass, six coefficients: surge 4 % off nominal (0.2 of the 20 % worth finding), sd
    1 % of nominal there (determined: 0.2 + 2 x 0.05 = 0.3, cut); heave at nominal with sd 30 %
    (undetermined, above half the reference): its 2 sd would have made the size 3.0."""
    am = next(c for c in core.candidates_for(V) if c.effect == "added_mass")
    x0 = np.asarray(am.x0, float)
    theta = x0 * np.array([1.04, 1, 1, 1, 1, 1])
    sd = x0 * np.array([0.01, 0.01, 0.30, 0.01, 0.01, 0.01])
    assert decide.correction_size(am, theta, V, sd) == pytest.approx(0.3)
    sd[0] = x0[0] * 0.2  # surge's own sd at 100 % of the reference: not determined, no 2 sd
    assert decide.correction_size(am, theta, V, sd) == pytest.approx(0.2)


def test_nothing_testable_is_not_within_its_noise():
    from ground.diagnose.cli import summary_text

    nan = float("nan")
    rest = {"fit": {"holdout": {"before": {"total": nan}, "after": {"total": nan}}, "method": "shooting"},
            "mismatch": {"windows": []}}
    none = dict(rest, findings=[], untestable=[{"effect": "buoyancy", "reason": "x"}],
                candidates=[{"effect": "buoyancy", "testable": False}])
    assert summary_text(none).startswith("no finding: this recording cannot test any candidate")
    some = dict(none, candidates=[{"effect": "buoyancy", "testable": True}])
    assert summary_text(some).startswith("no finding: the nominal model explains the recording within its noise")
    short = dict(rest, findings=[], untestable=[{"effect": "buoyancy", "reason": "x"}],
                 fit=dict(rest["fit"], method="none: too little data"))
    assert summary_text(short).startswith("no finding: this recording cannot test any candidate")
    # withheld (the estimator restarted, or too few null draws): the warnings say why, not "noise"
    diverged = dict(some, mismatch={"windows": [], "disturbance": {"divergences": 2}})
    assert summary_text(diverged).startswith("no finding named: the recording could not be tested")
    undrawn = dict(some, calibration={"null_draws": 1})
    assert summary_text(undrawn).startswith("no finding named: the recording could not be tested")
    assert summary_text(dict(some, calibration={"null_draws": 8})).startswith("no finding: the nominal model explains")
    weak = dict(some, negligible=[{"effect": "added_mass", "kind": "misestimated", "explained": 0.015}])
    assert summary_text(weak).startswith("no finding named: candidates passed the calibrated test but too small to "
                                         "name: added_mass (its fit removes 1.5 % of the held-out mismatch)")
    both = dict(weak, rejected=["imu_bias"])
    assert summary_text(both).startswith("no finding named: imu_bias passed the calibrated test but was withdrawn")
    assert "; other candidates passed the calibrated test but too small to name: added_mass" in summary_text(both)


def test_a_significant_candidate_whose_linear_step_says_nothing_held_out_is_still_fitted():
    """A review's find: `_to_fit` took the candidates whose linear held-out drop was above zero
    (the best few) and those below it (by S / threshold): a drop of exactly 0 or NaN was neither
    fitted nor listed anywhere. Now it is fitted with those whose step does not fit better; the
    IMU bias (no residual step) stays out."""
    def score(effect, stat, drop):
        return decide.Score(effect, 1, stat, drop, np.zeros(1), np.ones(1))

    cal = decide.Calibration(8, 1.0, {}, {e: 10.0 for e in "abcde"} | {"imu_bias": 10.0}, 0.01, {})
    above = [score("a", 50.0, 30.0), score("b", 40.0, -5.0), score("c", 30.0, 0.0), score("d", 90.0, math.nan),
             score("imu_bias", 99.0, math.nan)]
    got = [s.effect for s in core._to_fit(above, cal, top=3, failed=3)]
    assert got == ["a", "d", "b", "c"]


def test_a_recording_too_short_to_test_reports_in_the_same_shape(plain):
    """2 s of a recording: every candidate untestable with the reason, and the report has the
    keys a full one has (a reader of the JSON found no 'warnings' or 'candidates' in it) but
    'calibration': no null draw was made (and the summary would then say 'withheld')."""
    from ground.diagnose.cli import summary_text

    rep = core.diagnose(plain.between(plain.t_start_s, plain.t_start_s + 2.0), V).report
    full = {"recording", "mismatch", "findings", "warnings", "untestable", "rejected", "negligible", "fit",
            "candidates", "elapsed_s"}
    assert full <= set(rep), full - set(rep)
    assert rep["candidates"] and not any(c["testable"] for c in rep["candidates"])
    assert {c["effect"] for c in rep["candidates"]} == {u["effect"] for u in rep["untestable"]}
    assert all("too little data" in u["reason"] for u in rep["untestable"])
    assert summary_text(rep).startswith("no finding: this recording cannot test any candidate")


@pytest.mark.slow
def test_a_lag_whose_linear_step_fails_held_out_is_still_fitted_and_named_first(tmp_path):
    """Eval 496 (dev data now): a missing servo lag, joystick pilot, 50 Hz IMU, no motion capture.
    Its score test is far above threshold but the tangent at the default time constant fits
    worse on held-out data; ranked with that tangent, added mass (at its 4x bound) was named.
    Fitted anyway and ranked by its fit's held-out drop, the servo lag is named first."""
    row = prove.run_family_case("eval", 496, tmp_path)
    assert row["expect"] == ["servo_lag"]
    assert row["named"][:1] == ["servo_lag"], row["named"]
    assert row["nrmse_after"] < row["nrmse_before"]


@pytest.mark.slow
@pytest.mark.parametrize("index", [4468, 4456])
def test_a_missing_azimuth_transient_is_fitted_to_its_gain_and_nothing_else(tmp_path, index):
    """Eval 4468 and 4456 (dev data now): a missing azimuth transient, gain 0.049 N^-1, motion
    capture (sweep pilot at 100 Hz; legs pilot at 50 Hz). At 1082084, 4468's ranking fit (a few
    least-squares evaluations from the linear step) stopped at 0.036, 26 % short: the first
    finding is fitted on from there (core._polish). 4456's converged at 0.065, 34 % high, and a
    false added mass was paired with it: the windows' lead-in was 2 s, as for a nominal without the transient, so
    the slow axial-loss mode started short and the gain made up for it (core.lead_seconds now
    counts the filters a candidate switches on). Both land within 5 % of the truth, alone."""
    row = prove.run_family_case("eval", index, tmp_path)
    assert row["expect"] == ["azimuth_transient"]
    assert row["named"] == ["azimuth_transient"], row["named"]
    assert row["param_error"] is not None and row["param_error"] < 0.05, row["param_error"]
    assert row["nrmse_after"] < row["nrmse_before"]


@pytest.mark.parametrize("kind", ["scanned delay", "thruster fault", "commands delay", "no parameter"])
def test_what_the_smoother_cannot_take_is_not_estimated_again(kind):
    """core._reestimated returns None before any smoother run for a finding the smoother cannot
    carry (a thruster fault, a commands delay: no vehicle) or that has nothing to move (a scanned
    delay's Brent refinement converged; a switch with no parameter). With no fitting windows
    given, trying would raise."""
    nominal = load_vehicle()
    base = candidates.CorrectedModel(nominal)
    one = dict(keys=(("sensors.delay", None),), x0=(0.0,), lower=(0.0,), upper=(0.3,))
    cand, cm = {
        "scanned delay": (candidates.Candidate("sensor_delay", "misestimated", scan=(0.0, 0.1), **one), base),
        "thruster fault": (candidates.Candidate("thruster_fault", "misestimated", **one),
                           dataclasses.replace(base, thrust_fraction=(1.0, 1.0, 0.5, 1.0))),
        "commands delay": (candidates.Candidate("sensor_delay", "misestimated", **one),
                           dataclasses.replace(base, command_delay_s=0.05)),
        "no parameter": (candidates.Candidate("wall_proximity", "missing", (), (), (), ()), base),
    }[kind]
    f = candidates.Fit(cand, np.zeros(cand.n_params), 0.0, 0.0, 1.0, 1.0, 0.0, np.zeros(12), np.zeros((1, 12)), model=cm)
    assert core._reestimated([], [], replay.ActuatorRuns(), f, None, None, None, nominal, None) is None


@pytest.mark.slow
@pytest.mark.parametrize("index", [5089, pytest.param(5275, marks=pytest.mark.xfail(
    strict=True, reason="a false sensor delay second since the fitting windows tile the recording (2ef7a6f, "
                        "2026-11-28; the change also reshuffles the null draws, README known gaps), as on "
                        "fresh eval 6154"))])
def test_a_restoring_moment_without_motion_capture_is_estimated_again_with_it_in_the_smoother(tmp_path, index):
    """Eval 5089 and 5275 (dev data now): a restoring moment (centre of buoyancy a few mm off)
    without motion capture, 5089 from the IMU at full rate, 5275 at ArduSub rates. Fitted along
    the nominal smoother's trajectory, whose horizontal velocity carries part of the nominal's
    stronger righting moment, they came out 109 % and 162 % off the truth, outside 3 sd, at the
    fit's true minimum on that trajectory (README, block 5032-5331). Estimated again with the
    finding in the smoother (core._reestimated) both land within 8 % and 3 sd: shot from its own
    smoother's states the re-estimate fits held out better than the nominal and than the first
    estimate shot the same way."""
    row = prove.run_family_case("eval", index, tmp_path)
    assert row["expect"] == ["restoring_moment"]
    assert row["named"] == ["restoring_moment"], row["named"]
    assert row["param_error"] is not None and row["param_error"] < 0.15, row["param_error"]
    assert row["within_3sd"], row
    assert row["nrmse_after"] < row["nrmse_before"]
    rep = json.loads((tmp_path / f"eval_{index}.json").read_text())
    assert "estimated again" in rep["fit"]["method"]  # the re-estimate, not the first fit, is reported


@pytest.mark.slow
@pytest.mark.parametrize("index, named", [(2443, ["buoyancy", "added_mass"]), pytest.param(
    2622, ["azimuth_transient", "sensor_delay"], marks=pytest.mark.xfail(
        strict=True, reason="the masked delay is not named second since the fitting windows tile the recording "
                            "(2ef7a6f, 2026-11-28; the change also reshuffles the null draws, README known gaps)")),
                                          (4257, ["restoring_moment", "thrust_inflow"])])
def test_a_masked_effect_is_named_second_by_the_second_pass(tmp_path, index, named):
    """Eval 2443, 2622 and 4257 (dev data now), two effects each. 2443 (added mass x2.1 masked by
    buoyancy, no motion capture): the added mass's pair share was 10.8 % of the buoyancy's
    held-out drop, under the 15 % then asked. 2622 (the azimuth transient x2.0 masked by a
    sensor delay, ArduSub rates): the delay was not among the first round's fits at all. Scored
    again with the first finding in the model (core._second_pass: the smoother re-run on the
    corrected vehicle), the second effect is significant, fitted in a pair and named second.
    4257 (thrust inflow x1.8 masked by a restoring moment, motion capture): the inflow's pair
    removes 3.3 % of the held-out mismatch, under MIN_EXPLAINED, but its second-pass statistic
    stands 60x its threshold and 2.6x the next candidate's (core._standout)."""
    row = prove.run_family_case("eval", index, tmp_path)
    assert row["expect"] == sorted(named, key=row["expect"].index)
    assert row["named"][:2] == named, row["named"]
    assert row["nrmse_after"] < row["nrmse_before"]


@pytest.mark.slow
@pytest.mark.parametrize("index", [846, 1134, 1044])  # 1044 (a 52 ms delay at 100 Hz with motion capture,
# its statistic 7.3 against a threshold of 81.3 at af2c18c) is named since the fitting windows tile the recording
def test_a_sensor_delay_is_named_first_not_a_servo_lag(tmp_path, index):
    """Eval 846 (no motion capture, scripted pilot, 100 Hz, 92 ms) and 1134 (motion capture,
    scripted, 50 Hz, 55 ms), dev data now. 846 was named servo lag: its delay score was below a
    threshold the null draws had inflated (a secant of a fraction of a sample). 1134's delay
    was fitted 23 % off: least squares with a sub-sample difference step, and commands held from
    the start of each 20 ms grid step, stale by an amount that depends on the IMU's phase. With a
    50 ms secant, a scan refined by a bounded search (candidates._scan_fit) and the commands
    averaged over each step (replay.held_commands), the delay is named first and within 15 %."""
    row = prove.run_family_case("eval", index, tmp_path)
    assert row["expect"] == ["sensor_delay"]
    assert row["named"][:1] == ["sensor_delay"], row["named"]
    assert row["param_error"] is not None and row["param_error"] < 0.15, row["param_error"]
    assert row["within_3sd"], row
    assert row["nrmse_after"] < row["nrmse_before"]


@pytest.mark.slow
def test_a_significant_fit_that_removes_a_sliver_of_the_mismatch_is_no_finding(tmp_path):
    """Eval 884 (dev data now), a control with motion capture: added mass passed its calibrated
    test and its fit removed 1.5 % of the held-out excess; it was named. Below core.MIN_EXPLAINED
    it is no finding (`_too_small`), listed as negligible, and the summary says why nothing is
    named. (Since 2026-11-27 884 itself gives no such fit: its significance came from motion
    capture locked out in its windows, estimate.MOCAP_SETTLE_M; sensor delay's S fell from 139
    to 0.5. It stays a control that names nothing.)"""
    from ground.diagnose.cli import summary_text

    am = next(c for c in core.candidates_for(V) if c.effect == "added_mass")
    theta = np.array(am.x0) * np.array([1.5, 1.5, 1.4, 1, 1, 1])
    sd = np.full(6, 1e-6)
    assert core._too_small(am, theta, sd, 0.015, V, 100.0) == "its fit removes 1.5 % of the held-out mismatch"
    assert not core._too_small(am, theta, sd, core.MIN_EXPLAINED + 0.001, V, 100.0)
    row = prove.run_family_case("eval", 884, tmp_path)
    assert row["expect"] == [] and row["named"] == [], row["named"]
    rep = json.loads(next(tmp_path.rglob("*884*.json")).read_text())
    rep["negligible"] = [{"effect": "added_mass", "kind": "misestimated", "explained": 0.015,
                          "why": "its fit removes 1.5 % of the held-out mismatch"}]
    assert "added_mass (its fit removes 1." in summary_text(rep) and "no finding" in summary_text(rep)


def test_the_report_states_a_share_of_the_held_out_excess_between_0_and_1():
    """Eval 5045 (dev data now): its nominal fitted the held-out samples within the noise, so
    `Fit.explained` divided a drop of 5.1 by no excess (1e-9) and the report listed a negligible
    linear damping as explaining 5120230188. The report states the share clamped to 0-1, as a
    finding's explanation does; names reported elsewhere are left out."""
    from types import SimpleNamespace
    ld, qd = (next(c for c in core.candidates_for(V) if c.effect == e) for e in ("linear_damping", "quadratic_damping"))
    why = "its held-out improvement (chi2 -5.1) is within the noise of a 6-parameter fit"
    small = [(SimpleNamespace(candidate=ld, explained=5.1e9), why), (SimpleNamespace(candidate=qd, explained=-3e9), why)]
    out = core.negligible(small, set())
    assert [(n["effect"], n["explained"]) for n in out] == [("linear_damping", 1.0), ("quadratic_damping", 0.0)]
    assert [n["effect"] for n in core.negligible(small, {"linear_damping"})] == ["quadratic_damping"]
    assert core.reported_share(0.25) == 0.25
    # the share rule's reason, read before the noise rule's: no absurd percentage on the console either
    assert core._too_small(ld, np.array(ld.x0) * 1.5, np.full(6, 1e-9), -5.1e9, V, -5.1) == \
        "its fit removes 0.0 % of the held-out mismatch"


def test_a_held_out_improvement_within_the_noise_of_the_fit_is_no_finding():
    """Eval control 2180 (IMU-only, 120 s): an added mass passed its test (60.2 against 56.4) and
    its fit removed all the held-out excess there was, a chi-square drop of 2.1: within the noise
    of a six-parameter fit (Z_GATE sd of sqrt(12) = 8.7), no finding. The same fit with a drop
    above that, or a one-parameter candidate above 2.5 sqrt(2), is one."""
    am = next(c for c in core.candidates_for(V) if c.effect == "added_mass")
    theta = np.array(am.x0) * np.array([1.5, 1.5, 1.4, 1, 1, 1])
    sd = np.full(6, 1e-6)
    why = core._too_small(am, theta, sd, 1.0, V, 2.1)
    assert why == "its held-out improvement (chi2 -2.1) is within the noise of a 6-parameter fit"
    assert core._too_small(am, theta, sd, 1.0, V, 8.6) and not core._too_small(am, theta, sd, 1.0, V, 8.8)
    buoy = next(c for c in core.candidates_for(V) if c.effect == "buoyancy")
    th = np.array(buoy.x0) * 1.02
    assert core._too_small(buoy, th, np.full(1, 1e-9), 1.0, V, 3.5) and not core._too_small(buoy, th, np.full(1, 1e-9), 1.0, V, 3.6)


def test_a_fit_whose_sd_exceeds_the_smallest_error_worth_finding_everywhere_is_not_sized():
    """Hand computed: the added mass's smallest error worth finding is 20 % of each nominal term
    (decide.reference_magnitude); a fit sd of 1.1x it on every term is not sized, the same with
    one term at 0.9x is. The reported sd is the calibrated one, not below the fit's own
    (core.reported_sd): a calibrated sd of 0.1x does not hide a fit sd of 1.1x. An sd of another
    shape or none says nothing (0); a NaN sd is no size (inf)."""
    am = next(c for c in core.candidates_for(V) if c.effect == "added_mass")
    ref = 0.2 * np.abs(np.array(am.x0))
    np.testing.assert_allclose(decide.reference_magnitude(am, V), ref)
    assert decide.sd_in_worth(am, 1.1 * ref, V) == pytest.approx(1.1)
    assert decide.sd_in_worth(am, np.r_[1.1 * ref[:5], 0.9 * ref[5]], V) == pytest.approx(0.9)
    assert decide.sd_in_worth(am, None, V) == 0.0 and decide.sd_in_worth(am, ref[:3], V) == 0.0
    assert decide.sd_in_worth(am, np.full(6, np.nan), V) == math.inf
    # the shared measure: a NaN sd determines nothing (0.3 / 0.1 = 3 is the best-determined here)
    assert decide.relative_sd([np.nan, 0.3], [1.0, 0.1]) == pytest.approx(3.0)
    assert decide.relative_sd([np.nan, np.nan], [1.0, 0.1]) == math.inf
    np.testing.assert_allclose(core.reported_sd(0.1 * ref, 1.1 * ref), 1.1 * ref)
    np.testing.assert_allclose(core.reported_sd(0.1 * ref, None), 0.1 * ref)
    theta = np.array(am.x0) * 3.0  # 10 reference magnitudes off on every term: no other rule refuses it
    assert not core._too_small(am, theta, 0.1 * ref, 1.0, V, 100.0)
    why = core._too_small(am, theta, 0.1 * ref, 1.0, V, 100.0, fit_sd=1.1 * ref)
    assert why.startswith("its sd is 1.1x the smallest error worth finding") and "cannot size it" in why
    assert not core._too_small(am, theta, 0.1 * ref, 1.0, V, 100.0, fit_sd=np.r_[1.1 * ref[:5], 0.9 * ref[5]])
    # a missing effect switched on is the correction itself: its parameter's sd does not size it
    lag = next(c for c in core.candidates_for(V.with_effects(motor_lag=False)) if c.effect == "motor_lag")
    assert lag.switch_on and decide.sd_in_worth(lag, 5.0 * decide.reference_magnitude(lag, V), V) == 0.0
    # a nominally zero term with no typical magnitude (not a hydrodynamic coefficient, which has
    # one: candidates.size_of) has no relative size: judged on the others only
    zero = dataclasses.replace(am, keys=(("sensors.accel_bias", 0),) + am.keys[1:], x0=(0.0,) + tuple(am.x0[1:]))
    assert decide.reference_magnitude(zero, V)[0] < 1e-9
    assert decide.sd_in_worth(zero, np.r_[1.0, 0.5 * ref[1:]], V) == pytest.approx(0.5)


@pytest.mark.slow
@pytest.mark.parametrize("index, named", [(7243, ["restoring_moment"]), (7091, ["restoring_moment"])])
def test_an_added_mass_unsized_beside_a_restoring_moment_is_not_named(tmp_path, index, named):
    """Eval 7243 (restoring moment x3.6 masked by an IMU bias, IMU only; dev data now): added mass
    ranked first (held-out drop 2583 against the restoring moment's 2219) and was paired with the
    restoring moment, its sd in the pair 15x its smallest error worth finding, the restoring
    moment's 0.03x: the second explains what the first does, not the other way round, so the
    restoring moment is named and the added mass is not (core: `displaced`), listed untestable
    with it (here by the second pass, core._masked_untestable). Eval 7091
    (restoring moment, ArduSub rates): an added mass named second with its sd 9.8x; not
    paired (core._too_small with the pair's sd)."""
    row = prove.run_family_case("eval", index, tmp_path)
    assert row.get("error") is None, row.get("error")
    assert row["named"] == named, row["named"]
    rep = json.loads(next(tmp_path.glob("*.json")).read_text())
    if index == 7243:  # the displaced first: untestable with what displaced it, not "negligible"
        entry = next(u for u in rep["untestable"] if u["effect"] == "added_mass")
        assert entry.get("with") == "restoring_moment" and entry["reason"].endswith("confounded here"), entry
        assert all(n["effect"] != "added_mass" for n in rep["negligible"]), rep["negligible"]
    nominal = load_vehicle(next(tmp_path.glob("*.nominal.toml")))
    for f in rep["findings"]:  # what is named is sized
        ref = decide.reference_magnitude(next(c for c in core.candidates_for(nominal) if c.public == f["effect"]), nominal)
        if f["kind"] == "misestimated" and "std" in f:
            sd = np.ravel(np.array(next(iter(f["std"].values())), float))
            assert len(f["std"]) == 1 and sd.shape == ref.shape and np.min(sd / ref) <= decide.SIZE_SD, f


def test_a_fit_the_held_out_blocks_cannot_reach_is_not_testable_rather_than_rejected():
    """core._holdout_reach by hand, and core._unconfirmable: a significant quadratic damping
    whose fit fails the held-out gate is rejected when the held-out blocks could have shown it,
    and *not testable* when even were it exactly right it would lower the held-out chi-square by
    no more than the gate asks (eval 7648: S 68, one burst of heave in the training blocks)."""
    qd = next(c for c in core.candidates_for(V) if c.effect == "quadratic_damping")
    gate = core.drop_gate(qd)
    assert gate == pytest.approx(core.Z_GATE * math.sqrt(2.0 * qd.n_params))
    # what the fit changes on the held-out rows, weighted like the held-out chi-square: 4 rows
    # held out, one channel moved by 1.0 (sigma 2), neff 0.5: 4 * (1.0 / 2)^2 * 0.5 = 0.5; a
    # non-finite residual moves nothing
    n = 10
    sigma, neff = np.full(12, 2.0), np.full(12, 0.5)
    split = candidates.Split(np.arange(6), np.arange(6, 10), sigma, neff, np.ones(12, bool), 0.4, 4.0,
                         np.arange(n) >= 6)
    res0 = np.zeros((n, 12))
    moved = res0.copy()
    moved[:, 0] = 1.0
    moved[7, 1] = np.nan
    assert core._holdout_reach(types.SimpleNamespace(residual=moved), res0, split) == pytest.approx(4 * 0.25 * 0.5)

    theta = np.asarray(qd.x0, float) * 3.0  # a correction well worth finding
    sd = 0.05 * np.abs(decide.reference_magnitude(qd, V))
    score = decide.Score(qd.effect, qd.n_params, 40.0, 0.0, theta, sd)

    def judged(drop, reach, th=theta):
        return core._unconfirmable(score, types.SimpleNamespace(delta_holdout=drop, theta=th), qd, sd, V, reach)

    why = judged(-3.9, 0.4)
    assert why.startswith("significant on the fitting blocks (S 40.0) but not testable held out: were its fit right it "
                          "would lower the held-out chi-square by 0.4"), why
    assert f"under the {gate:.1f} a finding must show" in why
    assert judged(-3.9, 2 * gate) == ""  # the held-out blocks could show it: judged as usual (rejected)
    assert judged(2 * gate, 0.4) == ""  # passes the gate
    assert judged(float("nan"), 0.4) == ""  # no evidence either way: as before
    # a correction too small to be worth finding stays negligible, whatever the held-out blocks hold
    assert judged(-1.0, 0.4, np.asarray(qd.x0, float)) == ""


def test_a_fit_that_passed_alone_but_was_refused_beside_the_first_is_listed_with_it():
    """core._unpaired (a hostile review's find: a truncated 7243 had a restoring moment whose lone
    fit lowered the held-out chi-square by 159 stand in no list of the report, its pair with the
    wall effect named fitting worse held out): listed untestable with the first, with the pair's
    reason; not when reported otherwise, not when the first is no longer the report's first."""
    by = {c.effect: c for c in core.candidates_for(V)}
    wall, rm, am = by["wall_proximity"], by["restoring_moment"], by["added_mass"]
    fits = [types.SimpleNamespace(candidate=c, delta_holdout=d) for c, d in ((wall, 163.2), (rm, 159.0), (am, 40.0))]
    why_not = {"restoring_moment": "the pair fits worse held out (chi2 +12.6)"}
    out = core._unpaired(fits, fits[:1], wall, why_not, {"wall_proximity"}, set())
    assert [u["effect"] for u in out] == ["restoring_moment", "added_mass"] and all(u["with"] == "wall_proximity" for u in out)
    assert out[0]["reason"] == ("significant alone (its fit lowers the held-out chi-square by 159.0) but not beside "
                                "wall_proximity: the pair fits worse held out (chi2 +12.6); the two are confounded here")
    assert out[1]["reason"].endswith("not beside wall_proximity: it was not fitted in a pair with it; the two are "
                                     "confounded here")
    # never fitted in a pair: its score with the first in the model (the second pass) says why
    again = {"added_mass": decide.Score("added_mass", 6, 3.2, 0.0, np.zeros(6), np.ones(6))}
    cal = types.SimpleNamespace(threshold={"added_mass": 4.5})
    out = core._unpaired(fits, fits[:1], wall, why_not, {"wall_proximity"}, set(), again, cal)
    assert "not beside wall_proximity: with wall_proximity in the model it scores S 3.2 against 4.5;" in out[1]["reason"]
    assert [u["effect"] for u in core._unpaired(fits, fits[:1], wall, why_not, {"wall_proximity"}, {"added_mass"})] == [
        "restoring_moment"]  # already listed (rejected, negligible, untestable)
    # a first displaced by the one named (its pair left it unsized): that is its reason; one
    # displaced by another candidate is not
    unsized = "its sd is 15x the smallest error worth finding on its best-determined parameter: the recording cannot size it"
    confounded = [(am, rm, unsized), (wall, am, "its sd is 3x")]
    assert core._displaced(confounded, rm) == {"added_mass": "in the pair with it, " + unsized}
    assert core._displaced(confounded, None) == {}
    out = core._unpaired(fits[1:] + fits[:1], fits[1:2], rm, core._displaced(confounded, rm), {"restoring_moment"}, set())
    assert [u["effect"] for u in out] == ["added_mass", "wall_proximity"], out
    assert out[0]["reason"] == ("significant alone (its fit lowers the held-out chi-square by 40.0) but not beside "
                                "restoring_moment: in the pair with it, " + unsized + "; the two are confounded here")
    assert core._unpaired(fits, fits[1:2], wall, why_not, {"restoring_moment"}, set()) == []  # named alone after
    assert core._unpaired(fits, fits[:1], wall, why_not, set(), set()) == []  # withdrawn: nothing to be tested with
    assert core._unpaired(fits, [], None, {}, set(), set()) == []


@pytest.mark.slow
def test_a_quadratic_damping_the_held_out_blocks_miss_is_listed_not_testable(tmp_path):
    """Eval 7648 (quadratic damping x3.8, joystick pilot, motion capture, 90 s; dev data now):
    its one burst of heave falls in the fitting blocks, the score test finds the damping (S 68
    against 3.5) and its fit moves nothing held out. The report lists it not testable, with the
    reason, not negligible or rejected."""
    row = prove.run_family_case("eval", 7648, tmp_path)
    assert row.get("error") is None, row.get("error")
    assert row["named"] == [] and row["testable"] is False, row
    rep = json.loads(next(tmp_path.glob("*.json")).read_text())
    entry = [u for u in rep["untestable"] if u["effect"] == "quadratic_damping"]
    assert len(entry) == 1 and "not testable held out" in entry[0]["reason"], rep["untestable"]
    assert "quadratic_damping" not in rep["rejected"] + [n["effect"] for n in rep["negligible"]], rep
    cand = next(c for c in rep["candidates"] if c["effect"] == "quadratic_damping")
    assert cand["statistic"] > cand["threshold"] and cand["testable"] is False, cand
    assert entry[0]["significant"] is True
    assert "quadratic_damping" in no_finding_text(rep) and "the held-out blocks cannot test" in no_finding_text(rep)


def test_a_second_refused_by_its_share_is_paired_when_it_stands_out_on_the_second_pass():
    """core._standout, from dev 4326's second pass (thrust inflow 108x its threshold, linear
    damping 42.7x, under a restoring moment whose fit dropped 88,000): the inflow, refused by
    its share of the pair alone, is paired when it is SECOND_STANDOUT x its threshold and
    SECOND_MARGIN x the next candidate (those left out of `public`, not testable, do not count);
    not when another candidate tops it, not when the top is not among the refused pairs, not
    under SECOND_STANDOUT x its threshold, not when a ratio is not finite; a thrust curve and a
    thruster fault are one name; a local effect whose own pair failed another rule (dev 6159's
    wall effect, within one sd) is no competitor, one not fitted in a pair still is, and one whose
    pair was refused by its share alone is picked through that pair (dev 8265's wall effect, 40x
    its threshold and 3.0x the next); 6336's added mass (4.4x its threshold, 2.2x the next) is paired."""
    ratios = {"thrust_inflow": 108.4, "linear_damping": 42.7, "quadratic_damping": 42.4, "wall_proximity": 300.0,
              "thrust_curve": 30.0, "thruster_fault": 40.0}
    cal = types.SimpleNamespace(threshold={e: 14.0 + i for i, e in enumerate(ratios)})
    score = lambda e, r: types.SimpleNamespace(statistic=r * cal.threshold[e])  # noqa: E731
    again = {e: score(e, r) for e, r in ratios.items()}
    pair = lambda e: ("fit", types.SimpleNamespace(effect=e), again[e])  # noqa: E731
    shared = [pair("thrust_inflow"), pair("linear_damping"), pair("wall_proximity")]
    public = {e: e for e in ratios if e != "wall_proximity"} | {"thrust_curve": "thruster_fault"}
    standout = lambda sh=shared, pub=public, ag=again, fl=(): core._standout(sh, set(fl), ag, cal, pub, None)  # noqa: E731
    assert standout() == shared[0]
    wall = public | {"wall_proximity": "wall_proximity"}
    assert standout(pub=wall) == shared[2]  # the wall effect tops it (300x, 2.8x the inflow): its own pair
    assert standout(pub=wall, ag=again | {"wall_proximity": score("wall_proximity", 200.0)}) is None  # 1.8x: no margin
    assert standout(sh=shared[:2], pub=wall) is None  # not fitted in a pair: still the top, never picked
    assert standout(sh=shared[:2], pub=wall, fl={"wall_proximity"}) == shared[0]  # its pair failed: no competitor
    assert standout(sh=shared[:2], pub=wall, fl={"linear_damping"}) is None  # only a local effect's failure counts
    assert standout(sh=shared[1:]) is None
    assert core.SECOND_MARGIN * 42.7 < 108.4  # the inflow stands out by its margin alone
    assert standout(ag=again | {"linear_damping": score("linear_damping", 108.4 / core.SECOND_MARGIN + 0.1)}) is None
    alone = {e: score(e, 0.0) for e in ratios}  # the inflow alone above 1x: only SECOND_STANDOUT judges it
    assert standout(ag=alone | {"thrust_inflow": score("thrust_inflow", core.SECOND_STANDOUT - 0.1)}) is None
    assert standout(ag=alone | {"thrust_inflow": score("thrust_inflow", core.SECOND_STANDOUT + 0.1)}) == shared[0]
    assert standout(ag=alone | {"thrust_inflow": score("thrust_inflow", 4.4),
                                "linear_damping": score("linear_damping", 2.0)}) == shared[0]  # dev 6336's ratios
    assert standout(ag=again | {"thrust_inflow": score("thrust_inflow", 11.0), "linear_damping": score("linear_damping", 0.0),
                               "quadratic_damping": score("quadratic_damping", 0.0), "thruster_fault": score("thruster_fault", 5.0),
                               "thrust_curve": score("thrust_curve", 5.0)}) == shared[0]
    # one name: the thrust curve and the thruster fault at 60x each are one competitor under 54.2
    assert standout(ag=again | {"thrust_curve": score("thrust_curve", 60.0), "thruster_fault": score("thruster_fault", 60.0)}) is None
    assert standout(ag=again | {"thrust_curve": score("thrust_curve", 50.0), "thruster_fault": score("thruster_fault", 50.0)}) == shared[0]
    for bad in (math.nan, math.inf):
        assert standout(ag=again | {"quadratic_damping": types.SimpleNamespace(statistic=bad)}) is None


def test_the_page_opens_with_the_same_no_finding_line_as_the_summary(tmp_path):
    from ground.diagnose.cli import summary_text
    from ground.diagnose.report import _page

    nan = float("nan")
    base = {"recording": {"source": "r.tlog", "duration_s": 60.0, "skipped_bytes": 0},
            "fit": {"holdout": {"before": {"total": nan}, "after": {"total": nan}}, "method": "shooting"},
            "mismatch": {"windows": []}, "findings": [], "untestable": [{"effect": "buoyancy", "reason": "x"}]}
    for rep, says in [(dict(base, candidates=[{"effect": "buoyancy", "testable": False}]), "cannot test any candidate"),
                      (dict(base, candidates=[{"effect": "buoyancy", "testable": True}]), "within its noise"),
                      (dict(base, candidates=[], rejected=["imu_bias"]), "imu_bias passed the calibrated test but was withdrawn"),
                      (dict(base, candidates=[], negligible=[{"effect": "current", "explained": 0.02, "why": "w"}]),
                       "too small to name: current (w)"),
                      (dict(base, candidates=[], mismatch={"windows": [], "disturbance": {"divergences": 1}}),
                       "could not be tested against the nominal model")]:
        page = _page(tmp_path, rep, []).read_text()
        assert says in page and says in summary_text(rep)


@pytest.fixture(scope="module")
def sweep_start(tmp_path_factory):
    """30 s of 3-2-1-1 multisteps from the first second (the sweep pilot), motion capture, 100 Hz."""
    path = tmp_path_factory.mktemp("rec") / "sweep.tlog"
    prove.record_session(V.with_values({"sensors.imu_rate": 100.0}), path, 30.0, seed=2, mocap=True, pilot="sweep")
    return read_recording(path)


def test_the_null_draws_on_threads_give_the_same_report(sweep_start, monkeypatch):
    """core._each: the null draws run on threads (numba nogil, a locked actuator-run cache) and
    the report is the one of the draws made one at a time, to the last digit (each draw has its
    own random streams); the progress still counts every draw, in order."""
    v = V.with_values({"body.volume": V.body.volume * 1.004})  # a finding, so the whole flow runs
    monkeypatch.setattr(core, "cores", lambda: 2)  # two threads however many cores run the test
    reports, said = [], []
    for threads in (1, 2):
        monkeypatch.setattr(core, "DRAW_THREADS", threads)
        lines = []
        rep = core.diagnose(sweep_start, v, progress=lines.append, draws=4).report
        rep.pop("elapsed_s")
        reports.append(json.dumps(rep, sort_keys=True))
        said.append([m.split(" (")[0] for m in lines if m.startswith("null draw")])
    assert reports[0] == reports[1]
    assert said[0] == said[1] == [f"null draw {b}/4" for b in range(1, 5)]


def test_the_draw_threads_keep_the_callers_floating_point_handling(monkeypatch):
    """core._each: np.errstate is a context variable a new thread does not inherit; the CLI's
    errstate (and a caller's 'raise') must hold in the draws as in the caller (a review's find:
    the draws printed overflow warnings the CLI silences)."""
    monkeypatch.setattr(core, "cores", lambda: 2)
    big = lambda x: np.float64(1e308) * x  # noqa: E731
    with np.errstate(over="raise"):
        with pytest.raises(FloatingPointError):
            list(core._each(big, [1.0, 10.0]))
    with np.errstate(over="ignore"), warnings.catch_warnings():
        warnings.simplefilter("error")
        assert list(core._each(big, [1.0, 10.0])) == [1e308, math.inf]
    seen = []  # errstate's 'call' mode: the caller's handler, not none
    with np.errstate(over="call", call=lambda kind, flag: seen.append(kind)):
        assert list(core._each(big, [10.0, 10.0])) == [math.inf, math.inf]
    assert seen == ["overflow", "overflow"]


def test_the_first_finding_is_fitted_on_and_kept_only_when_it_still_passes_the_rules(sweep_start):
    """core._polish on a real window: the reference vehicle flew it (azimuth transient gain 0.0126)
    and the nominal model has a tenth of that gain. Its fit from the nominal value with the fewest
    evaluations stops on the way (the trust region starts no wider than the start); fitted on
    from there it lands near the truth and is kept. With a calibrated sd wider than the
    correction, the same polished fit fails a first finding's rules (`_too_small`: within one sd
    of the nominal value) and the short fit is kept, saying why."""
    w = sweep_start.between(5.0, 25.0)
    truth = V.effects.azimuth_transient.gain_per_newton
    nominal = V.with_values({"effects.azimuth_transient.gain_per_newton": 0.1 * truth})
    ev = Evaluator(w, nominal)
    res0 = ev.residual(ev.base)
    split = locate.make_split(ev.traj0, locate.noise_realisation(ev, res0))
    at = next(c for c in candidates.candidates_for(nominal) if c.effect == "azimuth_transient")
    assert at.kind == "misestimated" and at.x0 == pytest.approx((0.1 * truth,))
    short = candidates.fit(ev, at, split, res0, max_iter=0)
    assert abs(short.theta[0] - truth) > 0.3 * truth, short.theta  # stopped on the way
    said = []
    got = core._polish(ev, short, split, res0, np.full(1, 1e-9), nominal, said.append)
    assert got is not short and abs(got.theta[0] - truth) < 0.1 * truth, got.theta
    assert got.chi2_train < short.chi2_train and said[-1].startswith("azimuth_transient fitted on: ")
    said = []
    kept = core._polish(ev, short, split, res0, np.full(1, 10.0), nominal, said.append)
    assert kept is short
    assert said == [said[0]] and said[0].endswith("not kept: its correction is within one sd of the nominal value")


def test_motion_capture_position_is_not_locked_out_while_the_filter_settles(sweep_start):
    """Motion-capture position was gated from a window's first sample: on this window (10-20 s of
    a multistep flight) the first accelerometer updates gave the surge velocity a wrong value with
    a small variance, x failed the 6-sigma gate (1 mm noise) within 0.05 s and was never fused
    again: 502 samples gated, the estimate 2.2 m off (dev case 3603 the same: a thrust inflow
    fitted worse than nothing there and was not named). Settling like depth (SETTLE_S ungated,
    within MOCAP_SETTLE_M), the estimate stays on the markers."""
    w = sweep_start.between(10.0, 20.0)
    ev = Evaluator(w, V)
    meas = estimate.measurements(w, V, ev.traj0.time_s)
    err = np.abs(ev.traj0.pos_ned_m - meas.mocap[:, :3])[meas.mocap_ok]
    assert ev.traj0.estimate.outliers < 20, ev.traj0.estimate.outliers
    assert np.percentile(err, 99) < 0.01, np.percentile(err, 99, axis=0)


@pytest.mark.parametrize("size_m, seconds", [(3.0, 0.1), (0.3, 0.2)])
def test_a_motion_capture_glitch_while_the_filter_settles_is_not_fused(sweep_start, size_m, seconds):
    """Ungated is not unguarded: a sample more than MOCAP_SETTLE_M + 6 sd from the estimate while
    settling is a glitch (a marker swap), skipped and counted. With 0.5 m, the first choice, a
    0.3 m swap of 0.2 s half a second into a window was fused: it moved the accelerometer bias
    0.6-0.95 m/s^2, the accelerometer was gated for the rest of the window and a linear damping
    was lost (a hostile session's find)."""
    t, p, cmd, act, meas, x0 = _smoother_inputs(sweep_start, 10.0)
    rows = np.flatnonzero(meas.mocap_ok)
    bad = rows[(t[rows] >= t[0] + 0.5) & (t[rows] < t[0] + 0.5 + seconds)]
    moc = meas.mocap.copy()
    moc[bad, 0] += size_m
    est = estimate.smooth(dataclasses.replace(meas, mocap=moc), act, cmd, p, x0)
    clean = estimate.smooth(meas, act, cmd, p, x0)
    assert est.outliers - clean.outliers == len(bad) > 0
    assert np.abs(est.x[:, 0] - clean.x[:, 0]).max() < 0.01, np.abs(est.x[:, 0] - clean.x[:, 0]).max()
    bias = slice(estimate.I_BA, estimate.I_BA + 3)
    assert np.abs(est.x[:, bias] - clean.x[:, bias]).max() < 0.02


def test_motion_capture_height_is_left_to_the_depth(sweep_start):
    """Two absolute heights that disagree (motion capture's z 3 cm off the pressure's depth: 300 Pa
    of atmospheric pressure) took turns to reset the height every 5 s once both could time out
    (a hostile session's find: heave speed spikes of 0.57 m/s, held-out NRMSE 0.018 -> 0.094). Only
    the depth settles ungated and times out: the estimate follows it and the heave stays smooth."""
    t, p, cmd, act, meas, x0 = _smoother_inputs(sweep_start, 30.0)
    clean = estimate.smooth(meas, act, cmd, p, x0)
    est = estimate.smooth(dataclasses.replace(meas, mocap=meas.mocap + np.array([0, 0, 0.03, 0, 0, 0])),
                          act, cmd, p, x0)
    heave = estimate.I_NU + 2
    assert np.abs(est.x[:, heave] - clean.x[:, heave]).max() < 0.05, np.abs(est.x[:, heave] - clean.x[:, heave]).max()
    late = meas.depth_ok & (t > t[0] + estimate.SETTLE_S)
    err = est.x[late, estimate.I_POS + 2] - float(p[model.P_SURF]) - meas.depth_m[late]
    assert np.median(np.abs(err)) < 0.01, np.median(np.abs(err))


@pytest.mark.parametrize("axis", ["depth", "mocap x", pytest.param("yaw", marks=pytest.mark.xfail(
    strict=True, reason="only positions are retried: fusing ATTITUDE or motion-capture attitude ungated after a "
                        "second (their yaw origins can differ for good) cost three right verdicts (estimate.GATE_RETRY_S)"))])
def test_a_filter_gone_astray_comes_back_to_its_sensor(plain, sweep_start, axis, monkeypatch):
    """Move every depth sample (or motion-capture x) after the settling time 2 m (or start the
    smoother 1 rad off in yaw, with little process noise on the rotation) with a tight velocity
    covariance: every innovation of that axis from then on is beyond the 6-sigma gate. Gated
    forever, the estimate never came back (dev case 1195: 6.5 m of depth drift over 60 s; a yaw
    gated while roll and pitch passed stayed 1.06 rad off, a reviewer's find: the retry had one
    timer per kind, which the passing axes kept resetting). After GATE_RETRY_S of gated-out
    innovations the position (depth, or the motion-capture axis) is reset to the measurement (fused ungated instead, it overshot and oscillated once the timeout
    was 5 s), so the estimate follows the sensor from then on, and chunks shorter than the retry
    time give the same answer (the timer is carried across them)."""
    t, p, cmd, act, meas, x0 = _smoother_inputs(plain, 30.0)
    if axis == "depth":
        moved = t > t[0] + 2.0 * estimate.SETTLE_S
        meas = dataclasses.replace(meas, depth_m=np.where(moved, meas.depth_m + 2.0, meas.depth_m))
        noise, state = estimate.Noise(p0_vel_m_s=1e-3), estimate.I_POS + 2
        got = lambda est: est.x[:, state] - float(p[model.P_SURF])  # noqa: E731
        ok, want, tol = meas.depth_ok, meas.depth_m, 0.02
    elif axis == "mocap x":  # the pool's frame moved 2 m (a re-calibration), or a marker swap
        t, p, cmd, act, meas, x0 = _smoother_inputs(sweep_start, 30.0)
        moved = (t > t[0] + 2.0 * estimate.SETTLE_S)[:, None] * np.array([2.0, 0, 0, 0, 0, 0])
        meas = dataclasses.replace(meas, mocap=meas.mocap + moved)
        noise, state = estimate.Noise(p0_vel_m_s=1e-3), estimate.I_POS
        got = lambda est: est.x[:, state]  # noqa: E731
        ok, want, tol = meas.mocap_ok, meas.mocap[:, 0], 0.01
        # (its variance grown, the step passed the gate by itself after 12 s: the retry's 2 s before)
        after = 2.0 * estimate.SETTLE_S + estimate.GATE_RETRY_S + 0.5
        ok = ok & (t < t[0] + after + 2.0)
    else:
        x0[estimate.I_ATT + 2] += 1.0
        noise, state = estimate.Noise(nu_ang_rad_s2=0.001), estimate.I_ATT + 2
        got = lambda est: est.x[:, state]  # noqa: E731
        ok, want, tol = meas.att_ok, meas.att_rad[:, 2], 0.02
    est = estimate.smooth(meas, act, cmd, p, x0, noise)
    late = ok & (t > t[0] + (after if axis == "mocap x" else 3.0 * estimate.GATE_RETRY_S))
    err = (got(est)[late] - want[late] + np.pi) % (2 * np.pi) - np.pi
    assert est.outliers > 0  # the first innovations were gated out
    assert np.median(np.abs(err)) < tol, np.median(np.abs(err))
    monkeypatch.setattr(estimate, "CHUNK", 80)  # 0.8 s at 100 Hz: shorter than the retry time
    chunked = estimate.smooth(meas, act, cmd, p, x0, noise)
    np.testing.assert_allclose(chunked.x, est.x, atol=1e-9)


def test_a_start_far_off_in_depth_is_not_gated_while_the_filter_settles(plain):
    """A smoother started from its generic prior has no converged estimate for the gate to guard:
    depth is fused ungated for SETTLE_S. Gated from the first sample, a 10 s window's filter that
    one accelerometer update had given a wrong vertical velocity with a small variance rejected
    every depth sample for 5 s and drifted 0.3 m (dev case 2679, ArduSub rates): that window
    inflated the heave channel's noise floor fivefold and hid a buoyancy error. Started 2 m off
    with a tight velocity covariance, the estimate is on the sensor within the settling time,
    with no sample gated out."""
    t, p, cmd, act, meas, x0 = _smoother_inputs(plain, 12.0)
    x0[estimate.I_POS + 2] += 2.0
    est = estimate.smooth(meas, act, cmd, p, x0, estimate.Noise(p0_vel_m_s=1e-3))
    after = meas.depth_ok & (t > t[0] + estimate.SETTLE_S) & (t < t[0] + estimate.GATE_RETRY_S)  # before any retry
    err = est.x[after, estimate.I_POS + 2] - float(p[model.P_SURF]) - meas.depth_m[after]
    assert est.outliers == 0
    assert np.median(np.abs(err)) < 0.02, np.median(np.abs(err))


@pytest.mark.parametrize("garbage", ["random for 2.5 s", "one spike at the start", "three stuck at the start",
                                     "a constant on every other sample for 2.5 s"])
def test_garbage_pressure_while_the_filter_settles_is_not_fused(plain, garbage):
    """Ungated is not unguarded (a hostile user's finds): random pressure (0-5000 hPa) over a
    recording's first 2.5 s was fused while the filter settled and ruined the whole diagnosis;
    one +2000 hPa sample at t = 0 became the initial depth and restarted the estimator; so did
    three stuck samples, and a constant on every other sample, against a median of five. Only depth
    samples that agree with most of their neighbours are fused while settling (and the initial
    state is the first of them): the estimate is on the true depth from the last garbage
    sample's settling time on, no restart, and the garbage counted as outliers."""
    t, p, cmd, act, meas, _ = _smoother_inputs(plain, 12.0)
    env = V.environment
    rows = np.flatnonzero(meas.depth_ok)
    first = rows[t[rows] < t[0] + 2.5]
    bad = {"random for 2.5 s": first, "one spike at the start": rows[:1], "three stuck at the start": rows[:3],
           "a constant on every other sample for 2.5 s": first[::2]}[garbage]
    rng = np.random.default_rng(3)
    press = rng.uniform(0.0, 5000e2, len(bad)) if garbage.startswith("random") else np.full(len(bad), 2000e2 + env.p_atm)
    depth = meas.depth_m.copy()
    depth[bad] = (press - env.p_atm) / (env.rho * env.g)
    tampered = dataclasses.replace(meas, depth_m=depth)
    good = tampered.depth_ok & estimate.depth_plausible(tampered)
    assert not good[bad].any()
    x0 = estimate.initial_state(tampered, 0.0)
    assert x0[estimate.I_POS + 2] == meas.depth_m[np.argmax(good)]
    est = estimate.smooth(tampered, act, cmd, p, x0)
    after = meas.depth_ok & (t > t[bad[-1]] + estimate.SETTLE_S)
    err = est.x[after, estimate.I_POS + 2] - float(p[model.P_SURF]) - meas.depth_m[after]
    assert est.divergences == 0
    assert est.outliers >= len(bad)
    assert np.median(np.abs(err)) < 0.02, np.median(np.abs(err))
    assert np.abs(err).max() < 0.1, np.abs(err).max()


def test_depth_plausibility_by_hand():
    """A sample is plausible when its run (no step between samples faster than the heave limit)
    lasts PLAUSIBLE_RUN_S or holds most of its segment, and it agrees with most samples within
    PLAUSIBLE_S or 2.5 periods (at 2 Hz: two each side), by hand, with a 1 m/s heave limit:
    a spike disagrees with its four neighbours (and each of them still agrees with three of four);
    a dive at 0.9 m/s seen at 2 Hz agrees with itself, one at 1.5 m/s does not; a run of random
    values does not, nor the first good sample after it (two of its four neighbours are garbage);
    a stream with one neighbour a sample agrees with it; two samples must agree with each other,
    one alone cannot be judged; a spike first in a jittered 2 Hz stream is voted out. At 50 Hz, an
    adversary's finds against a median of five (three stuck samples at the start, a constant on
    every other sample) and a hostile session's against a 1 s, 2 m/s vote (+1 m on the first
    sample or for 0.2 s, 27 samples stuck 1 m off, +1.5 m fading over 0.52 s) are voted out up to
    the first sample within 0.2 m of the truth; a wrong start fading no faster than the heave
    limit wins (the documented limit). Finds against the runs are mended: a 0.15 m spike once a
    second left no run long enough, a lone first sample ahead of a gap joined the truth's run,
    0.6 m off for 1.1-2.5 s then a step was believed, and the rule that mended it (the later of
    two long runs believed) threw a true start away for a glitch (hostile sessions); lost packets
    split runs (a review). An hour at 1 kHz is judged (the 1 s vote, with all offsets, took 24 s)."""
    def meas(t, d):
        n = len(t)
        ok = np.isfinite(d)
        z = np.zeros((n, 6))
        return estimate.Measurements(np.asarray(t, float), 0.5, z, np.ones(n, bool), np.nan_to_num(d), ok, z[:, :3],
                                     np.zeros(n, bool), z, np.zeros(n, bool), np.full(6, 1e-3), np.zeros(n, bool), 1.0)
    t = np.arange(10) * 0.5
    flat = np.full(10, 1.0)
    spike = flat.copy()
    spike[4] = 20.0
    assert estimate.depth_plausible(meas(t, spike)).tolist() == [True] * 4 + [False] + [True] * 5
    assert estimate.depth_plausible(meas(t, 0.5 + 0.45 * np.arange(10))).all()
    assert not estimate.depth_plausible(meas(t, 0.5 + 0.75 * np.arange(10))).any()
    noisy = flat.copy()
    noisy[:6] = [3.0, 17.0, 9.0, 31.0, 25.0, 12.0]
    assert estimate.depth_plausible(meas(t, noisy)).tolist() == [False] * 7 + [True] * 3
    gaps = np.where(np.arange(10) % 2 == 0, flat, np.nan)  # every other row has no sample
    assert estimate.depth_plausible(meas(t, gaps)).tolist() == [True, False] * 5
    assert not estimate.depth_plausible(meas(t[:2], np.array([1.0, 40.0]))).any()  # one neighbour: both must agree
    assert estimate.depth_plausible(meas(t[:2], np.array([1.0, 1.2]))).all()
    assert estimate.depth_plausible(meas(t[:1], np.array([40.0]))).all()  # alone: nothing to judge it by
    rng = np.random.default_rng(0)  # the reviewer's 2 Hz stream with 30 ms of jitter, a spike first
    for _ in range(50):
        tj = np.arange(8) * 0.5 + rng.uniform(-0.03, 0.03, 8)
        assert not estimate.depth_plausible(meas(tj, np.r_[21.0, np.full(7, 1.0)]))[0]
    t = np.arange(300) * 0.02
    stuck = np.full(300, 1.0)
    stuck[:3] = 21.0
    assert estimate.depth_plausible(meas(t, stuck)).tolist() == [False] * 3 + [True] * 297
    every_other = np.where((np.arange(300) % 2 == 0) & (t < 2.5), 21.0, 1.0)
    got = estimate.depth_plausible(meas(t, every_other))
    assert not got[every_other > 2.0].any() and got[t > 3.5].all()
    t = np.arange(3000) * 0.02
    truth = 0.5 + 0.005 * np.random.default_rng(1).normal(size=len(t))
    for bad in (t < 0.01, t < 0.2, t < 0.53):  # +1 m: one sample, 0.2 s, 27 samples stuck
        d = np.where(bad, truth[0] + 1.0, truth)
        got = estimate.depth_plausible(meas(t, d))
        assert not got[bad].any() and got[t > 1.0].all()
    fade = truth + np.clip(1.5 * (1.0 - t / 0.52), 0.0, None)
    got = estimate.depth_plausible(meas(t, fade))
    assert (fade - truth)[np.argmax(got)] < 0.2 and got[t > 1.0].all()
    for lasts in (1.1, 1.5, 2.5):  # a long wrong start that steps into the truth: it disagrees with the longest run
        wrong = t < lasts
        got = estimate.depth_plausible(meas(t, np.where(wrong, truth + 0.6, truth)))
        assert not got[wrong].any() and got[~wrong][1:].all()  # (the first after the step: half its votes are wrong)
    slow = truth + np.clip(1.0 - 0.5 * t, 0.0, None)  # fading no faster than the heave limit: the
    assert estimate.depth_plausible(meas(t, slow))[0]  # documented limit, it wins
    glitch = (t >= 3.0) & (t < 4.5)  # a true start, then a 1.5 s glitch and random junk: believing the
    junk = (t >= 4.5) & (t < 5.0)  # later of two long runs that meet in a step threw the start away
    d = np.where(junk, np.random.default_rng(3).uniform(0.0, 10.0, len(t)), truth + 0.5 * glitch)
    assert estimate.depth_plausible(meas(t, d))[t < 2.9].all()
    spikes = truth.copy()  # once a second: a run split at each spike was never long enough
    spikes[::50] += 0.15  # (0.15 m wins its vote: its neighbours bridge it)
    assert estimate.depth_plausible(meas(t, spikes)).all()
    spikes = truth.copy()
    spikes[::45] += 0.5  # voted out, and nothing else
    assert (~estimate.depth_plausible(meas(t, spikes)) == (np.arange(len(t)) % 45 == 0)).all()
    rng = np.random.default_rng(5)  # a review's find: lost packets split runs at every gap longer than
    for rate in (5.0, 10.0):  # the window, and good samples were voted out (4.5-5.6 % at 10 Hz)
        tl = np.arange(int(600 * rate)) / rate
        kept = rng.random(len(tl)) > 0.2
        got = estimate.depth_plausible(meas(tl[kept], 0.5 + 0.005 * rng.normal(size=kept.sum())))
        assert got.mean() > 0.99, got.mean()
    kept = t % 0.8 < 0.5  # 0.3 s dropouts every 0.8 s at 50 Hz: all were voted out
    assert estimate.depth_plausible(meas(t[kept], truth[kept])).all()
    tg = np.r_[0.0, t[75:]]  # a lone first sample 1.3 m off, 1.5 s before the rest: its own run
    assert estimate.depth_plausible(meas(tg, np.r_[truth[0] + 1.3, truth[75:]])).tolist() == [False] + [True] * 2925
    t = np.arange(3_600_000) * 1e-3
    assert estimate.depth_plausible(meas(t, 0.5 + 0.002 * np.random.default_rng(2).normal(size=len(t)))).all()


def test_settling_counts_from_each_segments_first_plausible_depth_or_its_first_depth():
    """`_settle_from` by hand: segments start at row 0 and at each reset; a segment with no
    plausible depth settles from its first depth sample (before, it settled for ever and never
    fused depth: a hostile session's find), one with no depth at all past the end (2 n + 1)."""
    reset = np.array([0, 0, 0, 1, 0, 0, 1, 0, 1, 0], bool)
    ok = np.array([0, 1, 1, 0, 1, 1, 0, 1, 0, 0], bool)
    good = np.array([0, 1, 1, 0, 0, 0, 0, 1, 0, 0], bool)
    assert estimate._settle_from(reset, good, ok).tolist() == [1] * 3 + [4] * 3 + [7] * 2 + [21] * 2


@pytest.mark.slow
@pytest.mark.parametrize("tamper", ["+1 m on the first sample", "+1 m for 0.2 s", "+1.5 m fading over 0.52 s",
                                    "27 samples stuck 1 m off", "+0.6 m for 2.5 s", "+0.15 m once a second",
                                    pytest.param("no pressure at all", marks=pytest.mark.xfail(
                                        strict=True, reason="since the fitting windows tile it (2ef7a6f) a linear "
                                                            "damping passes its threshold on this perfect recording "
                                                            "without any depth and is rejected held out: no "
                                                            "finding, but not 'nothing rejected'; at draw seeds "
                                                            "1-3 of the shared stream nothing passed (a review); "
                                                            "with one stream per draw and window (22efbc1) the "
                                                            "linear damping still passes its threshold"))])
def test_a_wrong_start_of_the_pressure_names_nothing_on_a_perfect_recording(tmp_path_factory, tamper):
    """A hostile session's finds against a 1 s, 2 m/s vote (60 s, 50 Hz IMU, no motion capture):
    +1 m on the first sample was voted plausible, became the initial depth and took the held-out
    NRMSE from 0.05 to 7.7; 27 stuck samples won their vote (3.3); +1.5 m fading over 0.52 s named
    a sensor delay with confidence 1.0; all-NaN pressure gave no warning; and against the runs that
    mended it, a 15 hPa spike once a second left no run long enough, every depth sample was
    voted out and never fused (sensor delay named, held-out 0.53); 0.6 m off for 1.5 s, then a
    step, named a delay and a motor lag, and for 2.5 s left the truth gated until the retry
    (held-out 0.38). Now nothing is named, the fit is as on the clean recording, and a missing
    pressure is said. (The fade's last 0.17 m,
    no faster than 1 m/s against the samples after it, passes the vote: linear and quadratic
    damping are tested on it and rejected. Spikes throughout stay in the measured depth the fit
    is scored against: 0.085 held out, five candidates tested and rejected.)"""
    rec = _session(tmp_path_factory, "start", V.with_values({"sensors.imu_rate": 50.0}), mocap=False, seed=7)
    pr = rec.pressure
    t = pr.time_s - pr.time_s[0]
    rho_g = V.environment.rho * V.environment.g
    press = np.array(pr.press_abs_pa, float)
    if tamper == "no pressure at all":
        press[:] = np.nan
    elif tamper.startswith("+1.5"):
        press += 1.5 * rho_g * np.clip(1.0 - t / 0.52, 0.0, None)
    elif tamper.startswith("+0.15"):
        press[::50] += 0.15 * rho_g
    else:
        bad = {"+1 m on the first sample": t < 1e-6, "+1 m for 0.2 s": t < 0.2, "+0.6 m for 2.5 s": t < 2.5,
               "27 samples stuck 1 m off": np.arange(len(t)) < 27}[tamper]
        off = 0.6 if tamper.startswith("+0.6") else 1.0
        press[bad] = press[0] + off * rho_g if tamper.startswith("27") else press[bad] + off * rho_g
    rep = core.diagnose(dataclasses.replace(rec, pressure=dataclasses.replace(pr, press_abs_pa=press)), V).report
    assert rep["findings"] == [], rep["findings"]
    # the fade's last 0.17 m passes the vote and is fused (two dampings are tested on it and
    # rejected); the spikes stay in the measured depth throughout (five candidates are)
    if not tamper.startswith(("+1.5", "+0.15")):
        assert rep.get("rejected", []) == [], rep.get("rejected")
    assert rep["mismatch"]["disturbance"]["divergences"] == 0
    if tamper == "no pressure at all":
        assert any(w.startswith("no usable depth sample") for w in rep["warnings"]), rep["warnings"]
        path = tmp_path_factory.mktemp("report") / "report.json"  # strict JSON: what was NaN is null
        write_json(rep, path)
        json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"{c} in the report"))
    else:
        # the spikes are in the measured depth the fit is scored against: 0.085 here
        bound = 0.1 if tamper.startswith("+0.15") else 0.06
        assert rep["fit"]["holdout"]["before"]["total"] < bound, rep["fit"]["holdout"]["before"]
        said = [w for w in rep["warnings"] if "depth samples" in w]  # more than 1 % voted out is said
        assert len(said) == (tamper == "+0.6 m for 2.5 s"), rep["warnings"]


@pytest.mark.slow
def test_a_four_second_pressure_glitch_names_nothing_on_a_perfect_recording(tmp_path_factory):
    """An adversary's find: +5000 Pa (+0.51 m) on the pressure for 4 s of a perfect 60 s
    recording (50 Hz IMU, no motion capture). With the depth retry after 1 s the glitch was fused,
    the smoothed depth reached 1.14 m, the sphere met the 1.2 m floor, and a wall effect was named
    with confidence 1.00. After ArduPilot's 5 s (estimate.GATE_RETRY_S) it is an outlier."""
    rec = _session(tmp_path_factory, "glitch", V.with_values({"sensors.imu_rate": 50.0}), mocap=False, seed=7)
    pr = rec.pressure
    bad = (pr.time_s >= 20.0) & (pr.time_s < 24.0)
    rec = dataclasses.replace(rec, pressure=dataclasses.replace(pr, press_abs_pa=pr.press_abs_pa + 5000.0 * bad))
    d = core.diagnose(rec, V)
    assert d.report["findings"] == [], d.report["findings"]
    assert d.report["mismatch"]["disturbance"]["outliers"] >= bad.sum() * 0.9


@pytest.mark.slow
def test_random_pressure_in_the_first_seconds_names_nothing_on_a_perfect_recording(tmp_path_factory):
    """A hostile user's find: random pressure (0-5000 hPa) over the first 2.5 s of a perfect
    60 s recording (50 Hz IMU, no motion capture) was fused while the smoother settled: here the
    nominal's held-out NRMSE went from 0.052 (clean) to 8.0 with 43 estimator restarts, and a wall
    effect and a current were withdrawn, with no warning. Only plausible depth is fused while
    settling: nothing named, nothing withdrawn, the fit as on the clean recording (0.0505), and a
    warning counts the garbage samples in the water (those below the surface are dropped as air)
    among the depth samples that disagree with the samples around them."""
    rec = _session(tmp_path_factory, "garbage", V.with_values({"sensors.imu_rate": 50.0}), mocap=False, seed=7)
    pr = rec.pressure
    bad = pr.time_s < pr.time_s[0] + 2.5
    rng = np.random.default_rng(5)
    press = np.where(bad, rng.uniform(0.0, 5000e2, len(bad)), pr.press_abs_pa)
    d = core.diagnose(dataclasses.replace(rec, pressure=dataclasses.replace(pr, press_abs_pa=press)), V)
    rep = d.report
    assert rep["findings"] == [] and rep.get("rejected", []) == [], (rep["findings"], rep.get("rejected"))
    assert rep["mismatch"]["disturbance"]["divergences"] == 0
    assert rep["fit"]["holdout"]["before"]["total"] < 0.06, rep["fit"]["holdout"]["before"]
    env = V.environment
    wet = (press - env.p_atm) / (env.rho * env.g) > 0.01  # estimate.measurements: the rest reads the air
    garbage = int((bad & wet).sum())
    said = [re.search(r"(\d+) of (\d+) depth samples \((\d+) %\) disagree", w) for w in rep["warnings"]]
    said = [m for m in said if m]
    assert len(said) == 1, rep["warnings"]
    n, total, pct = (int(g) for g in said[0].groups())
    assert 0.9 * garbage <= n <= garbage  # on the grid a sample may share a row: never more than were fed
    assert abs(total - wet.sum()) <= 0.02 * wet.sum() and pct == round(100 * n / total)


def test_signal_nrmse_by_hand_and_a_stuck_sensor_is_left_out():
    t = np.linspace(0.0, 2 * np.pi, 1000, endpoint=False)
    ref = np.sin(t)  # RMS deviation 1/sqrt(2)
    assert core.signal_nrmse(ref + 0.1, ref) == pytest.approx(0.1 * math.sqrt(2.0), rel=1e-12)
    # a noise probe of variance 0.01 comes out of both: sqrt((0.02 - 0.01) / (0.5 - 0.01))
    probe = np.full_like(t, 0.1)
    err = np.full_like(t, math.sqrt(0.02))
    assert core.signal_nrmse(ref + err, ref, probe) == pytest.approx(math.sqrt(0.01 / 0.49), rel=1e-12)
    # a pressure sensor pinned at its limit: nothing but rounding moves (the adversary's 1.8e13)
    stuck = 2.0 + 1e-15 * np.cos(7 * t)
    assert math.isnan(core.signal_nrmse(stuck + 0.05, stuck))
    assert math.isnan(core.signal_nrmse(ref + 0.1, ref, np.full_like(t, 1.0)))  # under its noise
    # moving beyond its noise by less than the noise itself (0.5 - 0.3 < 0.3): the estimated
    # noise level's error would be the denominator (eval control 2163's yaw rate at 4.98)
    assert math.isnan(core.signal_nrmse(ref + 0.1, ref, np.full_like(t, math.sqrt(0.3))))
    assert core.signal_nrmse(ref + 0.1, ref, np.full_like(t, math.sqrt(0.2))) == pytest.approx(0.0)
    small = 1e-4 * np.sin(t)  # a small motion that is real stays measured
    assert core.signal_nrmse(small * 1.1, small) == pytest.approx(0.1, rel=1e-9)
    assert core.signal_nrmse(np.where(t > 3, np.nan, ref), ref) == math.inf  # a diverged model: worst


def test_held_out_totals_compare_the_same_signals_before_and_after():
    """A signal left out on one side is left out of both totals; a corrected model that diverged
    (inf after) stays worst; a signal on which the nominal diverged (inf before) is left out, so
    a fit worse on every other signal cannot pass the held-out gate on it (a review's find)."""
    b = {"gyro_z": 4.98, "roll": 0.3, "pitch": 0.1, "depth": math.nan}
    a = {"gyro_z": math.nan, "roll": 0.6, "pitch": 0.2, "depth": 0.05}
    assert core.paired_totals(b, a) == pytest.approx((0.2, 0.4), rel=1e-12)
    assert core.paired_totals({"x": 0.2, "y": 0.4}, {"x": math.inf, "y": 0.1}) == (pytest.approx(0.3), math.inf)
    assert all(math.isnan(v) for v in core.paired_totals({"x": math.nan}, {"x": 0.1}))
    before, after = core.paired_totals({"x": math.inf, "y": 0.1}, {"x": 5.0, "y": 3.0})
    assert (before, after) == (pytest.approx(0.1), pytest.approx(3.0)) and not after < before


@pytest.mark.parametrize("nominal, hi", [(0.0, 0.5), (0.015, 0.5), (0.48, 0.78), (1.2, 1.5), (1.9, 2.0)])
def test_the_delay_is_searched_past_the_vehicle_files_own_delay(nominal, hi):
    """Up to 0.3 s past the file's own delay, never past the 2 s a file may say (a fitted value
    must paste back), scanned every 0.1 s at most beyond 0.5 s and 50 ms either side of it."""
    c = next(c for c in candidates.candidates_for(V.with_values({"sensors.delay": nominal}))
             if c.effect == "sensor_delay")
    assert c.upper == pytest.approx((hi,)) and c.lower == (0.0,)
    V.with_values({"sensors.delay": c.upper[0]})  # a vehicle file takes the bound
    assert c.scan[0] == 0.0 and c.scan[-1] == pytest.approx(hi) and list(c.scan) == sorted(set(c.scan))
    assert c.scan[:len(candidates.DELAY_SCAN_S)] == candidates.DELAY_SCAN_S  # the fixed points stay
    assert np.diff(c.scan).max() <= 0.1 + 1e-9
    if 0.5 < nominal + 0.05 <= hi:  # (below 0.5 s the fixed points serve)
        assert any(abs(x - (nominal + 0.05)) < 1e-9 for x in c.scan)
    if nominal - 0.05 > 0.5:
        assert any(abs(x - (nominal - 0.05)) < 1e-9 for x in c.scan)


def test_a_family_tested_by_some_parameters_lists_the_others_by_name():
    """Per parameter, decide.testable's rule: the damping family whose surge is not determined
    (sd 0.6 of its reference against the 0.5 cut; sway 0.3, heave 0.1) names surge alone; a
    significant family, or one with every parameter determined, has no entry."""
    c = next(c for c in candidates.candidates_for(V) if c.effect == "linear_damping")
    ref = decide.reference_magnitude(c, V)
    sd = ref * np.array([0.6, 0.3, 0.1, 0.2, 0.2, 0.2])
    s = decide.Score("linear_damping", 6, 3.0, 0.0, np.asarray(c.x0), sd, ref)
    cal = decide.Calibration(8, 1.0, {"linear_damping": 1.0}, {"linear_damping": 20.0}, 0.003, {}, {})
    u = core._partly_untestable(c, s, cal)
    assert u["effect"] == "linear_damping" and u["parameters"] == ["hydro.linear_damping[0]"]
    assert u["reason"].startswith("hydro.linear_damping[0] (the family's other parameters are tested)")
    assert "sd 0.6x" in u["reason"]
    assert core._partly_untestable(c, dataclasses.replace(s, statistic=25.0), cal) is None  # significant
    assert core._partly_untestable(c, dataclasses.replace(s, sd=ref * 0.4), cal) is None  # all determined
    assert decide.testable(s, cal)  # the family as a whole stays testable (its heave is)


def test_the_benchmark_counts_a_case_untestable_only_for_its_checked_parameter():
    case = prove.Case("x", ("linear_damping",), check={"hydro.linear_damping[0]": 2.5})
    part = lambda *names: {"effect": "linear_damping", "parameters": list(names), "reason": "r"}  # noqa: E731
    assert prove._testable(case, [])
    assert prove._testable(case, [part("hydro.linear_damping[2]")])
    assert not prove._testable(case, [part("hydro.linear_damping[2]", "hydro.linear_damping[0]")])
    assert not prove._testable(case, [{"effect": "linear_damping", "reason": "r"}])  # the whole family
    assert prove._testable(case, [{"effect": "buoyancy", "reason": "r"}])
    cur = prove.Case("c", ("current",), check={"environment.current": [0.04, -0.03, 0.0]})
    horiz = {"effect": "current", "parameters": ["environment.current[0]", "environment.current[1]"], "reason": "r"}
    assert not prove._testable(cur, [horiz])  # a vector key: any listed element covers it ...
    vert = {"effect": "current", "parameters": ["environment.current[2]"], "reason": "r"}
    assert not prove._testable(cur, [vert])
    assert prove._testable(cur, [vert], V)  # ... that differs from the nominal's, when it is given
    assert not prove._testable(cur, [horiz], V)
    fault = prove.Case("f", ("thruster_fault",), check={"thruster_fault.unit[2].thrust_fraction": 0.5})
    assert prove._testable(fault, [{"effect": "thruster_fault", "parameters": ["x"], "reason": "r"}], V)
    free = prove.Case("t", ("thrust_inflow",))  # nothing checked: a listed family is untestable
    assert not prove._testable(free, [{"effect": "thrust_inflow", "parameters": ["a"], "reason": "r"}])
    # untestable only with the report's own first finding in the model: the first pass's verdict counts
    assert prove._testable(case, [{"effect": "linear_damping", "with": "quadratic_damping", "reason": "r"}])


@pytest.mark.slow
def test_a_surfacing_in_a_recordings_last_seconds_is_fitted_and_named(tmp_path):
    """Dev 5655 (surface effect x4.2, 90 s, scripted pilot, ArduSub rates): the pilot surfaces at
    77-84 s, and the fitting windows counted whole from the start (0-80 s) held 2.7 s of it;
    nothing was named. Tiling the recording (core.fit_windows) fits all of it."""
    row = prove.run_family_case("eval", 5655, tmp_path)
    assert row["expect"] == ["surface_proximity"] and row["duration_s"] == 90.0
    assert row["named"][:1] == ["surface_proximity"], row["named"]
    assert row["nrmse_after"] < row["nrmse_before"]


@pytest.mark.slow
@pytest.mark.parametrize("index, first, masked", [(5882, "restoring_moment", "added_mass"),
                                                  (5864, None, None)])
def test_a_masked_effect_undetermined_on_the_second_pass_is_listed_untestable(tmp_path, index, first, masked):
    """Dev 5882 (added mass x2.3 masked by a restoring moment): the restoring moment is named
    alone and, with it in the model, the added mass is undetermined (core._masked_untestable):
    listed untestable with the restoring moment, not read as absent; the benchmark still counts
    the case tested (and missed). Dev 5864 (added mass x2.4): its first finding is withdrawn
    after the second pass (its held-out fit not better), and nothing is listed 'with' a finding
    the report does not make (it had raised IndexError)."""
    row = prove.run_family_case("eval", index, tmp_path)
    assert row.get("error") is None, row.get("error")
    rep = json.loads(next(tmp_path.glob("*.json")).read_text())
    named = [f["effect"] for f in rep["findings"]]
    withs = {u["effect"]: u.get("with") for u in rep["untestable"] if u.get("with")}
    assert set(withs.values()) <= set(named), (named, withs)
    for u in rep["untestable"]:  # the candidates rows are the first pass's: significant there is testable
        rows = [c for c in rep["candidates"] if c["effect"] == u["effect"]]
        if u.get("with"):
            assert all(c["testable"] == (c["statistic"] > c["threshold"]) for c in rows), (u, rows)
            assert u["reason"].startswith("significant alone") == any(c["testable"] for c in rows), (u, rows)
    if first is not None:
        assert named[:1] == [first], named
        assert withs.get(masked) == first and row["masked_by"] == first and row["testable"], (withs, row)
