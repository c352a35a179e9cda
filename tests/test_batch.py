"""The batch plant (hil/batch.py): many vehicles at once equal the same vehicles run one by one."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from hil import batch
from onboard import model
from onboard.vehicle import VehicleFileError, load_vehicle

DT = 0.002
N = 6


@pytest.fixture(scope="module")
def vehicle():
    return load_vehicle()


@pytest.fixture(scope="module")
def fleet(vehicle):
    """N vehicles with different added mass, damping and mass, commands and start states."""
    params = batch.monte_carlo(
        vehicle, {"hydro.added_mass": 0.2, "hydro.linear_damping": 0.3, "body.mass": 0.05}, N, seed=11
    )
    rng = np.random.default_rng(5)
    commands = np.column_stack([rng.uniform(10.0, 70.0, (N, 4)), rng.uniform(-0.6, 0.6, (N, 8))])
    states = np.array([model.initial_state(vehicle, 0.3 + 0.1 * i, commands[i]) for i in range(N)])
    states[:, 7:13] = rng.uniform(-0.2, 0.2, (N, 6))  # moving, so damping and added mass matter
    return states, commands, params


def test_batch_equals_independent_single_vehicle_runs(fleet):
    states, commands, params = fleet
    out = batch.simulate_batch(states, commands, params, DT, 150)
    for i in range(N):
        ref = model.rk4_steps(states[i].copy(), commands[i], params[i], DT, 150)
        np.testing.assert_array_equal(out[i], ref)
    # the vehicles really differ: with different parameters the same run ends elsewhere
    same = batch.simulate_batch(states, commands, np.repeat(params[:1], N, axis=0), DT, 150)
    assert np.abs(same - out).max() > 1e-6
    # the inputs are not changed
    assert np.array_equal(states, fleet[0])


def test_schedule_rows_hold_their_share_of_the_steps(fleet):
    states, commands, params = fleet
    rng = np.random.default_rng(9)
    schedule = np.stack([commands, commands * 0.5, commands + rng.uniform(-0.2, 0.2, commands.shape)])
    schedule[1, :, 4:] = commands[:, 4:]  # joint commands within limits either way
    out = batch.simulate_batch(states, schedule, params, DT, 3 * 40)
    for i in range(N):
        x = states[i].copy()
        for s in range(3):  # row s over steps [40 s, 40 (s + 1))
            x = model.rk4_steps(x, schedule[s, i], params[i], DT, 40)
        np.testing.assert_array_equal(out[i], x)


def test_record_holds_the_state_every_k_steps(fleet, vehicle):
    states, commands, params = fleet
    rec = batch.simulate_batch_record(states, commands, params, DT, 100, 25, record=("pos", "quat", "nu"))
    assert rec.values.shape == (N, 100 // 25 + 1, 13)
    np.testing.assert_allclose(rec.time_s, [0.0, 0.05, 0.1, 0.15, 0.2], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(rec.state_index, np.arange(13))
    for i in (0, N - 1):
        x = states[i].copy()
        np.testing.assert_array_equal(rec.values[i, 0], x[:13])
        for s in range(1, 5):
            x = model.rk4_steps(x, commands[i], params[i], DT, 25)
            np.testing.assert_array_equal(rec.values[i, s], x[:13])
        np.testing.assert_array_equal(rec.final_state[i], x)
    # a subset by name and by index, in the order asked
    lay = model.StateLayout(4)
    sub = batch.simulate_batch_record(states, commands, params, DT, 10, 10, record=("n", 2))
    np.testing.assert_array_equal(sub.state_index, [*range(lay.size)[lay.n], 2])
    np.testing.assert_array_equal(sub.values[:, 1, :4], sub.final_state[:, lay.n])
    np.testing.assert_array_equal(sub.values[:, 1, 4], sub.final_state[:, 2])
    # samples fall on multiples of `every`; a remainder is run but not sampled
    odd = batch.simulate_batch_record(states, commands, params, DT, 10, 4, record="pos")
    assert odd.values.shape == (N, 3, 3)
    np.testing.assert_allclose(odd.time_s, [0.0, 4 * DT, 8 * DT])


def test_result_is_deterministic_and_independent_of_thread_count(fleet):
    states, commands, params = fleet
    a = batch.simulate_batch(states, commands, params, DT, 60)
    b = batch.simulate_batch(states, commands, params, DT, 60)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        c = batch.simulate_batch(states, commands, params, DT, 60)
    finally:
        numba.set_num_threads(threads)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)


def test_zero_steps_returns_the_start_state(fleet):
    states, commands, params = fleet
    np.testing.assert_array_equal(batch.simulate_batch(states, commands, params, DT, 0), states)


def test_monte_carlo_draws_nominal_times_one_plus_sigma_z(vehicle):
    sigma_ma, sigma_m = 0.1, 0.05
    params = batch.monte_carlo(vehicle, {"body.mass": sigma_m, "hydro.added_mass": sigma_ma}, 5, seed=42)
    # keys drawn in sorted order from default_rng(seed): body.mass (5 x 1), then hydro.added_mass (5 x 6)
    rng = np.random.default_rng(42)
    z_mass = rng.standard_normal((5, 1))
    z_ma = rng.standard_normal((5, 6))
    np.testing.assert_allclose(params[:, model.P_MASS], 6.5 * (1 + sigma_m * z_mass[:, 0]), rtol=1e-15)
    ma = np.array([3.3, 3.3, 4.1, 0.006, 0.006, 0.002])
    np.testing.assert_allclose(params[:, model.P_MA:model.P_MA + 6], ma * (1 + sigma_ma * z_ma), rtol=1e-15)
    # everything not perturbed is the nominal vehicle
    nominal = model.pack_params(vehicle)
    untouched = np.ones(nominal.size, bool)
    untouched[model.P_MASS] = False
    untouched[model.P_MA:model.P_MA + 6] = False
    np.testing.assert_array_equal(params[:, untouched], np.tile(nominal[untouched], (5, 1)))


def test_monte_carlo_is_seeded_and_ignores_dict_order(vehicle):
    a = batch.monte_carlo(vehicle, {"hydro.linear_damping": 0.2, "body.mass": 0.1}, 4, seed=1)
    b = batch.monte_carlo(vehicle, {"body.mass": 0.1, "hydro.linear_damping": 0.2}, 4, seed=1)
    c = batch.monte_carlo(vehicle, {"body.mass": 0.1, "hydro.linear_damping": 0.2}, 4, seed=2)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    values = batch.perturbed_values(vehicle, {"body.mass": 0.1, "hydro.linear_damping": 0.2}, 4, seed=1)
    np.testing.assert_array_equal(values["body.mass"][:, 0], a[:, model.P_MASS])
    np.testing.assert_array_equal(values["hydro.linear_damping"], a[:, model.P_DL:model.P_DL + 6])


def test_monte_carlo_spread_matches_sigma(vehicle):
    values = batch.perturbed_values(vehicle, {"hydro.quadratic_damping": 0.1}, 4000, seed=0)
    rel = values["hydro.quadratic_damping"] / np.array([18.0, 18.0, 24.0, 0.05, 0.05, 0.03]) - 1.0
    # sample std of 4000 normal draws: 0.1 +- 0.1 / sqrt(2 * 4000) ~ 0.0011 (1 sigma)
    np.testing.assert_allclose(rel.std(axis=0), 0.1, atol=0.005)
    np.testing.assert_allclose(rel.mean(axis=0), 0.0, atol=0.1 * 4 / np.sqrt(4000))


@pytest.mark.parametrize(
    "what, message",
    [
        ("states_width", r"states: 12 values per vehicle is not a state vector"),
        ("states_1d", r"states: expected a 2-D array \(N, nx\)"),
        ("params_rows", r"params: expected shape \(6, 144\)"),
        ("commands_width", r"commands: expected shape \(6, 12\) held, or \(S, 6, 12\)"),
        ("commands_text", r"commands: expected a float array \(6, 12\) or \(S, 6, 12\), got list"),
        ("schedule_split", r"commands: a schedule of 7 rows must divide n_steps = 20"),
        ("nan_state", r"states: every value must be finite; states\[2, 7\] is nan"),
        ("dt", r"dt_s: expected a finite step > 0 s"),
        ("n_steps", r"n_steps: expected a whole number >= 0"),
        ("every", r"every: expected a whole number of steps >= 1"),
        ("record", r"record: unknown state piece 'velocity'"),
        ("record_index", r"record: expected state piece names .* or indices 0..104, got 105"),
    ],
)
def test_bad_input_gives_a_clear_message(fleet, what, message):
    states, commands, params = fleet
    args = dict(states=states, commands=commands, params=params, dt_s=DT, n_steps=20)
    extra = {}
    if what == "states_width":
        args["states"] = states[:, :12]
    elif what == "states_1d":
        args["states"] = states[0]
    elif what == "params_rows":
        args["params"] = params[:3]
    elif what == "commands_width":
        args["commands"] = commands[:, :8]
    elif what == "commands_text":
        args["commands"] = [["fast"] * 12] * N
    elif what == "schedule_split":
        args["commands"] = np.repeat(commands[None], 7, axis=0)
    elif what == "nan_state":
        bad = states.copy()
        bad[2, 7] = np.nan
        args["states"] = bad
    elif what == "dt":
        args["dt_s"] = 0.0
    elif what == "n_steps":
        args["n_steps"] = -1
    elif what == "every":
        extra["every"] = 0
    elif what == "record":
        extra = {"every": 5, "record": ("pos", "velocity")}
    elif what == "record_index":
        extra = {"every": 5, "record": (105,)}
    with pytest.raises(ValueError, match=message):
        if extra:
            batch.simulate_batch_record(**args, **{"every": 5, **extra})
        else:
            batch.simulate_batch(**args)


def test_monte_carlo_bad_input_names_the_key_or_draw(vehicle):
    with pytest.raises(VehicleFileError, match="hydro.added_mas: unknown vehicle key"):
        batch.monte_carlo(vehicle, {"hydro.added_mas": 0.1}, 3, seed=0)
    with pytest.raises(ValueError, match=r"perturb\['body.mass'\]: expected a relative sigma >= 0"):
        batch.monte_carlo(vehicle, {"body.mass": -0.1}, 3, seed=0)
    with pytest.raises(ValueError, match="not a numeric vehicle key"):
        batch.monte_carlo(vehicle, {"effects.current.enabled": 0.1}, 3, seed=0)
    with pytest.raises(ValueError, match="n: expected a whole number of vehicles >= 1"):
        batch.monte_carlo(vehicle, {"body.mass": 0.1}, 0, seed=0)
    # sigma 3: some of 50 draws of 1 + 3 z are negative, which a vehicle file rejects
    with pytest.raises(VehicleFileError, match=r"monte_carlo draw \d+ \(seed 0\): .*body.mass"):
        batch.monte_carlo(vehicle, {"body.mass": 3.0}, 50, seed=0)


def test_benchmark_baseline_is_the_same_model_interpreted(vehicle):
    """bench/bench_plant.py's baseline runs model.py's own source without numba, and agrees."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "bench" / "bench_plant.py"
    spec = importlib.util.spec_from_file_location("bench_plant", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    py = bench.interpreted_model()
    assert not hasattr(py.derivative, "py_func") and not hasattr(py.jet_frame, "py_func")
    assert hasattr(model.derivative, "py_func")  # the real module is still the compiled one
    v, u, x0 = bench.setup()
    p = model.pack_params(v)
    x_py, x_c = x0.copy(), x0.copy()
    for _ in range(20):
        x_py = py.rk4_step(x_py, u, p, 0.001)
        x_c = model.rk4_step(x_c, u, p, 0.001)
    assert np.abs(x_c[model.StateLayout(4).alpha] - x0[model.StateLayout(4).alpha]).max() > 0.05  # joints slew
    np.testing.assert_allclose(x_py, x_c, rtol=0, atol=1e-12)


def test_kernel_cache_is_invalidated_by_a_model_edit():
    """numba's own cache looks only at hil/batch.py; ours also holds onboard/model.py's hash."""
    import hashlib
    from pathlib import Path

    digest = hashlib.sha256(Path(model.__file__).read_bytes()).hexdigest()
    stamp = batch._run._cache._impl.locator.get_source_stamp()
    assert stamp[1] == (digest,)


def test_every_onboard_kernel_that_compiles_the_model_is_keyed_on_it():
    """The same guard for the onboard modules whose kernels call onboard.model functions; the
    compensator's kernels also compile allocation.py's thrust kernels in, so they are keyed on
    that file too."""
    import hashlib
    from pathlib import Path

    from numba.core.caching import FunctionCache

    from onboard import allocation, compensation, control, estimator

    def digest(module):
        return hashlib.sha256(Path(module.__file__).read_bytes()).hexdigest()

    also = {compensation: (digest(allocation),)}
    for module in (allocation, compensation, control, estimator):
        kernels = [o for o in vars(module).values()
                   if isinstance(getattr(o, "_cache", None), FunctionCache) and o.py_func.__module__ == module.__name__]
        assert kernels, module.__name__
        for k in kernels:
            want = (digest(model),) + also.get(module, ())
            assert k._cache._impl.locator.get_source_stamp()[1] == want, (module.__name__, k.__name__)
