"""Locate the mismatch: noise floor from the data, flagged windows and axes, regime tags.

Noise floor. Each sensor's white-noise level is estimated from its own samples (the robust
spread of second differences: for white noise of sigma s, diff2 has sigma s sqrt(6); smooth
motion contributes little at the sensor rate). A fresh noise draw of those levels is added to
the recording, replayed, and the change in the residual is one realisation of how sensor noise
reaches each residual channel through the reconstruction: its spread is the channel's floor,
its autocorrelation says how many samples are independent.

Windows. The residual is averaged over 1 s bins; a bin is flagged on a channel when its mean
exceeds `Z_FLAG` times the floor of a bin mean (from the same noise realisation). Adjacent
flagged bins merge into a window with its axes, its score (largest |z|) and regime tags.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from onboard.vehicle import Vehicle

from . import replay
from .replay import white_noise_sigma  # noqa: F401  (part of this module's API)
from .candidates import CHANNEL_AXIS, CHANNELS, Evaluator, Split

Z_FLAG = 5.0
BIN_S = 1.0
BLOCK_S = 4.0
HOLDOUT_BLOCKS = (2, 5, 8)  # of every 10 blocks: 30 % held out, spread over the whole run
HOLDOUT_SHARE = len(HOLDOUT_BLOCKS) / 10
NEAR_SURFACE_R = 1.5  # "near the surface": within this many hull radii (near_boundaries)
NEAR_FLOOR_R = 2.0  # "near the floor": within this many hull radii
MIN_NEAR_BALANCE = 2 / 3  # near the surface (or floor): 20-53 % of the samples held out, or the phase moves (block_shift)
DECIMATE_S = 0.05
EDGE_S = 1.0
NEFF_MAX_LAG_S = 5.0


def sensor_noise(rec, floor: bool = False) -> dict:
    """Estimated white-noise sigma of each stream, in the stream's units; with `floor`, not below
    the estimator's floors (a quantised stream can show no spread between samples)."""
    out = {
        "gyro_rad_s": white_noise_sigma(rec.imu.gyro_frd_rad_s),
        "accel_m_s2": white_noise_sigma(rec.imu.accel_frd_m_s2),
        "pressure_pa": white_noise_sigma(rec.pressure.press_abs_pa),
    }
    if rec.attitude is not None:
        e = np.array(rec.attitude.euler_rad)
        e[:, 2] = np.unwrap(e[:, 2])
        out["attitude_rad"] = white_noise_sigma(e)
    if rec.mocap is not None:
        out["mocap_m"] = white_noise_sigma(rec.mocap.pos_ned_m)
        out["mocap_quat"] = white_noise_sigma(rec.mocap.quat_wxyz)
    if floor:
        from .estimate import SIGMA_FLOOR

        env = 1000.0 * 9.81  # Pa per metre of fresh water: the depth floor in pressure units
        lows = {"gyro_rad_s": SIGMA_FLOOR[0], "accel_m_s2": SIGMA_FLOOR[1], "pressure_pa": SIGMA_FLOOR[2] * env,
                "attitude_rad": SIGMA_FLOOR[3], "mocap_m": SIGMA_FLOOR[4], "mocap_quat": SIGMA_FLOOR[5] / 2}
        out = {k: np.maximum(v, lows[k]) for k, v in out.items()}
    return out


def with_extra_noise(rec, sigmas: dict, seed: int = 12345):
    """The recording with one more draw of white noise at the estimated levels."""
    rng = np.random.default_rng(seed)
    r = dataclasses.replace
    imu = r(rec.imu, gyro_frd_rad_s=rec.imu.gyro_frd_rad_s + rng.normal(size=rec.imu.gyro_frd_rad_s.shape) * sigmas["gyro_rad_s"],
            accel_frd_m_s2=rec.imu.accel_frd_m_s2 + rng.normal(size=rec.imu.accel_frd_m_s2.shape) * sigmas["accel_m_s2"])
    pr = r(rec.pressure, press_abs_pa=rec.pressure.press_abs_pa + rng.normal(size=rec.pressure.press_abs_pa.shape) * sigmas["pressure_pa"])
    att = rec.attitude
    if att is not None:
        att = r(att, euler_rad=att.euler_rad + rng.normal(size=att.euler_rad.shape) * sigmas["attitude_rad"])
    mc = rec.mocap
    if mc is not None:
        q = mc.quat_wxyz + rng.normal(size=mc.quat_wxyz.shape) * sigmas["mocap_quat"]
        mc = r(mc, pos_ned_m=mc.pos_ned_m + rng.normal(size=mc.pos_ned_m.shape) * sigmas["mocap_m"],
               quat_wxyz=q / np.linalg.norm(q, axis=1, keepdims=True))
    return r(rec, imu=imu, pressure=pr, attitude=att, mocap=mc)


def noise_realisation(ev: Evaluator, res0: np.ndarray) -> np.ndarray:
    """One realisation (N, 12) of sensor noise as it reaches the residual channels."""
    noisy = Evaluator(with_extra_noise(ev.rec, sensor_noise(ev.rec)), ev.nominal, ev.lead, ev.runs)
    return noisy.residual(noisy.base) - res0


def near_boundaries(traj: replay.Trajectory, vehicle: Vehicle) -> np.ndarray:
    """(N, 2) bool: within NEAR_SURFACE_R hull radii of the surface, within NEAR_FLOOR_R of the
    floor: where the surface and wall effects are largest (spec 4: the submerged fraction is below
    1 only above R; the wall factor 1 + k (R/d)^3 is 1 + k/8 at d = 2 R), the `regimes` tags and
    `block_shift`'s strata."""
    e = vehicle.environment
    R = vehicle.body.radius
    z = traj.pos_ned_m[:, 2]
    return np.column_stack([z - e.surface_depth < NEAR_SURFACE_R * R, e.floor_depth - z < NEAR_FLOOR_R * R])


def block_shift(time_s, near, spans) -> int:
    """The phase (0-9) of the held-out blocks (counted from time_s[0]) for a recording sampled at
    `time_s` whose `near_boundaries` are `near`, fitted on the windows `spans` [(t0, t1)].
    Stratified cross-validation (Kohavi 1995): the surface and wall effects are largest near
    them, so each boundary the vehicle visits inside the fitting windows (their samples that
    `make_split` uses: EDGE_S in from each end) should be both fitted and tested. A boundary's
    balance is min(held / HOLDOUT_SHARE, trained / (1 - HOLDOUT_SHARE)) of its samples, capped
    at 1; phase 0 is kept while every visited boundary's is at least MIN_NEAR_BALANCE, otherwise
    the phase with the best worst balance (the smallest such phase; 0 unless it does better).
    The one phase serves the windows and the whole recording alike (`make_split`), so what the
    fits train on is never what the held-out shooting shows. With phase 0 only, the only
    surfacing of a 90 s flight fell wholly in training blocks, the surface effect stood at 276x
    its threshold and its fit moved nothing held out (eval 5580); holding all of it out instead
    left nothing to fit (the first version of this rule: the surface effect and a wall effect
    became untestable, dev 5580 and 5505). The phase comes from the depth alone, never from a
    residual."""
    t = np.asarray(time_s, float)
    used = np.zeros(len(t), bool)
    for a, b in spans:
        used |= (t >= a + EDGE_S) & (t <= b - EDGE_S)
    n = np.asarray(near, bool)[used]
    cols = [c for c in range(n.shape[1]) if n[:, c].any()]
    if not cols:
        return 0
    blocks = ((t[used] - t[0]) // BLOCK_S).astype(int)

    def worst(shift):
        held = np.isin((blocks + shift) % 10, HOLDOUT_BLOCKS)
        return min(min(h / HOLDOUT_SHARE, (1.0 - h) / (1.0 - HOLDOUT_SHARE), 1.0)
                   for h in (float(held[n[:, c]].mean()) for c in cols))

    balance = [worst(s) for s in range(10)]
    if balance[0] >= MIN_NEAR_BALANCE or max(balance) <= balance[0]:
        return 0
    return int(np.argmax(balance))


def make_split(trajs, noises, shift: int = 0, origin: float | None = None) -> Split:
    """Train/holdout decimated indices (blocks of BLOCK_S, HOLDOUT_BLOCKS of every 10 held out,
    at the phase `shift` (block_shift), blocks counted from `origin`: the first sample's time
    unless given; the fitting windows count from the recording's start, as its whole split does).

    `trajs` and `noises` may be lists (segments of one recording, concatenated in that order).
    """
    if isinstance(trajs, replay.Trajectory):
        trajs, noises = [trajs], [noises]
    origin = trajs[0].time_s[0] if origin is None else origin
    train, hold, idx_all, masks = [], [], [], []
    off = 0
    for traj in trajs:
        t = traj.time_s - traj.time_s[0]
        step = max(1, int(round(DECIMATE_S / traj.dt_s)))
        idx = np.arange(0, len(t), step)
        idx = idx[(t[idx] >= EDGE_S) & (t[idx] <= t[-1] - EDGE_S)]
        block = (((traj.time_s - origin) // BLOCK_S).astype(int) + shift) % 10
        hold_mask = np.isin(block, HOLDOUT_BLOCKS)
        train.append(idx[~hold_mask[idx]] + off)
        hold.append(idx[hold_mask[idx]] + off)
        idx_all.append(idx + off)
        masks.append(hold_mask)
        off += len(t)
    train, hold, idx = np.concatenate(train), np.concatenate(hold), np.concatenate(idx_all)
    hold_mask = np.concatenate(masks)
    noise = np.concatenate(noises)
    dt = trajs[0].dt_s
    step = max(1, int(round(DECIMATE_S / dt)))
    z = noise[idx]
    sigma = np.sqrt(np.mean(z ** 2, axis=0))
    active = sigma > 1e-12
    if not all(t.has_mocap for t in trajs):
        active[9:] = False
    # effective independent samples per decimated sample, per channel: 1 / (1 + 2 sum rho_k),
    # summing the autocorrelation of the noise realisation up to its first non-positive lag
    neff = np.ones(len(sigma))
    max_lag = max(2, int(round(NEFF_MAX_LAG_S / (step * dt))))
    for c in np.nonzero(active)[0]:
        zc = z[:, c] / sigma[c]
        tail = 0.0
        for j in range(1, min(max_lag, len(zc) - 1)):
            r = float(np.mean(zc[:-j] * zc[j:]))
            if r <= 0.0:
                break
            tail += r
        neff[c] = 1.0 / (1.0 + 2.0 * tail)
    sigma = np.where(active, sigma, 1.0)
    return Split(train, hold, sigma, neff, active, float(hold_mask.mean()), BLOCK_S, hold_mask)


def bin_means(traj: replay.Trajectory, y: np.ndarray):
    """(bin start times, (B, C) means) over BIN_S bins."""
    t = traj.time_s - traj.time_s[0]
    b = (t // BIN_S).astype(int)
    nb = int(b[-1]) + 1
    sums = np.zeros((nb, y.shape[1]))
    np.add.at(sums, b, y)
    counts = np.bincount(b, minlength=nb)[:, None]
    means = sums / np.maximum(counts, 1)
    full = counts[:, 0] >= 0.8 * BIN_S / traj.dt_s
    return traj.time_s[0] + BIN_S * np.arange(nb), means, full


def flag_windows(traj: replay.Trajectory, res: np.ndarray, noise: np.ndarray, split: Split,
                 vehicle: Vehicle, act: np.ndarray | None = None) -> list[dict]:
    """Windows where the residual exceeds the floor: t0, t1, axes, score, regimes, channels."""
    t0s, m, full = bin_means(traj, res)
    _, mn, _ = bin_means(traj, noise)
    floor = np.sqrt(np.mean(mn[full] ** 2, axis=0))
    floor = np.where(floor > 0, floor, np.inf)
    z = np.abs(m) / floor
    z[:, ~split.active] = 0.0
    z[~full] = 0.0
    edge = (t0s < traj.time_s[0] + EDGE_S) | (t0s + BIN_S > traj.time_s[-1] - EDGE_S)
    z[edge] = 0.0  # the smoothers' ends are not evidence
    flagged = z.max(axis=1) > Z_FLAG
    windows = []
    i = 0
    nb = len(t0s)
    while i < nb:
        if not flagged[i]:
            i += 1
            continue
        j = i
        while j + 1 < nb and flagged[j + 1]:
            j += 1
        zz = z[i:j + 1]
        chans = [c for c in range(len(CHANNELS)) if zz[:, c].max() > Z_FLAG]
        axes = sorted({replay.AXES[CHANNEL_AXIS[c]] for c in chans}, key=replay.AXES.index)
        t0, t1 = float(t0s[i]), float(min(t0s[j] + BIN_S, traj.time_s[-1]))
        windows.append({
            "t0": round(t0, 2), "t1": round(t1, 2), "axes": axes, "score": round(float(zz.max()), 2),
            "channels": [CHANNELS[c] for c in chans],
            "regimes": regimes(traj, vehicle, t0, t1, act),
        })
        i = j + 1
    return windows


def regimes(traj: replay.Trajectory, vehicle: Vehicle, t0: float, t1: float, act=None) -> list[str]:
    """Regime tags of a time span: near the surface / floor, speed, joint slews, thrust, turning."""
    sel = (traj.time_s >= t0) & (traj.time_s < t1)
    if not sel.any():
        return []
    near = near_boundaries(traj, vehicle)[sel]
    tags = []
    if near[:, 0].any():
        tags.append("near surface")
    if near[:, 1].any():
        tags.append("near floor")
    speed = np.linalg.norm(traj.nu[sel, :3], axis=1)
    if speed.max() > 0.15:
        tags.append("fast")
    elif speed.max() < 0.03:
        tags.append("still")
    if np.abs(traj.nu[sel, 5]).max() > 0.3:
        tags.append("turning")
    k = vehicle.n_units
    if act is not None:
        rates = np.abs(np.diff(act[:, k:3 * k], axis=0)) / traj.dt_s
        if rates[sel[1:]].max(initial=0.0) > 1.0:
            tags.append("joint slews")
        thrust = act[sel, :k].mean() / vehicle.thruster.n_max
        tags.append("high thrust" if thrust > 0.5 else "low thrust")
    return tags
