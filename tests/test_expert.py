"""The expert's rules as pure functions (no SUMO)."""

import dataclasses
import math

import pytest

from datagen.world import expert
from datagen.world.behaviour import PROFILES
from datagen.world.expert import Decision, ExpertInput, Obstacle, decide

P = PROFILES["normal"]
LIMIT = 13.89


def test_cruises_at_limit_times_profile_factor_when_nothing_binds():
    d = decide(ExpertInput(speed_mps=10.0, speed_limit_mps=LIMIT), P)
    assert d == Decision(pytest.approx(LIMIT * P.ego_speed_factor), "none")


def test_profiles_scale_cruise_speed_in_documented_order():
    speeds = {
        name: decide(ExpertInput(10.0, LIMIT), p).target_speed_mps for name, p in PROFILES.items()
    }
    assert speeds["cautious"] < speeds["normal"] < speeds["aggressive"]


def test_above_the_limit_reports_speed_limit():
    assert decide(ExpertInput(speed_mps=20.0, speed_limit_mps=LIMIT), P).reason == "speed_limit"


def test_lower_limit_ahead_is_approached_at_comfortable_deceleration():
    d = decide(ExpertInput(13.0, LIMIT, limits_ahead=((20.0, 8.33),)), P)
    assert d.reason == "speed_limit"
    v_end = 8.33 * P.ego_speed_factor
    assert d.target_speed_mps == pytest.approx(
        math.sqrt(v_end**2 + 2 * P.ego_comfort_decel_mps2 * 20)
    )


def test_sharp_curve_limits_lateral_acceleration():
    k = 1 / 10.0  # radius 10 m, right here
    d = decide(ExpertInput(10.0, LIMIT, curvature_ahead=((0.0, k),)), P)
    assert d.reason == "curve"
    assert d.target_speed_mps**2 * k == pytest.approx(P.ego_lat_accel_mps2)
    gentle = decide(ExpertInput(10.0, LIMIT, curvature_ahead=((0.0, 1 / 1000.0),)), P)
    assert gentle.reason == "none"


def test_follow_speed_holds_the_profile_time_gap_at_equal_speeds():
    for p in PROFILES.values():
        v = 10.0
        gap = p.ego_min_gap_m + v * p.ego_time_gap_s
        assert expert.follow_speed(gap, v, p) == pytest.approx(v)
        assert expert.follow_speed(gap - 5, v, p) < v < expert.follow_speed(gap + 5, v, p)


def test_vehicle_close_ahead_binds_and_stopped_lead_means_stop():
    d = decide(ExpertInput(10.0, LIMIT, obstacles=(Obstacle(15.0, 5.0, "vehicle"),)), P)
    assert d.reason == "vehicle" and d.target_speed_mps < 10.0
    stop = decide(
        ExpertInput(0.0, LIMIT, obstacles=(Obstacle(P.ego_min_gap_m, 0.0, "vehicle"),)), P
    )
    assert stop.target_speed_mps == 0.0


def test_cautious_keeps_longer_gaps_than_aggressive():
    c, a = PROFILES["cautious"], PROFILES["aggressive"]
    assert expert.follow_speed(30.0, 10.0, c) < expert.follow_speed(30.0, 10.0, a)


def test_yields_to_pedestrian_on_path_with_margin():
    ped = Obstacle(P.ego_ped_margin_m + 0.01, 0.0, "pedestrian")
    d = decide(ExpertInput(0.5, LIMIT, obstacles=(ped,)), P)
    assert d == Decision(0.0, "pedestrian")
    far = decide(ExpertInput(10.0, LIMIT, obstacles=(Obstacle(80.0, 0.0, "pedestrian"),)), P)
    assert far.reason == "none"


def test_red_light_stops_before_the_line():
    d = decide(ExpertInput(10.0, LIMIT, light="red", light_distance_m=30.0), P)
    assert d.reason == "red_light"
    room = 30.0 - expert.STOP_LINE_MARGIN_M
    assert d.target_speed_mps == pytest.approx(math.sqrt(2 * P.ego_comfort_decel_mps2 * room))
    at_line = decide(ExpertInput(0.0, LIMIT, light="red", light_distance_m=0.9), P)
    assert at_line == Decision(0.0, "red_light")
    green = decide(ExpertInput(10.0, LIMIT, light="green", light_distance_m=5.0), P)
    assert green.reason == "none"


def test_yellow_stops_only_when_comfortable():
    can = decide(ExpertInput(10.0, LIMIT, light="yellow", light_distance_m=25.0), P)
    assert can.reason == "red_light"
    cannot = decide(ExpertInput(13.0, LIMIT, light="yellow", light_distance_m=8.0), P)
    assert cannot.reason == "none"


def test_red_too_close_to_stop_even_hard_goes_on():
    # committed on yellow, the light turns red 2 m before the line at 13 m/s
    d = decide(ExpertInput(13.0, LIMIT, light="red", light_distance_m=2.0), P)
    assert d.reason != "red_light"


def test_slow_car_waits_for_the_next_green_when_this_one_ends_before_it_clears():
    def at(speed, dist, green_left):
        inp = ExpertInput(
            speed,
            LIMIT,
            light="green",
            light_distance_m=dist,
            junction_entry_m=dist,
            junction_exit_m=dist + 20.0,
            green_left_s=green_left,
        )
        return decide(inp, P)

    # creeping up to the line at 1 m/s with 1 s of green left: 26 m at 4 m/s take 6.5 s
    assert at(1.0, 2.0, 1.0).reason == "red_light"
    assert at(0.0, 0.5, 1.0) == Decision(0.0, "red_light")
    assert at(1.0, 2.0, 10.0).reason == "none"  # enough green left
    assert at(10.0, 8.0, 0.5).reason == "none"  # too close to stop comfortably: goes on
    assert at(10.0, 40.0, 0.5).reason == "none"  # at 10 m/s it clears within the yellow
    assert at(1.0, 2.0, None).reason == "none"  # green left unknown (no signal read)


def test_a_turn_is_timed_at_the_speed_its_curve_allows_and_stopped_for_at_the_firm_decel():
    # a left turn 30 m ahead, 25 m through, radius ~9 m (curvature 0.11): ~5 m/s inside it
    turn = ((30.0, 0.004), (37.0, 0.11), (43.0, 0.088))
    inp = ExpertInput(
        15.0,
        LIMIT,
        curvature_ahead=turn,
        light="green",
        light_distance_m=30.0,
        junction_entry_m=30.0,
        junction_exit_m=55.0,
        green_left_s=1.5,
    )
    v_in = math.sqrt(P.ego_lat_accel_mps2 / 0.11)
    assert expert.clear_time_s(inp, P) == pytest.approx(30.0 / 15.0 + 31.0 / v_in)
    straight = ExpertInput(15.0, LIMIT, junction_entry_m=30.0, junction_exit_m=55.0)
    assert expert.clear_time_s(straight, P) == pytest.approx(61.0 / 15.0)
    # 15 m/s needs 45 m at the comfortable 2.5 m/s^2, 37.5 m at 1.2 x: too close, it goes on
    assert expert.light_rule(inp, P) == math.inf
    # from 40 m (needs > 37.5) it stops: the green ends (+ yellow) long before it clears
    far = dataclasses.replace(
        inp, light_distance_m=40.0, junction_entry_m=40.0, junction_exit_m=65.0
    )
    assert expert.light_rule(far, P) < 15.0
    assert expert.light_rule(dataclasses.replace(far, green_left_s=10.0), P) == math.inf


def test_after_the_stop_the_car_waits_at_the_line_while_a_foe_is_near():
    def at(eta, speed=0.0, dist=expert.STOP_SIGN_MARGIN_M):
        inp = ExpertInput(speed, LIMIT, stop_distance_m=dist, stop_done=True, stop_foe_eta_s=eta)
        return decide(inp, P)

    assert at(2.0) == Decision(0.0, "stop_sign")  # a foe due in 2 s: wait
    assert at(0.0).reason == "stop_sign"  # one inside the junction
    assert at(None).reason == "none" and at(expert.FOE_GAP_S + 1.0).reason == "none"
    assert at(2.0, speed=5.0).reason == "none"  # already going: do not stop in the entry
    assert at(2.0, dist=-0.5).reason == "none"  # past the line


def test_stop_sign_full_stop_then_released():
    d = decide(ExpertInput(0.05, LIMIT, stop_distance_m=expert.STOP_SIGN_MARGIN_M), P)
    assert d == Decision(0.0, "stop_sign")
    approaching = decide(ExpertInput(10.0, LIMIT, stop_distance_m=20.0), P)
    assert approaching.reason == "stop_sign" and approaching.target_speed_mps < 10.0
    done = decide(ExpertInput(0.0, LIMIT, stop_distance_m=0.5, stop_done=True), P)
    assert done.reason == "none" and done.target_speed_mps > 0


def test_route_end_stops():
    d = decide(ExpertInput(0.2, LIMIT, route_end_m=2.0), P)
    assert d == Decision(0.0, "route_end")


def test_lowest_cap_wins_and_names_the_reason():
    inp = ExpertInput(
        10.0,
        LIMIT,
        obstacles=(Obstacle(50.0, 8.0, "vehicle"),),
        light="red",
        light_distance_m=12.0,
    )
    d = decide(inp, P)
    assert d.reason == "red_light"
    caps = [rule(inp, P) for _, rule in expert.RULES]
    assert d.target_speed_mps == pytest.approx(min(caps))


def test_every_reason_is_a_schema_category():
    from schemas import EXPERT_REASONS

    assert {name for name, _ in expert.RULES} | {"none", "junction"} <= set(EXPERT_REASONS)


def test_keeps_the_junction_clear_of_a_standing_queue_beyond_it():
    # junction from 20 m to 35 m ahead; a car stands 38 m ahead: no room for the ego past it
    queue = (Obstacle(38.0, 0.0, "vehicle"),)
    inp = ExpertInput(8.0, LIMIT, obstacles=queue, junction_entry_m=20.0, junction_exit_m=35.0)
    d = decide(inp, P)
    assert d.reason == "junction"
    room = 20.0 - expert.STOP_LINE_MARGIN_M
    assert d.target_speed_mps == pytest.approx(math.sqrt(2 * P.ego_comfort_decel_mps2 * room))
    # room enough beyond the exit, or the queue moving: no hold
    far = (Obstacle(35.0 + expert.KEEP_CLEAR_ROOM_M + 1.0, 0.0, "vehicle"),)
    assert (
        decide(
            ExpertInput(8.0, LIMIT, obstacles=far, junction_entry_m=20.0, junction_exit_m=35.0), P
        ).reason
        != "junction"
    )
    moving = (Obstacle(38.0, 8.0, "vehicle"),)
    assert (
        decide(
            ExpertInput(8.0, LIMIT, obstacles=moving, junction_entry_m=20.0, junction_exit_m=35.0),
            P,
        ).reason
        != "junction"
    )


def test_waits_before_the_junction_for_someone_on_its_exit_crossing():
    ped = (Obstacle(30.0, 0.0, "pedestrian"),)  # on the crossing at the junction's exit
    d = decide(
        ExpertInput(6.0, LIMIT, obstacles=ped, junction_entry_m=12.0, junction_exit_m=28.0), P
    )
    assert d.reason == "junction"
    assert d.target_speed_mps == pytest.approx(
        expert.approach_speed(12.0 - expert.STOP_LINE_MARGIN_M, 0.0, P.ego_comfort_decel_mps2)
    )
    # standing at the stop line it stays there (snapped to 0)
    ped = (Obstacle(18.0, 0.0, "pedestrian"),)
    at_line = ExpertInput(0.0, LIMIT, obstacles=ped, junction_entry_m=1.0, junction_exit_m=17.0)
    assert decide(at_line, P) == Decision(0.0, "junction")


def test_too_late_to_stop_before_the_junction_it_goes_on():
    queue = (Obstacle(12.0, 0.0, "vehicle"),)
    inp = ExpertInput(14.0, LIMIT, obstacles=queue, junction_entry_m=0.5, junction_exit_m=10.0)
    assert expert.junction_rule(inp, P) == math.inf


def test_emergency_brake_only_when_the_vtype_decel_cannot_stop_short_of_a_cut_in():
    decel = 1.2 * P.ego_comfort_decel_mps2  # what SUMO lets a command brake (world.py)
    v = 12.0
    # a car cutting in 15 m ahead, nearly standing: braking at decel needs 144 / 7.2 = 20 m
    close = ExpertInput(v, LIMIT, obstacles=(Obstacle(15.0, 1.0, "vehicle"),))
    need = (v * v - 1.0) / (2.0 * (15.0 - expert.EMERGENCY_GAP_M))
    assert decide(close, P, decel).brake_mps2 == pytest.approx(need)
    assert decel < need < P.emergency_decel_mps2
    # far enough for the ordinary braking, or the same car moving away faster: no emergency
    far = ExpertInput(v, LIMIT, obstacles=(Obstacle(40.0, 1.0, "vehicle"),))
    assert decide(far, P, decel).brake_mps2 == 0.0
    away = ExpertInput(v, LIMIT, obstacles=(Obstacle(5.0, 13.0, "vehicle"),))
    assert decide(away, P, decel).brake_mps2 == 0.0
    # someone stepping out 3 m ahead: as hard as the car can, no harder
    ped = ExpertInput(v, LIMIT, obstacles=(Obstacle(3.0, 0.0, "pedestrian"),))
    assert decide(ped, P, decel).brake_mps2 == P.emergency_decel_mps2
    # without a decel to compare with (the default), never
    assert decide(close, P).brake_mps2 == 0.0


# ---------------------------------------------------------------- the expert's plan (rollout)

TIMES = (0.5, 1.0, 1.5, 2.0)


def test_rollout_from_standstill_on_a_free_road_accelerates_at_the_profiles_rate():
    dists, first = expert.rollout(ExpertInput(0.0, LIMIT), P, TIMES)
    assert first.reason == "none"
    a = P.ego_accel_mps2
    for t, d in zip(TIMES, dists):  # 0.5 a t^2 while below the cruise speed
        assert d == pytest.approx(0.5 * a * t * t, rel=1e-6)


def test_rollout_stops_before_a_red_light_and_never_passes_it():
    inp = ExpertInput(6.0, LIMIT, light="red", light_distance_m=12.0)
    dists, first = expert.rollout(inp, P, (*TIMES, 3.0, 4.0), P.ego_comfort_decel_mps2 * 1.2)
    assert first.reason == "red_light"
    assert all(b >= a for a, b in zip(dists, dists[1:]))  # never backwards
    assert dists[-1] <= 12.0 - expert.STOP_LINE_MARGIN_M + 0.5


def test_rollout_follows_a_slower_lead_that_keeps_its_speed():
    lead = Obstacle(distance_m=30.0, speed_mps=5.0, kind="vehicle")
    dists, first = expert.rollout(ExpertInput(12.0, LIMIT, obstacles=(lead,)), P, TIMES)
    gaps = [30.0 + 5.0 * t - d for t, d in zip(TIMES, dists)]
    assert min(gaps) > P.ego_min_gap_m  # it stays behind the lead


def test_advance_moves_distances_and_drops_what_was_passed():
    inp = ExpertInput(
        8.0,
        LIMIT,
        limits_ahead=((3.0, 8.0),),
        obstacles=(Obstacle(20.0, 4.0, "vehicle"),),
        light="green",
        light_distance_m=2.0,
        route_end_m=50.0,
        green_left_s=4.0,
    )
    out = expert.advance(inp, travelled_m=4.0, dt_s=0.5, speed_mps=8.0)
    assert out.speed_limit_mps == 8.0 and out.limits_ahead == ()  # the lower limit applies now
    assert out.obstacles[0].distance_m == pytest.approx(20.0 - 4.0 + 2.0)
    assert out.light == "none" and out.light_distance_m is None  # passed
    assert out.route_end_m == pytest.approx(46.0) and out.green_left_s == pytest.approx(3.5)
