"""REPORT.md's verdicts on synthetic per-route, per-frame and swap tables whose answer is known:
supported, contradicted and undecided, with seeds as a level of their own (at least two routes
and two seeds), and the seen-town route selection."""

import numpy as np
import pytest

from drive.swap import BLOCK_FRAMES
from experiments import report, runner, verdicts


def test_the_interval_collapses_on_constant_data_and_covers_the_mean():
    assert verdicts.hierarchical({0: np.full(5, 3.0)}) == (3.0, 3.0, 3.0)
    est, lo, hi = verdicts.hierarchical({0: np.array([1.0, 2.0, 3.0, 4.0, 5.0])})
    assert est == pytest.approx(3.0) and 1.0 < lo < 3.0 < hi < 5.0
    # the same bootstrap twice: the same interval (its own seeded generator)
    assert verdicts.hierarchical({0: np.arange(7.0)}) == verdicts.hierarchical({0: np.arange(7.0)})


def test_seeds_are_a_level_of_their_own_not_more_routes():
    rng = np.random.default_rng(1)
    # two training seeds far apart, routes tight around each: 20 routes per seed
    units = {0: 10.0 + rng.normal(0, 0.5, 20), 1: 20.0 + rng.normal(0, 0.5, 20)}
    est, lo, hi = verdicts.hierarchical(units)
    assert est == pytest.approx(15.0, abs=0.3)
    pooled = verdicts.hierarchical({0: np.concatenate(list(units.values()))})
    # pooling 40 routes as independent samples claims a far narrower interval than 2 seeds give
    assert (hi - lo) > 3 * (pooled[2] - pooled[1])
    assert hi - lo > 5.0


def _docs(ds_by_route: dict[str, float]) -> list[dict]:
    """Route result documents with DS = RC (no infraction) per route."""
    return [
        {
            "route": {"route_id": r, "length_m": 500.0, "town": "boulevard"},
            "rc": ds,
            "counts": {},
            "off_route_share": 0.0,
            "ds": ds,
            "ended": "route_complete",
        }
        for r, ds in ds_by_route.items()
    ]


ROUTES = ("r0", "r1", "r2")


def _variant(per_seed: dict[int, tuple[float, ...]]) -> dict[int, list[dict]]:
    return {s: _docs(dict(zip(ROUTES, v))) for s, v in per_seed.items()}


def _claim(full, other) -> str:
    held = {"full": _variant(full), "no_bev": _variant(other)}
    text = "\n".join(report._claims(held, {}, {}))
    assert "All tasks drive better than No BEV Map" in text
    return text


def test_paired_route_differences_come_out_supported_contradicted_or_undecided():
    good = {0: (90.0, 85.0, 95.0), 1: (88.0, 92.0, 80.0)}
    bad = {0: (50.0, 55.0, 45.0), 1: (52.0, 48.0, 41.0)}
    assert ": supported (" in _claim(good, bad)
    assert ": contradicted (" in _claim(bad, good)
    mixed = {0: (60.0, 40.0, 55.0), 1: (45.0, 62.0, 50.0)}
    other = {0: (50.0, 50.0, 50.0), 1: (50.0, 50.0, 50.0)}
    assert ": undecided (" in _claim(mixed, other)
    # one route on one seed: no interval
    assert "too few samples" in _claim({0: (90.0,)}, {0: (10.0,)})


def test_pairing_by_route_sees_what_two_independent_means_miss():
    # routes differ a lot (easy and hard), the variant is 5 points worse on every one of them
    full = {0: (95.0, 60.0, 20.0), 1: (94.0, 61.0, 21.0)}
    minus5 = {s: tuple(x - 5.0 for x in v) for s, v in full.items()}
    mean, lo, hi, n, ok = report.paired(_variant(full), _variant(minus5))
    assert mean == pytest.approx(5.0) and lo == pytest.approx(5.0) and hi == pytest.approx(5.0)
    assert n == 6 and ok
    # unpaired, the two intervals overlap entirely
    a, b = report.interval(_variant(full)), report.interval(_variant(minus5))
    assert a[1] < b[2]


def _swap(ratio, lo, hi, frames=4 * BLOCK_FRAMES, per_frame=None):
    doc = {
        "summary": {
            "frames": frames,
            "weathers": ["sunny", "rainy"],
            "speed_ratio": ratio,
            "speed_ratio_ci95": [lo, hi],
        }
    }
    if per_frame is not None:
        doc["per_frame"] = per_frame
    return doc


def test_the_weather_swap_verdict_uses_the_interval_and_its_sign():
    slower = report.swap_claims({"full-s0": _swap(0.8, 0.75, 0.85)})[0]
    assert slower.endswith(": supported.")
    # faster in rain must not support a claim of slowing down (no abs())
    faster = report.swap_claims({"full-s0": _swap(1.2, 1.15, 1.25)})[0]
    assert faster.endswith(": contradicted.")
    # the interval straddles 1: undecided however far the estimate is from 1
    wide = report.swap_claims({"full-s0": _swap(0.85, 0.6, 1.05)})[0]
    assert wide.endswith(": undecided.")
    few = report.swap_claims({"full-s0": _swap(0.8, 0.75, 0.85, frames=3)})[0]
    assert "too few samples" in few


def test_the_no_weather_comparison_is_paired_over_the_same_frames():
    rng = np.random.default_rng(0)
    n = 6 * BLOCK_FRAMES
    t = [0.5 * k for k in range(n)]
    sun = list(10.0 + rng.normal(0, 0.3, n))
    full = {"time_s": t, "speed_mps": {"sunny": sun, "rainy": [0.8 * v for v in sun]}}
    same = {"time_s": t, "speed_mps": {"sunny": sun, "rainy": list(sun)}}
    claims = report.swap_claims(
        {
            "full-s0": _swap(0.8, 0.78, 0.82, n, full),
            "no_weather-s0": _swap(1.0, 0.99, 1.01, n, same),
        }
    )
    assert claims[1].endswith(": supported."), claims[1]
    # reversed: the model without the weather head slows down more
    claims = report.swap_claims(
        {
            "full-s0": _swap(1.0, 0.99, 1.01, n, same),
            "no_weather-s0": _swap(0.8, 0.78, 0.82, n, full),
        }
    )
    assert claims[1].endswith(": contradicted."), claims[1]
    est, lo, hi = report.ratio_difference(_swap(0, 0, 0, n, same), _swap(0, 0, 0, n, full))
    assert est == pytest.approx(-0.2) and hi < 0


def _analysis(values: dict[str, np.ndarray]) -> dict:
    return {
        "frames": len(next(iter(values.values()))),
        "trained": {
            h: {"raw": 0.0, "centred": float(v.mean()), "kernel": 0.0} for h, v in values.items()
        },
        "trained_per_frame": {h: {"centred": list(v)} for h, v in values.items()},
    }


def test_table_ii_gets_an_interval_and_can_come_out_undecided():
    rng = np.random.default_rng(2)

    def model(det, bev, traffic, weather, sd=0.05, n=50):
        return _analysis(
            {h: m + rng.normal(0, sd, n) for h, m in
             (("detection", det), ("bev", bev), ("traffic", traffic), ("weather", weather))}
        )  # fmt: skip

    ordered = {"full-s0": model(0.6, 0.55, 0.2, 0.3), "full-s1": model(0.62, 0.5, 0.25, 0.2)}
    assert report.table_ii_claim(ordered).endswith(": supported.")
    flipped = {"full-s0": model(0.2, 0.3, 0.6, 0.55), "full-s1": model(0.25, 0.2, 0.62, 0.5)}
    assert report.table_ii_claim(flipped).endswith(": contradicted.")
    close = {
        "full-s0": model(0.41, 0.4, 0.4, 0.39, 0.2),
        "full-s1": model(0.4, 0.42, 0.41, 0.4, 0.2),
    }
    assert report.table_ii_claim(close).endswith(": undecided.")
    cis = report.table_ii(ordered)
    est, lo, hi = cis["detection"]
    assert lo < est < hi and est == pytest.approx(0.61, abs=0.03)


def test_seen_routes_leave_out_the_val_town_and_cover_several_towns():
    p = runner.PRESETS["small"]
    routes = runner.seen_routes(p)
    assert len(routes) == p.seen_routes
    towns = [r.town for r in routes]
    assert p.val_town not in towns and len(set(towns)) == len(towns) == 4  # one each, in turn
    every = runner.seen_routes(runner.Preset(**{**p.__dict__, "seen_routes": 0}))
    assert len({r.town for r in every}) == 7 and p.val_town not in {r.town for r in every}
    assert len(every) == 4 * 7  # the checked-in file's four routes of each of the 7 towns
