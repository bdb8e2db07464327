"""Scoring as the CARLA leaderboard 1.0: one table of penalties, RC, IS and DS per route, and
the benchmark's aggregates.

Source: carla-simulator/leaderboard (1.0), `leaderboard/utils/statistics_manager.py`
(penalty coefficients, DS = RC x IS per route, infractions per km driven),
`leaderboard/scenarios/route_scenario.py` (the route timeout, the criteria and their settings)
and scenario_runner 0.9.10's `atomic_criteria.py` (RouteCompletionTest, InRouteTest,
CollisionTest, RunningRedLightTest, RunningStopTest). Definitions:

- RC_i (%): the share of the route's length completed (the ego's front projected on the
  route, never going back); 100 once it is over COMPLETE_PCT and the front is within
  END_DISTANCE_M of the route's end (RouteCompletionTest), else the share itself (99.5 stays
  99.5).
- IS_i = prod_j p_j^n_j x (1 - off_route_share): n_j events of infraction type j with
  penalty p_j (PENALTIES); off-route driving multiplies by one minus the share of the driven
  distance spent outside the route's lanes (leaderboard: "outside route lanes").
- DS_i = RC_i x IS_i. The benchmark's DS is the mean of DS_i over routes (not mean RC x mean IS).
- Repetitions (`drive eval --repetitions N`, the leaderboard's `--repetitions`): a route's RC,
  IS, DS and per-km rates are first averaged over its repetitions; means and 95 % intervals
  are then taken over routes, the unit the benchmark samples.
- Rates per km (the paper's Table III): per route, count / km driven (RC_i x route length),
  averaged over the routes that drove any distance.
- Route deviation, agent blocked and timeout carry no penalty: they end the route, which ends
  RC there.
- A route that could not be driven (the simulation failed: `failure` in its result) scores
  RC 0, IS 1, DS 0 and counts in the means, as the leaderboard records a crashed route
  ("Failed - Simulation crashed"); the summary lists it with its reason.

Where this project differs from leaderboard 1.0, and why:
- Per-km rates: leaderboard 1.0 adds the routes' rates up (compute_global_statistics never
  divides them by the number of routes), so a benchmark's rate grows with its number of
  routes; we average them. Routes with no distance driven are skipped in both.
- RC is measured at the front bumper, not the vehicle's origin: a SUMO route ends where the
  front reaches the end of its last lane (SUMO takes a car out there), so a centre could
  never reach it.
- Blocked after BLOCKED_S = 90 s below 0.1 m/s, not 180 s: SUMO teleports a car that has
  waited sumo.TELEPORT_S (90 s), and a jammed expert ego with it.
- A red light is run when the front crosses a stop line whose own signal is red; the
  leaderboard judges the tail crossing (a car length later).
- A stop counts within STOP_ZONE_M before the stop line; the leaderboard's RunningStopTest
  accepts a stop anywhere in the sign's trigger volume or 20 m before it.
- Mounting the kerb (a wheel on a sidewalk) is a layout collision; CARLA's kerbs are
  physical, and its CollisionTest ignores sidewalk contacts. Nothing stops a placed car in
  SUMO, so the judge has to.
- Collisions are judged from the agents' boxes (SUMO misses collisions of a placed vehicle,
  eclipse-sumo/sumo#6327), with CollisionTest's debounce: the same agent again only after
  COLLISION_ID_S, nothing within COLLISION_AREA_M of an earlier collision's place.
  Bicycles are vehicles (0.60), as in CARLA, where they are vehicle actors.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# Penalty per event (statistics_manager.py: PENALTY_COLLISION_PEDESTRIAN ... PENALTY_STOP).
PENALTIES: dict[str, float] = {
    "collision_pedestrian": 0.50,  # pedestrians (bicycles are vehicles, as in CARLA)
    "collision_vehicle": 0.60,
    "collision_layout": 0.65,  # the leaderboard's "static" collisions: buildings, kerbs, poles
    "red_light": 0.70,
    "stop_sign": 0.80,
}
# Events that end the route and carry no penalty of their own.
ENDING = ("route_deviation", "agent_blocked", "route_timeout")
# Everything counted per km, in the column order (and with the short names) of Table III.
TABLE_COLUMNS: tuple[tuple[str, str], ...] = (
    ("collision_pedestrian", "Ped"),
    ("collision_vehicle", "Veh"),
    ("collision_layout", "Lay"),
    ("red_light", "Red"),
    ("stop_sign", "Stop"),
    ("off_road", "OR"),
    ("route_deviation", "Dev"),
    ("route_timeout", "TO"),
    ("agent_blocked", "Block"),
)
INFRACTION_TYPES = tuple(k for k, _ in TABLE_COLUMNS)

# route_scenario.py: the agent gets INITIAL_SECONDS_DELAY + SECONDS_GIVEN_PER_METERS x length.
TIMEOUT_INITIAL_S = 5.0
TIMEOUT_S_PER_M = 0.8
BLOCKED_S = 90.0  # ActorSpeedAboveThresholdTest: below BLOCKED_SPEED_MPS this long
BLOCKED_SPEED_MPS = 0.1
DEVIATION_M = 30.0  # InRouteTest (offroad_max): farther than this from the route ends it
DEVIATION_SHARE = 0.30  # InRouteTest: ... and so does more than this share of the route driven
# farther than DEVIATION_M / 2 (offroad_min) from it
COMPLETE_PCT = 99.0  # RouteCompletionTest: over this share ...
END_DISTANCE_M = 10.0  # ... and within this distance of the route's end: the route is complete


def route_timeout_s(route_length_m: float) -> float:
    """Simulated seconds a route may take (leaderboard 1.0's estimate)."""
    return TIMEOUT_INITIAL_S + TIMEOUT_S_PER_M * route_length_m


@dataclass(frozen=True)
class RouteScore:
    """Scores of one drive of a route.

    Attributes:
        rc: route completion, % (0..100).
        infraction_score: IS, 0..1.
        ds: driving score, % (rc x infraction_score).
        counts: events per type (INFRACTION_TYPES), each counted once per event.
        off_route_share: share of the driven distance outside the route's lanes, 0..1.
        km_driven: rc / 100 x route length, km (what the per-km rates divide by).
        route_id: the route driven (repetitions of one route share it; "" = its own route).
        failed: the drive could not be run (RC 0, IS 1, DS 0; module docstring).
    """

    rc: float
    infraction_score: float
    ds: float
    counts: dict[str, int]
    off_route_share: float
    km_driven: float
    route_id: str = ""
    failed: bool = False


def score_route(
    rc_pct: float,
    counts: dict[str, int],
    off_route_share: float,
    route_length_m: float,
    route_id: str = "",
) -> RouteScore:
    """DS_i = RC_i x prod_j p_j^n_j x (1 - off_route_share) (module docstring). `rc_pct` is
    the tracker's RC: 100 only for a completed route, anything less stays as it is."""
    unknown = set(counts) - set(INFRACTION_TYPES)
    if unknown:
        raise ValueError(f"unknown infraction types {sorted(unknown)}")
    rc = min(100.0, max(0.0, float(rc_pct)))
    penalty = 1.0
    for kind, p in PENALTIES.items():
        penalty *= p ** int(counts.get(kind, 0))
    share = min(1.0, max(0.0, float(off_route_share)))
    penalty *= 1.0 - share
    full = {k: int(counts.get(k, 0)) for k in INFRACTION_TYPES}
    return RouteScore(
        rc=rc,
        infraction_score=penalty,
        ds=rc * penalty,
        counts=full,
        off_route_share=share,
        km_driven=rc / 100.0 * route_length_m / 1000.0,
        route_id=route_id,
    )


def failed_route(route_id: str = "") -> RouteScore:
    """The score of a route whose drive failed: RC 0, IS 1, DS 0 (module docstring)."""
    zero = {k: 0 for k in INFRACTION_TYPES}
    return RouteScore(0.0, 1.0, 0.0, zero, 0.0, 0.0, route_id, failed=True)


@dataclass(frozen=True)
class Summary:
    """A benchmark's aggregates over its routes.

    Attributes:
        n_routes: routes scored (the unit of the means and intervals).
        ds, rc, is_: means over routes (DS and RC in %, IS 0..1) of the routes' means over
            their repetitions.
        ds_ci, rc_ci, is_ci: half-width of the 95% confidence interval of each mean (Student's
            t over routes; 0 for a single route).
        per_km: mean over routes (that drove any distance) of count / km driven, per type
            (INFRACTION_TYPES).
        km_driven: total km driven (all repetitions).
        n_drives: drives scored (routes x repetitions).
        n_failed: drives that failed (scored DS 0).
    """

    n_routes: int
    ds: float
    rc: float
    is_: float
    ds_ci: float
    rc_ci: float
    is_ci: float
    per_km: dict[str, float]
    km_driven: float
    n_drives: int = 0
    n_failed: int = 0


def ci95(values: Sequence[float]) -> float:
    """Half-width of the 95% confidence interval of the mean (Student's t), 0 for n < 2."""
    x = np.asarray(values, dtype=np.float64)
    if len(x) < 2:
        return 0.0
    from scipy.stats import t

    return float(t.ppf(0.975, len(x) - 1) * x.std(ddof=1) / math.sqrt(len(x)))


def _rates(s: RouteScore) -> dict[str, float] | None:
    """Events per km driven of one drive; None if it drove nothing (no rate to speak of)."""
    if s.km_driven <= 0.0:
        return None
    return {k: s.counts[k] / s.km_driven for k in INFRACTION_TYPES}


def per_route(scores: Sequence[RouteScore]) -> list[dict]:
    """One record per route: its DS, RC, IS and per-km rates averaged over its repetitions
    (drives with the same route_id; a drive without one is a route of its own), in order of
    first appearance. `per_km` is None for a route that never drove any distance."""
    groups: dict[str, list[RouteScore]] = {}
    for i, s in enumerate(scores):
        groups.setdefault(s.route_id or f"#{i}", []).append(s)
    out = []
    for rid, g in groups.items():
        rates = [r for r in map(_rates, g) if r is not None]
        out.append(
            {
                "route_id": rid,
                "drives": len(g),
                "ds": float(np.mean([s.ds for s in g])),
                "rc": float(np.mean([s.rc for s in g])),
                "is": float(np.mean([s.infraction_score for s in g])),
                "per_km": (
                    {k: float(np.mean([r[k] for r in rates])) for k in INFRACTION_TYPES}
                    if rates
                    else None
                ),
            }
        )
    return out


def summarise(scores: Sequence[RouteScore]) -> Summary:
    """Mean DS, RC, IS with 95% CIs over routes (repetitions averaged first) and per-km rates
    (module docstring)."""
    if not scores:
        raise ValueError("no routes to summarise")
    routes = per_route(scores)
    ds = [r["ds"] for r in routes]
    rc = [r["rc"] for r in routes]
    is_ = [r["is"] for r in routes]
    rates = [r["per_km"] for r in routes if r["per_km"] is not None]
    per_km = {k: float(np.mean([r[k] for r in rates])) if rates else 0.0 for k in INFRACTION_TYPES}
    return Summary(
        n_routes=len(routes),
        ds=float(np.mean(ds)),
        rc=float(np.mean(rc)),
        is_=float(np.mean(is_)),
        ds_ci=ci95(ds),
        rc_ci=ci95(rc),
        is_ci=ci95(is_),
        per_km=per_km,
        km_driven=float(sum(s.km_driven for s in scores)),
        n_drives=len(scores),
        n_failed=sum(s.failed for s in scores),
    )


def format_table(rows: Sequence[tuple[str, Summary]]) -> str:
    """Rows of (name, Summary) in the layout of the paper's Table III: DS, RC, IS with their
    95% CI, then infractions per km (Ped, Veh, Lay, Red, Stop, OR, Dev, TO, Block)."""
    head = f"{'policy':<18} {'DS':>13} {'RC':>13} {'IS':>11} | " + " ".join(
        f"{short:>5}" for _, short in TABLE_COLUMNS
    )
    lines = [head, "-" * len(head)]
    for name, s in rows:
        lines.append(
            f"{name:<18} {s.ds:>6.2f}±{s.ds_ci:<6.2f} {s.rc:>6.2f}±{s.rc_ci:<6.2f} "
            f"{s.is_:>5.2f}±{s.is_ci:<5.2f} | "
            + " ".join(f"{s.per_km[k]:>5.2f}" for k, _ in TABLE_COLUMNS)
        )
    return "\n".join(lines)
