"""The built-in towns: SUMO networks generated reproducibly from recipes, and cached.

Eight training towns (TOWN_NAMES, the ones a `datagen build --towns N` draws from) and one
held-out evaluation town (HELD_OUT_TOWNS), generated the same way but never part of a build, as
CARLA's Town05 is held out of training in the paper's Sec. IV-A (`drive routes` benchmarks it).

Each town is built in three passes with SUMO's own tools (from the `eclipse-sumo` wheel):

1. `netgenerate` draws the topology (grid, spider web or random graph) with a fixed seed and
   writes it as plain XML (nodes, edges);
2. Python edits the plain XML deterministically (a seeded `numpy.random.Generator`): junction
   control per node (`traffic_light`, `allway_stop`, `priority_stop`, `priority`), arterial
   lanes/speeds/priorities, a roundabout in place of a grid node;
3. `netconvert` builds the final network with guessed sidewalks and pedestrian crossings (and
   walking areas), traffic-light programs with pedestrian phases, and no U-turns except at dead
   ends.

The result is cached as `<cache>/<name>-<recipe hash>.net.xml` (default `~/.cache/iidsu/towns`,
`$IIDSU_CACHE/towns` if set), written atomically so parallel workers may race to build it. The
generation-date comment SUMO writes at the top of the file is stripped so that the same SUMO
version gives byte-identical networks (and the same `network_sha256`).

    datagen towns            # table: size, junctions (lights / stop / other), lane-km, sidewalk-km

Size: ~790 lines, one module on purpose: RECIPE_VERSION invalidates every cached town after a
change to this module, so the recipes and the passes that build them stay in it.
"""

from __future__ import annotations

import argparse
import functools
import gzip
import hashlib
import math
import os
import re
import shutil
import subprocess
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from datagen.errors import UserError
from schemas import outputs

HELP = "list the built-in towns (size, junctions, lane-km, sidewalk-km)"

TOWN_NAMES: tuple[str, ...] = (
    "grid_small",
    "downtown",
    "spider",
    "random_city",
    "arterial",
    "suburb",
    "roundabout",
    "mixed",
)
"""The training towns, in `--towns N` order."""

HELD_OUT_TOWNS: tuple[str, ...] = ("boulevard",)
"""Evaluation towns: built like the others, never in a build (closed-loop benchmark only)."""

ALL_TOWNS: tuple[str, ...] = TOWN_NAMES + HELD_OUT_TOWNS

RECIPE_VERSION = 1  # bump to invalidate every cached town after a change to this module

# netconvert options shared by every town. Sidewalks are guessed on roads up to 60 km/h and
# crossings at every junction whose roads are at most that fast (SUMO's defaults, 13.89 m/s,
# would leave the arterials without either).
COMMON_NETCONVERT = (
    "--sidewalks.guess",
    "--sidewalks.guess.max-speed",
    "17",
    "--crossings.guess",
    "--crossings.guess.speed-threshold",
    "17",
    "--walkingareas",
    "--no-turnarounds.except-deadend",
    "--junctions.corner-detail",
    "5",
    "--tls.default-type",
    "static",
    "--tls.yellow.time",
    "3",
    "--tls.crossing-min.time",
    "6",
    "--default.sidewalk-width",
    "2.0",
    "--offset.disable-normalization",
    "--precision",
    "2",
)


@dataclass(frozen=True)
class Recipe:
    """How one town is built.

    Attributes:
        name: town name (TOWN_NAMES).
        description: one line for `datagen towns`.
        netgenerate: netgenerate arguments (topology, lanes, speed); `--seed` is added.
        seed: seed of netgenerate and of the junction-control draw.
        control: probabilities of (traffic_light, allway_stop, priority_stop) for a junction
            with three or more neighbours; the rest stay priority junctions. At least two of
            each kind are forced so every town has lights and stop signs.
        edit: optional deterministic edit of the plain XML (nodes, edges, rng) before the
            junction draw, e.g. arterial roads or a roundabout.
        netconvert: extra netconvert arguments.
    """

    name: str
    description: str
    netgenerate: tuple[str, ...]
    seed: int
    control: tuple[float, float, float]
    edit: Callable[[ET.Element, ET.Element, np.random.Generator], None] | None = None
    netconvert: tuple[str, ...] = field(default_factory=tuple)


# --- plain-XML edits -----------------------------------------------------------------------


def _node_xy(nodes: ET.Element) -> dict[str, tuple[float, float]]:
    return {n.get("id"): (float(n.get("x")), float(n.get("y"))) for n in nodes.iter("node")}


def _arterials(every: int, lanes: int, speed_mps: float) -> Callable:
    """Edit: every `every`-th grid row and column becomes a multi-lane, higher-priority road."""

    def edit(nodes: ET.Element, edges: ET.Element, rng: np.random.Generator) -> None:
        xy = _node_xy(nodes)
        xs = sorted({round(p[0], 1) for p in xy.values()})
        ys = sorted({round(p[1], 1) for p in xy.values()})
        art_x = set(xs[every // 2 :: every])
        art_y = set(ys[every // 2 :: every])
        for e in edges.iter("edge"):
            (x0, y0), (x1, y1) = xy[e.get("from")], xy[e.get("to")]
            vertical = round(x0, 1) == round(x1, 1) and round(x0, 1) in art_x
            horizontal = round(y0, 1) == round(y1, 1) and round(y0, 1) in art_y
            if vertical or horizontal:
                e.set("numLanes", str(lanes))
                e.set("speed", f"{speed_mps:.2f}")
                e.set("priority", "10")
            else:
                e.set("priority", "5")

    return edit


def _roundabouts(n: int, radius_m: float) -> Callable:
    """Edit: replace `n` inner 4-way nodes (spread over the town) by roundabouts of `radius_m`.

    Each arm ends at a new node on the circle; the ring is one-way counter-clockwise (right-hand
    traffic) with arc geometry; netconvert's `--roundabouts.guess` then gives it priority.
    """

    def edit(nodes: ET.Element, edges: ET.Element, rng: np.random.Generator) -> None:
        xy = _node_xy(nodes)
        nbrs: dict[str, set[str]] = {k: set() for k in xy}
        for e in edges.iter("edge"):
            nbrs[e.get("from")].add(e.get("to"))
            nbrs[e.get("to")].add(e.get("from"))
        cx = np.mean([p[0] for p in xy.values()])
        cy = np.mean([p[1] for p in xy.values()])
        inner = sorted(k for k, v in nbrs.items() if len(v) == 4)
        # the most central node first, then the ones farthest from the chosen ones
        chosen: list[str] = []
        for _ in range(n):
            if not inner:
                break
            if not chosen:
                best = min(inner, key=lambda k: math.hypot(xy[k][0] - cx, xy[k][1] - cy))
            else:
                best = max(
                    inner,
                    key=lambda k: min(
                        math.hypot(xy[k][0] - xy[c][0], xy[k][1] - xy[c][1]) for c in chosen
                    ),
                )
            chosen.append(best)
            inner = [k for k in inner if k not in nbrs[best] and k != best]
        node_by_id = {nd.get("id"): nd for nd in nodes.iter("node")}
        for c in chosen:
            x0, y0 = xy[c]
            arms = sorted(nbrs[c], key=lambda k: math.atan2(xy[k][1] - y0, xy[k][0] - x0))
            ring = []
            for k in arms:
                ang = math.atan2(xy[k][1] - y0, xy[k][0] - x0)
                rid = f"{c}_r{k}"
                ET.SubElement(
                    nodes,
                    "node",
                    id=rid,
                    x=f"{x0 + radius_m * math.cos(ang):.2f}",
                    y=f"{y0 + radius_m * math.sin(ang):.2f}",
                    type="priority",
                )
                ring.append((rid, ang))
                for e in edges.iter("edge"):
                    if e.get("from") == c and e.get("to") == k:
                        e.set("from", rid)
                    elif e.get("to") == c and e.get("from") == k:
                        e.set("to", rid)
            for i, (rid, a0) in enumerate(ring):
                nid, a1 = ring[(i + 1) % len(ring)]
                if a1 <= a0:
                    a1 += 2 * math.pi
                pts = [
                    (x0 + radius_m * math.cos(a), y0 + radius_m * math.sin(a))
                    for a in np.linspace(a0, a1, 9)
                ]
                ET.SubElement(
                    edges,
                    "edge",
                    id=f"{rid}_to_{nid}",
                    attrib={
                        "from": rid,
                        "to": nid,
                        "priority": "20",
                        "numLanes": "1",
                        "speed": "8.33",
                        "shape": " ".join(f"{px:.2f},{py:.2f}" for px, py in pts),
                    },
                )
            nodes.remove(node_by_id[c])

    return edit


def _narrow(width_m: float) -> Callable:
    """Edit: narrow lanes and a random speed per road (rural/suburban streets). Narrower than
    3 m with acute random angles, SUMO's junction geometry lets turning vehicles touch."""

    def edit(nodes: ET.Element, edges: ET.Element, rng: np.random.Generator) -> None:
        for e in sorted(edges.iter("edge"), key=lambda e: e.get("id")):
            e.set("width", f"{width_m:.2f}")
            e.set("speed", f"{rng.choice([8.33, 11.11, 13.89]):.2f}")

    return edit


def _mixed(nodes: ET.Element, edges: ET.Element, rng: np.random.Generator) -> None:
    """Edit: a roundabout, plus a random speed/priority class per road pair."""
    _roundabouts(1, 22.0)(nodes, edges, rng)
    classes = [(1, 8.33, 3), (1, 11.11, 5), (2, 13.89, 8)]
    pair_class: dict[frozenset, tuple] = {}
    for e in sorted(edges.iter("edge"), key=lambda e: e.get("id")):
        if e.get("shape"):  # the roundabout ring keeps its own attributes
            continue
        key = frozenset((e.get("from"), e.get("to")))
        if key not in pair_class:
            pair_class[key] = classes[int(rng.integers(len(classes)))]
        lanes, speed, prio = pair_class[key]
        e.set("numLanes", str(lanes))
        e.set("speed", f"{speed:.2f}")
        e.set("priority", str(prio))


def _boulevard(nodes: ET.Element, edges: ET.Element, rng: np.random.Generator) -> None:
    """Edit: three-lane avenues every third row and column, then one roundabout."""
    _arterials(every=3, lanes=3, speed_mps=16.67)(nodes, edges, rng)
    _roundabouts(1, 26.0)(nodes, edges, rng)


RECIPES: dict[str, Recipe] = {
    r.name: r
    for r in (
        Recipe(
            "grid_small",
            "small single-lane grid, 40 km/h",
            ("--grid", "--grid.number", "7", "--grid.length", "110", "-L", "1", "-S", "11.11"),
            seed=11,
            control=(0.35, 0.25, 0.2),
        ),
        Recipe(
            "downtown",
            "two-lane downtown grid, 50 km/h, mostly signalised",
            (
                "--grid",
                "--grid.x-number",
                "8",
                "--grid.y-number",
                "7",
                "--grid.length",
                "100",
                "-L",
                "2",
                "-S",
                "13.89",
            ),
            seed=12,
            control=(0.6, 0.1, 0.15),
        ),
        Recipe(
            "spider",
            "spider web: ring roads and radials, 50 km/h",
            (
                "--spider",
                "--spider.arm-number",
                "9",
                "--spider.circle-number",
                "6",
                "--spider.space-radius",
                "80",
                "--spider.omit-center",
                "-L",
                "1",
                "-S",
                "13.89",
            ),
            seed=13,
            control=(0.35, 0.2, 0.25),
        ),
        Recipe(
            "random_city",
            "irregular random city, 1-2 lanes",
            (
                "--rand",
                "--rand.iterations",
                "260",
                "--rand.min-distance",
                "80",
                "--rand.max-distance",
                "150",
                "--rand.min-angle",
                "60",
                "--rand.connectivity",
                "0.9",
                "--random-lanenumber",
                "-L",
                "2",
                "-S",
                "13.89",
            ),
            seed=14,
            control=(0.35, 0.2, 0.25),
        ),
        Recipe(
            "arterial",
            "grid with three-lane 60 km/h arterials and single-lane side streets",
            (
                "--grid",
                "--grid.x-number",
                "9",
                "--grid.y-number",
                "6",
                "--grid.length",
                "120",
                "-L",
                "1",
                "-S",
                "11.11",
            ),
            seed=15,
            control=(0.4, 0.15, 0.35),
            edit=_arterials(every=3, lanes=3, speed_mps=16.67),
        ),
        Recipe(
            "suburb",
            "suburb/rural: narrow roads, long links, cul-de-sacs",
            (
                "--rand",
                "--rand.iterations",
                "140",
                "--rand.min-distance",
                "120",
                "--rand.max-distance",
                "260",
                "--rand.min-angle",
                "60",
                "--rand.neighbor-dist1",
                "2",
                "--rand.neighbor-dist2",
                "3",
                "--rand.neighbor-dist3",
                "6",
                "--rand.neighbor-dist4",
                "2",
                "-L",
                "1",
                "-S",
                "13.89",
            ),
            seed=16,
            control=(0.25, 0.25, 0.35),
            edit=_narrow(3.0),
        ),
        Recipe(
            "roundabout",
            "grid town with two roundabouts",
            (
                "--grid",
                "--grid.number",
                "7",
                "--grid.length",
                "120",
                "-L",
                "1",
                "-S",
                "13.89",
            ),
            seed=17,
            control=(0.35, 0.2, 0.25),
            edit=_roundabouts(2, 24.0),
            netconvert=("--roundabouts.guess",),
        ),
        Recipe(
            "mixed",
            "mixed town: random grid, mixed lanes and speeds, a roundabout",
            (
                "--rand",
                "--rand.grid",
                "--rand.iterations",
                "220",
                "--rand.min-distance",
                "100",
                "--rand.max-distance",
                "210",
                "--rand.connectivity",
                "0.95",
                "-L",
                "1",
                "-S",
                "13.89",
            ),
            seed=18,
            control=(0.4, 0.15, 0.25),
            edit=_mixed,
            netconvert=("--roundabouts.guess",),
        ),
        # Held out (HELD_OUT_TOWNS): a two-lane grid with three-lane avenues and a roundabout,
        # a layout none of the training towns has (Town05's role: multi-lane, signal-heavy).
        Recipe(
            "boulevard",
            "held out: two-lane grid, three-lane 60 km/h avenues, a roundabout",
            (
                "--grid",
                "--grid.x-number",
                "8",
                "--grid.y-number",
                "7",
                "--grid.length",
                "130",
                "-L",
                "2",
                "-S",
                "13.89",
            ),
            seed=19,
            control=(0.5, 0.15, 0.15),
            edit=_boulevard,
            netconvert=("--roundabouts.guess",),
        ),
    )
}


# --- building ------------------------------------------------------------------------------


def sumo_bin(tool: str) -> str:
    """Path of a SUMO executable from the `eclipse-sumo` wheel (fallback: $PATH)."""
    try:
        import sumo

        path = Path(sumo.SUMO_HOME) / "bin" / tool
        if path.exists():
            return str(path)
    except ImportError:
        pass
    found = shutil.which(tool)
    if not found:
        raise UserError(f"SUMO's '{tool}' not found: install the 'datagen' extra (eclipse-sumo)")
    return found


def _sumo_version() -> str:
    try:
        import sumo

        return getattr(sumo, "__version__", "") or Path(sumo.SUMO_HOME).parent.name
    except ImportError:
        return "system"


def _run(cmd: list[str], cwd: Path) -> None:
    env = dict(os.environ)
    env.setdefault("SUMO_HOME", str(Path(sumo_bin("netconvert")).parent.parent))
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"{Path(cmd[0]).name} failed:\n{proc.stdout}\n{proc.stderr}")


def _recipe_key(recipe: Recipe) -> str:
    """Hash of everything that shapes the town: the recipe, the builder code, SUMO's version."""
    import inspect

    builders = (_node_xy, _arterials, _roundabouts, _narrow, _mixed, _assign_control, build_town)
    parts = [
        str(RECIPE_VERSION),
        _sumo_version(),
        repr((recipe.name, recipe.netgenerate, recipe.seed, recipe.control, recipe.netconvert)),
        repr(COMMON_NETCONVERT),
        *(inspect.getsource(f) for f in builders),
    ]
    if recipe.edit is not None:
        cells = recipe.edit.__closure__ or ()
        parts.append(repr([c.cell_contents for c in cells if not callable(c.cell_contents)]))
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:10]


def _assign_control(nodes: ET.Element, edges: ET.Element, recipe: Recipe) -> None:
    """Draw each junction's control type from recipe.control (seeded, in node-id order)."""
    rng = np.random.default_rng(recipe.seed + 1000)
    nbrs: dict[str, set[str]] = {n.get("id"): set() for n in nodes.iter("node")}
    for e in edges.iter("edge"):
        nbrs[e.get("from")].add(e.get("to"))
        nbrs[e.get("to")].add(e.get("from"))
    ring = {e.get("from") for e in edges.iter("edge") if e.get("shape")}  # roundabout nodes
    node_by_id = {n.get("id"): n for n in nodes.iter("node")}
    cands = sorted(k for k, v in nbrs.items() if len(v) >= 3 and k not in ring)
    kinds = ("traffic_light", "allway_stop", "priority_stop")
    p = np.array([*recipe.control, 1.0 - sum(recipe.control)])
    draw = rng.choice(len(p), size=len(cands), p=p)
    for k in range(len(kinds)):  # force at least two junctions of each kind
        have = np.flatnonzero(draw == k)
        if len(have) < 2:
            spare = [i for i in rng.permutation(len(cands)) if draw[i] == 3]
            for i in spare[: 2 - len(have)]:
                draw[i] = k
    for node_id, d in zip(cands, draw):
        node_by_id[node_id].set("type", kinds[d] if d < 3 else "priority")
    for node_id in ring:
        node_by_id[node_id].set("type", "priority")


def _strip_header(path: Path) -> None:
    """Drop SUMO's leading '<!-- generated on DATE ... -->' comment (makes builds byte-stable)."""
    text = path.read_text()
    text = re.sub(r"<!-- generated on .*?-->\s*", "", text, count=1, flags=re.S)
    path.write_text(text)


def build_town(recipe: Recipe, out: Path) -> None:
    """Build `recipe`'s network into `out` (a .net.xml path)."""
    with tempfile.TemporaryDirectory(prefix=f"iidsu-{recipe.name}-") as tmp:
        tmpd = Path(tmp)
        _run(
            [
                sumo_bin("netgenerate"),
                *recipe.netgenerate,
                "--seed",
                str(recipe.seed),
                "--plain-output-prefix",
                "plain",
                "-o",
                "raw.net.xml",
                "--no-turnarounds",
            ],
            tmpd,
        )
        nod_tree = ET.parse(tmpd / "plain.nod.xml")
        edg_tree = ET.parse(tmpd / "plain.edg.xml")
        nodes, edges = nod_tree.getroot(), edg_tree.getroot()
        if recipe.edit is not None:
            recipe.edit(nodes, edges, np.random.default_rng(recipe.seed))
        _assign_control(nodes, edges, recipe)
        nod_tree.write(tmpd / "town.nod.xml")
        edg_tree.write(tmpd / "town.edg.xml")
        _run(
            [
                sumo_bin("netconvert"),
                "--node-files",
                "town.nod.xml",
                "--edge-files",
                "town.edg.xml",
                *COMMON_NETCONVERT,
                *recipe.netconvert,
                "--seed",
                str(recipe.seed),
                "-o",
                "town.net.xml",
            ],
            tmpd,
        )
        _strip_header(tmpd / "town.net.xml")
        out.parent.mkdir(parents=True, exist_ok=True)
        part = out.with_name(f".{out.name}.{os.getpid()}.part")
        shutil.copyfile(tmpd / "town.net.xml", part)
        os.replace(part, out)  # atomic: parallel builders of the same town are harmless


def build_plain_network(
    nodes: list[dict],
    edges: list[dict],
    out: Path,
    crossings: list[dict] | None = None,
    options: tuple[str, ...] = COMMON_NETCONVERT,
) -> Path:
    """Build a network from plain-XML node/edge attribute dicts with the towns' netconvert
    options (small hand-made networks for tests and experiments).

    Example: nodes=[{"id": "A", "x": 0, "y": 0, "type": "priority"}, ...],
    edges=[{"id": "AB", "from": "A", "to": "B", "numLanes": 1, "speed": 13.89}, ...],
    crossings=[{"node": "B", "edges": "AB BA", "priority": "true"}].
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="iidsu-net-") as tmp:
        tmpd = Path(tmp)
        for tag, rows, fname in (("nodes", nodes, "n.nod.xml"), ("edges", edges, "n.edg.xml")):
            root = ET.Element(tag)
            for row in rows:
                ET.SubElement(root, tag[:-1], {k: str(v) for k, v in row.items()})
            ET.ElementTree(root).write(tmpd / fname)
        cmd = [sumo_bin("netconvert"), "--node-files", "n.nod.xml", "--edge-files", "n.edg.xml"]
        if crossings:
            root = ET.Element("connections")
            for row in crossings:
                ET.SubElement(root, "crossing", {k: str(v) for k, v in row.items()})
            ET.ElementTree(root).write(tmpd / "n.con.xml")
            cmd += ["--connection-files", "n.con.xml"]
        _run([*cmd, *options, "-o", str(out.resolve())], tmpd)
    return out


def default_cache_dir() -> Path:
    base = os.environ.get("IIDSU_CACHE")
    return (Path(base) if base else Path.home() / ".cache" / "iidsu") / "towns"


def town_net_path(name: str, cache_dir: Path | None = None) -> Path:
    """The built-in town `name`'s .net.xml, built on first use and cached."""
    if name not in RECIPES:
        raise UserError(f"unknown town {name!r}; built-in towns: {', '.join(ALL_TOWNS)}")
    recipe = RECIPES[name]
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    path = cache / f"{name}-{_recipe_key(recipe)}.net.xml"
    if not path.exists():
        build_town(recipe, path)
    return path


# --- any network ---------------------------------------------------------------------------


def _opener(path: Path) -> Callable:
    """gzip.open for gzipped files (by magic number, whatever the name), else open."""
    with open(path, "rb") as f:
        magic = f.read(2)
    return gzip.open if magic == b"\x1f\x8b" else open


def _head(path: Path, n: int = 1 << 16) -> bytes:
    opener = _opener(path)
    try:
        with opener(path, "rb") as f:
            return f.read(n)
    except (OSError, EOFError) as e:
        raise UserError(f"{path}: cannot read ({e})") from e


def check_network(path: Path) -> Path:
    """Return `path` resolved if it is a SUMO network (.net.xml or .net.xml.gz), else UserError."""
    path = Path(path).expanduser()
    if not path.exists():
        raise UserError(f"{path}: no such file")
    if not path.is_file():
        raise UserError(f"{path}: not a file")
    head = _head(path).decode("utf-8", errors="replace")
    body = re.sub(r"<\?xml.*?\?>|<!--.*?-->", "", head, flags=re.S).lstrip()
    m = re.match(r"<\s*([A-Za-z_][\w.-]*)", body)
    if m is None or m.group(1) != "net":
        what = f"its root element is <{m.group(1)}>" if m else "it is not XML"
        raise UserError(
            f"{path}: not a SUMO network ({what}; expected <net>, e.g. a .net.xml written by "
            "netconvert)"
        )
    return path.resolve()


def network_sha256(path: Path) -> str:
    """sha256 of the network file's bytes, as stored (hex). Kept per process for a file whose
    size and modification time are unchanged (every episode asks twice)."""
    st = os.stat(path)
    return _file_sha256(str(Path(path).resolve()), st.st_size, st.st_mtime_ns)


def held_out_town_of(path: Path) -> str | None:
    """The held-out town (HELD_OUT_TOWNS) whose network `path` is (a copy of its cached file,
    gzipped or not, under any name), else None. Builds the held-out towns if not cached."""
    path = Path(path)
    mine = {network_sha256(path)}
    if _opener(path) is gzip.open:
        with gzip.open(path, "rb") as f:
            mine.add(hashlib.sha256(f.read()).hexdigest())
    for name in HELD_OUT_TOWNS:
        if network_sha256(town_net_path(name)) in mine:
            return name
    return None


@functools.lru_cache(maxsize=64)
def _file_sha256(path: str, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass(frozen=True)
class NetworkStats:
    """Summary of a network for `datagen towns`."""

    width_m: float
    height_m: float
    lights: int
    stops: int
    other: int
    lane_km: float
    sidewalk_km: float
    crossings: int


def network_stats(path: Path) -> NetworkStats:
    """Junction counts (signalised / stop-controlled / other real junctions), lane-km of
    vehicle lanes and km of sidewalk, from the network file."""
    with _opener(path)(path, "rb") as f:
        root = ET.parse(f).getroot()
    lights = stops = other = crossings = 0
    lane_m = sidewalk_m = 0.0
    for j in root.iter("junction"):
        t = j.get("type", "")
        if t in ("internal", "dead_end"):
            continue
        if t.startswith("traffic_light"):
            lights += 1
        elif t in ("allway_stop", "priority_stop"):
            stops += 1
        else:
            other += 1
    for e in root.iter("edge"):
        fn = e.get("function", "")
        if fn == "crossing":
            crossings += 1
        if fn in ("internal", "crossing", "walkingarea"):
            continue
        for lane in e.iter("lane"):
            length = float(lane.get("length", 0.0))
            if lane.get("allow", "") == "pedestrian":
                sidewalk_m += length
            elif "passenger" in lane.get("allow", "passenger") and "passenger" not in lane.get(
                "disallow", ""
            ):
                lane_m += length
    loc = root.find("location")
    x0, y0, x1, y1 = (float(v) for v in loc.get("convBoundary").split(","))
    return NetworkStats(
        width_m=x1 - x0,
        height_m=y1 - y0,
        lights=lights,
        stops=stops,
        other=other,
        lane_km=lane_m / 1000.0,
        sidewalk_km=sidewalk_m / 1000.0,
        crossings=crossings,
    )


# --- CLI -----------------------------------------------------------------------------------


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--net", type=Path, help="describe this SUMO network instead of the towns")
    p.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="where the generated towns are kept (default: ~/.cache/iidsu/towns)",
    )


def run(args: argparse.Namespace) -> int:
    rows = []
    if args.net is not None:
        path = check_network(args.net)
        rows.append((path.name.split(".")[0], "user network", path))
    else:
        cache = outputs.check_dir(args.cache, "--cache") if args.cache is not None else None
        for name in ALL_TOWNS:
            rows.append((name, RECIPES[name].description, town_net_path(name, cache)))
    head = (
        f"{'town':<12} {'size (m)':>11} {'lights':>6} {'stop':>5} {'other':>5} "
        f"{'crossings':>9} {'lane-km':>7} {'sidewalk-km':>11}  description"
    )
    print(head)
    print("-" * len(head))
    for name, desc, path in rows:
        s = network_stats(path)
        print(
            f"{name:<12} {s.width_m:>5.0f}x{s.height_m:<5.0f} {s.lights:>6} {s.stops:>5} "
            f"{s.other:>5} {s.crossings:>9} {s.lane_km:>7.1f} {s.sidewalk_km:>11.1f}  {desc}"
        )
    return 0
