import dataclasses
import math

import pytest
import torch

from tests.synthetic import write_shards
from training import data
from training.config import PRESETS, TrainConfig, preset
from training.losses import compute_losses, loss_terms
from training.model import IIDSU, INPUTS

TINY, PAPER = PRESETS["tiny"][0], PRESETS["paper"][0]  # the paper's architecture
OURS = preset("tiny", "ours")[0]  # the paper's plus the additions of ours, tiny


def _inputs(batch: int, device: str = "cpu"):
    with torch.device(device):
        return (
            torch.zeros(batch, 3, 256, 256, dtype=torch.uint8),
            torch.zeros(batch, 4, 256, 256, dtype=torch.uint8),
            torch.full((batch,), 3.0),
            torch.tensor([[20.0, 1.0]]).expand(batch, 2),
        )


def _shapes(out: dict) -> dict:
    return {k: tuple(v.shape) for k, v in out.items()}


def test_tiny_heads_have_paper_layout():
    R = TINY.output_px
    paper = {
        "planning": (2, 4, 2),
        "detection": (2, 21, R, R),
        "bev": (2, 3, R, R),
        "traffic": (2, 2),
        "weather": (2, 4),
    }
    assert _shapes(IIDSU(TINY)(*_inputs(2))) == paper
    # ours adds the traffic rule from the camera encoder alone
    assert _shapes(IIDSU(OURS)(*_inputs(2))) == {**paper, "camera_traffic": (2, 2)}


def test_camera_traffic_head_sees_the_camera_alone():
    torch.manual_seed(0)
    model = IIDSU(OURS).eval()
    image, lidar, speed, target = _inputs(2)
    image = torch.randint(0, 256, image.shape, dtype=torch.uint8)
    other_lidar = torch.randint(0, 6, lidar.shape, dtype=torch.uint8)
    with torch.no_grad():
        a = model(image, lidar, speed, target)
        b = model(image, other_lidar, speed * 3, target)
        c = model(image.flip(3), lidar, speed, target)
    # no LiDAR and no speed reach it (the fusion layers would carry both), while F_DSU's own
    # traffic head and the camera do
    assert torch.equal(a["camera_traffic"], b["camera_traffic"])
    assert not torch.allclose(a["traffic"], b["traffic"])
    assert not torch.allclose(a["camera_traffic"], c["camera_traffic"])


def test_camera_traffic_head_goes_with_the_traffic_head_and_old_checkpoints_lack_it():
    from training.config import ModelConfig

    for cfg in (
        dataclasses.replace(OURS, camera_traffic=False),
        dataclasses.replace(OURS, traffic=False),  # "No Traffic Rule" learns no rule elsewhere
    ):
        assert "camera_traffic" not in IIDSU(cfg)(*_inputs(1))
    old = {k: v for k, v in dataclasses.asdict(OURS).items() if k != "camera_traffic"}
    assert ModelConfig.from_dict(old).camera_traffic is False


def test_traffic_pool_keeps_a_one_cell_signal_that_the_mean_dilutes():
    from training.heads import TrafficRuleHead

    torch.manual_seed(0)
    # one channel lit in one of the 64 cells (a lamp), against the same map without it
    lamp = torch.zeros(1, 4, 8, 8)
    lamp[0, 2, 3, 5] = 8.0
    for pool, gap in (("avg", 8.0 / 64), ("avgmax", 8.0)):
        head = TrafficRuleHead(4, pool)
        with torch.no_grad():
            head.fc.weight.zero_()
            head.fc.weight[0, 2] = 1.0  # the mean's channel 2
            if pool == "avgmax":
                head.fc.weight[0, 4 + 2] = 1.0  # and its maximum
            delta = head(lamp) - head(torch.zeros_like(lamp))
        assert delta[0, 0].item() == pytest.approx(gap + (8.0 / 64 if pool == "avgmax" else 0))
        assert delta[0, 1].item() == 0.0
    with pytest.raises(ValueError, match="traffic_pool"):
        dataclasses.replace(OURS, traffic_pool="median")


def test_old_checkpoints_load_with_mean_pooled_traffic_heads_and_no_lamp_maps():
    from training.checkpoint import model_from_checkpoint
    from training.config import ModelConfig

    assert OURS.traffic_pool == "avgmax" and OURS.lamp_channels == 8 and OURS.traffic_residual
    assert OURS.pixel_lamp_channels == 8
    old_cfg = dataclasses.replace(
        OURS, traffic_pool="avg", lamp_channels=0, pixel_lamp_channels=0, traffic_residual=False
    )
    old = IIDSU(old_cfg)
    assert old.lamps is None
    assert old.camera_traffic.fc.in_features == OURS.dims[-1]
    new = ("traffic_pool", "lamp_channels", "pixel_lamp_channels", "traffic_residual")
    saved = {k: v for k, v in dataclasses.asdict(old_cfg).items() if k not in new}
    assert ModelConfig.from_dict(saved) == old_cfg
    state = {"model_config": saved, "model": old.state_dict()}
    loaded = model_from_checkpoint(state).eval()
    with torch.no_grad():
        a, b = old.eval()(*_inputs(2)), loaded(*_inputs(2))
    assert torch.equal(a["traffic"], b["traffic"])
    assert torch.equal(a["camera_traffic"], b["camera_traffic"])


def test_fused_traffic_head_corrects_the_camera_heads_logits():
    torch.manual_seed(0)
    image, lidar, speed, target = _inputs(2)
    image = torch.randint(0, 256, image.shape, dtype=torch.uint8)
    model = IIDSU(OURS).eval()
    with torch.no_grad():
        out = model(image, lidar, speed, target)
        own = model.heads["traffic"](model.eca["traffic"](model.encode(image, lidar, speed)))
        assert torch.allclose(out["traffic"], own + out["camera_traffic"], atol=1e-6)
        model.heads["traffic"].fc.weight.zero_()  # F_DSU adds nothing: the camera's logits
        model.heads["traffic"].fc.bias.zero_()
        out = model(image, lidar, speed, target)
    assert torch.equal(out["traffic"], out["camera_traffic"])
    # the paper's form (flag off), and off without the camera head it would add
    for cfg in (
        dataclasses.replace(OURS, traffic_residual=False),
        dataclasses.replace(OURS, camera_traffic=False),
    ):
        torch.manual_seed(0)
        model = IIDSU(cfg).eval()
        with torch.no_grad():
            out = model(image, lidar, speed, target)
            own = model.heads["traffic"](model.eca["traffic"](model.encode(image, lidar, speed)))
        assert torch.equal(out["traffic"], own)


@pytest.mark.slow
def test_traffic_residual_dropout_drops_the_correction_in_training_only():
    torch.manual_seed(0)
    image, lidar, speed, target = _inputs(64)
    image = torch.randint(0, 256, image.shape, dtype=torch.uint8)
    model = IIDSU(dataclasses.replace(OURS, traffic_residual_dropout=0.5))
    with torch.no_grad():
        model.eval()
        kept = model(image, lidar, speed, target)
        correction = kept["traffic"] - kept["camera_traffic"]
        model.train()
        torch.manual_seed(1)
        out = model(image, lidar, speed, target)
    # LayerNorm encoders and drop_path 0 in tiny: train mode changes only this dropout
    assert torch.allclose(out["camera_traffic"], kept["camera_traffic"], atol=1e-5)
    got = out["traffic"] - out["camera_traffic"]
    dropped = got.abs() < 1e-6
    assert 0.3 < dropped.float().mean() < 0.7  # about half of 128 logits
    assert torch.allclose(got[~dropped], 2 * correction[~dropped], atol=1e-4)
    with pytest.raises(ValueError, match="traffic_residual_dropout"):
        dataclasses.replace(OURS, traffic_residual_dropout=1.0)


def test_lamp_maps_keep_a_small_lamp_where_it_is_and_feed_f_dsu():
    torch.manual_seed(0)
    cfg = dataclasses.replace(OURS, pixel_lamp_channels=0)  # the first stage's maps alone
    model = IIDSU(cfg).eval()
    assert model.to_dsu.in_channels == 2 * OURS.dims[-1] + OURS.lamp_channels
    image, lidar, speed, target = _inputs(1)
    lit = image.clone()
    lit[0, 0, 100:102, 200:202] = 255  # a 2x2 px red lamp: 32 px cells, row 3, column 6
    with torch.no_grad():
        a = model._encode(image, lidar, speed)
        b = model._encode(lit, lidar, speed)
    changed = (a[1] - b[1]).abs().amax(dim=(0, 1)) > 0  # (8, 8) cells of the lamp maps
    assert changed[3, 6]
    rows, cols = torch.nonzero(changed, as_tuple=True)  # only cells the first stage reaches
    assert rows.min() >= 2 and rows.max() <= 3 and cols.min() >= 5 and cols.max() <= 6
    assert not torch.equal(a[0], b[0])  # F_DSU sees it
    with torch.no_grad():
        model.lamps.stage.weight.zero_()
        model.lamps.stage.bias.zero_()
        c = model._encode(lit, lidar, speed)
    assert not c[1].any()


def test_pixel_lamp_maps_keep_a_one_pixel_lamp_in_its_cell():
    from training.config import ModelConfig

    torch.manual_seed(0)
    cfg = dataclasses.replace(OURS, pixel_lamp_channels=4)  # the tiny config has 8
    model = IIDSU(cfg).eval()
    k = OURS.lamp_channels
    assert model.to_dsu.in_channels == 2 * OURS.dims[-1] + k + 4
    assert model.camera_traffic.fc.in_features == 2 * (k + 4)  # avgmax pooling: two per map
    image, lidar, speed, target = _inputs(1)
    lit = image.clone()
    lit[0, 0, 100, 200] = 255  # one red pixel: 32 px cells, row 3, column 6
    with torch.no_grad():
        a = model._encode(image, lidar, speed)
        b = model._encode(lit, lidar, speed)
    pixel = (a[1][0, k:] - b[1][0, k:]).abs().amax(dim=0) > 0  # (8, 8) cells of the pixel maps
    assert pixel[3, 6] and pixel.sum() == 1  # stride 1: no other cell sees that pixel
    assert not torch.equal(a[0], b[0])  # F_DSU sees it
    assert "camera_traffic" in model(lit, lidar, speed, target)
    # without stage lamp maps the camera-only head reads the pixel maps alone
    alone = IIDSU(dataclasses.replace(cfg, lamp_channels=0))
    assert alone.camera_traffic.fc.in_features == 2 * 4 and alone.lamps.stage is None
    saved = {key: v for key, v in dataclasses.asdict(OURS).items() if key != "pixel_lamp_channels"}
    assert ModelConfig.from_dict(saved).pixel_lamp_channels == 0  # runs from before: off
    with pytest.raises(ValueError, match="pixel_lamp_channels"):
        dataclasses.replace(OURS, pixel_lamp_channels=-1)


def test_planner_reads_the_speed_and_old_checkpoints_load_without_it():
    from training.checkpoint import model_from_checkpoint
    from training.config import ModelConfig

    head = IIDSU(OURS).heads["planning"]
    f = torch.randn(2, OURS.feature_dim, 8, 8)
    tp = torch.tensor([[20.0, 1.0], [20.0, 1.0]])
    with torch.no_grad():
        slow, fast = head(f, tp, torch.tensor([0.0, 0.0])), head(f, tp, torch.tensor([8.0, 8.0]))
    assert not torch.allclose(slow, fast)
    # a config saved before `planner_speed` existed is a planner without the speed input
    old = {k: v for k, v in dataclasses.asdict(OURS).items() if k != "planner_speed"}
    assert ModelConfig.from_dict(old).planner_speed is False
    state = {"model": IIDSU(ModelConfig.from_dict(old)).state_dict(), "model_config": old}
    model = model_from_checkpoint(state)
    assert model.heads["planning"].mlp[0].in_features == OURS.feature_dim
    assert model(*_inputs(1))["planning"].shape == (1, 4, 2)


def test_paper_model_shapes_on_meta_device():
    # The paper model (70 M parameters, R = 256) costs seconds per frame on a CPU; meta tensors
    # check every shape without computing anything.
    with torch.device("meta"):
        model = IIDSU(PAPER)
        f = model.encode(*_inputs(1, "meta")[:3])
        out = model(*_inputs(1, "meta"))
    assert tuple(f.shape) == (1, 1024, 8, 8)  # F_DSU
    assert _shapes(out) == {
        "planning": (1, 4, 2),
        "detection": (1, 21, 256, 256),
        "bev": (1, 3, 256, 256),
        "traffic": (1, 2),
        "weather": (1, 4),
    }
    assert [m.conv.kernel_size[0] for m in model.eca.values()] == [5] * 5


def _children(model: torch.nn.Module) -> dict[str, tuple[str, int]]:
    """Module path -> (class name, parameters) for every module two levels down."""
    out = {}
    for name, m in model.named_modules():
        if name and name.count(".") < 2:
            out[name] = (type(m).__name__, sum(p.numel() for p in m.parameters()))
    return out


# The paper's II-DSU at its size (Sec. III): what `train fit --config paper` builds.
PAPER_MODULES = {
    "image_encoder": ("ConvNeXt", 12_450_880),
    "image_encoder.stem": ("Sequential", 3_264),
    "image_encoder.stages": ("ModuleList", 12_447_616),
    "lidar_encoder": ("ConvNeXt", 12_451_904),  # 4 LiDAR channels in: 1,024 more in the stem
    "lidar_encoder.stem": ("Sequential", 4_288),
    "lidar_encoder.stages": ("ModuleList", 12_447_616),
    "fusion": ("ModuleList", 33_649_920),
    "fusion.0": ("TransFuserLayer", 408_320),
    "fusion.1": ("TransFuserLayer", 1_603_072),
    "fusion.2": ("TransFuserLayer", 6_351_872),
    "fusion.3": ("TransFuserLayer", 25_286_656),
    "to_dsu": ("Conv2d", 1_049_600),  # 1x1 conv, 2 x 512 -> 1024
    "eca": ("ModuleDict", 25),
    "eca.planning": ("ECA", 5),  # k = 5, no bias
    "eca.detection": ("ECA", 5),
    "eca.bev": ("ECA", 5),
    "eca.traffic": ("ECA", 5),
    "eca.weather": ("ECA", 5),
    "heads": ("ModuleDict", 10_547_360),
    "heads.planning": ("PlanningHead", 740_738),  # MLP 1024-512-256-128, GRUCell(4, 128)
    "heads.detection": ("DensityHead", 4_900_533),
    "heads.bev": ("BEVHead", 4_899_939),
    "heads.traffic": ("TrafficRuleHead", 2_050),  # mean over positions, FC 1024 -> 2
    "heads.weather": ("WeatherHead", 4_100),
}
PAPER_PARAMETERS = 70_149_689


def test_paper_architecture_is_pinned():
    # Every module two levels down, its class and parameter count, and the total: the paper's
    # model as Sec. III describes it, with nothing of ours (no lamp maps, no camera-only head).
    with torch.device("meta"):
        model = IIDSU(PAPER)
    assert model.lamps is None and model.camera_traffic is None
    assert _children(model) == PAPER_MODULES
    assert sum(p.numel() for p in model.parameters()) == PAPER_PARAMETERS
    assert model.heads["planning"].mlp[0].in_features == 1024  # F_DSU alone, no speed
    assert model.heads["traffic"].fc.in_features == 1024  # the mean, no maximum
    assert model.to_dsu.in_channels == 2 * 512  # the two last stages, nothing else


def test_ours_is_the_paper_plus_the_additions_each_switchable():
    from training.config import OURS_MODEL, OURS_TRAIN, architecture, with_architecture

    paper_model, paper_train = PRESETS["tiny"]
    ours_model, ours_train = preset("tiny", "ours")
    assert architecture(paper_model, paper_train) == "paper" and paper_model.additions == ()
    assert architecture(ours_model, ours_train) == "ours"
    assert ours_model.additions == tuple(OURS_MODEL)
    assert (ours_train.zoom_out, paper_train.zoom_out) == (OURS_TRAIN["zoom_out"], 1.0)
    # everything else is the paper's: back to it, and the sizes of `paper` and `tiny` kept
    assert with_architecture(ours_model, ours_train, "paper") == (paper_model, paper_train)
    assert preset("paper", "ours")[0].dims == PAPER.dims
    one = dataclasses.replace(paper_model, planner_speed=True)
    assert architecture(one) == "paper + planner_speed"
    assert architecture(dataclasses.replace(ours_model, lamp_channels=0)).startswith("paper + ")
    with torch.device("meta"):
        n_ours = sum(p.numel() for p in IIDSU(preset("paper", "ours")[0]).parameters())
    assert n_ours > PAPER_PARAMETERS


def test_plan_is_forwards_planning_output_for_either_architecture():
    torch.manual_seed(0)
    image, lidar, speed, target = _inputs(2)
    image = torch.randint(0, 256, image.shape, dtype=torch.uint8)
    for cfg in (TINY, OURS):
        model = IIDSU(cfg).eval()
        with torch.no_grad():
            assert torch.equal(
                model.plan(image, lidar, speed, target),
                model(image, lidar, speed, target)["planning"],
            )


def test_checkpoints_from_before_the_additions_moved_load_their_lamp_maps():
    # Until the additions moved to training/lamps.py the lamp convs were IIDSU.lamp and
    # IIDSU.pixel_lamp; such a state dict loads into today's IIDSU.lamps with the same outputs.
    from training.checkpoint import model_from_checkpoint

    torch.manual_seed(0)
    model = IIDSU(OURS).eval()
    state = model.state_dict()
    old = {}
    for k, v in state.items():
        k = k.replace("lamps.stage.", "lamp.").replace("lamps.pixel.", "pixel_lamp.")
        old[k] = v
    assert "lamp.weight" in old and "pixel_lamp.0.weight" in old
    loaded = model_from_checkpoint({"model_config": OURS.to_dict(), "model": old})
    image, lidar, speed, target = _inputs(1)
    image = torch.randint(0, 256, image.shape, dtype=torch.uint8)
    with torch.no_grad():
        a, b = model(image, lidar, speed, target), loaded(image, lidar, speed, target)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_output_resolution_is_configurable():
    cfg = dataclasses.replace(TINY, output_px=32)
    assert IIDSU(cfg)(*_inputs(1))["bev"].shape[-1] == 32
    with pytest.raises(ValueError, match="output_px"):
        dataclasses.replace(TINY, output_px=48)


@pytest.mark.parametrize(
    "switch, head, terms",
    [
        ("detection", "detection", {"det", "heat", "reg"}),
        ("bev", "bev", {"bev"}),
        ("traffic", "traffic", {"tf", "light", "stop"}),
        ("weather", "weather", {"weather"}),
    ],
)
def test_each_ablation_removes_its_head_and_loss(switch, head, terms, tmp_path_factory):
    batch = _batch(tmp_path_factory, n=2)
    for base in (TINY, OURS):  # the ablations of the paper's model, and of ours
        cfg = dataclasses.replace(base, **{switch: False})
        model = IIDSU(cfg)
        assert head not in model.heads and head not in model.eca
        full = IIDSU(base)
        n = sum(p.numel() for p in model.parameters())
        assert n < sum(p.numel() for p in full.parameters())
        losses = compute_losses(model(*(batch[k] for k in INPUTS)), batch, TrainConfig())
        assert not terms & losses.keys()
        camera = cfg.has_camera_traffic  # ours, and only with the traffic head
        assert camera == (base is OURS and switch != "traffic")
        expected = set(loss_terms(base.heads, base is OURS)) - terms
        expected -= set() if camera else {"camera_tf"}
        assert set(losses) == set(loss_terms(cfg.heads, camera)) == expected


def test_single_frame_lidar_reads_two_channels():
    model = IIDSU(dataclasses.replace(TINY, single_frame_lidar=True))
    assert model.lidar_encoder.stem[0].in_channels == 2
    image, lidar, speed, target = _inputs(1)
    assert model(image, lidar[:, :2], speed, target)["planning"].shape == (1, 4, 2)
    with pytest.raises(ValueError, match="4 channels; this model takes 2"):
        model(image, lidar, speed, target)  # the summed ground channel: refused, not sliced


def _batch(tmp_path_factory, n: int) -> dict:
    root = write_shards(tmp_path_factory.mktemp("frames"), towns=("alpha",), episodes=1, frames=n)
    stream = data.FrameStream(data.scan(root), TINY.output_px)
    return next(iter(data.make_loader(stream, n, num_workers=0)))


@pytest.mark.slow
def test_loss_falls_when_overfitting_a_few_frames(tmp_path_factory):
    torch.manual_seed(0)
    batch = _batch(tmp_path_factory, n=4)
    model = IIDSU(TINY)
    optimizer = torch.optim.AdamW(model.parameters(), lr=2e-3)
    cfg = TrainConfig()
    history = []
    for _ in range(40):
        losses = compute_losses(model(*(batch[k] for k in INPUTS)), batch, cfg)
        optimizer.zero_grad()
        losses["total"].backward()
        optimizer.step()
        history.append({k: v.item() for k, v in losses.items()})
    first, last = history[0], history[-1]
    assert last["total"] < 0.3 * first["total"]
    for term in ("wp", "heat", "reg", "bev", "tf", "weather"):
        assert last[term] < first[term], term


def test_red_light_and_stop_sign_positives_weigh_traffic_pos_weight(tmp_path_factory):
    batch = _batch(tmp_path_factory, n=2)
    out = {"planning": batch["waypoints"], "traffic": torch.zeros(2, 2)}  # p = 0.5 everywhere
    batch = {**batch, "traffic": torch.tensor([[1.0, 0.0], [0.0, 1.0]])}
    for w in ((1.0, 1.0), (3.0, 5.0)):
        cfg = TrainConfig(traffic_pos_weight=w, traffic_context_weight=1.0)
        losses = compute_losses(out, batch, cfg)
        # one positive and one negative per column: (w log 2 + log 2) / 2
        for term, wi in zip(("light", "stop"), w):
            assert losses[term].item() == pytest.approx((wi + 1) / 2 * math.log(2))


def test_frames_whose_speed_contradicts_the_traffic_label_weigh_traffic_context_weight(
    tmp_path_factory,
):
    batch = _batch(tmp_path_factory, n=4)
    out = {"planning": batch["waypoints"], "traffic": torch.zeros(4, 2)}  # p = 0.5 everywhere
    # red while moving (hard), red while stopped, none while stopped (hard), none while moving;
    # stop sign: the other way round
    truth = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])
    speed = torch.tensor([8.0, 0.0, 0.2, 5.0])
    batch = {**batch, "traffic": truth, "speed": speed}
    log2 = math.log(2)
    for k in (1.0, 3.0):
        cfg = TrainConfig(traffic_pos_weight=(1.0, 1.0), traffic_context_weight=k)
        losses = compute_losses(out, batch, cfg)
        # light: frames 0 and 2 are hard; stop sign: frames 1 (stopped, none) and 3 (moving,
        # sign) are hard
        assert losses["light"].item() == pytest.approx((2 * k + 2) / 4 * log2)
        assert losses["stop"].item() == pytest.approx((2 * k + 2) / 4 * log2)
    # old runs resume without the weighting
    saved = TrainConfig().to_dict()
    del saved["traffic_context_weight"]
    assert TrainConfig.from_dict(saved).traffic_context_weight == 1.0
    assert TrainConfig().traffic_context_weight == 1.0


@pytest.mark.parametrize("layout", [torch.channels_last, torch.contiguous_format])
def test_pooled_pixel_lamps_equal_the_max_pool_of_the_full_maps(layout):
    from torch import nn
    from torch.nn import functional as F

    from training.lamps import pooled_pixel_lamps

    torch.manual_seed(0)
    lamps = nn.Sequential(nn.Conv2d(3, 8, 1), nn.GELU())
    nn.init.normal_(lamps[0].weight, std=1.0)  # outputs on both sides of GELU's minimum
    # flat 8x8 cells of random colours plus noise: in some cells every output lies below
    # GELU's minimum, where the cell's smallest output gives the largest GELU
    cells = torch.randint(0, 256, (3, 3, 8, 8)).repeat_interleave(8, 2).repeat_interleave(8, 3)
    image = (cells + torch.randint(-20, 21, cells.shape)).clamp(0, 255).to(torch.uint8)
    x = ((image.float() / 255 - 0.45) / 0.225).contiguous(memory_format=layout)
    z = lamps[0](x)
    full = F.adaptive_max_pool2d(lamps(x), 8)  # the definition: GELU everywhere, then pool
    fast = pooled_pixel_lamps(lamps, x, 8)
    assert fast.shape == full.shape and torch.allclose(fast, full, atol=1e-5)
    at_high = torch.isclose(full, F.gelu(F.adaptive_max_pool2d(z, 8)), atol=1e-6)
    assert at_high.any() and not at_high.all()  # both of a cell's extremes occur
    grad = torch.randn_like(full)
    want = torch.autograd.grad(full, list(lamps.parameters()), grad)
    got = torch.autograd.grad(fast, list(lamps.parameters()), grad)
    for w, g in zip(want, got):
        assert torch.allclose(w, g, rtol=1e-4, atol=1e-5)


def test_without_the_speed_input_the_plan_does_not_depend_on_the_speed():
    from training.config import architecture

    torch.manual_seed(0)
    image, lidar, speed, target = _inputs(2)
    for base, arch in ((TINY, "paper + speed_input"), (preset("tiny", "ours")[0], None)):
        blind = IIDSU(dataclasses.replace(base, speed_input=False)).eval()
        seeing = IIDSU(base).eval()
        seeing.load_state_dict(blind.state_dict())  # the same weights, the same modules
        with torch.no_grad():
            still = blind.plan(image, lidar, torch.zeros_like(speed), target)
            fast = blind.plan(image, lidar, torch.full_like(speed, 3.0), target)
            assert torch.equal(still, fast)
            assert torch.equal(blind(image, lidar, speed, target)["planning"], fast)
            assert not torch.allclose(seeing.plan(image, lidar, speed + 3.0, target), fast)
        if arch:
            assert architecture(blind.cfg) == arch
        else:  # ours without the speed input is no longer `ours`
            assert architecture(blind.cfg).endswith("speed_input")
