"""The weather swap (the paper's Fig. 6): one scene in two weathers, and what a model plans in each.

    drive swap --policy ckpt:runs/x/last.pt --town downtown --frames 120 --out runs/swap

The expert drives one episode (SUMO seeded by --seed; traffic drawn for --world-weather and
--behaviour) and every recorded 2 Hz instant is sensed twice from the identical traffic state,
only the sensors' weather differing (camera light, sky, rain, fog; LiDAR drop-outs and noise):
once in the first of --weathers (sunny) and once in the second (rainy). The model plans from
each. Per frame: the planned speed (mean spacing of the 4 waypoints from the ego over 0.5 s
steps, m/s) and, with a lead vehicle (a vehicle ahead within LEAD_HALF_WIDTH_M of the ego's axis
and LEAD_RANGE_M), the gap its plan keeps at +2 s (lead's rear now minus the last waypoint's x,
m). Summary: mean planned speed per weather, the ratio second / first with a 95 % interval from
a block bootstrap (blocks of BLOCK_FRAMES frames: consecutive frames are not independent), mean
gaps. Writes OUT/swap.json and OUT/swap.png: the frame whose speed ratio is the median, both
cameras and a BEV of both plans (Fig. 6's layout). The data's rule (rain and fog -> cautious
traffic, Sec. IV) means a model that reads the weather should plan slower in rain.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import schemas
from datagen.errors import UserError
from datagen.state import FrameState
from schemas import outputs

LEAD_HALF_WIDTH_M = 1.8  # a vehicle whose centre is this close to the ego's axis is in its lane
LEAD_RANGE_M = 30.0
BLOCK_FRAMES = 10
BOOTSTRAP_DRAWS = 2000


def planned_speed(waypoints: np.ndarray) -> float:
    """Mean speed (m/s) of a plan: (4, 2) ego-frame waypoints at +0.5 .. +2.0 s from the ego."""
    pts = np.vstack([[0.0, 0.0], np.asarray(waypoints, np.float64)])
    return float(np.hypot(*np.diff(pts, axis=0).T).mean() / schemas.FRAME_PERIOD_S)


def lead_rear_m(frame: FrameState) -> float | None:
    """Distance (m, ego frame x) from the ego's centre to the rear of the nearest vehicle ahead
    in its lane (|y| < LEAD_HALF_WIDTH_M, within LEAD_RANGE_M); None without one."""
    best = None
    for a in frame.agents:
        if a.cls != "vehicle":
            continue
        x, y = frame.ego.pose.ego_from_world(np.array([[a.pose.x_m, a.pose.y_m]]))[0]
        rear = x - 0.5 * a.length_m
        if x > 0.0 and abs(y) < LEAD_HALF_WIDTH_M and rear < LEAD_RANGE_M:
            best = rear if best is None else min(best, rear)
    return best


def ratio_interval(
    first: np.ndarray, second: np.ndarray, rng: np.random.Generator, block: int = BLOCK_FRAMES
) -> tuple[float, float, float]:
    """mean(second) / mean(first) over paired per-frame values, and its 95 % interval from a
    moving-block bootstrap (blocks of `block` consecutive frames, drawn with replacement)."""
    first, second = np.asarray(first, np.float64), np.asarray(second, np.float64)
    n = len(first)
    if n == 0:
        raise UserError("no frames to compare")
    ratio = float(second.mean() / max(first.mean(), 1e-9))
    block = max(1, min(block, n))
    starts = rng.integers(0, n - block + 1, size=(BOOTSTRAP_DRAWS, -(-n // block)))
    idx = (starts[..., None] + np.arange(block)).reshape(BOOTSTRAP_DRAWS, -1)[:, :n]
    draws = second[idx].mean(1) / np.maximum(first[idx].mean(1), 1e-9)
    lo, hi = np.percentile(draws, [2.5, 97.5])
    return ratio, float(lo), float(hi)


def weather_swap(
    plan,
    net: Path,
    seed: int,
    behaviour: str,
    n_frames: int,
    weathers: tuple[str, str] = ("sunny", "rainy"),
    world_weather: str | None = None,
) -> tuple[dict, dict]:
    """Drive one expert episode and plan every frame in both `weathers` with
    `plan(frame, image_jpeg, lidar_png, ground_png) -> (4, 2)` (drive.policy.ModelPolicy.plan).

    Returns (document, figure inputs): the document holds per-frame speeds and gaps per weather
    and the summary; the figure inputs the median frame, its two JPEGs and two plans."""
    from datagen.episode import Sensors, episode_rng
    from datagen.sensors.config import SensorConfig
    from datagen.sensors.scene import load_static_scene
    from datagen.world import World, WorldConfig, record
    from drive.sim import SensorStream

    cfg = SensorConfig()
    static = load_static_scene(net)
    streams = {
        w: SensorStream(Sensors(static, cfg, w, episode_rng(seed)), cfg.jpeg_quality)
        for w in weathers
    }
    world_cfg = WorldConfig(
        net_path=net, seed=seed, weather=world_weather or weathers[0], behaviour=behaviour
    )
    frames, speeds, gaps, shots = [], {w: [] for w in weathers}, {w: [] for w in weathers}, []
    with World(world_cfg) as world:
        for frame in record(world, n_frames):
            lead = lead_rear_m(frame)
            shot = {}
            for w in weathers:
                jpeg, bev, ground = streams[w].encode(frame)
                wp = np.asarray(plan(frame, jpeg, bev, ground), np.float64)
                speeds[w].append(planned_speed(wp))
                gaps[w].append(None if lead is None else float(lead - wp[-1, 0]))
                shot[w] = (jpeg, wp)
            frames.append(frame)
            shots.append(shot)
    if not frames:
        raise UserError(f"{net}: the episode ended before its first frame")
    a, b = weathers
    rng = np.random.default_rng(seed)
    ratio, lo, hi = ratio_interval(np.array(speeds[a]), np.array(speeds[b]), rng)
    with_lead = [i for i, g in enumerate(gaps[a]) if g is not None]
    summary = {
        "frames": len(frames),
        "weathers": list(weathers),
        "world": {"weather": world_cfg.weather, "behaviour": behaviour, "seed": seed},
        "mean_speed_mps": {w: float(np.mean(speeds[w])) for w in weathers},
        "speed_ratio": ratio,
        "speed_ratio_ci95": [lo, hi],
        "frames_with_lead": len(with_lead),
        "mean_gap_m": {
            w: float(np.mean([gaps[w][i] for i in with_lead])) if with_lead else None
            for w in weathers
        },
    }
    per_frame = np.array(speeds[b]) / np.maximum(np.array(speeds[a]), 1e-9)
    k = int(np.argsort(per_frame)[len(per_frame) // 2])
    doc = {
        "summary": summary,
        "per_frame": {
            "time_s": [f.time_s for f in frames],
            "speed_mps": speeds,
            "gap_m": gaps,
        },
        "figure_frame": k,
    }
    return doc, {"frame": frames[k], "shots": shots[k]}


def figure(frame: FrameState, shots: dict) -> np.ndarray:
    """Fig. 6's layout (BGR): the cameras of both weathers and a BEV (ego frame, 40 m ahead,
    20 m each side, 6.4 px/m) with the agents and both plans (first weather orange, second
    blue)."""
    import cv2

    from schemas import codecs

    colours = [(0, 140, 255), (255, 120, 0)]  # BGR: orange, blue
    panels = []
    for w, (jpeg, _) in shots.items():
        img = cv2.cvtColor(codecs.decode_image(jpeg), cv2.COLOR_RGB2BGR)
        cv2.putText(img, w, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
        panels.append(img)
    side = panels[0].shape[0]
    bev = np.full((side, side, 3), 40, np.uint8)
    scale = side / 40.0

    def px(xy: np.ndarray) -> np.ndarray:  # ego frame (x ahead, y left) -> BEV pixels
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return np.stack([side / 2 - xy[:, 1] * scale, side - 8 - xy[:, 0] * scale], 1)

    for a in frame.agents:
        c = frame.ego.pose.ego_from_world(np.array([[a.pose.x_m, a.pose.y_m]]))[0]
        size = max(2, int(0.5 * a.width_m * scale))
        p = px(c)[0].astype(int)
        cv2.rectangle(bev, tuple(p - size), tuple(p + size), (200, 200, 200), 1)
    cv2.rectangle(bev, (side // 2 - 6, side - 20), (side // 2 + 6, side - 2), (0, 255, 0), 1)
    for colour, (_, wp) in zip(colours, shots.values()):
        for q in px(wp).astype(int):
            cv2.circle(bev, tuple(q), 3, colour, -1)
    return np.hstack(panels + [bev])


def run(args) -> int:
    import cv2

    from datagen.sensors.config import SensorConfig
    from datagen.world.towns import check_network, town_net_path
    from drive.policy import ModelPolicy, parse_policy

    spec = parse_policy(args.policy, args.device)
    if spec.kind != "ckpt":
        raise UserError("--policy: the weather swap needs a model (ckpt:PATH)")
    if args.frames < 1:
        raise UserError(f"--frames must be >= 1, got {args.frames}")
    weathers = tuple(args.weathers.split(","))
    if len(weathers) != 2 or any(w not in schemas.WEATHERS for w in weathers):
        raise UserError(f"--weathers: two of {schemas.WEATHERS}, e.g. sunny,rainy")
    out = outputs.check_dir(args.out)  # before any driving
    net = check_network(args.net) if args.net else town_net_path(args.town)
    policy = ModelPolicy(spec, SensorConfig().to_dict())
    doc, fig = weather_swap(policy.plan, net, args.seed, args.behaviour, args.frames, weathers)
    outputs.write_json(out / "swap.json", doc)
    with outputs.atomic(out / "swap.png") as tmp:
        if not cv2.imwrite(str(tmp), figure(fig["frame"], fig["shots"])):
            raise UserError(f"{out / 'swap.png'}: cannot write the PNG")
    s = doc["summary"]
    a, b = weathers
    lo, hi = s["speed_ratio_ci95"]
    print(
        f"{s['frames']} frames: planned speed {a} {s['mean_speed_mps'][a]:.2f} m/s, "
        f"{b} {s['mean_speed_mps'][b]:.2f} m/s, ratio {s['speed_ratio']:.3f} "
        f"(95% CI {lo:.3f}-{hi:.3f}); wrote {out / 'swap.json'} and {out / 'swap.png'}"
    )
    return 0


def add_arguments(p) -> None:
    p.add_argument("--policy", required=True, help="ckpt:PATH (a trained II-DSU)")
    p.add_argument("--town", default="downtown", help="a built-in town")
    p.add_argument("--net", default=None, help="a SUMO network instead of --town")
    p.add_argument("--frames", type=int, default=120, help="frames compared, at 2 Hz")
    p.add_argument("--seed", type=int, default=0, help="the world's and the sensors' seed")
    p.add_argument(
        "--behaviour", default="normal", choices=schemas.BEHAVIOURS, help="the traffic's profile"
    )
    p.add_argument("--weathers", default="sunny,rainy", help="the two sensor weathers")
    p.add_argument("--out", required=True, help="directory for swap.json and swap.png")
    p.add_argument(
        "--device",
        default="auto",
        choices=("auto", "cpu", "cuda"),
        help="where the model runs; auto: CUDA if present",
    )
