"""`drive eval` with real SUMO on small routes: the expert scores as the ceiling, `constant` far
lower, results are reproducible, and bad input is one clear line with a non-zero exit."""

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from datagen.world.towns import build_plain_network, town_net_path
from drive import cli
from drive.evaluate import Task, drive_route, summary_doc
from drive.policy import PolicySpec
from drive.routes import generate, load_routes, save_routes


@pytest.fixture(scope="module")
def route_file(tmp_path_factory):
    # seed 0: both routes turn at a junction, so driving straight cannot complete them
    d = tmp_path_factory.mktemp("routes")
    routes = generate(town_net_path("grid_small"), 2, 0, seed=0, prefix="gs", town="grid_small")
    path = d / "gs.json"
    save_routes(routes, path, "gs")
    return path


@pytest.fixture(scope="module")
def expert_docs(route_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("expert")
    _, routes = load_routes(route_file)
    return [drive_route(Task(r, PolicySpec("expert"), str(out), False)) for r in routes]


def _numbers(doc):
    return {k: v for k, v in doc.items() if k not in ("timing", "run")}  # run: how it was asked


@pytest.mark.slow
def test_expert_scores_the_ceiling_without_collisions_or_red_lights(expert_docs):
    s = summary_doc("gs", expert_docs)
    assert s["ds"] >= 95.0, [(d["ds"], d["ended"], d["events"]) for d in expert_docs]
    for d in expert_docs:
        c = d["counts"]
        assert c["collision_vehicle"] == c["collision_pedestrian"] == c["collision_layout"] == 0
        assert c["red_light"] == 0 and c["stop_sign"] == 0
        assert d["ended"] == "route_complete"


@pytest.mark.slow
def test_same_route_and_seed_give_identical_numbers(route_file, expert_docs, tmp_path):
    _, routes = load_routes(route_file)
    again = drive_route(Task(routes[0], PolicySpec("expert"), str(tmp_path), False))
    assert _numbers(again) == _numbers(expert_docs[0])
    on_disk = json.loads((tmp_path / "routes" / f"{routes[0].route_id}.json").read_text())
    assert _numbers(on_disk) == _numbers(again)


@pytest.fixture(scope="module")
def constant_docs(route_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("constant")
    _, routes = load_routes(route_file)
    return [drive_route(Task(r, PolicySpec("constant"), str(out), False)) for r in routes]


@pytest.mark.slow
def test_constant_scores_far_below_the_expert(constant_docs, expert_docs):
    docs = constant_docs
    ds = summary_doc("gs", docs)["ds"]
    assert ds < 0.5 * summary_doc("gs", expert_docs)["ds"], [(d["ds"], d["ended"]) for d in docs]


@pytest.mark.slow
def test_two_workers_give_the_serial_numbers(route_file, constant_docs, tmp_path, capsys):
    out = tmp_path / "two"
    argv = ["eval", "--policy", "constant", "--routes", str(route_file), "--out", str(out)]
    assert cli.main(argv + ["--workers", "2", "--record", "1"]) == 0
    assert "DS" in capsys.readouterr().out
    for d in constant_docs:
        got = json.loads((out / "routes" / f"{d['route']['route_id']}.json").read_text())
        assert _numbers(got) == _numbers(d)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ds"] == pytest.approx(summary_doc("gs", constant_docs)["ds"])
    videos = sorted((out / "videos").glob("*.mp4"))
    assert [v.name for v in videos] == [f"{constant_docs[0]['route']['route_id']}.mp4"]
    assert videos[0].stat().st_size > 10_000


def _error(capsys, argv):
    rc = cli.main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0
    assert len(err) == 1 and err[0].startswith(f"drive {argv[0]}: error:"), err
    return err[0]


def test_bad_policies_are_one_line_errors(route_file, tmp_path, capsys):
    base = ["eval", "--routes", str(route_file), "--out", str(tmp_path / "o")]
    assert "no such checkpoint" in _error(capsys, base + ["--policy", f"ckpt:{tmp_path}/x.pt"])
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    assert "not a checkpoint" in _error(capsys, base + ["--policy", f"ckpt:{junk}"])
    assert "expected expert, expert-plan, constant" in _error(capsys, base + ["--policy", "human"])
    assert not (tmp_path / "o").exists()


def test_a_checkpoint_of_other_sensors_is_refused(route_file, tmp_path, capsys):
    torch = pytest.importorskip("torch")
    from datagen.sensors.config import SensorConfig
    from training.config import PRESETS
    from training.model import IIDSU

    cfg = PRESETS["tiny"][0]
    sensors = SensorConfig().to_dict()
    sensors["lidar"]["channels"] = 16  # data recorded with another LiDAR
    ckpt = tmp_path / "other.pt"
    torch.save(
        {"model": IIDSU(cfg).state_dict(), "model_config": cfg.to_dict(), "sensor_config": sensors},
        ckpt,
    )
    argv = ["eval", "--routes", str(route_file), "--out", str(tmp_path / "o")]
    msg = _error(capsys, argv + ["--policy", f"ckpt:{ckpt}"])
    assert "other sensors" in msg and "lidar" in msg


@pytest.mark.slow
def test_a_route_file_for_another_network_is_refused(route_file, tmp_path, capsys):
    _, routes = load_routes(route_file)
    moved = tmp_path / "moved.json"
    save_routes([replace(routes[0], network_sha256="0" * 64)], moved, "moved")
    argv = ["eval", "--policy", "expert", "--routes", str(moved), "--out", str(tmp_path / "o")]
    assert "another network" in _error(capsys, argv)
    # a --net route file driven on a different --net
    other = build_plain_network(
        [dict(id="A", x=0, y=0), dict(id="B", x=300, y=0)],
        [{"id": "AB", "from": "A", "to": "B", "numLanes": 1, "speed": 13.89}],
        tmp_path / "other.net.xml",
    )
    net_routes = tmp_path / "net.json"
    save_routes(
        [replace(routes[0], town=None, net_name=town_net_path("grid_small").name)], net_routes, "n"
    )
    argv = ["eval", "--policy", "expert", "--routes", str(net_routes), "--net", str(other)]
    assert "another network" in _error(capsys, argv + ["--out", str(tmp_path / "o")])
    garbage = tmp_path / "garbage.json"
    garbage.write_text("{}")
    argv = ["eval", "--policy", "expert", "--routes", str(garbage), "--out", str(tmp_path / "o")]
    assert "not a route file" in _error(capsys, argv)


@pytest.mark.slow
def test_drive_routes_writes_reproducible_route_sets_on_any_network(tmp_path, capsys):
    net = town_net_path("spider")
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    for out in (a, b):
        assert (
            cli.main(
                ["routes", "--net", str(net), "--short", "2", "--long", "1", "--out", str(out)]
            )
            == 0
        )
    assert a.read_text() == b.read_text()
    name, routes = load_routes(a)
    assert [r.kind for r in routes] == ["short", "short", "long"]
    assert all(100 <= r.length_m <= 500 for r in routes[:2]) and 1000 <= routes[2].length_m <= 2000
    assert routes[0].town is None and routes[0].net_name == net.name
    # portable: no path of this machine in the file; moved beside its network, it drives
    assert str(net.parent) not in a.read_text()
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    shutil.copyfile(net, moved / net.name)
    shutil.copyfile(a, moved / "routes.json")
    argv = ["eval", "--policy", "constant", "--routes", str(moved / "routes.json")]
    argv += ["--out", str(tmp_path / "o"), "--limit", "1", "--max-sim-s", "3"]
    assert cli.main(argv) == 0
    capsys.readouterr()
    (moved / net.name).unlink()
    assert "give it with --net" in _error(capsys, argv[:5] + ["--out", str(tmp_path / "o2")])
    for r in routes:  # the weather's behaviour, by the data's rule
        assert (
            r.behaviour == "cautious"
            if r.weather in ("rainy", "foggy")
            else r.behaviour != "cautious"
        )


def test_standard_benchmarks_are_checked_in_and_cover_what_they_promise():
    from datagen.world.towns import HELD_OUT_TOWNS, TOWN_NAMES
    from drive.routes import ROUTES_DIR

    _, train = load_routes(ROUTES_DIR / "training_towns.json")
    assert {r.town for r in train} == set(TOWN_NAMES)
    for town in TOWN_NAMES:
        assert {r.weather for r in train if r.town == town} == {"sunny", "cloudy", "rainy", "foggy"}
    for name, kind, lo, hi in (
        ("heldout_short", "short", 100, 500),
        ("heldout_long", "long", 1000, 2000),
    ):
        _, rs = load_routes(ROUTES_DIR / f"{name}.json")
        assert len(rs) == 10 and {r.town for r in rs} == set(HELD_OUT_TOWNS)
        assert all(r.kind == kind and lo <= r.length_m <= hi for r in rs)


def test_a_route_the_ego_cannot_start_is_found_when_generated(tmp_path):
    """Issue 38 item 8: `undrivable` inserts the ego as a build does; routes failing it are
    not written (drive.routes._pick_route)."""
    from drive.routes import undrivable

    nodes = [dict(id="A", x=0, y=0), dict(id="B", x=100, y=0), dict(id="C", x=200, y=0)]
    edges = [
        {"id": "AB", "from": "A", "to": "B", "numLanes": 1, "speed": 13.89, "allow": "bicycle"},
        {"id": "BC", "from": "B", "to": "C", "numLanes": 1, "speed": 13.89},
    ]
    net = build_plain_network(nodes, edges, tmp_path / "bike.net.xml")
    assert undrivable(net, ("BC",)) is None
    # a first edge only bicycles may use: SUMO cannot start the ego there
    why = undrivable(net, ("AB", "BC"))
    assert why  # the reason, whatever SUMO or the world raised


def _gs_routes(tmp_path):
    path = tmp_path / "gs2.json"
    save_routes(generate(town_net_path("grid_small"), 2, 0, 0, "gs", "grid_small"), path, "gs")
    return path


def test_a_failing_route_is_recorded_the_others_go_on_and_a_rerun_resumes(tmp_path, capsys):
    """Issue 38 item 8: a route whose drive fails is recorded with its reason (DS 0) and does
    not stop the benchmark; the same command again keeps the finished route and drives the
    failed one; another policy in the same directory is refused."""
    from drive.evaluate import execute, summary_doc

    _, routes = load_routes(_gs_routes(tmp_path))
    # a route file edited after the check (its edges no longer connect) fails in its worker
    broken = replace(routes[1], route_id="broken", edges=tuple(reversed(routes[1].edges)))
    out = tmp_path / "direct"
    spec = PolicySpec("constant")
    tasks = [Task(r, spec, str(out), False, max_sim_s=10.0) for r in (broken, routes[0])]
    docs = list(execute(tasks, workers=1))
    assert [d["route"]["route_id"] for d in docs] == ["broken", routes[0].route_id]
    assert docs[0]["failure"].startswith("ValueError: edges") and docs[0]["ds"] == 0.0
    assert "do not connect" in docs[0]["failure"] and not docs[1].get("failure")
    on_disk = json.loads((out / "routes" / "broken.json").read_text())
    assert on_disk["failure"] == docs[0]["failure"]
    summary = summary_doc("x", docs)
    assert summary["n_routes"] == 2 and summary["n_failed"] == 1
    assert summary["failed"] == {"broken": docs[0]["failure"]}
    assert summary["ds"] == pytest.approx(docs[1]["ds"] / 2, rel=1e-4)
    # through the command: a result left failed (as a crash leaves it) is driven again
    path = tmp_path / "two.json"
    save_routes(routes, path, "two")
    out = tmp_path / "o"
    argv = ["eval", "--policy", "constant", "--routes", str(path), "--out", str(out)]
    argv += ["--max-sim-s", "10"]
    assert cli.main(argv) == 0
    capsys.readouterr()
    first, second = (out / "routes" / f"{r.route_id}.json" for r in routes)
    doc = json.loads(second.read_text())
    second.write_text(json.dumps({**doc, "failure": "RuntimeError: it crashed", "ds": 0.0}))
    mtime = first.stat().st_mtime_ns
    assert cli.main(argv) == 0
    assert "keeping 1 finished route result(s), driving 1" in capsys.readouterr().out
    assert first.stat().st_mtime_ns == mtime and not json.loads(second.read_text()).get("failure")
    msg = _error(capsys, ["eval", "--policy", "expert", *argv[3:]])
    assert "driven by another policy" in msg


def test_repetitions_drive_each_route_with_its_own_seed_and_average_per_route(tmp_path):
    """Issue 38 item 9: repetition 0 is the route's own seed (the single run's numbers),
    repetition r a seed drawn from (route seed, r); the summary's unit is the route."""
    from drive.evaluate import repetition_seed

    _, routes = load_routes(_gs_routes(tmp_path))
    path = tmp_path / "one.json"
    save_routes(routes[:1], path, "one")
    out = tmp_path / "reps"
    argv = ["eval", "--policy", "constant", "--routes", str(path), "--out", str(out)]
    assert cli.main(argv + ["--repetitions", "3", "--max-sim-s", "20"]) == 0
    rid = routes[0].route_id
    docs = [json.loads((out / "routes" / f"{n}.json").read_text())
            for n in (rid, f"{rid}_rep1", f"{rid}_rep2")]  # fmt: skip
    assert [d["repetition"] for d in docs] == [0, 1, 2]
    assert docs[0]["seed"] == routes[0].seed
    assert {d["seed"] for d in docs} == {repetition_seed(routes[0].seed, r) for r in range(3)}
    assert len({d["seed"] for d in docs}) == 3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_routes"] == 1 and summary["n_drives"] == 3 and summary["ds_ci"] == 0.0
    assert summary["ds"] == pytest.approx(np.mean([d["ds"] for d in docs]), rel=1e-4)
    assert repetition_seed(7, 1) == repetition_seed(7, 1) != repetition_seed(7, 2)
