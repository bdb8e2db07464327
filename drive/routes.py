"""Route sets: deterministic benchmarks of routes, each with its seed, weather and behaviour.

    drive routes --standard                          # the checked-in benchmarks (drive/routes/)
    drive routes --town grid_small --short 3 --long 1 --out my_routes.json
    drive routes --net my_city.net.xml --short 10 --out my_city_routes.json

A route is a sequence of edges a passenger car can drive, chosen as in the paper's Town05
benchmark (Sec. IV-A, after Prakash et al. 2021): short routes of SHORT_M (100-500 m) through
about 3 junctions, long routes of LONG_M (1-2 km) through about 10. Every route carries its own
seed (the world's traffic and the sensors' noise), weather and the behaviour profile that
weather implies, drawn by the data's own rule (datagen.world.behaviour.draw_condition, Sec. IV-A).

Standard benchmarks (BENCHMARKS), generated from `--seed 0` and checked into drive/routes/:
- `training_towns`: every training town, two short and two long routes, the four weathers once
  each per town (the role of CARLA's 42 Routes: seen towns, every condition);
- `heldout_short`, `heldout_long`: ten routes each on the held-out town (datagen.world.towns.
  HELD_OUT_TOWNS, never in a build), weathers in turn (the role of Town05 Short / Long).

The JSON (ROUTESET_VERSION) names the network of every route by built-in town or by file name,
with its sha256, so a route file is never driven on another network and stays portable: the
file is found at run time (`--net`, else beside the route file, else in the working directory;
resolve_net). Every route is checked drivable when it is generated: the ego is inserted at its
start as a build inserts it (datagen.world.World, no traffic); a route it cannot start is not
written.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from datagen.errors import UserError
from schemas import WEATHERS, outputs

ROUTESET_VERSION = 2  # 1: user networks named by absolute path ("net_path"), still read
SHORT_M = (100.0, 500.0)
LONG_M = (1000.0, 2000.0)
SHORT_JUNCTIONS = (2, 4)  # "about 3"
LONG_JUNCTIONS = (7, 14)  # "about 10"
ROUTES_DIR = Path(__file__).parent / "routes"


@dataclass(frozen=True)
class Route:
    """One route to drive.

    Attributes:
        route_id: unique within its set, e.g. "boulevard-short-03".
        town: built-in town name, or None for a user network (then net_name).
        net_name: the file name of a user network (`drive routes --net`), found at run time
            (resolve_net); None for a built-in town.
        network_sha256: sha256 of the network's bytes (datagen.world.towns.network_sha256).
        edges: edge ids, in driving order.
        length_m: centreline length, m.
        junctions: junctions with three or more roads on the way.
        kind: "short" or "long".
        seed: the world's and the sensors' seed.
        weather, behaviour: schemas.WEATHERS, the profile that weather implies.
    """

    route_id: str
    town: str | None
    net_name: str | None
    network_sha256: str
    edges: tuple[str, ...]
    length_m: float
    junctions: int
    kind: str
    seed: int
    weather: str
    behaviour: str

    def to_dict(self) -> dict:
        d = asdict(self)
        d["edges"] = list(self.edges)
        return d

    @staticmethod
    def from_dict(d: dict) -> Route:
        d = dict(d)
        if "net_path" in d:  # version 1: the network's path on the machine that wrote it
            path = d.pop("net_path")
            d["net_name"] = Path(path).name if path else None
        return Route(**{**d, "edges": tuple(d["edges"])})


def resolve_net(
    route: Route, net_override: Path | None = None, routes_file: Path | None = None
) -> Path:
    """The network file of `route`, checked against its sha256 (UserError if it differs): a
    built-in town's, else `net_override` (--net), else the file named net_name beside
    `routes_file`, else in the working directory."""
    from datagen.world.towns import check_network, network_sha256, town_net_path

    if net_override is not None:
        path = check_network(net_override)
    elif route.town is not None:
        path = town_net_path(route.town)
    elif route.net_name:
        where = [Path(routes_file).parent] if routes_file is not None else []
        found = [d / route.net_name for d in [*where, Path.cwd()] if (d / route.net_name).is_file()]
        if not found:
            raise UserError(
                f"route {route.route_id} is for the network {route.net_name} (sha256 "
                f"{route.network_sha256[:12]}...), not found beside the route file or here; "
                "give it with --net"
            )
        path = check_network(found[0])
    else:
        raise UserError(f"route {route.route_id}: names neither a town nor a network file")
    if network_sha256(path) != route.network_sha256:
        raise UserError(
            f"route {route.route_id} was made for another network than {path} (sha256 differs);"
            " regenerate the routes with `drive routes` for this network"
        )
    return path


def save_routes(routes: list[Route], path: Path, name: str) -> None:
    """Write a route set as JSON, atomically (a temp name, then a rename)."""
    doc = {"version": ROUTESET_VERSION, "name": name, "routes": [r.to_dict() for r in routes]}
    outputs.write_json(path, doc)


def load_routes(path: Path) -> tuple[str, list[Route]]:
    """(name, routes) of a route file; UserError for anything that is not one."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such route file")
    try:
        doc = json.loads(path.read_text())
        if doc.get("version") not in (1, ROUTESET_VERSION):
            raise ValueError(f"version {doc.get('version')!r}, expected {ROUTESET_VERSION}")
        routes = [Route.from_dict(r) for r in doc["routes"]]
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise UserError(f"{path}: not a route file written by `drive routes` ({e})") from None
    if not routes:
        raise UserError(f"{path}: holds no routes")
    return str(doc.get("name", path.stem)), routes


def undrivable(net_path: Path, edges: tuple[str, ...]) -> str | None:
    """Why the ego cannot start on the route `edges` (None if it can): it is inserted at the
    route's start as a build inserts it (datagen.world.World: SUMO's own checks of the route for
    the ego's type, then insertion at the first edge's start), with no other traffic."""
    from datagen.world import World, WorldConfig

    config = WorldConfig(
        net_path=Path(net_path),
        seed=0,
        weather="sunny",
        behaviour="normal",
        n_vehicles=0,
        n_pedestrians=0,
        reroute=False,
        warmup_s=0.0,
        ego_route=tuple(edges),
    )
    try:
        with World(config):
            return None
    except UserError:
        raise
    except Exception as e:  # noqa: BLE001 - SUMO's refusal, whatever its type
        return f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"


def _pick_route(net, edges, rng, length_m, junctions, geometry_of, taken, check=None):
    """One random car route with its length and junction count in range, not in `taken`,
    on which `check(ids)` finds nothing wrong (or None)."""
    xy = np.array([e.getShape()[len(e.getShape()) // 2] for e in edges])
    lo, hi = length_m
    for _ in range(400):
        a = int(rng.integers(len(edges)))
        d = np.hypot(*(xy - xy[a]).T)
        cand = np.flatnonzero((d >= 0.4 * lo) & (d <= 0.9 * hi))
        if not len(cand):
            continue
        b = int(cand[rng.integers(len(cand))])
        path, _cost = net.getShortestPath(edges[a], edges[b], vClass="passenger")
        if not path or len(path) < 2:
            continue
        ids = tuple(e.getID() for e in path)
        if ids in taken:
            continue
        try:
            geom = geometry_of(ids)
        except ValueError:
            continue
        if lo <= geom.length_m <= hi and junctions[0] <= geom.junctions <= junctions[1]:
            if check is not None and check(ids) is not None:
                continue
            return ids, geom
    return None


def generate(
    net_path: Path,
    n_short: int,
    n_long: int,
    seed: int,
    prefix: str,
    town: str | None,
    weathers: tuple[str, ...] = WEATHERS,
) -> list[Route]:
    """`n_short` short and `n_long` long routes on one network, reproducible from `seed`;
    weathers in turn over the routes, behaviour drawn from each route's seed."""
    from datagen.world.behaviour import draw_condition
    from datagen.world.towns import network_sha256
    from drive.geometry import read_net, route_geometry

    net = read_net(str(net_path))
    edges = sorted(
        (
            e
            for e in net.getEdges()
            if e.getFunction() == "" and e.allows("passenger") and e.getLength() >= 20.0
        ),
        key=lambda e: e.getID(),
    )
    if not edges:
        raise UserError(f"{net_path}: no edge a passenger car may drive")
    sha = network_sha256(net_path)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xD21]))
    out: list[Route] = []
    k = 0
    for kind, n, length, junc in (
        ("short", n_short, SHORT_M, SHORT_JUNCTIONS),
        ("long", n_long, LONG_M, LONG_JUNCTIONS),
    ):
        for i in range(n):
            found = _pick_route(
                net,
                edges,
                rng,
                length,
                junc,
                lambda ids: route_geometry(net_path, ids),
                {r.edges for r in out},
                lambda ids: undrivable(net_path, ids),
            )
            if found is None:
                raise UserError(
                    f"{net_path}: found no drivable {kind} route of {length[0]:.0f}-{length[1]:.0f} m "
                    f"through {junc[0]}-{junc[1]} junctions"
                )
            ids, geom = found
            route_seed = int(rng.integers(2**31 - 1))
            weather = weathers[k % len(weathers)]
            _, behaviour = draw_condition(np.random.default_rng(route_seed), {weather: 1.0})
            out.append(
                Route(
                    route_id=f"{prefix}-{kind}-{i:02d}",
                    town=town,
                    net_name=None if town else Path(net_path).name,
                    network_sha256=sha,
                    edges=ids,
                    length_m=round(geom.length_m, 2),
                    junctions=geom.junctions,
                    kind=kind,
                    seed=route_seed,
                    weather=weather,
                    behaviour=behaviour,
                )
            )
            k += 1
    return out


def standard_benchmarks(seed: int = 0) -> dict[str, list[Route]]:
    """The checked-in benchmarks (module docstring), by file stem."""
    from datagen.world.towns import HELD_OUT_TOWNS, TOWN_NAMES, town_net_path

    training: list[Route] = []
    for t, town in enumerate(TOWN_NAMES):
        # the four weathers once per town, rotated so short and long routes see each
        weathers = tuple(WEATHERS[(t + j) % len(WEATHERS)] for j in range(len(WEATHERS)))
        training += generate(town_net_path(town), 2, 2, seed + t, town, town, weathers)
    heldout = HELD_OUT_TOWNS[0]
    net = town_net_path(heldout)
    return {
        "training_towns": training,
        "heldout_short": generate(net, 10, 0, seed + 100, heldout, heldout),
        "heldout_long": generate(net, 0, 10, seed + 101, heldout, heldout),
    }


BENCHMARKS = ("training_towns", "heldout_short", "heldout_long")


def add_arguments(p) -> None:
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--standard", action="store_true", help="write the standard benchmarks")
    where.add_argument("--town", help="a built-in town (datagen towns)")
    where.add_argument("--net", type=Path, help="any SUMO network (.net.xml)")
    p.add_argument("--short", type=int, default=10, help="short routes (100-500 m)")
    p.add_argument("--long", type=int, default=0, help="long routes (1-2 km)")
    p.add_argument("--seed", type=int, default=0, help="draws the routes and their seeds")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="route file (default: drive/routes/ for --standard, else routes.json)",
    )


def run(args) -> int:
    from datagen.world.towns import check_network, town_net_path

    if args.short < 0 or args.long < 0 or args.short + args.long == 0:
        raise UserError("--short and --long must be >= 0 and not both 0")
    if args.standard:
        out_dir = outputs.check_dir(args.out or ROUTES_DIR)  # before any route is drawn
        for name, routes in standard_benchmarks(args.seed).items():
            save_routes(routes, out_dir / f"{name}.json", name)
            km = sum(r.length_m for r in routes) / 1000.0
            print(f"{out_dir / (name + '.json')}: {len(routes)} routes, {km:.1f} km")
        return 0
    out = outputs.check_file(args.out or Path("routes.json"), "--out", suffixes=(".json",))
    if args.town:
        net, prefix, town = town_net_path(args.town), args.town, args.town
    else:
        net = check_network(args.net)
        prefix, town = net.name.split(".")[0], None
    routes = generate(net, args.short, args.long, args.seed, prefix, town)
    save_routes(routes, out, prefix)
    km = sum(r.length_m for r in routes) / 1000.0
    print(f"{out}: {len(routes)} routes, {km:.1f} km")
    return 0
