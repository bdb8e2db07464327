"""The rule-based expert: pure functions from what the ego perceives to a target speed and reason.

`planning.py` gathers an `ExpertInput` from libsumo each 0.1 s step; `decide` turns it into
(target speed, reason). Every rule is a speed cap; the lowest cap wins and its name is the
`expert_reason` (schemas.EXPERT_REASONS). Rules that stop the car for something ahead use the
same comfortable-braking profile: the speed now from which the car can still reach `v_end`
within `distance` at the profile's comfortable deceleration b,

    v = sqrt(v_end^2 + 2 b distance)                                   (approach_speed)

so following the target never asks for more than b. Braking harder is for emergencies only:
`Decision.brake_mps2` is the deceleration needed to stop EMERGENCY_GAP_M short of a vehicle or
person on the path (to match its speed there), when that is more than the vType's decel lets
SUMO brake for a command (at most the profile's emergency deceleration). A car cutting in close
ahead is such a case: braking at decel only, the ego hit it (arterial, build seed 21, episode 5,
"ego hit v40"). SUMO's own safety checks stay on besides (see world.py).

Rules:
    none          cruise at lane limit x profile speed factor
    speed_limit   slow for a lower limit ahead, or when above the limit now
    curve         v^2 * curvature <= lateral acceleration, approached at b
    vehicle       keep the profile's time gap T behind a lead (or a vehicle cutting in): the
                  Krauss safe speed  v = -bT + sqrt((bT)^2 + v_lead^2 + 2 b (gap - min_gap))
                  holds gap - min_gap = v T at equal speeds
    pedestrian    stop `ped_margin` before a pedestrian on or entering the path
    red_light     stop `stop_line_margin` before the line at red, and at yellow when it can
                  stop comfortably (v^2 / 2b <= distance); otherwise it goes on through. At a
                  green that ends too soon for the car to clear the junction (it would need
                  longer than the green left plus YELLOW_S at the speed the junction's curves
                  allow, at least CLEAR_SPEED_MPS, and it can still stop comfortably before
                  the line), wait for the next green: lingering inside into the crossing phase
                  got the ego hit (arterial seed 284, "v51 hit ego"; arterial, build seed 0,
                  episode 20, "v182 hit ego": a left turn begun at 14 m/s, 1 s before yellow)
    stop_sign     come to a full stop at the stop line until `stop_done` (rules.py holds the
                  stop for `STOP_WAIT_S` and until no other vehicle is inside the junction), then
                  SUMO's right-of-way model decides when to enter; still at the line, the car
                  also waits while another vehicle is inside the junction or due within
                  FOE_GAP_S (SUMO let it enter ahead of a car turning across it: "ego hit v65",
                  mixed, build seed 0, episode 44)
    route_end     stop at the end of a route that cannot be extended
    junction      keep the junction clear: stop before its entry while something slow or
                  standing (a vehicle, or a person on a crossing, or crossing traffic) inside
                  it or beyond its exit leaves no room for the whole car past the exit, or
                  while a foe vehicle is within FOE_GAP_S of a junction where the ego's turn
                  would give way inside it (one standing at a stop line into it counts: it
                  may start at any moment, perception.foe_eta_s); unless the car can no
                  longer stop before the entry (then it goes on); also reported by world.py
                  when SUMO's right-of-way model holds the ego back
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from datagen.world.behaviour import EGO_DECEL_SLACK, Profile

STOP_LINE_MARGIN_M = 1.0  # the ego's front stops this far before a red light's stop line
STOP_SIGN_MARGIN_M = 0.5  # ... and this far before a stop sign's line
STOP_WAIT_S = 1.0  # a full stop at a stop sign lasts at least this long
STOPPED_MPS = 0.1  # "stopped" (the tests' threshold)
MIN_CURVATURE_1PM = 1.0 / 300.0  # gentler curves than radius 300 m never limit speed
# Keep the junction clear: room needed beyond its exit = the ego's length (4.7 m) + 1.3 m, and
# what counts as blocking it: anything moving slower than this along the path.
KEEP_CLEAR_ROOM_M = 6.0
BLOCKING_MPS = 2.0
# A turn that gives way inside the junction (SUMO's internal waiting point) is not begun while a
# foe vehicle is less than this far from the junction: waiting inside, the car's front can
# reach into the foe's lane (measured: a "v77 hit ego (junction)" collision in the spider town).
FOE_GAP_S = 5.0
# A green is not entered when clearing the junction at (at least) this speed would outlast the
# green left plus the shortest yellow (SUMO's tls default: 3 s); see light_rule.
CLEAR_SPEED_MPS = 4.0
YELLOW_S = 3.0
# A green that ends too soon is still stopped for at up to the ego vType's decel
# (EGO_DECEL_SLACK x the comfortable deceleration): with the comfort limit only, a car that
# began braking for it on the boundary fell behind its profile and went on into a left turn 1 s
# before yellow ("v182 hit ego", arterial, build seed 0, episode 20).
EMERGENCY_GAP_M = 1.0  # emergency braking stops this short of a vehicle or person on the path


@dataclass(frozen=True)
class Obstacle:
    """Something on (or entering) the ego's path ahead.

    Attributes:
        distance_m: free distance along the path from the ego's front to the obstacle's
            nearest extent, m (may be <= 0 when touching).
        speed_mps: its speed along the path, m/s (0 for something crossing).
        kind: "vehicle" or "pedestrian".
        track_id: who it is (diagnostics only; the rules ignore it).
    """

    distance_m: float
    speed_mps: float
    kind: str
    track_id: str = ""


@dataclass(frozen=True)
class ExpertInput:
    """What the expert perceives at one step (distances along the route from the ego's front).

    Attributes:
        speed_mps: ego speed now.
        speed_limit_mps: limit of the lane the ego is on.
        limits_ahead: (distance_m, limit_mps) of lower limits on later lanes of the route.
        curvature_ahead: (distance_m, curvature_1pm) samples of the path ahead (1/m, >= 0).
        obstacles: vehicles and pedestrians on or entering the path.
        light: "none", "red", "yellow" or "green" of the next signal on the route.
        light_distance_m: distance to its stop line; None without a signal.
        stop_distance_m: distance to the next stop-controlled entry's line; None without one.
        stop_done: the ego has completed its full stop at that entry.
        route_end_m: distance to the end of a route that will not be extended; None otherwise.
        junction_entry_m, junction_exit_m: distance to the next junction's entry (its first
            internal lane) and exit (the lane after it) while the ego is before it; None
            inside a junction or without one ahead.
        waits_inside: the ego's link there gives way at a waiting point inside the junction.
        foe_eta_s: soonest arrival of another vehicle at that junction, s; None if none.
        green_left_s: seconds until a green `light` at that junction ends; None if unknown.
        stop_foe_eta_s: soonest arrival of another vehicle at the stop-controlled junction
            ahead (0 inside it), s; None if none or no stop ahead.
    """

    speed_mps: float
    speed_limit_mps: float
    limits_ahead: tuple[tuple[float, float], ...] = ()
    curvature_ahead: tuple[tuple[float, float], ...] = ()
    obstacles: tuple[Obstacle, ...] = ()
    light: str = "none"
    light_distance_m: float | None = None
    stop_distance_m: float | None = None
    stop_done: bool = False
    route_end_m: float | None = None
    junction_entry_m: float | None = None
    junction_exit_m: float | None = None
    waits_inside: bool = False
    foe_eta_s: float | None = None
    green_left_s: float | None = None
    stop_foe_eta_s: float | None = None


@dataclass(frozen=True)
class Decision:
    """The expert's command: target speed (m/s), the binding rule (schemas.EXPERT_REASONS) and
    the braking an emergency needs (m/s^2; 0 when braking at the vType's decel suffices)."""

    target_speed_mps: float
    reason: str
    brake_mps2: float = 0.0


def approach_speed(distance_m: float, v_end_mps: float, decel_mps2: float) -> float:
    """Highest speed now from which `v_end_mps` is reached within `distance_m` at `decel_mps2`."""
    return math.sqrt(v_end_mps * v_end_mps + 2.0 * decel_mps2 * max(0.0, distance_m))


def follow_speed(gap_m: float, lead_speed_mps: float, p: Profile) -> float:
    """Krauss safe speed keeping the profile's time gap behind a lead `gap_m` ahead."""
    b, tau = p.ego_comfort_decel_mps2, p.ego_time_gap_s
    free = max(0.0, gap_m - p.ego_min_gap_m)
    v_lead = max(0.0, lead_speed_mps)
    return max(0.0, -b * tau + math.sqrt((b * tau) ** 2 + v_lead * v_lead + 2.0 * b * free))


def cruise_rule(inp: ExpertInput, p: Profile) -> float:
    return inp.speed_limit_mps * p.ego_speed_factor


def speed_limit_rule(inp: ExpertInput, p: Profile) -> float:
    b = p.ego_comfort_decel_mps2
    caps = [approach_speed(d, lim * p.ego_speed_factor, b) for d, lim in inp.limits_ahead]
    return min(caps, default=math.inf)


def curve_rule(inp: ExpertInput, p: Profile) -> float:
    b, a_lat = p.ego_comfort_decel_mps2, p.ego_lat_accel_mps2
    caps = [
        approach_speed(d, math.sqrt(a_lat / k), b)
        for d, k in inp.curvature_ahead
        if k > MIN_CURVATURE_1PM
    ]
    return min(caps, default=math.inf)


def vehicle_rule(inp: ExpertInput, p: Profile) -> float:
    caps = [
        follow_speed(o.distance_m, o.speed_mps, p) for o in inp.obstacles if o.kind != "pedestrian"
    ]
    return min(caps, default=math.inf)


def pedestrian_rule(inp: ExpertInput, p: Profile) -> float:
    b = p.ego_comfort_decel_mps2
    caps = [
        approach_speed(o.distance_m - p.ego_ped_margin_m, 0.0, b)
        for o in inp.obstacles
        if o.kind == "pedestrian"
    ]
    return min(caps, default=math.inf)


def clear_time_s(inp: ExpertInput, p: Profile) -> float:
    """Seconds until the front is KEEP_CLEAR_ROOM_M past the junction's exit: to the entry at
    the present speed, then through the junction at the speed its curves allow (a left turn
    is driven at ~6 m/s however fast the car comes), both at least CLEAR_SPEED_MPS."""
    entry = inp.junction_entry_m or 0.0
    v = max(inp.speed_mps, CLEAR_SPEED_MPS)
    inside = [
        math.sqrt(p.ego_lat_accel_mps2 / k)
        for d, k in inp.curvature_ahead
        if entry <= d <= inp.junction_exit_m and k > MIN_CURVATURE_1PM
    ]
    v_in = max(min([v, *inside]), CLEAR_SPEED_MPS)
    return entry / v + (inp.junction_exit_m - entry + KEEP_CLEAR_ROOM_M) / v_in


def light_rule(inp: ExpertInput, p: Profile) -> float:
    if inp.light_distance_m is None:
        return math.inf
    b = p.ego_comfort_decel_mps2
    room = inp.light_distance_m - STOP_LINE_MARGIN_M
    v = inp.speed_mps
    if inp.light == "green":
        if inp.green_left_s is None or inp.junction_exit_m is None:
            return math.inf
        t_clear = clear_time_s(inp, p)
        if t_clear <= inp.green_left_s + YELLOW_S:
            return math.inf  # clears it in time
        if v * v / (2.0 * EGO_DECEL_SLACK * b) > inp.light_distance_m:
            return math.inf  # cannot stop before it at the firmest commanded braking: go on
        return approach_speed(room, 0.0, b)
    if inp.light not in ("red", "yellow"):
        return math.inf
    if inp.light == "yellow" and v * v / (2.0 * b) > room + 0.5:
        return math.inf  # cannot stop comfortably: clear the junction on yellow
    if inp.light == "red" and v * v / (2.0 * p.emergency_decel_mps2) > inp.light_distance_m:
        return math.inf  # committed on yellow and past the point of stopping: go on
    return approach_speed(room, 0.0, b)


def stop_sign_rule(inp: ExpertInput, p: Profile) -> float:
    if inp.stop_distance_m is None:
        return math.inf
    if inp.stop_done:
        foe = inp.stop_foe_eta_s is not None and inp.stop_foe_eta_s < FOE_GAP_S
        if not (foe and inp.speed_mps < BLOCKING_MPS and inp.stop_distance_m > 0.0):
            return math.inf  # the stop is done and no foe is near: SUMO's right of way decides
    return approach_speed(inp.stop_distance_m - STOP_SIGN_MARGIN_M, 0.0, p.ego_comfort_decel_mps2)


def route_end_rule(inp: ExpertInput, p: Profile) -> float:
    if inp.route_end_m is None:
        return math.inf
    return approach_speed(inp.route_end_m - 2.0, 0.0, p.ego_comfort_decel_mps2)


def junction_rule(inp: ExpertInput, p: Profile) -> float:
    if inp.junction_entry_m is None or inp.junction_exit_m is None:
        return math.inf
    need = inp.junction_exit_m + KEEP_CLEAR_ROOM_M
    blocked = any(
        inp.junction_entry_m - 0.5 < o.distance_m < need and o.speed_mps < BLOCKING_MPS
        for o in inp.obstacles
    )
    if inp.waits_inside and inp.foe_eta_s is not None and inp.foe_eta_s < FOE_GAP_S:
        blocked = True  # do not start a turn that would have to wait inside, a foe is near
    if not blocked:
        return math.inf
    v = inp.speed_mps
    if v * v / (2.0 * p.emergency_decel_mps2) > inp.junction_entry_m:
        return math.inf  # past the point of stopping before it: clear it instead
    return approach_speed(inp.junction_entry_m - STOP_LINE_MARGIN_M, 0.0, p.ego_comfort_decel_mps2)


# Order matters only for ties: the first rule with the lowest cap names the reason.
RULES = (
    ("red_light", light_rule),
    ("stop_sign", stop_sign_rule),
    ("pedestrian", pedestrian_rule),
    ("vehicle", vehicle_rule),
    ("curve", curve_rule),
    ("speed_limit", speed_limit_rule),
    ("route_end", route_end_rule),
    ("junction", junction_rule),
)


def emergency_brake_mps2(inp: ExpertInput, p: Profile, decel_mps2: float) -> float:
    """Deceleration (m/s^2) that slows the ego to each obstacle's speed EMERGENCY_GAP_M short of
    it, the highest over the obstacles, capped at the profile's emergency deceleration; 0 when
    `decel_mps2` (what SUMO allows a command) suffices. Treating the obstacle as standing where
    it is now errs on the safe side."""
    v = inp.speed_mps
    need = 0.0
    for o in inp.obstacles:
        v_o = max(0.0, o.speed_mps)
        if v_o >= v:
            continue
        room = max(o.distance_m - EMERGENCY_GAP_M, 0.1)
        need = max(need, (v * v - v_o * v_o) / (2.0 * room))
    return min(need, p.emergency_decel_mps2) if need > decel_mps2 else 0.0


def decide(inp: ExpertInput, p: Profile, decel_mps2: float = math.inf) -> Decision:
    """Target speed and reason: the minimum over the rules' caps, and the emergency braking
    beyond `decel_mps2` (the vType's decel; inf: none) that the obstacles need (module
    docstring)."""
    target, reason = cruise_rule(inp, p), "none"
    if inp.speed_mps > target + 0.5:
        reason = "speed_limit"  # above the (profile-scaled) limit now: slowing to it
    for name, rule in RULES:
        cap = rule(inp, p)
        if cap < target:
            target, reason = cap, name
    # Below walking pace towards a stop point, snap to 0 so the car really stands still.
    if target < 0.3 and reason in ("red_light", "stop_sign", "pedestrian", "route_end", "junction"):
        target = 0.0
    return Decision(max(0.0, target), reason, emergency_brake_mps2(inp, p, decel_mps2))


# ---------------------------------------------------------------- the expert's plan from a state


def advance(inp: ExpertInput, travelled_m: float, dt_s: float, speed_mps: float) -> ExpertInput:
    """`inp` after the ego's front moved `travelled_m` along its path in `dt_s`, now at
    `speed_mps`, in a constant-velocity world: every distance ahead shrinks by `travelled_m`,
    an obstacle moves on along the path at its own speed, timers run down by `dt_s`, and signal
    states stay as they are. What has been passed is dropped (a lower limit passed becomes the
    lane's limit)."""

    def ahead(d: float | None, behind_m: float = 0.0) -> float | None:
        return None if d is None or d - travelled_m < -behind_m else d - travelled_m

    limit = inp.speed_limit_mps
    limits = []
    for d, lim in inp.limits_ahead:
        if d - travelled_m <= 0.0:
            limit = lim
        else:
            limits.append((d - travelled_m, lim))
    exit_m = ahead(inp.junction_exit_m)
    entry_m = ahead(inp.junction_entry_m, math.inf) if exit_m is not None else None
    timer = lambda t: None if t is None else t - dt_s  # noqa: E731
    return ExpertInput(
        speed_mps=speed_mps,
        speed_limit_mps=limit,
        limits_ahead=tuple(limits),
        curvature_ahead=tuple(
            (d - travelled_m, k) for d, k in inp.curvature_ahead if d - travelled_m >= -1.0
        ),
        obstacles=tuple(
            Obstacle(
                o.distance_m - travelled_m + max(0.0, o.speed_mps) * dt_s,
                o.speed_mps,
                o.kind,
                o.track_id,
            )
            for o in inp.obstacles
        ),
        light=inp.light if ahead(inp.light_distance_m) is not None else "none",
        light_distance_m=ahead(inp.light_distance_m),
        stop_distance_m=ahead(inp.stop_distance_m, 1.0),
        stop_done=inp.stop_done,
        route_end_m=ahead(inp.route_end_m, math.inf),
        junction_entry_m=entry_m if entry_m is None or entry_m > 0.0 else None,
        junction_exit_m=exit_m if entry_m is not None and entry_m > 0.0 else None,
        waits_inside=inp.waits_inside,
        foe_eta_s=timer(inp.foe_eta_s),
        green_left_s=timer(inp.green_left_s),
        stop_foe_eta_s=timer(inp.stop_foe_eta_s),
    )


def rollout(
    inp: ExpertInput,
    p: Profile,
    times_s: tuple[float, ...],
    decel_mps2: float = math.inf,
    dt_s: float = 0.1,
) -> tuple[tuple[float, ...], Decision]:
    """How far (m, along its path) the expert's front gets by each of `times_s` (s, ascending)
    from the state `inp` describes, and its decision now.

    The decision is re-taken every `dt_s` on `advance`d input, and the speed follows it as SUMO
    moves the expert's car: towards the target at most at the profile's acceleration and at
    `decel_mps2` (the vType's decel; an emergency brakes at `Decision.brake_mps2`). The rest of
    the world keeps its velocity: the expert's plan under that assumption, which it revises
    every step as the recorded expert does."""
    first = decide(inp, p, decel_mps2)
    out: list[float] = []
    s, v, t, cur, dec = 0.0, inp.speed_mps, 0.0, inp, first
    k = 0
    while k < len(times_s):
        down = dec.brake_mps2 if dec.brake_mps2 > 0.0 else decel_mps2
        v1 = min(max(dec.target_speed_mps, v - down * dt_s), v + p.ego_accel_mps2 * dt_s)
        v1 = max(v1, 0.0)
        ds = 0.5 * (v + v1) * dt_s
        s, v, t = s + ds, v1, t + dt_s
        while k < len(times_s) and t >= times_s[k] - 1e-9:
            out.append(s)
            k += 1
        cur = advance(cur, ds, dt_s, v)
        dec = decide(cur, p, decel_mps2)
    return tuple(out), first
