"""Weather draws and behaviour profiles."""

from collections import Counter

import numpy as np
import pytest

from datagen.world.behaviour import PROFILES, draw_condition, vtype_attributes
from schemas import BEHAVIOURS, WEATHERS


def test_rain_and_fog_are_cautious_sun_and_cloud_normal_or_aggressive_half_each():
    rng = np.random.default_rng(0)
    draws = [draw_condition(rng) for _ in range(4000)]
    by_weather = {w: Counter(b for ww, b in draws if ww == w) for w in WEATHERS}
    for w in ("rainy", "foggy"):
        assert set(by_weather[w]) == {"cautious"}
    for w in ("sunny", "cloudy"):
        c = by_weather[w]
        assert set(c) == {"normal", "aggressive"}
        assert abs(c["normal"] / sum(c.values()) - 0.5) < 0.05
    weathers = Counter(w for w, _ in draws)
    assert all(abs(weathers[w] / 4000 - 0.25) < 0.03 for w in WEATHERS)  # default uniform


def test_weather_mix_is_respected():
    rng = np.random.default_rng(1)
    draws = [draw_condition(rng, {"foggy": 1.0}) for _ in range(50)]
    assert set(draws) == {("foggy", "cautious")}
    with pytest.raises(ValueError):
        draw_condition(rng, {"snowy": 1.0})
    with pytest.raises(ValueError):
        draw_condition(rng, {"sunny": 0.0})


def test_draws_are_reproducible_from_the_generator():
    a = [draw_condition(np.random.default_rng(7)) for _ in range(3)]
    b = [draw_condition(np.random.default_rng(7)) for _ in range(3)]
    assert a == b


def test_profile_table_covers_the_schema_and_orders_its_columns():
    assert set(PROFILES) == set(BEHAVIOURS)
    c, n, a = PROFILES["cautious"], PROFILES["normal"], PROFILES["aggressive"]
    for faster in (
        "speed_factor",
        "accel_mps2",
        "ego_speed_factor",
        "ego_accel_mps2",
        "impatience",
    ):
        assert getattr(c, faster) <= getattr(n, faster) <= getattr(a, faster), faster
    for longer in ("tau_s", "min_gap_m", "jm_timegap_minor_s", "jm_crossing_gap_m"):
        assert getattr(c, longer) > getattr(n, longer) > getattr(a, longer), longer
    for longer in ("ego_time_gap_s", "ego_min_gap_m", "ego_ped_margin_m"):
        assert getattr(c, longer) > getattr(n, longer) > getattr(a, longer), longer


def test_vtype_attributes_are_sumo_strings_and_never_ignore_right_of_way():
    for p in PROFILES.values():
        attrs = vtype_attributes(p)
        assert all(isinstance(v, str) for v in attrs.values())
        assert attrs["jmIgnoreFoeProb"] == "0"
        assert float(attrs["tau"]) == p.tau_s
