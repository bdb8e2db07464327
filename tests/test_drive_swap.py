"""The weather swap (drive/swap.py, the paper's Fig. 6): the statistics as pure functions, then
real SUMO and real sensors with planners whose answer is known, then the CLI with a checkpoint."""

import json
import math

import numpy as np
import pytest

from datagen.state import AgentState, FrameState, Pose
from datagen.world.towns import town_net_path
from drive import cli, swap


def _frame(*agents):
    ego = AgentState("ego", "vehicle", Pose(0.0, 0.0, 0.0), 4.7, 1.85, 1.5, 5.0)
    return FrameState(0.0, ego, tuple(agents), "follow", (30.0, 0.0), "none", None, False, None,
                      "none", ())  # fmt: skip


def _car(x, y, length=4.5, cls="vehicle"):
    return AgentState(f"v{x}", cls, Pose(x, y, 0.0), length, 1.8, 1.5, 0.0)


def test_planned_speed_is_the_mean_waypoint_spacing_per_half_second():
    assert swap.planned_speed(np.array([[2.5 * k, 0.0] for k in (1, 2, 3, 4)])) == 5.0
    assert swap.planned_speed(np.zeros((4, 2))) == 0.0


def test_the_lead_is_the_nearest_vehicle_ahead_in_the_lane():
    f = _frame(_car(20.0, 0.5), _car(12.0, 3.5), _car(-8.0, 0.0), _car(9.0, 0.0, cls="pedestrian"))
    assert swap.lead_rear_m(f) == pytest.approx(
        20.0 - 2.25
    )  # the others: next lane, behind, a person
    assert swap.lead_rear_m(_frame(_car(40.0, 0.0))) is None  # beyond LEAD_RANGE_M


def test_ratio_interval_covers_the_true_ratio_and_is_a_point_without_noise():
    rng = np.random.default_rng(0)
    first = 5.0 + rng.normal(0.0, 1.0, 400)
    second = 0.8 * first + rng.normal(0.0, 0.3, 400)
    ratio, lo, hi = swap.ratio_interval(first, second, np.random.default_rng(1))
    assert lo < 0.8 < hi and hi - lo < 0.05 and lo < ratio < hi
    assert swap.ratio_interval(first, first, np.random.default_rng(1)) == (1.0, 1.0, 1.0)


def _brightness_planner(frame, jpeg, lidar_png, ground_png):
    """Plans faster the brighter the camera: a model that reads the weather."""
    from schemas import codecs

    v = codecs.decode_image(jpeg).mean() / 255.0 * 10.0
    return np.array([[v * t, 0.0] for t in (0.5, 1.0, 1.5, 2.0)])


@pytest.mark.slow
def test_the_same_traffic_is_sensed_in_both_weathers_and_plans_compared():
    net = town_net_path("grid_small")
    doc, fig = swap.weather_swap(_brightness_planner, net, 3, "normal", 6)
    s = doc["summary"]
    assert s["frames"] == 6 and s["world"] == {"weather": "sunny", "behaviour": "normal", "seed": 3}
    # rain darkens the camera: this planner plans slower in it, every frame
    sp = doc["per_frame"]["speed_mps"]
    assert all(r < u for u, r in zip(sp["sunny"], sp["rainy"]))
    assert s["speed_ratio"] < 1.0 and s["speed_ratio_ci95"][1] < 1.0
    assert set(fig["shots"]) == {"sunny", "rainy"}
    img = swap.figure(fig["frame"], fig["shots"])
    assert img.shape == (256, 3 * 256, 3) and img.dtype == np.uint8
    # a planner that ignores its inputs plans the same in both: ratio exactly 1
    blind = swap.weather_swap(lambda *a: np.full((4, 2), 1.0), net, 3, "normal", 3)[0]
    assert blind["summary"]["speed_ratio"] == 1.0
    assert blind["summary"]["speed_ratio_ci95"] == [1.0, 1.0]


def test_cli_writes_the_report_and_rejects_bad_input(tmp_path, capsys):
    torch = pytest.importorskip("torch")
    from datagen.sensors.config import SensorConfig
    from training.config import PRESETS
    from training.model import IIDSU

    cfg = PRESETS["tiny"][0]
    ckpt = tmp_path / "tiny.pt"
    state = {"model": IIDSU(cfg).state_dict(), "model_config": cfg.to_dict()}
    torch.save({**state, "sensor_config": SensorConfig().to_dict()}, ckpt)
    out = tmp_path / "swap"
    argv = ["swap", "--policy", f"ckpt:{ckpt}", "--town", "grid_small", "--frames", "2"]
    assert cli.main(argv + ["--out", str(out), "--device", "cpu"]) == 0
    doc = json.loads((out / "swap.json").read_text())
    assert doc["summary"]["frames"] == 2 and (out / "swap.png").stat().st_size > 0
    assert math.isfinite(doc["summary"]["speed_ratio"])
    capsys.readouterr()
    for bad, msg in [
        (["--weathers", "sunny"], "--weathers"),
        (["--frames", "0"], "--frames"),
    ]:
        assert cli.main(argv + ["--out", str(out)] + bad) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and msg in err[0], err
    assert cli.main(["swap", "--policy", "constant", "--out", str(out)]) == 2
    assert "needs a model" in capsys.readouterr().err
