"""Weather and behaviour profiles: one table governs all traffic and the expert ego.

The paper (Sec. IV-A) records sunny and cloudy episodes with normal or aggressive traffic and
rainy and foggy episodes with cautious traffic. A `Profile` is one row of that table: the SUMO
vType parameters applied to every background vehicle (car-following, dawdling, junction model)
and the expert ego's own target speed factor, time gap and comfortable deceleration, so that
driving in rain and fog is slower and keeps longer gaps in the data too.

SUMO parameter meanings (sumo.dlr.de "Definition of Vehicles, Vehicle Types, and Routes"):
speedFactor/speedDev: desired speed as a multiple of the lane limit (normal distribution);
tau: the driver's desired time headway (s); minGap: standstill gap (m); accel/decel: comfortable
acceleration/deceleration (m/s^2); emergencyDecel: the physical limit; sigma: Krauss dawdling
(0..1); impatience: how much a waiting driver accepts smaller gaps (0..1); jmTimegapMinor: time
gap a vehicle on a minor road needs before a priority vehicle arrives (s); jmCrossingGap: gap to
pedestrians on a crossing a vehicle needs to pass (m); jmStoplineGap: distance to the stop line
at which a vehicle stops at a stop sign/red (m); lcAssertive: willingness to accept smaller
gaps when changing lanes. `jmIgnoreFoeProb` is left at 0 for all profiles: no profile ignores
right of way (that would produce collisions the data should not contain).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas import BEHAVIOURS, WEATHERS

# The ego vType's decel (the cap on commanded braking) is this much above the comfortable
# deceleration the expert plans with (Profile.ego_comfort_decel_mps2): room to track the planned
# profile at a 0.1 s step without overshooting stop points (measured: at exactly b a red-light
# stop ends ~0.7 m further). The expert's firmest stop for a green that ends too soon uses it.
EGO_DECEL_SLACK = 1.2


@dataclass(frozen=True)
class Profile:
    """One behaviour profile (traffic vType parameters + ego expert parameters).

    Attributes (traffic, SUMO vType):
        speed_factor, speed_dev: desired speed / lane limit, mean and std.
        tau_s: desired time headway, s.
        min_gap_m: standstill gap, m.
        accel_mps2, decel_mps2, emergency_decel_mps2: m/s^2.
        sigma: Krauss dawdling, 0..1.
        impatience: 0..1.
        jm_timegap_minor_s: gap a minor-road driver accepts before a priority vehicle, s.
        jm_crossing_gap_m: gap to pedestrians on a crossing a driver accepts, m.
        lc_assertive: lane-change gap acceptance factor (>1: accepts smaller gaps).
    Attributes (expert ego, see expert.py):
        ego_speed_factor: target speed / lane limit.
        ego_time_gap_s: time gap kept to the lead vehicle, s.
        ego_min_gap_m: standstill gap to the lead vehicle, m.
        ego_comfort_decel_mps2: deceleration the expert plans with, m/s^2.
        ego_accel_mps2: ego acceleration, m/s^2.
        ego_lat_accel_mps2: lateral acceleration allowed in curves, m/s^2.
        ego_ped_margin_m: distance kept to a pedestrian on the path, m.
    Attributes (scene):
        traffic_density: background vehicles per car-lane-km around the ego (tuned so that
            queues form at signals but jams that block the ego for minutes stay rare).
        pedestrian_density: pedestrians per sidewalk-km around the ego.
    """

    name: str
    speed_factor: float
    speed_dev: float
    tau_s: float
    min_gap_m: float
    accel_mps2: float
    decel_mps2: float
    emergency_decel_mps2: float
    sigma: float
    impatience: float
    jm_timegap_minor_s: float
    jm_crossing_gap_m: float
    lc_assertive: float
    ego_speed_factor: float
    ego_time_gap_s: float
    ego_min_gap_m: float
    ego_comfort_decel_mps2: float
    ego_accel_mps2: float
    ego_lat_accel_mps2: float
    ego_ped_margin_m: float
    traffic_density: float
    pedestrian_density: float


# The documented table. Direction of every column: cautious < normal < aggressive in speed and
# acceleration, > in gaps and time headways. Normal follows SUMO's defaults (tau 1 s, minGap 2.5 m,
# accel 2.6, decel 4.5, sigma 0.5); the others deviate by roughly 30 %.
PROFILES: dict[str, Profile] = {
    "normal": Profile(
        name="normal",
        speed_factor=1.0,
        speed_dev=0.1,
        tau_s=1.0,
        min_gap_m=2.5,
        accel_mps2=2.6,
        decel_mps2=4.5,
        emergency_decel_mps2=9.0,
        sigma=0.5,
        impatience=0.0,
        jm_timegap_minor_s=1.0,
        jm_crossing_gap_m=10.0,
        lc_assertive=1.0,
        ego_speed_factor=0.95,
        ego_time_gap_s=1.5,
        ego_min_gap_m=3.0,
        ego_comfort_decel_mps2=2.5,
        ego_accel_mps2=2.0,
        ego_lat_accel_mps2=2.5,
        ego_ped_margin_m=4.0,
        traffic_density=7.0,
        pedestrian_density=4.0,
    ),
    "aggressive": Profile(
        name="aggressive",
        speed_factor=1.15,
        speed_dev=0.1,
        tau_s=0.6,
        min_gap_m=1.5,
        accel_mps2=3.5,
        decel_mps2=5.5,
        emergency_decel_mps2=9.0,
        sigma=0.3,
        impatience=0.5,
        jm_timegap_minor_s=0.5,
        jm_crossing_gap_m=6.0,
        lc_assertive=2.0,
        ego_speed_factor=1.05,
        ego_time_gap_s=1.0,
        ego_min_gap_m=2.0,
        ego_comfort_decel_mps2=3.0,
        ego_accel_mps2=2.8,
        ego_lat_accel_mps2=3.2,
        ego_ped_margin_m=3.0,
        traffic_density=8.5,
        pedestrian_density=4.0,
    ),
    "cautious": Profile(
        name="cautious",
        speed_factor=0.85,
        speed_dev=0.05,
        tau_s=1.8,
        min_gap_m=3.5,
        accel_mps2=1.8,
        decel_mps2=3.5,
        emergency_decel_mps2=9.0,
        sigma=0.2,
        impatience=0.0,
        jm_timegap_minor_s=2.0,
        jm_crossing_gap_m=14.0,
        lc_assertive=0.7,
        ego_speed_factor=0.75,
        ego_time_gap_s=2.5,
        ego_min_gap_m=4.5,
        ego_comfort_decel_mps2=2.0,
        ego_accel_mps2=1.5,
        ego_lat_accel_mps2=1.8,
        ego_ped_margin_m=5.0,
        traffic_density=6.0,
        pedestrian_density=2.5,  # fewer people walk in rain and fog
    ),
}
assert set(PROFILES) == set(BEHAVIOURS)

# Paper, Sec. IV-A: sunny/cloudy -> normal or aggressive (50/50); rainy/foggy -> cautious.
BEHAVIOURS_BY_WEATHER: dict[str, dict[str, float]] = {
    "sunny": {"normal": 0.5, "aggressive": 0.5},
    "cloudy": {"normal": 0.5, "aggressive": 0.5},
    "rainy": {"cautious": 1.0},
    "foggy": {"cautious": 1.0},
}


def draw_condition(
    rng: np.random.Generator, weather_mix: dict[str, float] | None = None
) -> tuple[str, str]:
    """Draw (weather, behaviour) for one episode.

    Args:
        rng: the episode's generator (two draws are taken from it).
        weather_mix: relative weights per weather (missing ones are 0); default uniform.
    """
    mix = weather_mix or {w: 1.0 for w in WEATHERS}
    unknown = set(mix) - set(WEATHERS)
    if unknown:
        raise ValueError(f"unknown weathers {sorted(unknown)}; expected some of {WEATHERS}")
    p = np.array([max(0.0, float(mix.get(w, 0.0))) for w in WEATHERS])
    if p.sum() <= 0:
        raise ValueError("weather_mix has no positive weight")
    weather = WEATHERS[int(rng.choice(len(WEATHERS), p=p / p.sum()))]
    options = BEHAVIOURS_BY_WEATHER[weather]
    names = list(options)
    q = np.array([options[n] for n in names])
    behaviour = names[int(rng.choice(len(names), p=q / q.sum()))]
    return weather, behaviour


def vtype_attributes(profile: Profile) -> dict[str, str]:
    """The profile as SUMO vType XML attributes (shared by every background vType)."""
    return {
        "speedFactor": f"{profile.speed_factor:g}",
        "speedDev": f"{profile.speed_dev:g}",
        "tau": f"{profile.tau_s:g}",
        "minGap": f"{profile.min_gap_m:g}",
        "accel": f"{profile.accel_mps2:g}",
        "decel": f"{profile.decel_mps2:g}",
        "emergencyDecel": f"{profile.emergency_decel_mps2:g}",
        "sigma": f"{profile.sigma:g}",
        "impatience": f"{profile.impatience:g}",
        "jmTimegapMinor": f"{profile.jm_timegap_minor_s:g}",
        "jmCrossingGap": f"{profile.jm_crossing_gap_m:g}",
        "lcAssertive": f"{profile.lc_assertive:g}",
        "jmIgnoreFoeProb": "0",
    }
