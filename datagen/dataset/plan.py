"""The build's plan: which episodes make up a dataset, as a pure function of its arguments.

The frame budget is split evenly across the towns, each town's share across the weathers (by
`--weather-mix`, default uniform), and each (town, weather) share into episodes of at most
`--episode-seconds` of driving. Episode ids, seeds and behaviour profiles come from `--seed`
alone, so the plan does not depend on worker count, executor or timing. An episode that ends
early (route end, teleport, blocked ego) delivers fewer rows than asked; once every episode of a
town's round is finished, the missing frames of each weather are planned as a further round of
episodes, numbered after the last (`plan_town`).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.metadata
import math
import zlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import schemas

PAPER_FRAMES = 146_000  # paper Sec. IV "Dataset Collection": 146k frames from 8 towns at 2 FPS
EPISODE_SECONDS = 180.0  # "a few minutes of driving" per episode: 360 frames at 2 Hz
MAX_ROUNDS = 8
"""Top-up rounds per town for episodes that ended early. A weather whose whole round delivered no
rows is given up at once (a network where the ego cannot drive); the manifest records any
shortfall."""


# --------------------------------------------------------------------------------------------
# Configuration and plan


@dataclass(frozen=True)
class Town:
    """A town of the build: a built-in town, or a user's network (`--net`, named by its stem)."""

    name: str
    net_path: str
    network_sha256: str
    builtin: bool


@dataclass(frozen=True)
class BuildConfig:
    """What determines the dataset. Workers, executor and output directory do not.

    Attributes:
        towns: the towns, in order.
        frames: total rows in the dataset, split evenly across towns.
        seed: the one seed every episode seed derives from.
        episode_seconds: driving time per planned episode (frames = seconds x 2 Hz).
        weather_mix: ((weather, weight), ...) normalised to sum 1; None = uniform.
        sensors: a datagen.sensors.config.SensorConfig, or None for its defaults.
    """

    towns: tuple[Town, ...]
    frames: int = PAPER_FRAMES
    seed: int = 0
    episode_seconds: float = EPISODE_SECONDS
    weather_mix: tuple[tuple[str, float], ...] | None = None
    sensors: object | None = None

    @property
    def episode_frames(self) -> int:
        return max(1, round(self.episode_seconds * schemas.FRAME_RATE_HZ))

    def weights(self) -> dict[str, float]:
        mix = dict(self.weather_mix) if self.weather_mix else dict.fromkeys(schemas.WEATHERS, 1.0)
        total = sum(mix.values())
        return {w: mix.get(w, 0.0) / total for w in schemas.WEATHERS}

    def sensors_dict(self) -> dict:
        sensors = self.sensors
        if sensors is None:
            from datagen.sensors.config import SensorConfig

            sensors = SensorConfig()
        return jsonable(sensors.to_dict() if hasattr(sensors, "to_dict") else sensors)

    def identity(self) -> dict:
        """The manifest's record of the arguments; a different identity is a different dataset."""
        return {
            "schema_version": schemas.SCHEMA_VERSION,
            "generator_version": generator_version(),
            "towns": [{"name": t.name, "network_sha256": t.network_sha256} for t in self.towns],
            "frames": self.frames,
            "seed": self.seed,
            "episode_frames": self.episode_frames,
            "weather_mix": self.weights(),
            "sensors": self.sensors_dict(),
        }


@dataclass(frozen=True)
class Episode:
    """One planned episode (the fields of datagen.episode.EpisodeSpec, plus its round)."""

    episode_id: str
    town: str
    seed: int
    weather: str
    behaviour: str
    n_frames: int
    round: int = 0

    def key(self) -> dict:
        """What must match for a finished episode to count as this one."""
        return {
            k: getattr(self, k)
            for k in ("episode_id", "town", "seed", "weather", "behaviour", "n_frames")
        }


def generator_version() -> str:
    """The shards' `iidsu.generator_version` (package and scene version): a dataset is never
    resumed with a different generator."""
    try:
        from datagen.episode import generator_version as episode_generator_version
    except ImportError:  # pragma: no cover  (the sensors are part of the package)
        return importlib.metadata.version("iidsu")
    return episode_generator_version()


def split_evenly(total: int, parts: int) -> list[int]:
    """`total` as `parts` integers differing by at most one, larger ones first."""
    base, extra = divmod(total, parts)
    return [base + (i < extra) for i in range(parts)]


def apportion(total: int, weights: dict[str, float]) -> dict[str, int]:
    """Largest-remainder split of `total` by `weights` (ties go to the earlier key)."""
    exact = {k: total * w for k, w in weights.items()}
    counts = {k: math.floor(v) for k, v in exact.items()}
    order = sorted(weights, key=lambda k: -(exact[k] - counts[k]))  # stable: earlier key first
    for k in order[: total - sum(counts.values())]:
        counts[k] += 1
    return counts


def town_quotas(cfg: BuildConfig) -> dict[str, dict[str, int]]:
    """Frames per town and weather: {town: {weather: frames}}."""
    per_town = split_evenly(cfg.frames, len(cfg.towns))
    return {t.name: apportion(n, cfg.weights()) for t, n in zip(cfg.towns, per_town)}


def _episode(cfg: BuildConfig, town: str, index: int, weather: str, n: int, rnd: int) -> Episode:
    return _episode_of_seed(cfg.seed, town, index, weather, n, rnd)


@functools.lru_cache(maxsize=65536)
def _episode_of_seed(seed: int, town: str, index: int, weather: str, n: int, rnd: int) -> Episode:
    # Cached: the build re-plans after every finished episode, and drawing an episode's seeds
    # and condition is most of a plan's cost (the plan of a 350-episode build took 0.2 s).
    # A town's episodes are keyed by (seed, town name, index): the same town and index give the
    # same episode in any build with the same seed, whatever the other towns are.
    root = np.random.SeedSequence(seed, spawn_key=(zlib.crc32(town.encode()), index))
    sim_seed, draw_seed = root.spawn(2)
    from datagen.world.behaviour import draw_condition

    w, behaviour = draw_condition(np.random.default_rng(draw_seed), {weather: 1.0})
    assert w == weather, (w, weather)
    return Episode(
        episode_id=f"{town}-{seed}-{index:04d}",
        town=town,
        seed=int(sim_seed.generate_state(1)[0] & 0x7FFFFFFF),  # SUMO takes a signed 32-bit seed
        weather=weather,
        behaviour=behaviour,
        n_frames=n,
        round=rnd,
    )


def _round_episodes(
    cfg: BuildConfig, town: str, need: dict[str, int], first_index: int, rnd: int
) -> list[Episode]:
    """Episodes of at most cfg.episode_frames covering `need` frames per weather, weathers
    interleaved so that a partial build already holds every weather."""
    sizes = {
        w: split_evenly(n, math.ceil(n / cfg.episode_frames)) for w, n in need.items() if n > 0
    }
    out: list[Episode] = []
    for k in range(max((len(s) for s in sizes.values()), default=0)):
        for w in schemas.WEATHERS:
            if w in sizes and k < len(sizes[w]):
                out.append(_episode(cfg, town, first_index + len(out), w, sizes[w][k], rnd))
    return out


@dataclass
class TownPlan:
    """A town's episodes so far, whether its frames are all planned and done, and any frames it
    had to give up on (weathers where a whole round delivered nothing, or MAX_ROUNDS reached)."""

    episodes: list[Episode]
    complete: bool
    shortfall: dict[str, int]


def plan_town(cfg: BuildConfig, town: str, quota: dict[str, int], done: dict) -> TownPlan:
    """The pure planning function: rounds of `town` given the finished episodes `done`
    ({episode_id: record with "rows" and the Episode key}). Deterministic in its arguments."""
    episodes = _round_episodes(cfg, town, quota, 0, 0)
    current = episodes
    given_up: dict[str, int] = {}
    for rnd in range(1, MAX_ROUNDS + 1):
        if not all(is_done(e, done) for e in current):
            return TownPlan(episodes, False, given_up)
        got: Counter = Counter()
        for e in episodes:
            got[e.weather] += done[e.episode_id]["rows"]
        round_got: Counter = Counter()
        for e in current:
            round_got[e.weather] += done[e.episode_id]["rows"]
        need = {}
        for w, q in quota.items():
            missing = q - got[w]
            if missing <= 0 or w in given_up:
                continue
            if round_got[w] == 0 and any(e.weather == w for e in current):
                given_up[w] = missing  # a whole round of this weather delivered no rows
            else:
                need[w] = missing
        if not need or rnd == MAX_ROUNDS:
            given_up.update(need)
            return TownPlan(episodes, True, given_up)
        current = _round_episodes(cfg, town, need, len(episodes), rnd)
        episodes = episodes + current
    raise AssertionError("unreachable")


def is_done(e: Episode, done: dict) -> bool:
    record = done.get(e.episode_id)
    return record is not None and all(record.get(k) == v for k, v in e.key().items())


def plan(cfg: BuildConfig, done: dict) -> dict[str, TownPlan]:
    quotas = town_quotas(cfg)
    return {t.name: plan_town(cfg, t.name, quotas[t.name], done) for t in cfg.towns}


def jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return jsonable(dataclasses.asdict(obj))
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    return obj
