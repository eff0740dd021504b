"""The link-loss guard's Lua text (mrft_gcs.link.failsafe); flown in test_failsafe_sitl.py."""

from __future__ import annotations

import math
import re

import pytest

from mrft_gcs.errors import MrftError, UsageError
from mrft_gcs.link.failsafe import GuardFailed, GuardRefused, guard_script

BACKUP = {"ATC_RAT_RLL_P": 0.135, "ATC_ANG_RLL_P": 4.5, "ATC_ACCEL_R_MAX": 110000.0,
          "ATC_RAT_RLL_D": 0.0036}


def test_the_script_holds_every_backed_up_value_and_the_settings():
    text, guard_id = guard_script(BACKUP, 1.5)
    assert re.fullmatch(r"[0-9a-f]{6}", guard_id)
    assert f"local TAG = 'mrftguard {guard_id}'" in text
    rows = dict(re.findall(r"\{'([A-Z0-9_]+)', ([-0-9.e+]+)\}", text))
    assert {n: float(v) for n, v in rows.items()} == BACKUP
    assert "local SILENCE_MS = 1500" in text
    assert "local OFFBOARD_MODE = 20" in text and "local LAND_MODE = 9" in text
    assert "$" not in text  # every placeholder filled
    # STATUSTEXT carries 50 characters: the longest message the guard can send fits
    longest = f"mrftguard {guard_id} silent 30999ms 99/99 back NO LAND"
    assert len(longest) <= 50 and len(f"mrftguard {guard_id} no param ABCDEFGHIJKLMNOP") <= 50
    assert "'%s silent %dms %d/%d back %s'" in text and "'NO LAND'" in text


def test_the_id_follows_the_content():
    a = guard_script(BACKUP, 1.0)[1]
    assert guard_script(dict(reversed(BACKUP.items())), 1.0)[1] == a  # order does not matter
    assert guard_script({**BACKUP, "ATC_RAT_RLL_P": 0.14}, 1.0)[1] != a
    assert guard_script(BACKUP, 2.0)[1] != a
    assert guard_script(BACKUP, 1.0, land_mode=6)[1] != a


@pytest.mark.parametrize("restore, silence_s, match", [
    ({}, 1.0, "backed-up parameters"),
    ({f"P{i}": 0.0 for i in range(100)}, 1.0, "at most 99"),
    (BACKUP, 0.1, "0.3 to 30 s"),
    (BACKUP, math.nan, "0.3 to 30 s"),
    ({"atc_rat_rll_p": 0.1}, 1.0, "not an ArduPilot parameter name"),
    ({"ATC_RAT_RLL_P_TOO_LONG": 0.1}, 1.0, "at most 16"),
    ({"ATC_RAT_RLL_P'); x": 0.1}, 1.0, "not an ArduPilot parameter name"),
    ({"ATC_RAT_RLL_P": math.inf}, 1.0, "finite"),
])
def test_bad_input_is_refused_in_one_line(restore, silence_s, match):
    with pytest.raises(UsageError, match=match) as info:
        guard_script(restore, silence_s)
    assert "\n" not in str(info.value)


def test_errors_are_mrft_errors_with_exit_codes():
    assert issubclass(GuardRefused, MrftError) and GuardRefused("x").exit_code == 2
    assert issubclass(GuardFailed, MrftError) and GuardFailed("x").exit_code == 3
