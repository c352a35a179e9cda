"""Diagnosis of fixed two-way thrusters (issue 17): a degraded or reversed thruster and a wrong
thrust curve, on BlueROV2 Heavy recordings of `jetloop sim` whose true vehicle hides the fault.

The faults are concealed where a real vehicle has them: a thruster mounted or wired the wrong way
round is a `[[fixed]]` direction reversed in the TRUE vehicle file; a thrust table measured for
another supply is `table_thrust` scaled in it. The diagnosis gets the stock bluerov2_heavy."""

from __future__ import annotations

import dataclasses

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ARDUSUB

from ground.diagnose.candidates import CorrectedModel, candidates_for
from ground.prove import vehicle_toml
from onboard import model
from onboard.vehicle import DEFAULT_VEHICLE, load_vehicle, parse_vehicle

ROOT = Path(__file__).resolve().parents[1]
HEAVY = load_vehicle("bluerov2_heavy")
HEAVY_TEXT = (DEFAULT_VEHICLE.parent / "bluerov2_heavy.toml").read_text()


def test_faulty_command_by_hand():
    """A jet's speed command scales by sqrt(f) (T ~ n^2), a fixed thruster's thrust command by f,
    its sign too; the curve gains scale forward and reverse thrust apart; joints untouched."""
    asr4 = load_vehicle(None)
    c = np.array([[100.0, 100.0, 100.0, 100.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8]])
    out = model.faulty_command(asr4, c, thrust_fraction=(1.0, 0.25, 1.0, 0.0))
    assert out[0, :4].tolist() == [100.0, 50.0, 100.0, 0.0] and out[0, 4:].tolist() == c[0, 4:].tolist()
    t = np.array([[10.0, -10.0, 4.0, -4.0, 0, 0, 0, 0] + [0.0] * 16])
    out = model.faulty_command(HEAVY, t, thrust_fraction=(1.0, -1.0, 0.5, 1.0, 1, 1, 1, 1))
    assert out[0, :4].tolist() == [10.0, 10.0, 2.0, -4.0]
    out = model.faulty_command(HEAVY, t, curve_gain=(0.8, 1.25))
    assert out[0, :4].tolist() == [8.0, -12.5, 3.2, -5.0]
    assert model.faulty_command(asr4, c, curve_gain=(0.5, 0.5)).tolist() == c.tolist()  # no fixed thrusters


def test_the_fixed_thruster_candidates():
    """One degraded unit, tested one at a time, may be reversed on a fixed thruster but not on a
    jet; the curve candidate reports the vehicle-file keys it corrects, as thruster_fault."""
    cands = {c.effect: c for c in candidates_for(HEAVY)}
    tf = cands["thruster_fault"]
    assert tf.one_at_a_time and tf.lower == (-1.5,) * 8
    assert min(candidates_for(load_vehicle(None))[-1].lower) == 0.05  # asr4's jets cannot push backwards
    one = tf.subset((2,))
    cm = one.apply([-1.0], CorrectedModel(HEAVY))
    assert cm.thrust_fraction == (1, 1, -1.0, 1, 1, 1, 1, 1)
    assert one.parameters([-1.0], HEAVY) == {"thruster_fault.unit[2].thrust_fraction": -1.0}
    curve = cands["thrust_curve"]
    assert curve.public == "thruster_fault" and curve.kind == "misestimated"
    p = curve.parameters([0.8, 1.25], HEAVY)
    row = np.asarray(HEAVY.fixed_thruster.table_thrust[0])
    got = np.asarray(p["fixed_thruster.table_thrust"][0])
    assert np.allclose(got, np.where(row > 0, 0.8 * row, 1.25 * row), rtol=1e-4)
    assert "thrust_curve" not in {c.effect for c in candidates_for(load_vehicle(None))}


def _commands(path, seconds=90.0, seed=4):
    """Eight thrusters stepping every 1.5 s to random widths 1500 +- 60-160 us (both ways)."""
    rng = np.random.default_rng(seed)
    lines = ["t," + ",".join(f"pwm{c}" for c in range(1, 9))]
    for t in np.arange(0.0, seconds, 1.5):
        w = 1500 + rng.choice([-1, 1], 8) * rng.uniform(60, 160, 8) * (rng.random(8) < 0.6)
        lines.append(f"{t:.1f}," + ",".join(f"{x:.0f}" for x in w))
    lines.append(f"{seconds:.1f}," + ",".join(["1500"] * 8))
    path.write_text("\n".join(lines) + "\n")


def jetloop(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ground.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


def _diagnose(tmp_path, truth_text):
    (tmp_path / "truth.toml").write_text(truth_text)
    _commands(tmp_path / "cmds.csv")
    p = jetloop("sim", "--vehicle", str(tmp_path / "truth.toml"), "--commands", str(tmp_path / "cmds.csv"),
                "--out", str(tmp_path / "rec.tlog"), "--depth", "3", "--seed", "2", timeout=600)
    assert p.returncode == 0, p.stderr
    p = jetloop("diagnose", str(tmp_path / "rec.tlog"), "--vehicle", "bluerov2_heavy", "--quiet",
                "--json", str(tmp_path / "rep.json"), timeout=900)
    assert p.returncode == 0, p.stderr
    return json.loads((tmp_path / "rep.json").read_text())


@pytest.mark.slow
def test_a_reversed_bluerov_thruster_is_named(tmp_path):
    """Thruster 3 (rear right) pushes the wrong way: the diagnosis names that unit, fraction -1."""
    reversed3 = HEAVY_TEXT.replace("[[fixed]]   # 3: rear right\n", "[[fixed]]   # 3: rear right, REVERSED\n")
    head, tail = reversed3.split("# 3: rear right, REVERSED\n")
    tail = tail.replace("direction = [0.70711, 0.70711, 0.0]", "direction = [-0.70711, -0.70711, 0.0]", 1)
    truth = parse_vehicle(head + "# 3: rear right, REVERSED\n" + tail)
    assert truth.fixed[2].direction == (-0.70711, -0.70711, 0.0)
    rep = _diagnose(tmp_path, head + "# 3: rear right, REVERSED\n" + tail)
    assert rep["findings"], rep["candidates"]
    first = rep["findings"][0]
    assert first["effect"] == "thruster_fault" and first["kind"] == "missing", first
    assert list(first["parameters"]) == ["thruster_fault.unit[2].thrust_fraction"], first
    assert first["parameters"]["thruster_fault.unit[2].thrust_fraction"] == pytest.approx(-1.0, abs=0.15)
    assert rep["fit"]["holdout"]["after"]["total"] < rep["fit"]["holdout"]["before"]["total"]


@pytest.mark.slow
def test_a_wrong_bluerov_thrust_curve_is_named(tmp_path):
    """The true T200s give 75 % of the table forward and 130 % in reverse: named as the thrust
    curve misestimated, with the corrected table."""
    row = np.asarray(HEAVY.fixed_thruster.table_thrust[0])
    true_row = np.where(row > 0, 0.75 * row, 1.3 * row)
    truth = HEAVY.with_values({"fixed_thruster.table_thrust": [true_row.tolist()]})
    rep = _diagnose(tmp_path, vehicle_toml(truth, "# bluerov2_heavy, its T200 curve off"))
    assert rep["findings"], rep["candidates"]
    first = rep["findings"][0]
    assert first["effect"] == "thruster_fault" and first["kind"] == "misestimated", first
    got = np.asarray(first["parameters"]["fixed_thruster.table_thrust"][0])
    fwd, rev = row > 5, row < -5  # away from the dead band
    assert np.median(got[fwd] / row[fwd]) == pytest.approx(0.75, abs=0.1)
    assert np.median(got[rev] / row[rev]) == pytest.approx(1.3, abs=0.15)
    assert rep["fit"]["holdout"]["after"]["total"] < rep["fit"]["holdout"]["before"]["total"]


def test_two_candidates_of_one_effect_say_which_is_untestable():
    """A BlueROV2 report lists thruster_fault twice (a unit's fault, the curve): the console says
    which is which."""
    from ground.diagnose.cli import summary_text

    nan = float("nan")
    rep = {"findings": [], "untestable": [
        {"effect": "thruster_fault", "kind": "missing", "reason": "r1"},
        {"effect": "thruster_fault", "kind": "misestimated", "reason": "r2"},
        {"effect": "added_mass", "kind": "misestimated", "reason": "r3"}],
        "fit": {"holdout": {"before": {"total": nan}, "after": {"total": nan}}}, "mismatch": {"windows": []}}
    text = summary_text(rep)
    assert "no finding: the nominal model explains the recording within its noise" in text
    assert "not testable: thruster_fault (missing): r1" in text
    assert "not testable: thruster_fault (misestimated): r2" in text
    assert "not testable: added_mass: r3" in text


def test_a_withdrawn_finding_is_not_called_an_explained_recording():
    """small.tlog with the BlueROV2: an IMU bias passes its calibrated test, but no held-out
    stretch can show it fits better, so it is withdrawn; the console must not then say that the
    nominal model explains the recording."""
    from ground.diagnose.cli import summary_text

    nan = float("nan")
    rep = {"findings": [], "rejected": ["imu_bias"], "untestable": [],
           "fit": {"holdout": {"before": {"total": nan}, "after": {"total": nan}}}, "mismatch": {"windows": []}}
    text = summary_text(rep)
    assert "explains the recording" not in text
    assert text.startswith("no finding named: imu_bias passed the calibrated test but was withdrawn")
    rep["rejected"] = ["added_mass", "buoyancy"]
    assert summary_text(rep).startswith("no finding named: added_mass, buoyancy passed the calibrated test but were")


def test_ardusub_directions_by_hand():
    """The motor on a thruster's channel is the one its SERVOc_FUNCTION names (33-40: Motor1-8);
    a reversed motor reverses that thruster; nothing reversed, or no fixed thrusters: None."""
    from onboard.fixed import ardusub_directions

    assert ardusub_directions({"MOT_3_DIRECTION": -1.0}, HEAVY) == (1, 1, -1, 1, 1, 1, 1, 1)
    swapped = {"SERVO1_FUNCTION": 35.0, "SERVO3_FUNCTION": 33.0, "MOT_3_DIRECTION": -1.0}  # motor 3 on channel 1
    assert ardusub_directions(swapped, HEAVY) == (-1, 1, 1, 1, 1, 1, 1, 1)
    assert ardusub_directions({"SERVO2_FUNCTION": 0.0, "MOT_2_DIRECTION": -1.0}, HEAVY) is None  # no motor there
    assert ardusub_directions({"MOT_1_DIRECTION": 1.0}, HEAVY) is None
    assert ardusub_directions({"MOT_1_DIRECTION": -1.0}, load_vehicle(None)) is None


@pytest.mark.usefixtures("ardusub_data")
def test_the_logs_motor_directions_are_in_the_commands_the_smoother_sees():
    """small.tlog's MOT_1/2/5/8_DIRECTION = -1 sign those thrusters' commands in held_commands,
    the one place every part of the diagnosis (smoother, candidates, null draws) takes them from."""
    from ground.diagnose import replay
    from ground.recording import read_recording

    rec = read_recording(ARDUSUB / "small.tlog")
    t = np.arange(903.0, 905.0, 0.02)
    got = replay.held_commands(rec, HEAVY, t)
    raw = replay.held_commands(dataclasses.replace(rec, parameters={}), HEAVY, t)  # no directions
    assert np.abs(raw[:, :8]).max() > 5.0  # the burst: thrusters running
    np.testing.assert_allclose(got[:, :8], raw[:, :8] * np.array([-1, -1, 1, 1, -1, 1, 1, -1]), atol=1e-12)


def test_a_log_s_parameters_are_bounded_and_clean():
    """Hostile PARAM_VALUE rows: unprintable or empty names, NaN and inf are dropped, the last
    value of a name wins, and no log can hold more than MAX_PARAMETERS names."""
    from ground.recording import MAX_PARAMETERS, _parameters

    got, changed, dropped = _parameters([(b"MOT_1_DIRECTION\0", 1.0), (b"MOT_1_DIRECTION", -1.0), (b"\x1b[2J", 1.0),
                                         (b"", 1.0), (b"A", float("nan")), (b"B", float("inf")), ("C" * 17, 1.0),
                                         ("OK", "x"), ("Q", 2.0), ("Q", 2.0)])
    assert got == {"MOT_1_DIRECTION": -1.0, "Q": 2.0} and changed == ("MOT_1_DIRECTION",) and dropped == 0
    many, changed, dropped = _parameters((f"P{i}", float(i)) for i in range(MAX_PARAMETERS + 50))
    assert len(many) == MAX_PARAMETERS and dropped == 50


@pytest.mark.usefixtures("ardusub_data")
@pytest.mark.parametrize("with_vehicle, expect", [(False, 5), (True, 1)])
def test_scoring_windows_sit_where_the_thrusters_ran(with_vehicle, expect):
    """small.tlog idles for minutes around its 15 s armed stretch (900.7-915.7 s): given the
    vehicle, the scoring windows are the ones where a thruster is commanded; without it (and on
    every benchmark recording, where the jets always run) they are spread over the whole log."""
    from ground.diagnose.core import fit_windows
    from ground.recording import read_recording

    rec = read_recording(ARDUSUB / "small.tlog")
    w = fit_windows(rec, 120.0, HEAVY if with_vehicle else None)
    assert len(w) == expect
    if with_vehicle:
        # its thrust commands (903.7-910.7 s) inside one window: at 2 Hz a window is 40 samples = 20 s,
        # the segment 689.2-952.9 s tiles into 13 windows of 20.28 s, and the 11th (892.0-912.3 s)
        # holds all of them, the only one with thrust
        assert w[0][0] <= 903.7 and 910.7 <= w[-1][1] and all(900.7 - 21 <= a and b <= 915.7 + 21 for a, b in w)


def test_second_candidates_skip_the_first_s_namesake_and_refit_a_moved_unit():
    """The second effects worth a pair fit (core._second_candidates), with the real candidates of
    the stock BlueROV2: a thrust curve reports as a thruster fault, so after a thruster fault it is
    never paired (two findings of one name), on the second pass or on the nested fallback; a
    thruster fault fitted on unit 2 in the first round whose second-pass evidence moved to unit 3
    is fitted again on unit 3, not paired from unit 2's fit on unit 3's statistic (a review's
    find: unit 1 at S 2.1 under its threshold of 5.1 had been paired on unit 2's 342)."""
    from ground.diagnose import core, decide
    from ground.diagnose.candidates import Fit

    cands = candidates_for(HEAVY)
    by = {c.effect: c for c in cands}
    assert by["thrust_curve"].public == by["thruster_fault"].public == "thruster_fault"
    n = by["thruster_fault"].n_params

    def score(effect, stat, keep=None):
        return decide.Score(effect, 1, stat, 10.0, np.zeros(1), np.ones(1), np.ones(1), keep=keep)

    def fit(cand):
        z = np.zeros((3, 12))
        return Fit(cand, np.asarray(cand.x0, float), 0.0, 0.0, 10.0, 0.5, 0.0, np.zeros(12), z)

    cal = decide.Calibration(8, 1.0, {}, {c.effect: 5.0 for c in cands}, 0.01, {})
    best = fit(by["thruster_fault"].subset((0,)))
    curve = fit(by["thrust_curve"])
    by_effect = {"thruster_fault": score("thruster_fault", 50.0, (0,)), "thrust_curve": score("thrust_curve", 40.0)}
    # nested fallback (no second pass after a thruster fault): the curve is not tried
    assert core._second_candidates(best, [curve], by_effect, cands, cal, None, set(), None) == []
    # second pass: nor there
    again = {"thrust_curve": score("thrust_curve", 40.0)}
    assert core._second_candidates(best, [curve], by_effect, cands, cal, again, set(), None) == []
    # a first finding of another name; the fault's unit moved from 1 to 2 (0-based) on the second pass
    first = fit(by["buoyancy"])
    unit1 = fit(by["thruster_fault"].subset((1,)))
    by_effect = {"buoyancy": score("buoyancy", 90.0), "thruster_fault": score("thruster_fault", 50.0, (1,))}
    again = {"thruster_fault": score("thruster_fault", 40.0, (2,))}
    out = core._second_candidates(first, [unit1], by_effect, cands, cal, again, set(), None)
    assert len(out) == 1 and out[0][2], out  # fitted again, alone on top of the first
    assert out[0][0].keys == by["thruster_fault"].subset((2,)).keys and n > 2
    # the same unit: the first round's fit is reused
    again = {"thruster_fault": score("thruster_fault", 40.0, (1,))}
    out = core._second_candidates(first, [unit1], by_effect, cands, cal, again, set(), None)
    assert [(c.keys, alone) for c, _, alone in out] == [(unit1.candidate.keys, False)]


def test_a_family_the_second_pass_cannot_test_is_listed_untestable_with_the_first():
    """With the first finding in the model, a family the first pass could test and the second
    pass cannot (not significant, sd over half its reference) is listed untestable with the
    first named: not absent (dev 5460, 5395, 5291, 5135). Named, rejected, already untestable or
    still testable families are not; a thruster fault only when neither its units nor its
    thrust curve can be tested."""
    from ground.diagnose import core, decide

    cands = candidates_for(HEAVY)
    cal = decide.Calibration(8, 1.0, {}, {c.effect: 5.0 for c in cands}, 0.01, {})

    def score(effect, stat, sd):  # reference 1: the family is determined when sd <= 0.5
        return decide.Score(effect, 1, stat, 0.0, np.zeros(1), np.array([sd]), np.ones(1))

    first = next(c for c in cands if c.effect == "servo_lag")
    named = [{"effect": "imu_bias"}, {"effect": "servo_lag"}]  # a bias listed first: "with" the force
    again = {"linear_damping": score("linear_damping", 1.0, 2.0),  # undetermined: listed
             "added_mass": score("added_mass", 1.0, 0.2),  # determined: tested, absent
             "current": score("current", 9.0, 2.0),  # significant: tested
             "motor_lag": score("motor_lag", 1.0, 3.0),  # not testable on the first pass already
             "buoyancy": score("buoyancy", 1.0, 3.0),  # rejected: keeps that verdict
             "thruster_fault": score("thruster_fault", 1.0, 3.0),
             "thrust_curve": score("thrust_curve", 1.0, 0.1)}  # the fault's curve still tested
    out = core._masked_untestable(cands, {"motor_lag"}, again, first, named, cal, {"buoyancy"})
    assert [u["effect"] for u in out] == ["linear_damping"], out
    assert out[0]["with"] == "servo_lag" and "with servo_lag in the model" in out[0]["reason"]
    assert "Cramer-Rao sd 2x the smallest error worth finding (a test needs at most 0.5x)" in out[0]["reason"]
    # significant on the first pass (S 9 against 5) and undetermined with the first in the model:
    # said to be confounded with it, not only "not testable" (a hostile review's find, 6068)
    alone = core._masked_untestable(cands, {"motor_lag"}, again, first, named, cal, {"buoyancy"},
                                    {"linear_damping": score("linear_damping", 9.0, 2.0)})
    assert alone[0]["reason"] == ("significant alone (S 9.0 against 5.0) but not determined with servo_lag in "
                                  "the model: Cramer-Rao sd 2x the smallest error worth finding (a test needs at "
                                  "most 0.5x); the two are confounded here"), alone
    again["thrust_curve"] = score("thrust_curve", 1.0, 3.0)
    out = core._masked_untestable(cands, {"motor_lag"}, again, first, named, cal, {"buoyancy"})
    assert sorted(u["effect"] for u in out) == ["linear_damping", "thruster_fault"]
    # nothing to be tested with: the first withdrawn (another finding, or none), or no second pass
    for findings in ([], [{"effect": "buoyancy"}]):
        assert core._masked_untestable(cands, set(), again, first, findings, cal, set()) == []
    assert core._masked_untestable(cands, set(), None, first, named, cal, set()) == []
    assert core._masked_untestable(cands, set(), again, None, named, cal, set()) == []


def test_fitting_windows_tile_the_whole_recording():
    """Each segment is tiled by windows of WINDOW_S to twice that, its last seconds included (a
    90 s recording's surfacing at 77-84 s lay outside windows counted whole from its start)."""
    from types import SimpleNamespace

    from ground.diagnose.core import WINDOW_S, fit_windows

    imu = SimpleNamespace(time_s=np.arange(0.0, 89.9, 0.01))
    rec = SimpleNamespace(imu=imu, servo=None, t_start_s=0.0, t_end_s=89.9,
                          segment_bounds=lambda: [(0.0, 89.9)])
    w = fit_windows(rec, 120.0)
    assert len(w) == 8 and w[0][0] == 0.0 and w[-1][1] == pytest.approx(89.9)
    assert all(b0 == pytest.approx(a1) for (_, b0), (a1, _) in zip(w, w[1:]))  # no gap, no overlap
    assert all(WINDOW_S <= b - a < 2 * WINDOW_S for a, b in w)
    rec.segment_bounds = lambda: [(0.0, 600.0)]
    w = fit_windows(rec, 120.0)  # thinned to 12, spread from the first window to the last
    assert len(w) == 12 and w[0][0] == 0.0 and w[-1][1] == pytest.approx(600.0)
