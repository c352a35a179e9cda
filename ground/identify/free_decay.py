"""Free-decay identification (seed 001 sections 3.2-3.3): spring rig, pendulum, Chin K_L / K_Q.

Pure math: sample arrays in, frozen dataclasses out; files and plots live in `cli.py`.

Spring rig (seed 001 eq. 6-9). The body hangs on a spring K and oscillates about its
equilibrium y_eq:
    (m + m') y'' + K_L y' + K_Q |y'| y' + K (y - y_eq) = 0                           (eq. 6)
- log decrement (Figure 7): successive extrema give the damped period and the decrement
  delta, zeta = delta / sqrt(4 pi^2 + delta^2), omega_n = omega_d / sqrt(1 - zeta^2);
- least squares: a damped sinusoid y_eq + A exp(-zeta omega_n t) cos(omega_d t + phi) fitted to
  the whole trace gives omega_n and zeta;
- added mass m' = K / omega_n^2 - m (eq. 7), C_m = m' / (rho V) (eq. 3);
- C_D from the fluid part of the damping, zeta = zeta_s + zeta_f (eq. 8), with eq. 9 written in a
  dimensionally consistent form: zeta_f = rho D^2 (8/3) C_D A / (4 pi (m + m')), A the amplitude
  in metres and D^2 the reference area (the seed prints A/D, which leaves 1/m over); this is the
  energy-equivalent linearisation of (1/2) rho C_D D^2 |y'| y'. zeta and A are taken over the
  first period of the launch (Figure 7's two consecutive peaks);
- Chin's linear + quadratic form: eq. 6 itself fitted to the trace (equation error on smoothed
  derivatives, then output error by simulation), giving m', K_L (N s/m) and K_Q (N s^2/m^2)
  directly; C_D = 2 K_Q / (rho D^2).

Pendulum (seed 001 eq. 10-16). A body of mass m and volume V on a rod of length r:
    (m + m') r theta'' = (B - m g) sin(theta) - K_D r^2 |theta'| theta'                 (eq. 12)
    theta'' = a1 sin(theta) - a2 |theta'| theta'                                       (eq. 14)
with a1 = (B - m g) / ((m + m') r) and a2 = K_D r / (m + m'), so
    m' = (rho V g - m g) / (a1 r) - m        (eq. 15; the seed's eq. 13 and 15 drop r, i.e. r = 1 m)
    C_D = 2 K_D / (rho A_wet) = 2 a2 (m + m') / (rho A_wet r)   (eq. 16 with K_D recovered from a2)
Chin's form adds a linear term: theta'' = a1 sin(theta) - aL theta' - aQ |theta'| theta', with
K_L = aL (m + m') (N s/m) and K_Q = aQ (m + m') / r (N s^2/m^2), forces on the body along its path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from numba import njit
from scipy.signal import find_peaks, savgol_filter


# ------------------------------------------------------------------------------------------------
# Results

@dataclass(frozen=True)
class Decrement:
    """Natural frequency and damping ratio from the extrema of a decaying oscillation."""

    omega_n_rad_s: float
    zeta: float
    omega_d_rad_s: float
    period_s: float
    delta: float  # logarithmic decrement per full period
    n_extrema: int
    first_amplitude: float  # |y - y_eq| at the first extremum
    amplitudes: tuple = ()  # |y - y_eq| at each extremum used


@dataclass(frozen=True)
class DampedSine:
    """Least-squares y = offset + A exp(-zeta omega_n t) cos(omega_d t + phi)."""

    omega_n_rad_s: float
    zeta: float
    amplitude: float
    phase_rad: float
    offset: float
    rmse: float


@dataclass(frozen=True)
class SpringDecayFit:
    """Seed 001 spring free-decay results (eq. 6-9) and Chin's K_L / K_Q form."""

    omega_n_rad_s: float  # least squares (damped sinusoid)
    zeta: float
    omega_n_log_decrement_rad_s: float
    zeta_log_decrement: float
    added_mass_kg: float  # eq. 7 from omega_n
    cm: float  # added mass / (rho V)
    cd: float  # eq. 9 from zeta - zeta_s at the launch amplitude
    amplitude_m: float  # amplitude A used in eq. 9 (the first period's, see first_period_zeta)
    zeta_first_period: float  # decrement of the first period, the zeta eq. 9 pairs with A
    equilibrium_m: float
    sine_amplitude_m: float  # the least-squares damped sinusoid: A and phi
    sine_phase_rad: float
    # Chin / eq. 6 fitted directly
    chin_added_mass_kg: float
    chin_cm: float
    k_l_n_s_m: float
    k_q_n_s2_m2: float
    chin_cd: float
    chin_rmse_m: float
    chin_initial: tuple  # (y0 m, y0' m/s) of the fitted eq. 6 simulation


@dataclass(frozen=True)
class PendulumFit:
    """Seed 001 pendulum free-decay results (eq. 10-16) and Chin's K_L / K_Q form."""

    a1: float  # 1/s^2, eq. 14 (Morison: quadratic damping only)
    a2: float  # 1/rad, eq. 14
    added_mass_kg: float  # eq. 15
    cm: float
    cd: float  # eq. 16
    rmse_rad: float
    chin_a1: float
    chin_al: float  # 1/s
    chin_aq: float  # 1/rad
    chin_added_mass_kg: float
    k_l_n_s_m: float
    k_q_n_s2_m2: float
    chin_cd: float
    chin_rmse_rad: float
    initial: tuple  # (theta0 rad, theta0' rad/s) of the eq. 14 fit
    chin_initial: tuple  # the same for the Chin fit


# ------------------------------------------------------------------------------------------------
# Shared helpers

def uniform(t, y):
    """Arrays as float, checked: 1-D, same length, strictly increasing time, >= 20 samples.

    A slightly irregular time base is resampled onto its median step (linear interpolation).
    """
    t = np.asarray(t, float)
    y = np.asarray(y, float)
    if t.ndim != 1 or t.shape != y.shape:
        raise ValueError("time and signal must be 1-D arrays of one length")
    if t.size < 20:
        raise ValueError(f"a free-decay trace needs at least 20 samples, got {t.size}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
        raise ValueError("the trace holds NaN or infinite values")
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError("time must be strictly increasing")
    step = float(np.median(dt))
    if np.max(np.abs(dt - step)) > 0.01 * step:
        n = int(math.floor((t[-1] - t[0]) / step)) + 1
        if n > 2 * t.size + 16:  # resampling across a gap would fill it (and allocate by its span)
            i = int(np.argmax(dt))
            raise ValueError(f"the trace stops for {dt[i]:.4g} s after t = {t[i]:.6g} s (a gap in the recording): "
                             "a free decay is fitted on one stretch; choose it with --t0/--t1")
        tu = t[0] + step * np.arange(n)
        return tu, np.interp(tu, t, y), step
    return t, y, step


def _dominant_period(y, dt):
    """Period of the strongest spectral line of y (zero-padded FFT), seconds."""
    z = y - np.mean(y)
    n = 1 << int(math.ceil(math.log2(len(z) * 8)))
    spec = np.abs(np.fft.rfft(z * np.hanning(len(z)), n))
    spec[0] = 0.0
    k = int(np.argmax(spec))
    return n * dt / max(k, 1)


def noise_level(y):
    """White-noise sigma of a smooth signal from its second differences: std(diff2) / sqrt(6)."""
    return float(np.std(np.diff(y, 2)) / math.sqrt(6.0))


def _extrema(y, dt, period_s: float, floor: float):
    """Alternating maxima and minima of y (about zero), at least 0.35 period apart, above `floor`.

    The sequence stops at the first extremum below the floor or larger than the one before it
    (where the decay has sunk into the noise).
    """
    dist = max(int(0.35 * period_s / dt), 1)
    hi, _ = find_peaks(y, distance=dist)
    lo, _ = find_peaks(-y, distance=dist)
    idx = np.sort(np.concatenate([hi[y[hi] > 0], lo[y[lo] < 0]]))
    out = []
    for i in idx:
        if out and np.sign(y[i]) == np.sign(y[out[-1]]):
            if abs(y[i]) > abs(y[out[-1]]):
                out[-1] = i
            continue
        out.append(i)
    keep = []
    for i in out:
        if abs(y[i]) < floor or (keep and abs(y[i]) > abs(y[keep[-1]])):
            break
        keep.append(i)
    return np.array(keep, int)


def _refine_peak(t, y, i, half_width: int):
    """Time and value of an extremum from a parabola least-squares fitted around sample i."""
    lo, hi = max(i - half_width, 0), min(i + half_width + 1, len(y))
    if hi - lo < 3:
        return t[i], y[i]
    tt = t[lo:hi] - t[i]
    c2, c1, c0 = np.polyfit(tt, y[lo:hi], 2)
    if c2 == 0:
        return t[i], y[i]
    d = -c1 / (2 * c2)
    if abs(d) > (t[1] - t[0]) * half_width:
        return t[i], y[i]
    return t[i] + d, c0 + c1 * d + c2 * d * d


def log_decrement(t, y, offset: float = None, max_extrema: int = 12) -> Decrement:
    """omega_n and zeta from successive extrema (seed 001 Figure 7), about `offset`.

    Half-period steps between alternating extrema: delta = 2 mean ln(|A_i| / |A_i+1|),
    T_d = 2 mean(t_i+1 - t_i); zeta = delta / sqrt(4 pi^2 + delta^2); omega_n = 2 pi / T_d / sqrt(1 - zeta^2).
    """
    t, y, dt = uniform(t, y)
    y0 = float(np.median(y)) if offset is None else float(offset)
    z = y - y0
    period = _dominant_period(z, dt)
    floor = max(8.0 * noise_level(z), 0.03 * float(np.max(np.abs(z))))
    idx = _extrema(z, dt, period, floor)[:max_extrema]
    if idx.size < 3:
        raise ValueError(
            f"found {idx.size} clear extrema in the trace; a free decay needs at least 3 "
            "(one full period above the noise)"
        )
    hw = max(int(period / dt / 16), 1)
    pts = [_refine_peak(t, z, i, hw) for i in idx]
    tp = np.array([p[0] for p in pts])
    ap = np.abs(np.array([p[1] for p in pts]))
    half = np.diff(tp)
    period = 2.0 * float(np.mean(half))
    delta = 2.0 * float(np.mean(np.log(ap[:-1] / ap[1:])))
    zeta = delta / math.sqrt(4 * math.pi ** 2 + delta ** 2)
    omega_d = 2 * math.pi / period
    return Decrement(
        omega_n_rad_s=omega_d / math.sqrt(1 - zeta ** 2), zeta=zeta, omega_d_rad_s=omega_d,
        period_s=period, delta=delta, n_extrema=int(tp.size), first_amplitude=float(ap[0]),
        amplitudes=tuple(float(a) for a in ap),
    )


def damped_sine(t, y) -> DampedSine:
    """Least-squares fit of y = y_eq + A exp(-zeta w t) cos(w sqrt(1 - zeta^2) t + phi)."""
    t, y, dt = uniform(t, y)
    tt = t - t[0]
    dec = log_decrement(t, y)
    z0 = y - np.median(y)
    amp0 = float(np.max(np.abs(z0[: max(int(dec.period_s / dt), 3)])))

    def model(q):
        y_eq, a, zeta, w, phi = q
        wd = w * math.sqrt(max(1 - zeta ** 2, 1e-9))
        return y_eq + a * np.exp(-zeta * w * tt) * np.cos(wd * tt + phi)

    best = None
    for phi0 in np.linspace(-math.pi, math.pi, 8, endpoint=False):
        q0 = [float(np.median(y)), amp0, min(max(dec.zeta, 1e-3), 0.9), dec.omega_n_rad_s, phi0]
        r = least_squares(
            lambda q: model(q) - y, q0,
            bounds=([-np.inf, 0.0, 0.0, 0.2 * dec.omega_n_rad_s, -10.0],
                    [np.inf, np.inf, 0.99, 5.0 * dec.omega_n_rad_s, 10.0]),
            x_scale="jac",
        )
        if best is None or r.cost < best.cost:
            best = r
    y_eq, a, zeta, w, phi = best.x
    return DampedSine(
        omega_n_rad_s=float(w), zeta=float(zeta), amplitude=float(a),
        phase_rad=float((phi + math.pi) % (2 * math.pi) - math.pi), offset=float(y_eq),
        rmse=float(np.sqrt(np.mean(best.fun ** 2))),
    )


def derivatives(y, dt, window_s: float):
    """First and second derivatives by a cubic Savitzky-Golay filter over `window_s`."""
    w = max(int(round(window_s / dt)) | 1, 7)  # odd, at least 7 samples
    longest = len(y) if len(y) % 2 == 1 else len(y) - 1
    w = min(w, longest)
    ys = savgol_filter(y, w, 3)
    yd = savgol_filter(y, w, 3, deriv=1, delta=dt)
    ydd = savgol_filter(y, w, 3, deriv=2, delta=dt)
    return ys, yd, ydd


@njit(cache=True)
def _oscillator(c0, c1, c2, c3, c4, x0, v0, n, dt, sub):
    """Fixed-step RK4 of x'' = c0 + c1 x + c2 sin(x) - c3 x' - c4 |x'| x' from (x0, v0).

    One form covers both rigs: the spring (eq. 6: c1 = -K/M, c0 = K y_eq / M, c3 = K_L / M,
    c4 = K_Q / M) and the pendulum (eq. 14 / Chin: c2 = a1, c3 = aL, c4 = a2). n samples spaced
    dt, `sub` RK4 steps each.
    """
    h = dt / sub
    xs = np.empty(n)
    x, v = x0, v0
    for i in range(n):
        xs[i] = x
        for _ in range(sub):
            a1 = c0 + c1 * x + c2 * math.sin(x) - c3 * v - c4 * abs(v) * v
            x2, v2 = x + 0.5 * h * v, v + 0.5 * h * a1
            a2 = c0 + c1 * x2 + c2 * math.sin(x2) - c3 * v2 - c4 * abs(v2) * v2
            x3, v3 = x + 0.5 * h * v2, v + 0.5 * h * a2
            a3 = c0 + c1 * x3 + c2 * math.sin(x3) - c3 * v3 - c4 * abs(v3) * v3
            x4, v4 = x + h * v3, v + h * a3
            a4 = c0 + c1 * x4 + c2 * math.sin(x4) - c3 * v4 - c4 * abs(v4) * v4
            x += h / 6.0 * (v + 2 * v2 + 2 * v3 + v4)
            v += h / 6.0 * (a1 + 2 * a2 + 2 * a3 + a4)
        if not (abs(x) < 1e6):
            for j in range(i, n):
                xs[j] = 1e6
            return xs
    return xs


def _substeps(omega, dt, per_step: float = 0.05) -> int:
    return max(1, int(math.ceil(abs(omega) * dt / per_step)))


# ------------------------------------------------------------------------------------------------
# Spring rig (seed 001 section 3.2)

def spring_free_decay(t, y, mass_kg: float, spring_n_m: float, volume_m3: float, length_m: float,
                      rho: float = 1000.0, zeta_structural: float = 0.0) -> SpringDecayFit:
    """Seed 001 eq. 6-9 on a position trace y(t) (m) of a body of mass m on a spring K."""
    for name, val in (("mass", mass_kg), ("spring", spring_n_m), ("volume", volume_m3),
                      ("length", length_m), ("rho", rho)):
        if not (math.isfinite(val) and val > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {val!r}")
    t, y, dt = uniform(t, y)
    ds = damped_sine(t, y)
    dec = log_decrement(t, y, offset=ds.offset)
    added = spring_n_m / ds.omega_n_rad_s ** 2 - mass_kg  # eq. 7
    m_tot = mass_kg + added
    # eq. 9 pairs a damping ratio with the amplitude it was measured at: the first period
    # (extrema 0 and 2), with A0 A2 ln(A0/A2) / (A0 - A2), the amplitude at which a quadratic
    # damping's equivalent zeta equals that period's decrement (1/A grows linearly in time)
    a0, a2 = dec.amplitudes[0], dec.amplitudes[2]
    d1 = math.log(a0 / a2)
    zeta1 = d1 / math.sqrt(4 * math.pi ** 2 + d1 ** 2)
    amp = a0 * a2 * d1 / (a0 - a2) if a0 > a2 else a0
    zeta_f = zeta1 - zeta_structural  # eq. 8
    # eq. 9 (dimensionally consistent form, see the module docstring)
    cd = zeta_f * 4 * math.pi * m_tot / (rho * length_m ** 2 * (8.0 / 3.0) * amp)
    chin = _spring_chin(t, y, dt, spring_n_m, m_tot, ds)
    m_chin, k_l, k_q, rmse, init = chin
    return SpringDecayFit(
        omega_n_rad_s=ds.omega_n_rad_s, zeta=ds.zeta,
        omega_n_log_decrement_rad_s=dec.omega_n_rad_s, zeta_log_decrement=dec.zeta,
        added_mass_kg=added, cm=added / (rho * volume_m3), cd=cd, amplitude_m=amp, zeta_first_period=zeta1,
        equilibrium_m=ds.offset, sine_amplitude_m=ds.amplitude, sine_phase_rad=ds.phase_rad,
        chin_added_mass_kg=m_chin - mass_kg, chin_cm=(m_chin - mass_kg) / (rho * volume_m3),
        k_l_n_s_m=k_l, k_q_n_s2_m2=k_q, chin_cd=2 * k_q / (rho * length_m ** 2), chin_rmse_m=rmse,
        chin_initial=init,
    )


def _spring_chin(t, y, dt, K, m_tot0, ds: DampedSine):
    """Eq. 6 fitted directly: (M, K_L, K_Q) by equation error, refined by output error."""
    period = 2 * math.pi / ds.omega_n_rad_s
    ys, yd, ydd = derivatives(y, dt, period / 8)
    core = slice(len(y) // 50 + 3, len(y) - len(y) // 50 - 3)
    # y'' = -(K/M)(y - y_eq) - (K_L/M) y' - (K_Q/M)|y'|y'  ->  linear in [y, 1, y', |y'|y']
    A = np.column_stack([ys, np.ones_like(ys), yd, np.abs(yd) * yd])[core]
    th, *_ = np.linalg.lstsq(A, ydd[core], rcond=None)
    M0 = -K / th[0] if th[0] < 0 else m_tot0
    y_eq0 = th[1] * M0 / K if th[0] < 0 else ds.offset
    kl0 = max(-th[2] * M0, 0.0)
    kq0 = max(-th[3] * M0, 0.0)
    n = len(y)

    sub = _substeps(ds.omega_n_rad_s, dt)

    def sim(q):
        M, kl, kq, y_eq, y0, v0 = q
        return _oscillator(K * y_eq / M, -K / M, 0.0, kl / M, kq / M, y0, v0, n, dt, sub)

    q0 = [M0, kl0, kq0, y_eq0, y[0], yd[0]]
    scale = [M0, max(kl0, 0.1 * M0 * ds.omega_n_rad_s), max(kq0, 0.1 * M0 / (abs(ds.amplitude) + 1e-9)),
             abs(ds.amplitude) + 1e-9, abs(ds.amplitude) + 1e-9, abs(ds.amplitude) * ds.omega_n_rad_s + 1e-9]
    r = least_squares(
        lambda q: sim(q) - y, q0, x_scale=scale,
        bounds=([1e-6, 0.0, 0.0, -np.inf, -np.inf, -np.inf], [np.inf] * 6),
        max_nfev=200,
    )
    M, kl, kq = r.x[:3]
    return float(M), float(kl), float(kq), float(np.sqrt(np.mean(r.fun ** 2))), (float(r.x[4]), float(r.x[5]))


def synthesize_linear_decay(omega_n: float, zeta: float, amplitude: float, duration_s: float,
                            rate_hz: float, offset: float = 0.0, noise: float = 0.0, seed: int = 0):
    """y(t) = offset + A exp(-zeta w t) cos(w_d t): the trace seed 001 Table 7's omega_n, zeta imply."""
    t = np.arange(int(round(duration_s * rate_hz)) + 1) / rate_hz
    wd = omega_n * math.sqrt(1 - zeta ** 2)
    y = offset + amplitude * np.exp(-zeta * omega_n * t) * np.cos(wd * t)
    if noise > 0:
        y = y + np.random.default_rng(seed).standard_normal(t.size) * noise
    return t, y


def synthesize_spring_decay(total_mass_kg: float, spring_n_m: float, k_l: float, k_q: float,
                            amplitude: float, duration_s: float, rate_hz: float,
                            noise: float = 0.0, seed: int = 0):
    """y(t) of eq. 6 from y(0) = A, y'(0) = 0 (RK4, 8 sub-steps per sample)."""
    n = int(round(duration_s * rate_hz)) + 1
    dt = 1.0 / rate_hz
    M = total_mass_kg
    sub = 4 * _substeps(math.sqrt(spring_n_m / M), dt)
    y = _oscillator(0.0, -spring_n_m / M, 0.0, k_l / M, k_q / M, float(amplitude), 0.0, n, dt, sub)
    if noise > 0:
        y = y + np.random.default_rng(seed).standard_normal(n) * noise
    return np.arange(n) * dt, y


# ------------------------------------------------------------------------------------------------
# Pendulum (seed 001 section 3.3)

def pendulum_free_decay(t, theta, mass_kg: float, volume_m3: float, length_m: float,
                        wetted_area_m2: float, rho: float = 1000.0, g: float = 9.81) -> PendulumFit:
    """Seed 001 eq. 10-16 (Morison, quadratic damping) and Chin's linear + quadratic form."""
    for name, val in (("mass", mass_kg), ("volume", volume_m3), ("length", length_m),
                      ("wetted area", wetted_area_m2), ("rho", rho), ("g", g)):
        if not (math.isfinite(val) and val > 0):
            raise ValueError(f"{name} must be a finite number > 0, got {val!r}")
    if rho * volume_m3 >= mass_kg:
        raise ValueError(
            f"buoyancy rho V = {rho * volume_m3:.4g} kg is not below the mass {mass_kg:.4g} kg: "
            "a hanging pendulum needs a body heavier than the water it displaces"
        )
    t, th, dt = uniform(t, theta)
    dec = log_decrement(t, th, offset=0.0)
    period = 2 * math.pi / dec.omega_n_rad_s
    ths, thd, thdd = derivatives(th, dt, period / 8)
    core = slice(len(th) // 50 + 3, len(th) - len(th) // 50 - 3)
    s = np.sin(ths)
    q = np.abs(thd) * thd
    # equation error (eq. 14 and Chin), then output error by simulation
    c_m, *_ = np.linalg.lstsq(np.column_stack([s, -q])[core], thdd[core], rcond=None)
    c_c, *_ = np.linalg.lstsq(np.column_stack([s, -thd, -q])[core], thdd[core], rcond=None)
    n = len(th)

    sub = _substeps(dec.omega_n_rad_s, dt)

    def sim(a1, al, aq, x0, v0):
        return _oscillator(0.0, 0.0, a1, al, aq, x0, v0, n, dt, sub)

    w2 = dec.omega_n_rad_s ** 2
    amp = dec.first_amplitude
    r_m = least_squares(
        lambda p: sim(p[0], 0.0, p[1], p[2], p[3]) - th,
        [min(c_m[0], -1e-3 * w2), max(c_m[1], 0.0), th[0], thd[0]],
        bounds=([-np.inf, 0.0, -np.inf, -np.inf], [0.0, np.inf, np.inf, np.inf]),
        x_scale=[w2, 1.0 / (amp + 1e-9), amp, amp * dec.omega_n_rad_s], max_nfev=200,
    )
    r_c = least_squares(
        lambda p: sim(p[0], p[1], p[2], p[3], p[4]) - th,
        [min(c_c[0], -1e-3 * w2), max(c_c[1], 0.0), max(c_c[2], 0.0), th[0], thd[0]],
        bounds=([-np.inf, 0.0, 0.0, -np.inf, -np.inf], [0.0, np.inf, np.inf, np.inf, np.inf]),
        x_scale=[w2, dec.omega_n_rad_s * 0.05, 1.0 / (amp + 1e-9), amp, amp * dec.omega_n_rad_s],
        max_nfev=200,
    )
    a1, a2 = float(r_m.x[0]), float(r_m.x[1])
    net = (rho * volume_m3 - mass_kg) * g  # B - m g < 0
    added = net / (a1 * length_m) - mass_kg  # eq. 15
    cd = 2 * a2 * (mass_kg + added) / (rho * wetted_area_m2 * length_m)  # eq. 16
    ca1, cal, caq = (float(v) for v in r_c.x[:3])
    c_added = net / (ca1 * length_m) - mass_kg
    k_l = cal * (mass_kg + c_added)
    k_q = caq * (mass_kg + c_added) / length_m
    return PendulumFit(
        a1=a1, a2=a2, added_mass_kg=added, cm=added / (rho * volume_m3), cd=cd,
        rmse_rad=float(np.sqrt(np.mean(r_m.fun ** 2))),
        chin_a1=ca1, chin_al=cal, chin_aq=caq, chin_added_mass_kg=c_added,
        k_l_n_s_m=k_l, k_q_n_s2_m2=k_q, chin_cd=2 * k_q / (rho * wetted_area_m2),
        chin_rmse_rad=float(np.sqrt(np.mean(r_c.fun ** 2))),
        initial=(float(r_m.x[2]), float(r_m.x[3])), chin_initial=(float(r_c.x[3]), float(r_c.x[4])),
    )


def synthesize_pendulum(mass_kg: float, volume_m3: float, length_m: float, added_mass_kg: float,
                        k_l: float, k_q: float, theta0_rad: float, duration_s: float,
                        rate_hz: float, rho: float = 1000.0, g: float = 9.81,
                        noise_rad: float = 0.0, seed: int = 0):
    """theta(t) of eq. 12 with Chin's damping: (m + m') r th'' = (B - m g) sin th - K_L r th' - K_Q r^2 |th'| th'."""
    M = mass_kg + added_mass_kg
    net = (rho * volume_m3 - mass_kg) * g
    r = length_m
    n = int(round(duration_s * rate_hz)) + 1
    a1 = net / (M * r)
    sub = 4 * _substeps(math.sqrt(abs(a1)), 1.0 / rate_hz)
    th = _oscillator(0.0, 0.0, a1, k_l / M, k_q * r / M, float(theta0_rad), 0.0, n, 1.0 / rate_hz, sub)
    if noise_rad > 0:
        th = th + np.random.default_rng(seed).standard_normal(n) * noise_rad
    return np.arange(n) / rate_hz, th
