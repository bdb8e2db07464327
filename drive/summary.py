"""A `drive eval` run's per-route results into its summary: the leaderboard's aggregates
(drive/score.py: routes as the unit, repetitions averaged first), failed routes, and the
measures beyond the leaderboard (time-to-collision, traffic delay, standing where the expert
would drive on, creeps), as OUT/summary.json and OUT/summary.txt."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from drive import score
from drive.controller import CreepConfig


def result_name(route_id: str, repetition: int) -> str:
    """File stem of a route's result: the route id, with _rep<r> for repetitions r > 0."""
    return route_id if repetition == 0 else f"{route_id}_rep{repetition}"


def route_score(doc: dict) -> score.RouteScore:
    """The RouteScore of a per-route result document (route ids group repetitions)."""
    rid = doc["route"]["route_id"]
    if doc.get("failure"):
        return score.failed_route(rid)
    return score.score_route(
        doc["rc"], doc["counts"], doc["off_route_share"], doc["route"]["length_m"], rid
    )


def _delay_rate(doc: dict) -> float:
    """Traffic delay per simulated second of a route result."""
    return doc["traffic_delay_s"] / max(doc["sim_s"], 1e-6)


def result_key(doc: dict) -> str:
    """The result name of a per-route result document."""
    return result_name(doc["route"]["route_id"], doc.get("repetition", 0))


def summary_doc(name: str, docs: list[dict], baseline: dict[str, dict] | None = None) -> dict:
    """Aggregates of a run: the Summary (routes as the unit, repetitions averaged first), the
    failed routes with their reasons, plus the extra measures over the drives that ran."""
    s = score.summarise([route_score(d) for d in docs])
    ran = [d for d in docs if not d.get("failure")] or docs
    ttc = [d["min_ttc_s"] for d in ran if d["min_ttc_s"] is not None]
    out = {
        "routes_file": name,
        "policy": docs[0]["policy"],
        **{k: v for k, v in asdict(s).items()},
        "repetitions": max(d.get("repetition", 0) for d in docs) + 1,
        "complete": int(sum(bool(d.get("complete")) for d in docs)),
        "failed": {result_key(d): d["failure"] for d in docs if d.get("failure")},
        "min_ttc_s_median": float(np.median(ttc)) if ttc else None,
        "traffic_delay_s_mean": float(np.mean([d["traffic_delay_s"] for d in ran])),
        "traffic_delay_rate_mean": float(np.mean([_delay_rate(d) for d in ran])),
        "sim_s": float(sum(d["sim_s"] for d in docs)),
        "creeps": int(sum(d.get("creeps", 0) for d in docs)),
        # inertia: seconds standing where the privileged expert would drive on, per route
        "stuck_s_mean": float(np.mean([d.get("stuck_s", 0.0) for d in docs])),
        "standing_s_mean": float(np.mean([d.get("standing_s", 0.0) for d in docs])),
        "routes_with_creeps": int(sum(d.get("creeps", 0) > 0 for d in docs)),
        "wall_s": float(sum(d["timing"]["total"] for d in docs)),
    }
    if baseline:
        delta = [
            _delay_rate(d) - _delay_rate(baseline[result_key(d)])
            for d in ran
            if result_key(d) in baseline and not baseline[result_key(d)].get("failure")
        ]
        out["traffic_delay_rate_vs_baseline_mean"] = float(np.mean(delta)) if delta else None
    return out


def format_summary(doc: dict) -> str:
    s = score.Summary(**{f: doc[f] for f in score.Summary.__dataclass_fields__})
    lines = [score.format_table([(doc["policy"], s)])]
    reps = doc.get("repetitions", 1)
    times = f" x {reps} repetitions (averaged per route)" if reps > 1 else ""
    lines.append(
        f"{s.n_routes} routes{times}, {doc.get('complete', 0)} drives complete, "
        f"{s.km_driven:.2f} km driven, {doc['sim_s']:.0f} s simulated in "
        f"{doc['wall_s']:.0f} s of route wall time; infractions per km; ± 95% CI over routes"
    )
    for key, why in doc.get("failed", {}).items():
        lines.append(f"FAILED {key} (scored DS 0): {why}")
    ttc = doc["min_ttc_s_median"]
    extra = f"median min TTC {ttc:.1f} s" if ttc is not None else "no TTC below 5 s"
    extra += (
        f", traffic delay {doc['traffic_delay_s_mean']:.1f} vehicle-s per route, "
        f"{doc['traffic_delay_rate_mean']:.2f} vehicle-s per second driven"
    )
    if doc.get("traffic_delay_rate_vs_baseline_mean") is not None:
        extra += f" ({doc['traffic_delay_rate_vs_baseline_mean']:+.2f} vs the baseline)"
    lines.append(extra)
    if doc.get("stuck_s_mean"):
        lines.append(
            f"stood {doc['stuck_s_mean']:.1f} s per route where the expert would have driven on "
            f"(of {doc['standing_s_mean']:.1f} s standing)"
        )
    if doc.get("creeps"):
        lines.append(
            f"{doc['creeps']} creep(s) in {doc['routes_with_creeps']} route(s): stood "
            f"{CreepConfig().stuck_s:.0f} s and was pushed forward (drive.controller.Creep)"
        )
    return "\n".join(lines)
