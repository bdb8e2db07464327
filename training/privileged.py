"""The privileged planner: a small CNN that plans from ground truth instead of sensors.

Learning by Cheating (Chen et al. 2019), Roach (Zhang et al. 2021) and PlanT (Renz et al. 2022)
first teach a planner on privileged input and only then the sensor model; here it says whether
a failure to drive is the planning's or the perception's (issue 45). Its input is what the
shards' labels hold (paper Sec. IV-A), rasterised on a coarse copy of the BEV grid
(schemas.bev, 32 m ahead, 16 m to each side) at GRID_PX x GRID_PX (0.5 m per pixel):

- drivable area and lane markings (the `bev_semantic` label);
- vehicles (SUMO cars, trucks) and walkers (pedestrians, bicycles) at t (`boxes` with t = 0),
  and each moved on at its speed and heading for +0.5 s and +1.0 s (constant velocity: the
  recorded futures exist in the shards but not in closed loop, so neither reads them);

and, beside the raster, SCALARS: the ego speed, the target point, the route command, the light
of the junction ahead and its stop line's distance, the stop sign ahead and its distance.
The output is the sensor model's (the paper's GRU, training.heads.PlanningHead: 4 waypoints at
+0.5 .. +2.0 s in the ego frame), so `drive eval` drives it with the same controller.

`train fit --arch privileged` trains it (`fit`); in closed loop, drive/policy.py rasterises the
same input from the world's ground truth (datagen.labels, what the shards' labels are made of).
This module reads shards only (training never imports datagen).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq
import torch
from torch import nn

from schemas import COMMANDS, TRAFFIC_LIGHTS
from schemas.bev import BEV_SIZE_PX, ego_to_bev_px
from training import ego_history, pathspeed
from training.errors import UserError
from training.heads import PlanningHead

ARCH = "privileged"
GRID_PX = 64  # raster side: 0.5 m per pixel (the BEV grid's 256 px / 4)
_POOL = BEV_SIZE_PX // GRID_PX
FUTURE_S = (0.5, 1.0)  # the agents' constant-velocity positions, beside t
CHANNELS = (
    "drivable",
    "lane_marking",
    "vehicle",
    "vehicle+0.5s",
    "vehicle+1.0s",
    "walker",
    "walker+0.5s",
    "walker+1.0s",
)
WALKERS = ("pedestrian", "bicycle")
SIGNAL_RANGE_M = 30.0  # the shards' light and stop-sign columns look this far (schemas.FIELDS)
SCALARS = (
    "speed/10",
    "target_x/30",
    "target_y/30",
    *(f"command={c}" for c in COMMANDS),
    *(f"light={c}" for c in TRAFFIC_LIGHTS),
    "light_distance/30",
    "stop_sign",
    "stop_distance/30",
)
COLUMNS = (
    "episode_id",
    "frame",
    "town",
    "ego_speed",
    "command",
    "target_point",
    "waypoints",
    "traffic_light",
    "light_distance_m",
    "stop_sign",
    "stop_distance_m",
    "expert_reason",
    "bev_semantic",
    "boxes",
)
"""The shard columns the planner's samples are made of (no sensor column)."""


@dataclass(frozen=True)
class AgentBoxes:
    """The agents at t in the ego frame (m, rad), one entry per agent: centre x, y, heading,
    length, width, speed (m/s) and whether it walks (pedestrian, bicycle)."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    length: np.ndarray
    width: np.ndarray
    speed: np.ndarray
    walker: np.ndarray

    @classmethod
    def empty(cls) -> AgentBoxes:
        z = np.zeros(0)
        return cls(z, z, z, z, z, z, np.zeros(0, bool))


def _corners_px(b: AgentBoxes, dt_s: float) -> np.ndarray:
    """(N, 4, 2) corners (col, row) in GRID_PX pixels, each box moved on for `dt_s`."""
    c, s = np.cos(b.yaw), np.sin(b.yaw)
    x = b.x + b.speed * dt_s * c
    y = b.y + b.speed * dt_s * s
    hl, hw = b.length[:, None] / 2, b.width[:, None] / 2
    ox = np.array([1.0, 1.0, -1.0, -1.0])[None] * hl
    oy = np.array([1.0, -1.0, -1.0, 1.0])[None] * hw
    cx = x[:, None] + ox * c[:, None] - oy * s[:, None]
    cy = y[:, None] + ox * s[:, None] + oy * c[:, None]
    row, col = ego_to_bev_px(cx, cy)
    return np.stack([col, row], axis=2) / _POOL


_SHIFT = 3  # fillPoly sub-pixel bits


def _fill(img: np.ndarray, corners_px: np.ndarray) -> None:
    """Fill each box's polygon (a box narrower than a pixel still marks the pixel it is in)."""
    scale = 1 << _SHIFT
    for poly in corners_px:
        pts = ((poly - 0.5) * scale).round().astype(np.int32)  # pixel i's centre at i + 0.5
        cv2.fillPoly(img, [pts], 1, cv2.LINE_8, _SHIFT)
        centre = poly.mean(0).astype(int)
        if 0 <= centre[0] < GRID_PX and 0 <= centre[1] < GRID_PX:
            img[centre[1], centre[0]] = 1


def raster(bev_semantic: np.ndarray, agents: AgentBoxes) -> np.ndarray:
    """(len(CHANNELS), GRID_PX, GRID_PX) uint8 0/1: the map classes (a coarse pixel holds a
    class if any of its 4x4 fine pixels does) and the agents' boxes at t, +0.5 s, +1.0 s."""
    out = np.zeros((len(CHANNELS), GRID_PX, GRID_PX), np.uint8)
    coarse = bev_semantic.reshape(GRID_PX, _POOL, GRID_PX, _POOL)
    out[0] = (coarse == 1).any(axis=(1, 3))
    out[1] = (coarse == 2).any(axis=(1, 3))
    for group, walker in ((2, False), (5, True)):
        sel = agents.walker == walker
        if not sel.any():
            continue
        b = AgentBoxes(*(getattr(agents, f)[sel] for f in AgentBoxes.__dataclass_fields__))
        for k, dt in enumerate((0.0, *FUTURE_S)):
            _fill(out[group + k], _corners_px(b, dt))
    return out


def _distance(d: float | None) -> float:
    return 1.0 if d is None or not math.isfinite(d) else min(max(d, 0.0), SIGNAL_RANGE_M) / 30.0


@dataclass(frozen=True)
class Situation:
    """The non-spatial part of one instant, as the shard's columns hold it: ego speed (m/s),
    target point (2,) (m, ego frame), route command (schemas.COMMANDS), light of the junction
    ahead (schemas.TRAFFIC_LIGHTS) and its stop line's distance, stop sign ahead and its
    distance (m; None where there is none)."""

    speed_mps: float
    target_point: np.ndarray
    command: str
    traffic_light: str
    light_distance_m: float | None
    stop_sign: bool
    stop_distance_m: float | None


def scalars(s: Situation) -> np.ndarray:
    """(len(SCALARS),) float32: the planner's non-spatial input (target point clipped at
    +-60 m, distances at the 30 m the labels look; a missing distance reads 1)."""
    v = np.zeros(len(SCALARS), np.float32)
    v[0] = s.speed_mps / 10.0
    v[1:3] = np.clip(np.asarray(s.target_point, np.float64), -60.0, 60.0) / 30.0
    v[3 + COMMANDS.index(s.command)] = 1.0
    k = 3 + len(COMMANDS)
    v[k + TRAFFIC_LIGHTS.index(s.traffic_light)] = 1.0
    k += len(TRAFFIC_LIGHTS)
    v[k] = _distance(s.light_distance_m)
    v[k + 1] = float(s.stop_sign)
    v[k + 2] = _distance(s.stop_distance_m) if s.stop_sign else 1.0
    return v


OUTPUTS = ("waypoints", "path_speed")
"""waypoints: the paper's GRU, 4 timed waypoints; path_speed: TransFuser++'s path checkpoints
and target-speed classes (training/pathspeed.py), turned into 4 timed waypoints to drive."""


@dataclass(frozen=True)
class PrivilegedConfig:
    """The planner's size. width: channels of the first conv (doubling twice, down to 4x4);
    hidden: the feature the head reads; output: OUTPUTS; speed: the planner reads the ego speed (in its
    scalars and beside the GRU head's feature, as ours); False: it never does (the "inertia"
    of Codevilla et al. 2019: a planner that reads its speed learns that standing stays)."""

    width: int = 32
    hidden: int = 256
    speed: bool = True
    n_waypoints: int = 4
    output: str = "waypoints"  # or "path_speed": TF++'s path and speed classes (pathspeed.py)
    stood: bool = False  # also reads how long the ego has stood (ego_history.StandClock)
    arch: str = ARCH

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> PrivilegedConfig:
        return cls(**d)


def _conv(i: int, o: int, stride: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(i, o, 3, stride, 1, bias=False), nn.BatchNorm2d(o), nn.ReLU(inplace=True)
    )


class PrivilegedPlanner(nn.Module):
    """Raster (B, 8, 64, 64) -> 4 stride-2 convs -> (B, 4w, 4, 4), flattened (where an agent is
    matters, so no pooling) and joined with the scalars' embedding -> the feature (B, hidden,
    1, 1) -> the paper's GRU planning head (waypoints from the feature, target point, speed)."""

    def __init__(self, cfg: PrivilegedConfig = PrivilegedConfig()):
        super().__init__()
        self.cfg = cfg
        w = cfg.width
        self.encoder = nn.Sequential(
            _conv(len(CHANNELS), w, 1),
            _conv(w, w, 2),  # 32
            _conv(w, 2 * w, 2),  # 16
            _conv(2 * w, 4 * w, 2),  # 8
            _conv(4 * w, 4 * w, 2),  # 4
        )
        n_scalars = len(SCALARS) + cfg.stood
        self.embed = nn.Sequential(nn.Linear(n_scalars, 64), nn.ReLU(inplace=True))
        self.join = nn.Sequential(nn.Linear(4 * w * 16 + 64, cfg.hidden), nn.ReLU(inplace=True))
        if cfg.output not in OUTPUTS:
            raise ValueError(f"output {cfg.output!r}: expected one of {', '.join(OUTPUTS)}")
        if cfg.output == "path_speed":
            self.head = pathspeed.PathSpeedHead(cfg.hidden)
        else:
            self.head = PlanningHead(cfg.hidden, n_waypoints=cfg.n_waypoints, speed=cfg.speed)

    def forward(
        self, grid: torch.Tensor, scalar: torch.Tensor, target_point: torch.Tensor,
        speed: torch.Tensor, stood: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:  # fmt: skip
        """grid (B, 8, 64, 64) uint8 or float, scalar (B, S), target_point (B, 2) m, speed (B,)
        m/s, stood (B,) s (read with cfg.stood) -> the head's outputs: {"waypoints": (B, 4, 2)
        m, ego frame} or pathspeed's."""
        x = self.encoder(grid.float()).flatten(1)
        if not self.cfg.speed:
            scalar = torch.cat([torch.zeros_like(scalar[:, :1]), scalar[:, 1:]], dim=1)
        if self.cfg.stood:
            cap = ego_history.STOOD_CAP_S
            scalar = torch.cat([scalar, stood.float().clamp(0, cap)[:, None] / cap], dim=1)
        f = self.join(torch.cat([x, self.embed(scalar)], dim=1))
        if self.cfg.output == "path_speed":
            return self.head(f, target_point)
        return {"waypoints": self.head(f[:, :, None, None], target_point, speed)}

    def outputs(self, sample: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The head's outputs for a batch of `inputs` dicts."""
        keys = ("grid", "scalars", "target_point", "speed")
        return self(*(sample[k] for k in keys), sample.get("stood"))

    def plan(self, sample: dict[str, torch.Tensor]) -> torch.Tensor:
        """Waypoints (B, 4, 2) from a batch of `inputs` dicts (path_speed: turned into them)."""
        out = self.outputs(sample)
        return pathspeed.to_waypoints(out) if self.cfg.output == "path_speed" else out["waypoints"]

    def loss(self, sample: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B,) per-frame training loss: L1 of the waypoints (summed over x, y, mean over
        time), or pathspeed.loss."""
        out = self.outputs(sample)
        if self.cfg.output == "path_speed":
            return pathspeed.loss(out, sample)
        return (out["waypoints"] - sample["waypoints"]).abs().sum(2).mean(1)


def inputs(bev_semantic: np.ndarray, agents: AgentBoxes, s: Situation) -> dict[str, np.ndarray]:
    """One instant's input: grid (8, 64, 64) uint8, scalars (S,) float32, target_point (2,)
    float32 m, speed () float32 m/s. The one function training and `drive eval` both call."""
    return {
        "grid": raster(bev_semantic, agents),
        "scalars": scalars(s),
        "target_point": np.asarray(s.target_point, np.float32),
        "speed": np.float32(s.speed_mps),
    }


def _null(v) -> float | None:
    return None if v is None or (isinstance(v, float) and math.isnan(v)) else float(v)


def read_samples(index) -> dict[str, np.ndarray]:
    """The planner's samples of the frames of `index` (training.data.scan's rows), stacked:
    grid (N, 8, 64, 64) uint8, scalars, target_point, speed, waypoints (N, 4, 2) float32,
    the path labels (pathspeed), stood (N,) s (ego_history.StandClock) and expert_reason (N,)
    str; in `index`'s order."""
    parts: dict[int, dict] = {}
    for file, group in index.groupby("path", sort=False):
        table = pq.read_table(file, columns=list(COLUMNS))
        rows = _file_rows(file, group)
        paths, masks = ego_history.path_labels(file)
        stood = ego_history.stood_labels(file)
        for k, x in zip(group.index, table_samples(table.take(rows))):
            parts[k] = x
        for k, r in zip(group.index, rows):
            parts[k] |= {"path": paths[r], "path_mask": masks[r], "stood": stood[r]}
    rows = [parts[i] for i in index.index]
    return {k: np.stack([r[k] for r in rows]) for k in rows[0]} if rows else {}


def _file_rows(file: str, group) -> np.ndarray:
    """Row numbers within the file of `group`'s (row_group, row) pairs."""
    meta = pq.ParquetFile(file).metadata
    starts = np.concatenate(
        [[0], np.cumsum([meta.row_group(i).num_rows for i in range(meta.num_row_groups)])]
    )
    return starts[group.row_group.to_numpy()] + group.row.to_numpy()


def table_samples(table) -> list[dict]:
    """The planner's sample (`inputs`, plus waypoints and expert_reason) of every row of a
    shard table holding COLUMNS."""
    n = table.num_rows
    col = {c: table.column(c).combine_chunks() for c in COLUMNS}
    speed = col["ego_speed"].to_numpy()
    tp = col["target_point"].flatten().to_numpy().reshape(n, 2)
    wp = col["waypoints"].flatten().to_numpy().reshape(n, 4, 2)
    lists = {c: col[c].to_pylist() for c in ("command", "traffic_light", "light_distance_m",
                                             "stop_sign", "stop_distance_m", "expert_reason")}  # fmt: skip
    bev = col["bev_semantic"].to_pylist()
    offsets = col["boxes"].offsets.to_numpy()
    flat = col["boxes"].values
    box = {f: pc.struct_field(flat, f).to_numpy(zero_copy_only=False)
           for f in ("cls", "t", "x", "y", "yaw", "length", "width", "speed")}  # fmt: skip
    walker = np.isin(box["cls"], WALKERS)
    out = []
    for i in range(n):
        sl = slice(offsets[i], offsets[i + 1])
        now = box["t"][sl] == 0
        agents = AgentBoxes(
            *(box[f][sl][now].astype(np.float64) for f in ("x", "y", "yaw", "length", "width", "speed")),
            walker[sl][now],
        )  # fmt: skip
        sem = cv2.imdecode(np.frombuffer(bev[i], np.uint8), cv2.IMREAD_UNCHANGED)
        situation = Situation(
            float(speed[i]), tp[i], lists["command"][i], lists["traffic_light"][i],
            _null(lists["light_distance_m"][i]), bool(lists["stop_sign"][i]),
            _null(lists["stop_distance_m"][i]),
        )  # fmt: skip
        x = inputs(sem, agents, situation)
        x["waypoints"] = wp[i].astype(np.float32)
        x["expert_reason"] = np.array(lists["expert_reason"][i])
        out.append(x)
    return out


@dataclass(frozen=True)
class FitConfig:
    """`train fit --arch privileged`'s options (the sensor model's TrainConfig is another)."""

    shards: str
    out: str
    epochs: int = 12
    batch_size: int = 64
    lr: float = 1e-3
    weight_decay: float = 1e-4
    val_towns: tuple[str, ...] = ()
    val_fraction: float = 0.1
    seed: int = 0
    # stand -> go frames (the ego stands, below 0.5 m/s, and the label moves over 1.5 m in 2 s)
    # weigh this much in the loss; 1: as any frame
    go_weight: float = 1.0
    stay_weight: float = 1.0  # and the frames where it stands and stays (below 1.5 m in 2 s)
    speed_input: bool = True  # PrivilegedConfig.speed
    planner_output: str = "waypoints"  # PrivilegedConfig.output
    stood_input: bool = False  # PrivilegedConfig.stood
    threads: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


FIT_FLAGS = ("shards", "out", "epochs", "batch_size", "lr", "val_fraction", "val_towns", "seed",
             "threads", "go_weight", "stay_weight", "speed_input", "planner_output",
             "stood_input")  # fmt: skip
"""`train fit` flags (argparse names) that set a FitConfig field of the same name."""

CHECKPOINT = "last.pt"
METRICS = "metrics.jsonl"


def _ade(pred: torch.Tensor, wp: torch.Tensor) -> torch.Tensor:
    return (pred - wp).norm(dim=2).mean(1)


def stand_to_go(data: dict[str, np.ndarray]) -> np.ndarray:
    """(N,) bool: frames where the ego stands (below 0.5 m/s) and its label drives off (over
    1.5 m in the 2 s)."""
    standing = data["speed"] < ego_history.STAND_MPS
    return standing & (np.linalg.norm(data["waypoints"][:, -1], axis=1) > 1.5)


def go_weights(
    data: dict[str, np.ndarray], go_weight: float, stay_weight: float = 1.0
) -> np.ndarray:
    """(N,) float32 loss weights: `go_weight` on stand_to_go frames, `stay_weight` on frames
    where the ego stands and stays, 1 elsewhere."""
    w = np.where(data["speed"] < ego_history.STAND_MPS, stay_weight, 1.0)
    return np.where(stand_to_go(data), go_weight, w).astype(np.float32)


def evaluate(model: PrivilegedPlanner, data: dict[str, np.ndarray], batch: int = 256) -> dict:
    """Open-loop figures on `data` (read_samples): ADE/FDE (m) over all frames and per expert
    reason, and of constant velocity beside them."""
    model.eval()
    ade, fde, far = [], [], []
    with torch.no_grad():
        for s in range(0, len(data["speed"]), batch):
            b = {
                k: torch.from_numpy(v[s : s + batch])
                for k, v in data.items()
                if k != "expert_reason"
            }
            pred = model.plan(b)
            err = (pred - b["waypoints"]).norm(dim=2)
            ade.append(err.mean(1))
            fde.append(err[:, -1])
            far.append(pred[:, -1].norm(dim=1) > 1.5)
    ade_t, fde_t = torch.cat(ade).numpy(), torch.cat(fde).numpy()
    moves = torch.cat(far).numpy()  # the plan moves over 1.5 m in 2 s
    times = np.array([0.5, 1.0, 1.5, 2.0])
    cv = np.stack([data["speed"][:, None] * times, np.zeros((len(ade_t), 4))], axis=2)
    cv_ade = np.linalg.norm(cv - data["waypoints"], axis=2).mean(1)
    go = stand_to_go(data)
    reasons = data["expert_reason"]
    per = {str(r): float(ade_t[reasons == r].mean()) for r in np.unique(reasons)}
    return {
        "frames": len(ade_t),
        "ade_m": float(ade_t.mean()),
        "fde_m": float(fde_t.mean()),
        "cv_ade_m": float(cv_ade.mean()),
        "ade_by_reason": per,
        "stand_to_go_frames": int(go.sum()),
        "stand_to_go_ade_m": float(ade_t[go].mean()) if go.any() else None,
        "stand_to_go_moves": float(moves[go].mean()) if go.any() else None,
    }


def fit(
    cfg: FitConfig, model_cfg: PrivilegedConfig = PrivilegedConfig(), sensor_config=None
) -> Path:
    """Train the planner on `cfg.shards` (L1 on the waypoints, AdamW, cosine schedule; every
    epoch's figures to OUT/metrics.jsonl); writes OUT/last.pt and returns its path."""
    from tqdm import tqdm

    from training.data import scan, split
    from training.device import cpu_threads

    torch.set_num_threads(cpu_threads(cfg.threads))
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    index = scan(cfg.shards)
    val = split(index, cfg.val_fraction, cfg.val_towns, cfg.seed)
    t0 = time.perf_counter()
    train_data = read_samples(index[~val])
    val_data = read_samples(index[val]) if val.any() else {}
    read_s = time.perf_counter() - t0
    print(f"read {len(index)} frames ({int(val.sum())} held out) in {read_s:.0f} s", flush=True)
    if not train_data:
        raise UserError(f"{cfg.shards}: no training frames")
    if sensor_config is None:
        from training.data import sensor_config as shards_sensors

        sensor_config = shards_sensors(index)
    torch.manual_seed(cfg.seed)
    model = PrivilegedPlanner(
        replace(model_cfg, speed=cfg.speed_input, output=cfg.planner_output, stood=cfg.stood_input)
    )
    decay = [p for p in model.parameters() if p.ndim >= 2]
    rest = [p for p in model.parameters() if p.ndim < 2]
    opt = torch.optim.AdamW(
        [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": rest, "weight_decay": 0}],
        lr=cfg.lr,
    )
    n = len(train_data["speed"])
    steps_per_epoch = max(1, n // cfg.batch_size)
    total = steps_per_epoch * cfg.epochs
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, cfg.lr, total_steps=total, pct_start=0.05)
    rng = np.random.default_rng(cfg.seed)
    tensors = {k: torch.from_numpy(v) for k, v in train_data.items() if k != "expert_reason"}
    tensors["weight"] = torch.from_numpy(go_weights(train_data, cfg.go_weight, cfg.stay_weight))
    tensors["speed_class"] = torch.from_numpy(pathspeed.speed_class(train_data["waypoints"]))
    (out / METRICS).write_text("")
    for epoch in range(1, cfg.epochs + 1):
        model.train()
        order = rng.permutation(n)
        total_loss, t_epoch = 0.0, time.perf_counter()
        for s in tqdm(range(steps_per_epoch), desc=f"epoch {epoch}", unit="step", leave=False):
            idx = torch.from_numpy(order[s * cfg.batch_size : (s + 1) * cfg.batch_size])
            b = {k: v[idx] for k, v in tensors.items()}
            loss = (model.loss(b) * b["weight"]).sum() / b["weight"].sum()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            sched.step()
            total_loss += float(loss.detach())
        line = {"epoch": epoch, "train_l1": total_loss / steps_per_epoch,
                "epoch_s": time.perf_counter() - t_epoch}  # fmt: skip
        if val_data:
            line["val"] = evaluate(model, val_data)
        with open(out / METRICS, "a") as f:
            f.write(json.dumps(line) + "\n")
        v = line.get("val", {})
        print(f"epoch {epoch}: train L1 {line['train_l1']:.3f}" + (
            f", val ADE {v['ade_m']:.3f} m (constant velocity {v['cv_ade_m']:.3f})" if v else ""
        ), flush=True)  # fmt: skip
        state = {
            "model": model.state_dict(),
            "model_config": model.cfg.to_dict(),
            "train_config": cfg.to_dict(),
            "epoch": epoch,
            "metrics": line,
            "sensor_config": sensor_config,
            "val_towns": list(cfg.val_towns),
        }
        from training.checkpoint import save_checkpoint

        save_checkpoint(out / CHECKPOINT, state)
    return out / CHECKPOINT


def run_fit(args, given: list[str]) -> int:
    """`train fit --arch privileged`: `fit` with the flags that apply (`given`: the argparse
    names of the flags the user gave); UserError for a sensor model's flag, --config or
    --resume (a fit takes minutes: it starts afresh)."""
    from schemas import outputs

    other = [f"--{a.replace('_', '-')}" for a in given if a not in FIT_FLAGS]
    other += ["--config"] * bool(args.config) + ["--resume"] * bool(args.resume)
    if other:
        raise UserError(
            f"{', '.join(other)}: not an option of --arch privileged (it takes "
            f"{', '.join('--' + f.replace('_', '-') for f in FIT_FLAGS)}, --force)"
        )
    if not args.shards:
        raise UserError("--shards: give the shards to train on")
    values = {f: getattr(args, f) for f in FIT_FLAGS if getattr(args, f) is not None}
    cfg = FitConfig(**{"out": "runs/privileged", **values})
    out = outputs.check_dir(cfg.out)
    if (out / CHECKPOINT).exists() and not args.force:
        raise UserError(f"{out} holds a run ({CHECKPOINT}); replace it with --force")
    ckpt = fit(cfg)
    print(f"wrote {ckpt}; drive it: drive eval --policy ckpt:{ckpt} --routes ROUTES --out DIR")
    return 0


def is_privileged(state: dict) -> bool:
    """A checkpoint of this planner (not of II-DSU)."""
    return state.get("model_config", {}).get("arch") == ARCH


def model_from_state(state: dict, device="cpu") -> PrivilegedPlanner:
    model = PrivilegedPlanner(PrivilegedConfig.from_dict(state["model_config"]))
    model.load_state_dict(state["model"])
    return model.to(device).eval()
