"""Known-answer tests of every open-loop metric `train eval` prints (training/evaluate.py):
L1, ADE and FDE of the planner and of the constant-velocity baseline, AP at each distance
threshold, F1 and accuracy of the traffic rules, IoU and mIoU of the BEV map, weather accuracy;
each on a hand-built case whose answer is worked out in the test."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from training.evaluate import (  # noqa: E402
    DISTANCES_M,
    _collect,
    _score,
    average_precision,
    binary_scores,
)


def _raw(**over):
    raw = {"wp_err": [np.zeros((1, 4, 2))], "cv_err": [np.zeros((1, 4, 2))], "confusion": []}
    raw.update(over)
    return raw


def test_l1_ade_and_fde_of_hand_built_errors():
    err = np.array([[[3.0, 4.0], [0.0, 0.0], [0.0, 0.0], [6.0, 8.0]]])  # distances 5, 0, 0, 10
    cv = np.array([[[1.0, 0.0]] * 4])
    r = _score(_raw(wp_err=[err], cv_err=[cv]), ("planning",))
    assert r["frames"] == 1
    assert r["planning"]["ade_m"] == pytest.approx(15.0 / 4)
    assert r["planning"]["fde_m"] == pytest.approx(10.0)
    assert r["planning"]["l1_m"] == pytest.approx((3 + 4 + 6 + 8) / 8)
    assert r["constant_velocity"]["ade_m"] == pytest.approx(1.0)
    # two frames: means over frames
    r = _score(_raw(wp_err=[err, np.zeros((1, 4, 2))], cv_err=[cv, cv]), ("planning",))
    assert r["frames"] == 2 and r["planning"]["fde_m"] == pytest.approx(5.0)


class _Still(torch.nn.Module):
    """Plans to stand still (all waypoints at the ego): the planner's error is the truth."""

    class cfg:  # noqa: N801 - read as model.cfg.output_px
        output_px = 8

    def forward(self, image, lidar, speed, target_point):
        return {"planning": torch.zeros(len(speed), 4, 2)}


def test_constant_velocity_baseline_keeps_the_speed_straight_ahead():
    # at 4 m/s the baseline's waypoints are 2, 4, 6, 8 m ahead (WAYPOINT_TIMES_S 0.5 .. 2 s)
    truth = torch.tensor([[[2.0, 0.0], [4.0, 0.0], [6.0, 1.0], [8.0, 3.0]]])
    batch = {
        "image": torch.zeros(1, 3, 4, 4),
        "lidar": torch.zeros(1, 2, 4, 4),
        "speed": torch.tensor([4.0]),
        "target_point": torch.zeros(1, 2),
        "waypoints": truth,
    }
    raw = _collect(_Still(), [batch], torch.device("cpu"))
    r = _score(raw, ("planning",))
    assert r["constant_velocity"]["ade_m"] == pytest.approx((0 + 0 + 1 + 3) / 4)
    assert r["constant_velocity"]["fde_m"] == pytest.approx(3.0)
    dist = np.hypot(truth[0, :, 0].numpy(), truth[0, :, 1].numpy())
    assert r["planning"]["ade_m"] == pytest.approx(dist.mean(), rel=1e-6)


def test_average_precision_at_each_distance_threshold():
    truths = [np.array([[1.0, 0.0, 0.0], [1.0, 10.0, 0.0]])]
    # 0.3 m off the first, 1.5 m off the second, and a false positive far away
    preds = [np.array([[0.9, 0.3, 0.0], [0.8, 11.5, 0.0], [0.7, 50.0, 50.0]])]
    ap = {d: average_precision(preds, truths, d) for d in DISTANCES_M}
    # within 0.5 and 1 m only the first matches: precision 1 up to recall 0.5, then nothing;
    # 101-point interpolation counts the 51 recall levels 0, 0.01, .., 0.5
    assert ap[0.5] == pytest.approx(51 / 101) and ap[1.0] == pytest.approx(51 / 101)
    # within 2 and 4 m both match before the false positive: precision 1 at every recall
    assert ap[2.0] == pytest.approx(1.0) and ap[4.0] == pytest.approx(1.0)
    # the false positive first: precision 1/2 at recall 0.5, 2/3 at recall 1 -> 2/3 everywhere
    worse = [np.array([[0.95, 50.0, 50.0], [0.9, 0.3, 0.0], [0.8, 10.2, 0.0]])]
    assert average_precision(worse, truths, 1.0) == pytest.approx(2 / 3)
    # one true centre is matched once: a duplicate prediction is a false positive
    dup = [np.array([[0.9, 0.0, 0.0], [0.8, 0.1, 0.0]])]
    one = [np.array([[1.0, 0.0, 0.0]])]
    assert average_precision(dup, one, 1.0) == pytest.approx(1.0)  # recall 1 at rank 1
    assert average_precision([np.zeros((0, 3))], [np.zeros((0, 3))], 1.0) is None


def test_f1_and_accuracy_of_the_traffic_rules():
    s = binary_scores(np.array([0.9, 0.6, 0.2, 0.4]), np.array([1.0, 0.0, 1.0, 0.0]))
    # predicted positive: frames 0, 1; true positive: 0, 2 -> tp 1, F1 = 2 * 1 / (2 + 2)
    assert s["f1"] == pytest.approx(0.5) and s["accuracy"] == pytest.approx(0.5)
    assert s["positives"] == 2
    assert binary_scores(np.array([0.1, 0.2]), np.array([0.0, 0.0]))["f1"] is None
    assert binary_scores(np.array([0.5]), np.array([1.0]))["f1"] == pytest.approx(1.0)


def test_iou_and_miou_of_a_hand_built_confusion():
    # rows: truth (other, drivable, lane_marking), columns: prediction
    confusion = np.array([[5, 1, 0], [2, 3, 0], [0, 0, 0]])
    r = _score(_raw(confusion=[confusion]), ("planning", "bev"))
    iou = r["bev"]["iou"]
    assert iou["other"] == pytest.approx(5 / (7 + 6 - 5))  # 0.625
    assert iou["drivable"] == pytest.approx(3 / (4 + 5 - 3))  # 0.5
    assert iou["lane_marking"] is None  # neither true nor predicted: no IoU
    assert r["bev"]["miou"] == pytest.approx((0.625 + 0.5) / 2)


def test_weather_accuracy_and_confusion():
    raw = _raw(weather_pred=[np.array([0, 1, 2, 2])], weather_true=[np.array([0, 1, 2, 3])])
    r = _score(raw, ("planning", "weather"))
    assert r["weather"]["accuracy"] == pytest.approx(0.75)
    assert r["weather"]["confusion"][3][2] == 1 and r["weather"]["confusion"][0][0] == 1
