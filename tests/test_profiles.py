"""Autopilot profiles: loading, validation, and the PD <-> cascade conversion (SPEC 4.2)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mrft_gcs.errors import UsageError
from mrft_gcs.loops import Loop
from mrft_gcs.profiles import (
    G_M_S2,
    Actuation,
    Clamp,
    PDGains,
    clamp_to_ranges,
    gains_to_params,
    load_profile,
    params_in_range,
    params_to_gains,
    parse_profile,
)
from mrft_gcs.telemetry import AutopilotFamily


@pytest.mark.parametrize("name, family, actuation, offboard", [
    ("px4", AutopilotFamily.PX4, Actuation.ATTITUDE, (6, 0)),
    ("sitl", AutopilotFamily.PX4, Actuation.TORQUE, (6, 0)),
    ("ardupilot", AutopilotFamily.ARDUPILOT, Actuation.ATTITUDE, (20, 0)),
])
def test_bundled_profiles_load(name, family, actuation, offboard):
    p = load_profile(name)
    assert (p.name, p.family, p.actuation) == (name, family, actuation)
    assert (p.modes["offboard"].main, p.modes["offboard"].sub) == offboard
    assert 0 < p.safety.max_tilt_deg < 90 and p.safety.max_test_duration_s > 0
    assert len(p.parameter_names()) == len(set(p.parameter_names()))


def test_mode_numbers_match_appendix_a():
    px4, ap = load_profile("px4"), load_profile("ardupilot")
    assert (px4.modes["land"].main, px4.modes["land"].sub) == (4, 6)
    assert px4.modes["position"].main == 3
    assert (ap.modes["land"].main, ap.modes["position"].main) == (9, 5)


def test_sitl_profile_names_exist_on_the_sitl():
    onboard = pytest.importorskip("mrft_gcs.sitl.onboard")
    missing = [n for n in load_profile("sitl").parameter_names() if n not in onboard.PARAM_SPECS]
    assert not missing


def test_px4_conversion_values():
    p = load_profile("px4")
    g = {Loop.ROLL: PDGains(Kc=1.2, Kd=0.2), Loop.ALTITUDE: PDGains(Kc=0.3, Kd=0.15),
         Loop.X: PDGains(Kc=0.2, Kd=0.3)}
    v = gains_to_params(p, g, hover_thrust=0.5)
    assert v["MC_ROLL_P"] == pytest.approx(6.0)  # angle P = Kc/Kd
    assert v["MC_ROLLRATE_P"] == pytest.approx(0.2)  # rate P = Kd
    assert (v["MC_ROLLRATE_I"], v["MC_ROLLRATE_D"], v["MC_ROLLRATE_K"]) == (0.0, 0.0, 1.0)
    assert v["MPC_Z_P"] == pytest.approx(2.0)
    assert v["MPC_Z_VEL_P_ACC"] == pytest.approx(0.15 * G_M_S2 / 0.5)  # Kd g / hover
    assert v["MPC_XY_P"] == pytest.approx(0.2 / 0.3)
    assert v["MPC_XY_VEL_P_ACC"] == pytest.approx(G_M_S2 * 0.3)  # g Kd
    assert "MC_PITCH_P" not in v  # only the loops given


def test_ardupilot_altitude_goes_through_the_accel_loop():
    p = load_profile("ardupilot")
    v = gains_to_params(p, {Loop.ALTITUDE: PDGains(Kc=0.3, Kd=0.15)}, hover_thrust=0.4)
    a = 0.1 * 0.5  # throttle per m/s^2 from ACCZ_P = 0.5 (0.001 per cm/s^2)
    assert v["PSC_ACCZ_P"] == 0.5
    assert v["PSC_VELZ_P"] == pytest.approx(0.15 * (1 + a * G_M_S2 / 0.4) / a)
    # the closed accel loop then gives exactly Kd of throttle per m/s of velocity error
    thrust_per_acc_sp = a / (1 + a * G_M_S2 / 0.4)
    assert v["PSC_VELZ_P"] * thrust_per_acc_sp == pytest.approx(0.15)


def test_side_loops_share_one_set_the_lower_gains_win():
    p = load_profile("px4")
    v = gains_to_params(p, {Loop.X: PDGains(0.2, 0.3), Loop.Y: PDGains(0.3, 0.25)}, 0.5)
    assert v["MPC_XY_VEL_P_ACC"] == pytest.approx(G_M_S2 * 0.25)
    assert v["MPC_XY_P"] == pytest.approx(0.2 / 0.3)


gain = st.floats(min_value=1e-3, max_value=50.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(name=st.sampled_from(["px4", "sitl", "ardupilot"]), kc=gain, kd=gain,
       hover=st.floats(min_value=0.1, max_value=0.9))
def test_round_trip_gains_params_gains(name, kc, kd, hover):
    p = load_profile(name)
    gains = {loop: PDGains(kc, kd) for loop in Loop}
    values = gains_to_params(p, gains, hover)
    values[p.altitude.hover_thrust] = hover
    back = params_to_gains(p, values)
    for loop in Loop:
        assert back[loop].Kc == pytest.approx(kc, rel=1e-9)
        assert back[loop].Kd == pytest.approx(kd, rel=1e-9)


def test_bad_gains_and_hover_are_refused():
    p = load_profile("px4")
    with pytest.raises(UsageError, match="roll"):
        gains_to_params(p, {Loop.ROLL: PDGains(math.nan, 0.1)}, 0.5)
    with pytest.raises(UsageError, match="hover"):
        gains_to_params(p, {Loop.ROLL: PDGains(1.0, 0.1)}, 1.5)


def _px4_table():
    import tomllib

    from mrft_gcs.profiles import PROFILE_DIR
    data = tomllib.loads((PROFILE_DIR / "px4.toml").read_text())
    data["param_ranges"] = {"MPC_Z_P": [0.1, 1.5]}  # px4.toml keeps its ranges as comments
    return data


@pytest.mark.parametrize("edit, match", [
    (lambda d: d["autopilot"].update(actuation="rates"), "actuation"),
    (lambda d: d["autopilot"].pop("family"), "family"),
    (lambda d: d["roll"].update(angle_p="MC ROLL P"), "not a parameter name"),
    (lambda d: d["roll"].update(rate_p="A_NAME_FAR_TOO_LONG"), "not a parameter name"),
    (lambda d: d["modes"].pop("land"), "land"),
    (lambda d: d["modes"]["offboard"].update(main=300), "0-255"),
    (lambda d: d["safety"].update(max_tilt_deg=-5), "max_tilt_deg"),
    (lambda d: d["safety"].update(max_tilt_deg=95), "below 90"),
    (lambda d: d.pop("altitude"), "altitude"),
    (lambda d: d.update(param_ranges=3), r"bad.toml \[param_ranges\]: must be a table"),
    (lambda d: d["param_ranges"].update(MPC_Z_P=[1.5, 0.1]),
     r"bad.toml \[param_ranges\]: 'MPC_Z_P' must be \[min, max\].*min < max"),
    (lambda d: d["param_ranges"].update(MPC_Z_P=[1.0, 1.0]), "'MPC_Z_P' must be"),
    (lambda d: d["param_ranges"].update(MPC_Z_P=[0.1]), "'MPC_Z_P' must be"),
    (lambda d: d["param_ranges"].update(MPC_Z_P=[0.1, 1.5, 2.0]), "'MPC_Z_P' must be"),
    (lambda d: d["param_ranges"].update(MPC_Z_P=[0.1, math.inf]), "'MPC_Z_P' must be"),
    (lambda d: d["param_ranges"].update(MPC_Z_P=[0.1, math.nan]), "'MPC_Z_P' must be"),
    (lambda d: d["param_ranges"].update(MPC_Z_P=["0.1", 1.5]), "'MPC_Z_P' must be"),
    (lambda d: d["param_ranges"].update(MPC_Z_P=[False, 1.5]), "'MPC_Z_P' must be"),
    (lambda d: d["param_ranges"].update(MPC_Z_P=1.5), "'MPC_Z_P' must be"),
    (lambda d: d["param_ranges"].update(MPC_ZP=[0.1, 1.5]),
     "'MPC_ZP' is not a parameter of this profile"),
])
def test_invalid_profiles_fail_on_load(edit, match):
    data = _px4_table()
    edit(data)
    with pytest.raises(UsageError, match=match):
        parse_profile(data, "bad.toml")


def test_unknown_profile_names_the_known_ones(tmp_path):
    with pytest.raises(UsageError, match="px4"):
        load_profile("no-such-autopilot")
    bad = tmp_path / "broken.toml"
    bad.write_text("[autopilot\n")
    with pytest.raises(UsageError, match="cannot read profile"):
        load_profile(bad)


def test_safety_overrides_take_precedence():
    s = load_profile("px4").safety.with_overrides(max_tilt_deg=20.0, max_altitude_m=None)
    assert s.max_tilt_deg == 20.0 and s.max_altitude_m == load_profile("px4").safety.max_altitude_m


def test_docstring_examples_run():
    import doctest

    import mrft_gcs.link.connection
    import mrft_gcs.link.modes
    import mrft_gcs.link.quality
    import mrft_gcs.profiles
    for mod in (mrft_gcs.profiles, mrft_gcs.link.modes, mrft_gcs.link.connection,
                mrft_gcs.link.quality):
        assert doctest.testmod(mod).failed == 0, mod.__name__


# ---------------------------------------------------------------------- parameter ranges
def test_sitl_ranges_are_the_sitl_param_specs():
    """The sitl profile's ranges are what the SITL accepts, for every name it maps."""
    onboard = pytest.importorskip("mrft_gcs.sitl.onboard")
    p = load_profile("sitl")
    assert set(p.param_ranges) == set(p.parameter_names())
    for name, rng in p.param_ranges.items():
        spec = onboard.PARAM_SPECS[name]
        assert rng == (spec.low, spec.high), name


def test_ranges_are_parsed_and_optional():
    import tomllib

    from mrft_gcs.profiles import PROFILE_DIR

    # px4 and ardupilot keep their documented ranges as comments (not enforced by the
    # firmware, not clamped); uncommented, the tables are valid
    for name, key, rng in (("px4", "MPC_Z_P", (0.1, 1.5)),
                           ("ardupilot", "PSC_POSZ_P", (1.0, 3.0))):
        assert load_profile(name).param_ranges == {}
        text = (PROFILE_DIR / f"{name}.toml").read_text()
        lines = text[text.index("# [param_ranges]"):].splitlines()
        table = "\n".join(ln[2:] for ln in lines if ln.startswith("# ") and
                          (ln.startswith("# [") or " = [" in ln))
        p = parse_profile({**tomllib.loads(text), **tomllib.loads(table)}, name)
        assert p.param_ranges[key] == rng
        assert set(p.param_ranges) <= set(p.parameter_names())
        assert "MPC_Z_VEL_I_ACC" not in p.param_ranges  # its min would add an I term
    data = _px4_table()
    data["param_ranges"] = {"MPC_Z_P": [0, 2]}  # integers are numbers too
    assert parse_profile(data, "ok.toml").param_ranges == {"MPC_Z_P": (0.0, 2.0)}
    del data["param_ranges"]
    assert parse_profile(data, "ok.toml").param_ranges == {}


def _ranged(name, **ranges):
    from dataclasses import replace
    return replace(load_profile(name), param_ranges=ranges)


def test_clamp_to_ranges_moves_only_values_outside():
    p = _ranged("sitl", MPC_Z_P=(0.5, 10.0), MPC_XY_P=(0.5, 2.0), MC_ROLL_P=(0.0, 50.0))
    values = {"MC_ROLL_P": 6.0, "MPC_Z_P": 10.5, "MPC_XY_P": 0.2, "MPC_Z_VEL_P_ACC": 99.0,
              "MC_PITCH_P": 10.0}
    out, clamps = clamp_to_ranges(p, values)
    assert out == {"MC_ROLL_P": 6.0, "MPC_Z_P": 10.0, "MPC_XY_P": 0.5,
                   "MPC_Z_VEL_P_ACC": 99.0, "MC_PITCH_P": 10.0}  # no range: untouched
    assert list(out) == list(values)
    assert clamps == [Clamp("MPC_Z_P", 10.5, 10.0, 0.5, 10.0, (Loop.ALTITUDE,)),
                      Clamp("MPC_XY_P", 0.2, 0.5, 0.5, 2.0, (Loop.X, Loop.Y))]
    assert values["MPC_Z_P"] == 10.5  # the input is not changed
    assert clamp_to_ranges(p, {"MPC_Z_P": 10.0, "MPC_XY_P": 0.5}) == (
        {"MPC_Z_P": 10.0, "MPC_XY_P": 0.5}, [])  # the bounds themselves are inside


def test_racer250_altitude_gain_is_clamped_to_the_sitl_range_with_a_note():
    """The live failure: MPC_Z_P = 10.5 computed, the SITL accepts at most 10."""
    p = load_profile("sitl")
    gains = {Loop.ALTITUDE: PDGains(Kc=2.1, Kd=0.2), Loop.ROLL: PDGains(Kc=1.0, Kd=0.1)}
    assert gains_to_params(p, gains, 0.5)["MPC_Z_P"] == pytest.approx(10.5)
    r = params_in_range(p, gains, 0.5)
    assert r.values["MPC_Z_P"] == 10.0
    assert r.values["MC_ROLL_P"] == pytest.approx(10.0)  # inside: as computed
    assert [c.name for c in r.clamps] == ["MPC_Z_P"] and len(r.notes) == 1
    assert r.notes[0] == ("MPC_Z_P: the tuned 10.5 is above the profile's range 0 to 10; 10 "
                          "written (altitude position loop slower than designed; in effect "
                          "Kc 2, Kd 0.2 instead of Kc 2.1, Kd 0.2)")
    assert r.gains[Loop.ALTITUDE].Kc == pytest.approx(2.0)  # Kd unchanged: VELZ_P unchanged
    assert r.gains[Loop.ROLL] == PDGains(pytest.approx(1.0), pytest.approx(0.1))
    for name, value in r.values.items():
        lo, hi = p.param_ranges[name]
        assert lo <= value <= hi


def test_clamp_notes_say_what_the_loop_gets():
    p = _ranged("px4", MPC_XY_VEL_P_ACC=(1.2, 5.0), MPC_XY_VEL_D_ACC=(0.1, 2.0),
                MC_ROLLRATE_P=(0.01, 0.5))
    gains = {Loop.X: PDGains(0.02, 0.1), Loop.Y: PDGains(0.03, 0.12),
             Loop.ROLL: PDGains(6.0, 0.6)}
    r = params_in_range(p, gains, 0.5)
    notes = dict(zip((c.name for c in r.clamps), r.notes, strict=True))
    assert notes["MPC_XY_VEL_P_ACC"].startswith(
        "MPC_XY_VEL_P_ACC: the tuned 0.9807 is below the profile's range 1.2 to 5; 1.2 "
        "written (x and y velocity loop faster than designed, with less phase margin; in "
        "effect Kc 0.02447, Kd 0.1224 instead of Kc 0.02, Kd 0.1)")
    assert notes["MPC_XY_VEL_D_ACC"] == (
        "MPC_XY_VEL_D_ACC: the tuned 0 is below the profile's range 0.1 to 2; 0.1 written "
        "(x and y velocity D term 0.1 where the PD design has 0; in effect Kc 0.02447, "
        "Kd 0.1224 instead of Kc 0.02, Kd 0.1)")
    assert "roll rate loop slower than designed" in notes["MC_ROLLRATE_P"]
    assert set(r.gains) == {Loop.X, Loop.Y, Loop.ROLL}  # only the loops given
    assert r.gains[Loop.ROLL].Kd == pytest.approx(0.5)
    # the angle P is kept, so the whole roll PD scales down with the rate P
    assert r.gains[Loop.ROLL].Kc == pytest.approx(6.0 * 0.5 / 0.6)
