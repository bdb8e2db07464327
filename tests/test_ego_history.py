"""How long the ego has stood (training/ego_history.py, issue 45 item 3): the clock the
closed loop runs at its plans is the one the training labels run over an episode's frames,
per episode in frame order, and a planner that reads it can learn to drive off after a wait
that nothing else in its input shows."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from training.ego_history import STAND_MPS, StandClock, stood_labels
from training.privileged import SCALARS, PrivilegedConfig, PrivilegedPlanner


def test_the_clock_counts_the_plans_spent_standing():
    clock = StandClock()
    speeds = [3.0, 0.2, 0.1, 0.0, STAND_MPS, 0.0, 0.0]
    assert [clock.tick(v) for v in speeds] == [0.0, 0.0, 0.5, 1.0, 0.0, 0.0, 0.5]
    clock.reset()
    assert clock.tick(0.0) == 0.0


def test_the_labels_run_the_clock_per_episode_in_frame_order(tmp_path):
    # two episodes interleaved and out of frame order, as a shard may hold them
    rows = [("b", 1, 0.0), ("a", 2, 0.0), ("a", 0, 2.0), ("b", 0, 0.0), ("a", 1, 0.0),
            ("b", 2, 0.0), ("a", 3, 1.0)]  # fmt: skip
    table = pa.table({"episode_id": [r[0] for r in rows], "frame": [r[1] for r in rows],
                      "ego_speed": pa.array([r[2] for r in rows], pa.float32())})  # fmt: skip
    pq.write_table(table, tmp_path / "s.parquet")
    got = stood_labels(str(tmp_path / "s.parquet"))
    for ep in ("a", "b"):
        clock = StandClock()
        for i in sorted((i for i, r in enumerate(rows) if r[0] == ep), key=lambda i: rows[i][1]):
            assert got[i] == clock.tick(rows[i][2]), (ep, i)
    assert got.tolist() == [0.5, 0.5, 0.0, 0.0, 0.0, 1.0, 0.0]


def test_a_planner_that_reads_it_learns_to_drive_off_after_a_wait():
    """Identical standing scenes; the label drives off once the ego has stood 3 s or more."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    n = 256
    stood = rng.choice(np.arange(0, 8.5, 0.5), n).astype(np.float32)
    t = np.array([0.5, 1.0, 1.5, 2.0], np.float32)
    go = stood >= 3.0
    wp = np.zeros((n, 4, 2), np.float32)
    wp[go, :, 0] = 2.0 * t
    sample = {"grid": torch.zeros(n, 8, 64, 64, dtype=torch.uint8),
              "scalars": torch.zeros(n, len(SCALARS)), "target_point": torch.tensor([[20.0, 0.0]]).expand(n, 2),
              "speed": torch.zeros(n), "stood": torch.from_numpy(stood)}  # fmt: skip
    for reads in (False, True):
        torch.manual_seed(0)
        model = PrivilegedPlanner(PrivilegedConfig(width=8, hidden=32, stood=reads))
        opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
        for _ in range(200):
            loss = (model.plan(sample) - torch.from_numpy(wp)).abs().sum(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        model.eval()
        with torch.no_grad():
            moves = model.plan(sample)[:, -1, 0].numpy()
        err = np.abs(moves - wp[:, -1, 0]).mean()
        if reads:
            assert err < 0.5 and moves[go].min() > moves[~go].max(), err
        else:  # the same scene with nothing to tell the wait: the mean plan, ~2 m off
            assert err > 1.0, err
