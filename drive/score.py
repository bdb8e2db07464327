"""Scoring as the CARLA leaderboard 1.0: one table of penalties, RC, IS and DS per route, and
the benchmark's aggregates.

Source: carla-simulator/leaderboard (1.0), `leaderboard/utils/statistics_manager.py`
(penalty coefficients, DS = RC x IS per route, infractions per km driven) and
`leaderboard/scenarios/route_scenario.py` (the route timeout). Definitions:

- RC_i (%): the share of the route's length completed (its projection on the route, never
  going back), 100 when the ego reaches the end.
- IS_i = prod_j p_j^n_j x (1 - off_route_share): n_j events of infraction type j with
  penalty p_j (PENALTIES); off-route driving multiplies by one minus the share of the driven
  distance spent outside the route's lanes (leaderboard: "outside route lanes").
- DS_i = RC_i x IS_i. The benchmark's DS is the mean of DS_i over routes (not mean RC x mean IS).
- Rates per km (the paper's Table III): per route, count / km driven (RC_i x route length,
  at least 1 m), averaged over routes, as the leaderboard's global record does.
- Route deviation, agent blocked and timeout carry no penalty: they end the route, which ends
  RC there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# Penalty per event (statistics_manager.py: PENALTY_COLLISION_PEDESTRIAN ... PENALTY_STOP).
PENALTIES: dict[str, float] = {
    "collision_pedestrian": 0.50,  # pedestrians and bicycles
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
DEVIATION_M = 30.0  # InRouteTest: farther than this from the route ends it
COMPLETE_PCT = 99.0  # RouteCompletionTest: this share counts as the whole route


def route_timeout_s(route_length_m: float) -> float:
    """Simulated seconds a route may take (leaderboard 1.0's estimate)."""
    return TIMEOUT_INITIAL_S + TIMEOUT_S_PER_M * route_length_m


@dataclass(frozen=True)
class RouteScore:
    """Scores of one route.

    Attributes:
        rc: route completion, % (0..100).
        infraction_score: IS, 0..1.
        ds: driving score, % (rc x infraction_score).
        counts: events per type (INFRACTION_TYPES), each counted once per event.
        off_route_share: share of the driven distance outside the route's lanes, 0..1.
        km_driven: rc / 100 x route length, km (what the per-km rates divide by).
    """

    rc: float
    infraction_score: float
    ds: float
    counts: dict[str, int]
    off_route_share: float
    km_driven: float


def score_route(
    rc_pct: float, counts: dict[str, int], off_route_share: float, route_length_m: float
) -> RouteScore:
    """DS_i = RC_i x prod_j p_j^n_j x (1 - off_route_share) (module docstring)."""
    unknown = set(counts) - set(INFRACTION_TYPES)
    if unknown:
        raise ValueError(f"unknown infraction types {sorted(unknown)}")
    rc = 100.0 if rc_pct >= COMPLETE_PCT else max(0.0, float(rc_pct))
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
    )


@dataclass(frozen=True)
class Summary:
    """A benchmark's aggregates over its routes.

    Attributes:
        n_routes: routes scored.
        ds, rc, is_: means over routes (DS and RC in %, IS 0..1).
        ds_ci, rc_ci, is_ci: half-width of the 95% confidence interval of each mean (Student's
            t over routes; 0 for a single route).
        per_km: mean over routes of count / km driven, per type (INFRACTION_TYPES).
        km_driven: total km driven.
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


def ci95(values: Sequence[float]) -> float:
    """Half-width of the 95% confidence interval of the mean (Student's t), 0 for n < 2."""
    x = np.asarray(values, dtype=np.float64)
    if len(x) < 2:
        return 0.0
    from scipy.stats import t

    return float(t.ppf(0.975, len(x) - 1) * x.std(ddof=1) / math.sqrt(len(x)))


def summarise(scores: Sequence[RouteScore]) -> Summary:
    """Mean DS, RC, IS with 95% CIs and per-km rates over routes (module docstring)."""
    if not scores:
        raise ValueError("no routes to summarise")
    ds = [s.ds for s in scores]
    rc = [s.rc for s in scores]
    is_ = [s.infraction_score for s in scores]
    per_km = {
        k: float(np.mean([s.counts[k] / max(s.km_driven, 0.001) for s in scores]))
        for k in INFRACTION_TYPES
    }
    return Summary(
        n_routes=len(scores),
        ds=float(np.mean(ds)),
        rc=float(np.mean(rc)),
        is_=float(np.mean(is_)),
        ds_ci=ci95(ds),
        rc_ci=ci95(rc),
        is_ci=ci95(is_),
        per_km=per_km,
        km_driven=float(sum(s.km_driven for s in scores)),
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
