"""Azimuth-transient identification by signal compression (seed 004 sections 3-4, eq. 1-8).

1. Design (eq. 1-3): a pseudo-impulse joint-rate profile of N samples whose power spectrum is
   P(n) = Q exp(-(n / a)^12) (a = 450) and whose phase is the expansion filter
   H(jn) = exp(-j 12 n^2 / b) (b = 2100): an impulse spread out in time (each frequency delayed by
   24 n / b * N / (2 pi) samples), so a servo can follow it.
2. Run it: on a real rig (export the profile), or on the vehicle model held on a fixed rig
   (`simulate_fixed_rig`: the plant's own compiled model with the body clamped, a 6-axis
   force/torque sensor at the body origin, joint encoders).
3. Compress (Figure 5): the response is deconvolved by the input actually applied; on the design
   grid this is multiplication by the inverse filter H^-1, which turns the long response back
   into the (band-limited) impulse response. The frequency response G = Y / U gives the Bode
   magnitude (Figures 6d, 9, 11, 13) within the designed band.
4. Fit (eq. 5, 6): force rows K (s^2 + a s + b) / ((s^2 + c s + d)(s^2 + e s + g)), the moment
   row K s^2 / (s^4 + a s^3 + b s^2 + c s + d), to the magnitude in dB. The seed maximises the
   correlation number between measured and model magnitude; correlation ignores the gain and the
   dB scale, so we first fit least squares in dB (gain included, several starts), then polish
   the shape by maximising the correlation, with K set by the mean dB offset.

Rows follow spec/vehicle-model.md 4.1: f1x is driven by |azimuth rate|, f1y and m1z by the azimuth
rate, f2x by |elevation rate|, f2z by the elevation rate; every output is scaled by
gain_per_newton * T (T the unit's thrust), so a rig-measured gain K_meas gives the vehicle-file
K = K_meas / (gain_per_newton * T).

Pure math: arrays and a packed parameter vector in, frozen dataclasses out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.optimize import least_squares, minimize

from onboard.jit import MODEL_SOURCE, cache_keyed_on
from onboard import model

ROWS = ("f1x", "f1y", "m1z", "f2x", "f2z")
ROW_AXIS = {"f1x": "azimuth", "f1y": "azimuth", "m1z": "azimuth", "f2x": "elevation", "f2z": "elevation"}
ROW_ABS = {"f1x": True, "f1y": False, "m1z": False, "f2x": True, "f2z": False}
# Correlation numbers seed 004 reports at 75 % PWM (Tables 1-5).
SEED004_CORRELATION_75 = {"f1x": 0.56, "f1y": 0.76, "m1z": 0.84, "f2x": 0.76, "f2z": 0.60}


# ------------------------------------------------------------------------------------------------
# 1. Design (eq. 1-3)

@dataclass(frozen=True)
class PseudoImpulse:
    """A designed joint-rate profile and the angle command that produces it."""

    rate_hz: float
    a: float
    b: float
    q: float  # Q of eq. 1 after scaling to the rate limits
    rate_rad_s: np.ndarray  # (N,) the pseudo-impulse joint rate
    angle_rad: np.ndarray  # (N,) angle command: start offset + cumulative rate
    band_hz: float  # a * rate / N: where P has fallen to 1/e

    @property
    def n_samples(self) -> int:
        return int(self.rate_rad_s.size)

    @property
    def time_s(self) -> np.ndarray:
        return np.arange(self.n_samples) / self.rate_hz


def power_spectrum(n, a: float = 450.0, q: float = 1.0):
    """P(n) = Q exp(-(n / a)^12) (seed 004 eq. 1)."""
    return q * np.exp(-(np.asarray(n, float) / a) ** 12)


def expansion_filter(n, b: float = 2100.0):
    """H(jn) = exp(-j 12 n^2 / b) (seed 004 eq. 3): a phase delay growing with frequency."""
    n = np.asarray(n, float)
    return np.exp(-1j * 12.0 * n * n / b)


def pseudo_impulse_spectrum(n_samples: int, a: float = 450.0, b: float = 2100.0, q: float = 1.0):
    """X(n) + jY(n) of seed 004 eq. 2 on an N-point grid (upper half conjugate: a real signal)."""
    N = int(n_samples)
    if N < 16 or N % 2:
        raise ValueError(f"the pseudo-impulse needs an even number of samples >= 16, got {N}")
    spec = np.zeros(N, complex)
    k = np.arange(N // 2)
    spec[: N // 2] = power_spectrum(k, a, q) * expansion_filter(k, b)
    spec[N // 2] = 0.0
    spec[N // 2 + 1:] = np.conj(spec[1: N // 2][::-1])  # X(N - n) - jY(N - n)
    return spec


def design_pseudo_impulse(n_samples: int = 18000, rate_hz: float = 400.0, a: float = 450.0,
                          b: float = 2100.0, peak_rate_rad_s: float = 1.0,
                          angle_limit_rad: float = 1.3963) -> PseudoImpulse:
    """The pseudo-impulse joint rate (IFFT of eq. 2), scaled to a peak rate and an angle range.

    Q is chosen so that max |rate| = peak_rate_rad_s and the angle it sweeps stays within
    0.8 * angle_limit_rad about its centre (the smaller of the two scalings wins).
    """
    if not (rate_hz > 0 and peak_rate_rad_s > 0 and angle_limit_rad > 0 and a > 0 and b > 0):
        raise ValueError("rate, peak rate, angle limit, a and b must all be > 0")
    x1 = np.real(np.fft.ifft(pseudo_impulse_spectrum(n_samples, a, b, 1.0)))
    ang1 = np.cumsum(x1) / rate_hz
    span1 = 0.5 * (ang1.max() - ang1.min())
    s = min(peak_rate_rad_s / np.max(np.abs(x1)), 0.8 * angle_limit_rad / span1)
    rate = s * x1
    ang = s * ang1
    ang = ang - 0.5 * (ang.max() + ang.min())
    # the command at sample i is the angle the joint should reach by sample i + 1
    angle = np.concatenate([[ang[0] - rate[0] / rate_hz], ang[:-1]])
    return PseudoImpulse(rate_hz=float(rate_hz), a=float(a), b=float(b), q=float(s),
                         rate_rad_s=rate, angle_rad=angle, band_hz=float(a * rate_hz / n_samples))


# ------------------------------------------------------------------------------------------------
# 2. Fixed rig: the plant's model with the body clamped

@dataclass(frozen=True)
class RigRecord:
    """What a clamped-unit rig measures, per sample (seed 004 Figure 4, moving-frame forces)."""

    time_s: np.ndarray
    alpha_rate_rad_s: np.ndarray  # joint encoders, differentiated
    beta_rate_rad_s: np.ndarray
    axial_loss_n: np.ndarray  # T0 - thrust along d (f1x + f2x rows)
    lateral_alpha_n: np.ndarray  # force along e_alpha (f1y row)
    lateral_beta_n: np.ndarray  # force along e_beta (f2z row)
    reaction_moment_nm: np.ndarray  # reaction moment about body z, sign of M1z (m1z row)
    thrust_n: float  # T0, the unit's steady thrust
    gain_per_newton: float


# The two kernels below compile onboard.model's functions into themselves: they are cached on
# disk keyed on onboard/model.py too (hil.batch's helper), so a model edit never leaves a stale
# cached rig running old physics.
@njit
def _rig_derivative(x, u, p, xdot):
    model.derivative(x, u, p, xdot)
    for i in range(13):  # the rig holds the body: no motion
        xdot[i] = 0.0


@njit
def _rig_run(x, commands, p, dt, sub, unit, out):
    """Integrate the clamped vehicle; out[s] = [alpha, beta, loss, lat_a, lat_b, moment, T0]."""
    k = (x.shape[0] - 13) // (3 + model.N_TF_STATES)
    nx = x.shape[0]
    k1 = np.empty(nx)
    k2 = np.empty(nx)
    k3 = np.empty(nx)
    k4 = np.empty(nx)
    h = dt / sub
    nu_r = np.zeros(6)
    o = model.P_UNITS + 6 * unit
    rx, ry = p[o], p[o + 1]
    for s in range(commands.shape[0]):
        u = commands[s]
        # measure at the start of the sample
        xdot = np.zeros(nx)
        tau = np.zeros(6)
        thrust = np.empty(k)
        model.jets_and_transients(x, u, p, nu_r, k, xdot, tau, thrust)
        a = x[13 + k + unit]
        b = x[13 + 2 * k + unit]
        F = model.jet_frame(a, b, p[o + 3], p[o + 4])
        n = x[13 + unit]
        T0 = model.jet_thrust(n, 0.0, p)
        fx, fy, fz = tau[0], tau[1], tau[2]
        axial = F[0, 0] * fx + F[0, 1] * fy + F[0, 2] * fz
        out[s, 0] = a
        out[s, 1] = b
        out[s, 2] = T0 - axial
        out[s, 3] = F[1, 0] * fx + F[1, 1] * fy + F[1, 2] * fz
        out[s, 4] = F[2, 0] * fx + F[2, 1] * fy + F[2, 2] * fz
        # tau_z = (r x f)_z - g T M1z
        out[s, 5] = -(tau[5] - (rx * fy - ry * fx))
        out[s, 6] = T0
        for _ in range(sub):
            _rig_derivative(x, u, p, k1)
            _rig_derivative(x + 0.5 * h * k1, u, p, k2)
            _rig_derivative(x + 0.5 * h * k2, u, p, k3)
            _rig_derivative(x + h * k3, u, p, k4)
            x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
            model.project(x, u, p)
    return x


cache_keyed_on(_rig_derivative, MODEL_SOURCE)
cache_keyed_on(_rig_run, MODEL_SOURCE)


def simulate_fixed_rig(vehicle, design: PseudoImpulse, axis: str = "azimuth", unit: int = 0,
                       n_rev_s: float = None, tail_s: float = None, substeps: int = 1,
                       noise_n: float = 0.0, noise_nm: float = 0.0, seed: int = 0) -> RigRecord:
    """Apply the pseudo-impulse to one joint of one unit of the clamped vehicle; record the rig.

    The unit spins at `n_rev_s` (default 0.75 n_max, seed 004's 75 % PWM) from the start (its
    motor already at speed); the other units are off. The angle command of `design` drives the
    joint through `servo_lag` (spec 4); a zero tail of `tail_s` (default twice the design's
    length) follows so the slow transient poles settle and the FFT grid resolves them.
    `noise_n` adds white noise (N) to the force channels, `noise_nm` (N m) to the moment
    channel of the force/torque sensor.
    """
    if axis not in ("azimuth", "elevation"):
        raise ValueError(f"axis must be 'azimuth' or 'elevation', got {axis!r}")
    k = vehicle.n_units
    if not 0 <= unit < k:
        raise ValueError(f"unit must be 0..{k - 1}, got {unit}")
    if not vehicle.effects.on("servo_lag"):
        raise ValueError("effects.servo_lag is off: the joints jump and drive no transient (spec 4.1)")
    n = 0.75 * vehicle.thruster.n_max if n_rev_s is None else float(n_rev_s)
    p = model.pack_params(vehicle)
    tail = 2 * design.n_samples / design.rate_hz if tail_s is None else float(tail_s)
    n_tail = int(round(tail * design.rate_hz))
    angles = np.concatenate([design.angle_rad, np.full(n_tail, design.angle_rad[-1])])
    cmd = np.zeros((angles.size, 3 * k))
    cmd[:, unit] = n
    col = k + unit if axis == "azimuth" else 2 * k + unit
    cmd[:, col] = angles
    x = model.initial_state(vehicle, 0.5, cmd[0])
    x[13 + unit] = n if vehicle.effects.on("motor_lag") else 0.0
    x[13 + k + unit if axis == "azimuth" else 13 + 2 * k + unit] = design.angle_rad[0]
    out = np.zeros((angles.size, 7))
    _rig_run(x, cmd, p, 1.0 / design.rate_hz, int(substeps), int(unit), out)
    if noise_n > 0 or noise_nm > 0:
        rng = np.random.default_rng(seed)
        out[:, 2:6] += rng.standard_normal((angles.size, 4)) * np.array([noise_n] * 3 + [noise_nm])
    t = np.arange(angles.size) / design.rate_hz
    return RigRecord(
        time_s=t, alpha_rate_rad_s=encoder_rate(out[:, 0], design.rate_hz),
        beta_rate_rad_s=encoder_rate(out[:, 1], design.rate_hz), axial_loss_n=out[:, 2],
        lateral_alpha_n=out[:, 3], lateral_beta_n=out[:, 4], reaction_moment_nm=out[:, 5],
        thrust_n=float(out[0, 6]), gain_per_newton=vehicle.effects.azimuth_transient.gain_per_newton,
    )


def encoder_rate(angle_rad, rate_hz: float):
    """Joint rate over each sample interval from encoder angles: (a[s+1] - a[s]) * rate.

    The interval mean is what a transient filter integrates over the interval; the instantaneous
    rate at the sample instant would overstate it when the servo lags within the interval.
    """
    a = np.asarray(angle_rad, float)
    r = np.empty_like(a)
    r[:-1] = np.diff(a) * rate_hz
    r[-1] = r[-2] if a.size > 1 else 0.0
    return r


def row_signals(record: RigRecord, row: str):
    """(input, output) of a transient row from a rig record (spec 4.1 drives)."""
    if row not in ROWS:
        raise ValueError(f"row must be one of {', '.join(ROWS)}, got {row!r}")
    rate = record.alpha_rate_rad_s if ROW_AXIS[row] == "azimuth" else record.beta_rate_rad_s
    if ROW_ABS[row]:
        rate = np.abs(rate)
    out = {"f1x": record.axial_loss_n, "f2x": record.axial_loss_n, "f1y": record.lateral_alpha_n,
           "f2z": record.lateral_beta_n, "m1z": record.reaction_moment_nm}[row]
    return rate, out


# ------------------------------------------------------------------------------------------------
# 3. Compression and Bode magnitude

@dataclass(frozen=True)
class BodeMagnitude:
    """Measured frequency response magnitude on log-spaced points within the band."""

    omega_rad_s: np.ndarray
    magnitude_db: np.ndarray
    raw_omega_rad_s: np.ndarray  # every FFT bin in the band
    raw_magnitude_db: np.ndarray


def compress(y, n_design: int, b: float = 2100.0):
    """Signal compression (Figure 5): multiply the response's spectrum by the inverse filter H^-1.

    On a record of M samples the design bin n sits at FFT bin k = n M / N, so H^-1 is
    exp(+j 12 (k N / M)^2 / b). The result is the band-limited impulse response (times P).
    """
    y = np.asarray(y, float)
    M = y.size
    Y = np.fft.rfft(y)
    k = np.arange(Y.size)
    Y = Y * np.conj(expansion_filter(k * n_design / M, b))
    return np.fft.irfft(Y, M)


def frequency_response(u, y, rate_hz: float, band_hz: float, points: int = 60,
                       f_min_hz: float = None) -> BodeMagnitude:
    """|G(jw)| = |Y / U| in dB over the band, raw bins and a log-spaced average (for fitting)."""
    u = np.asarray(u, float)
    y = np.asarray(y, float)
    if u.shape != y.shape or u.ndim != 1:
        raise ValueError("input and output must be 1-D arrays of one length")
    U = np.fft.rfft(u)
    Y = np.fft.rfft(y)
    f = np.fft.rfftfreq(u.size, 1.0 / rate_hz)
    lo = f[1] if f_min_hz is None else max(f_min_hz, f[1])
    sel = (f >= lo) & (f <= band_hz)
    strong = np.abs(U) > 1e-3 * np.max(np.abs(U[sel]))
    sel &= strong
    G = np.abs(Y[sel]) / np.abs(U[sel])
    w = 2 * np.pi * f[sel]
    db = 20 * np.log10(np.maximum(G, 1e-300))
    # log-spaced points: the bin nearest each of `points` log-spaced frequencies (no averaging,
    # which would flatten a sharp resonance)
    pick = np.unique(np.searchsorted(w, np.geomspace(w[0], w[-1], points)).clip(0, w.size - 1))
    return BodeMagnitude(w[pick], db[pick], w, db)


# ------------------------------------------------------------------------------------------------
# 4. Fit eq. 5 / eq. 6 to the magnitude

@dataclass(frozen=True)
class RowFit:
    """A fitted transient row in the vehicle-file layout and its correlation number."""

    row: str
    coeffs: tuple  # [K, a, b, c, d, e, g] (eq. 5) or [K, a, b, c, d] (eq. 6), K in vehicle units
    measured_gain: float  # K as measured on the rig (N or N m per rad/s)
    correlation: float  # Pearson correlation of measured and model dB over the band
    rms_db: float  # rms dB error of the fit
    at_bound: tuple = ()  # names of coefficients that ended on their bound (not resolved by the band)


def magnitude_db(row: str, coeffs, omega):
    """20 log10 |TF(jw)| of a seed-004 row (eq. 5 for forces, eq. 6 for the moment)."""
    num, den = model.transfer_function(row, coeffs)
    s = 1j * np.asarray(omega, float)
    return 20 * np.log10(np.abs(np.polyval(num, s) / np.polyval(den, s)) + 1e-300)


def correlation(x, y) -> float:
    x = np.asarray(x, float) - np.mean(x)
    y = np.asarray(y, float) - np.mean(y)
    den = math.sqrt(float(x @ x) * float(y @ y))
    return float(x @ y / den) if den > 0 else 0.0


def fit_row(row: str, bode: BodeMagnitude, prior, gain_scale: float = 1.0, starts: int = 6,
            seed: int = 0, spread: float = 1.0, bound: float = 30.0) -> RowFit:
    """Fit eq. 5 (force rows) or eq. 6 (m1z) to a measured Bode magnitude.

    `prior` is a coefficient row to start from (e.g. the vehicle file's); `starts` - 1 more
    starts are drawn around it, each coefficient times exp(N(0, spread)). `gain_scale` is
    gain_per_newton * T: the returned K is the measured gain divided by it. Every coefficient
    but K stays within a factor `bound` of the prior.
    Stage 1: least squares in dB with log-coefficients. Stage 2: maximise the correlation number
    over the shape coefficients (Nelder-Mead from the stage-1 optimum), K from the dB offset.
    """
    if row not in ROWS:
        raise ValueError(f"row must be one of {', '.join(ROWS)}, got {row!r}")
    nc = 5 if row == "m1z" else 7
    prior = np.asarray(prior, float)
    if prior.shape != (nc,) or np.any(prior <= 0):
        raise ValueError(f"{row}: prior must be {nc} positive coefficients, got {prior.tolist()}")
    # least squares on every FFT bin, each weighted by its share of log-frequency (so each
    # decade counts alike and a sharp resonance is not smeared by averaging); the correlation
    # number on the log-spaced points, as a Bode plot shows them
    w, meas = bode.raw_omega_rad_s, bode.raw_magnitude_db
    lw = np.log(w)
    wt = np.sqrt(np.gradient(lw) / (lw[-1] - lw[0]) * w.size)
    if w.size < nc + 2:
        raise ValueError(f"{row}: only {w.size} frequency points in the band; need more than {nc + 1}")

    def shape_db(logp):
        return magnitude_db(row, np.concatenate([[1.0], np.exp(logp)]), w)

    rng = np.random.default_rng(seed)
    p0 = np.log(prior[1:])
    # each coefficient stays within a factor `bound` of the prior: a zero or pole beyond the band
    # is otherwise free to run off while the product with K stays put
    lo = np.concatenate([[-60.0], p0 - math.log(bound)])
    hi = np.concatenate([[60.0], p0 + math.log(bound)])
    inits = [p0] + [np.clip(p0 + rng.normal(0.0, spread, p0.size), lo[1:] + 1e-9, hi[1:] - 1e-9)
                    for _ in range(max(starts - 1, 0))]
    best = None
    for init in inits:
        def resid(z):
            return (shape_db(z[1:]) + 20 * z[0] / math.log(10) - meas) * wt

        offset0 = float(np.mean(meas - shape_db(init)))
        z0 = np.concatenate([[offset0 * math.log(10) / 20], init])
        r = least_squares(resid, z0, bounds=(lo, hi), max_nfev=100 * nc)
        if best is None or r.cost < best.cost:
            best = r
    z = best.x

    wl, ml = bode.omega_rad_s, bode.magnitude_db

    def shape_db_log(logp):
        return magnitude_db(row, np.concatenate([[1.0], np.exp(logp)]), wl)

    def neg_corr(logp):
        return -correlation(ml, shape_db_log(logp))

    pol = minimize(neg_corr, z[1:], method="Nelder-Mead", bounds=list(zip(lo[1:], hi[1:])),
                   options={"xatol": 1e-6, "fatol": 1e-10, "maxiter": 300 * nc,
                            "initial_simplex": z[1:] + 0.02 * np.vstack([np.zeros(nc - 1), np.eye(nc - 1)])})
    shape = pol.x if -pol.fun >= -neg_corr(z[1:]) else z[1:]
    sdb = shape_db_log(shape)
    offset = float(np.mean(ml - sdb))
    k_meas = 10 ** (offset / 20)
    model_db = sdb + offset
    coeffs = (k_meas / gain_scale,) + tuple(float(c) for c in np.exp(shape))
    names = ("a", "b", "c", "d") if row == "m1z" else ("a", "b", "c", "d", "e", "g")
    edge = 1e-3 * math.log(bound)
    at_bound = tuple(nm for nm, x, l, h in zip(names, shape, lo[1:], hi[1:]) if x - l < edge or h - x < edge)
    return RowFit(
        row=row, coeffs=tuple(float(c) for c in coeffs), measured_gain=float(k_meas),
        correlation=correlation(ml, model_db),
        rms_db=float(np.sqrt(np.mean((ml - model_db) ** 2))), at_bound=at_bound,
    )
