"""The privileged planner (training/privileged.py, issue 45 item 2): its raster puts the map and
the agents where the BEV grid says, its scalars encode what the labels say, `train fit --arch
privileged` trains and writes a checkpoint `drive eval` loads, it learns a plan that depends on
its input, and a user's mistake is one line."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from schemas import COMMANDS, TRAFFIC_LIGHTS
from training import cli
from training.privileged import (
    CHANNELS,
    GRID_PX,
    SCALARS,
    AgentBoxes,
    PrivilegedPlanner,
    Situation,
    inputs,
    raster,
    scalars,
)


def _agents(**fields) -> AgentBoxes:
    n = len(fields["x"])
    base = {"yaw": np.zeros(n), "length": np.full(n, 4.0), "width": np.full(n, 2.0)}
    base |= {"speed": np.zeros(n), "walker": np.zeros(n, bool)}
    return AgentBoxes(**{k: np.asarray(v) for k, v in (base | fields).items()})


def test_the_raster_puts_map_and_agents_where_the_bev_grid_says():
    sem = np.zeros((256, 256), np.uint8)
    sem[:, 120:136] = 1  # a road straight ahead, 2 m wide (8 px per m)
    sem[40, 128] = 2  # one lane-marking pixel 27 m ahead
    # a car 10 m ahead driving on at 10 m/s, a pedestrian 5 m ahead and 4 m to the left
    agents = _agents(
        x=[10.0, 5.0], y=[0.0, 4.0], speed=[10.0, 0.0], length=[4.0, 0.5], width=[2.0, 0.5],
        walker=[False, True],
    )  # fmt: skip
    g = raster(sem, agents)
    assert g.shape == (len(CHANNELS), GRID_PX, GRID_PX) and g.dtype == np.uint8
    assert g[0, :, 30:34].all() and not g[0, :, :30].any() and not g[0, :, 34:].any()
    assert np.argwhere(g[1]).tolist() == [[10, 32]]
    # 0.5 m per pixel, row 0 is 32 m ahead: 10 m ahead is row 44; 15 m (+0.5 s) row 34; 20 m row 24
    for channel, row in ((2, 44), (3, 34), (4, 24)):
        rows = np.flatnonzero(g[channel].any(1))
        assert rows.min() <= row <= rows.max() and rows.max() - rows.min() <= 9, channel
        cols = np.flatnonzero(g[channel].any(0))
        assert cols.min() >= 29 and cols.max() <= 34
    # the pedestrian stands: the same pixels at t and +1 s, row 54 (5 m), column 24 (4 m left)
    assert np.array_equal(g[5], g[7]) and g[5][53:56, 23:26].any() and g[5].sum() <= 4
    assert not g[2][50:58, 20:28].any()  # a walker is not a vehicle


def test_the_scalars_say_what_the_labels_say():
    v = scalars(Situation(5.0, np.array([30.0, -90.0]), "left", "red", 15.0, False, None))
    named = dict(zip(SCALARS, v.tolist()))
    assert named["speed/10"] == 0.5 and named["target_x/30"] == 1.0
    assert named["target_y/30"] == -2.0  # clipped at 60 m
    assert [named[f"command={c}"] for c in COMMANDS] == [1, 0, 0, 0]
    assert [named[f"light={c}"] for c in TRAFFIC_LIGHTS] == [0, 1, 0, 0]
    assert named["light_distance/30"] == 0.5 and named["stop_distance/30"] == 1.0
    assert scalars(Situation(0, np.zeros(2), "follow", "none", None, True, 3.0))[
        -1
    ] == pytest.approx(0.1)


def _dataset(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Frames where the plan depends on the input: a vehicle ahead (stand) or none (drive on
    at 8 m/s), turning towards the target point's side."""
    rows = []
    for _ in range(n):
        blocked, side = rng.random() < 0.5, rng.choice([-1.0, 1.0])
        agents = _agents(x=[6.0], y=[0.0]) if blocked else AgentBoxes.empty()
        sem = np.ones((256, 256), np.uint8)
        situation = Situation(4.0, np.array([20.0, 10 * side]), "follow", "none", None, False, None)
        x = inputs(sem, agents, situation)
        t = np.array([0.5, 1.0, 1.5, 2.0])
        wp = np.zeros((4, 2)) if blocked else np.stack([8 * t, side * 0.5 * t**2], 1)
        rows.append(x | {"waypoints": wp.astype(np.float32), "expert_reason": np.array("none")})
    return {k: np.stack([r[k] for r in rows]) for k in rows[0]}


def test_it_learns_a_plan_that_depends_on_the_scene():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    train, val = _dataset(256, rng), _dataset(64, rng)
    model = PrivilegedPlanner()
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    tensors = {k: torch.from_numpy(v) for k, v in train.items() if k != "expert_reason"}
    for _ in range(150):
        idx = torch.from_numpy(rng.choice(256, 32, replace=False))
        b = {k: v[idx] for k, v in tensors.items()}
        loss = (model.plan(b) - b["waypoints"]).abs().sum(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    from training.privileged import evaluate

    m = evaluate(model, val)
    # the mean plan (half stand, half go) is ~4 m off; constant velocity (4 m/s) too
    assert m["ade_m"] < 1.0 < m["cv_ade_m"], m


def test_train_fit_arch_privileged_writes_a_checkpoint_drive_loads(synthetic_shards, tmp_path):
    out = tmp_path / "priv"
    argv = ["fit", "--arch", "privileged", "--shards", str(synthetic_shards), "--out", str(out)]
    assert cli.main([*argv, "--epochs", "2", "--val-towns", "beta", "--batch-size", "2"]) == 0
    lines = (out / "metrics.jsonl").read_text().splitlines()
    assert len(lines) == 2 and '"val"' in lines[-1]
    from drive.policy import ModelPolicy, parse_policy

    policy = ModelPolicy(parse_policy(f"ckpt:{out / 'last.pt'}"), {})
    assert not policy.needs_sensors and isinstance(policy.model, PrivilegedPlanner)
    assert cli.main([*argv, "--epochs", "1"]) == 2  # a second fit into it needs --force


@pytest.mark.parametrize("flag", [["--config", "tiny"], ["--no-bev"], ["--resume"]])
def test_a_sensor_model_flag_is_one_line(synthetic_shards, tmp_path, capsys, flag):
    argv = [
        "fit",
        "--arch",
        "privileged",
        "--shards",
        str(synthetic_shards),
        "--out",
        str(tmp_path),
    ]
    assert cli.main([*argv, *flag]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not an option of --arch privileged" in err[0], err


def test_stand_to_go_frames_and_their_weights():
    from training.privileged import go_weights

    t = np.array([0.5, 1.0, 1.5, 2.0])
    wp = np.stack([np.stack([v * t, 0 * t], 1) for v in (0.0, 2.0, 2.0)]).astype(np.float32)
    data = {"speed": np.array([0.0, 0.0, 3.0], np.float32), "waypoints": wp}
    # stands and stays / stands and drives off / drives
    assert go_weights(data, 5.0, 0.25).tolist() == [0.25, 5.0, 1.0]
