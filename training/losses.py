"""The multi-task loss of II-DSU (paper Sec. III-C, Eq. 1-3):

    L = l_wp L_wp + l_O (alpha L_heat + beta L_reg) + l_M L_M + l_tf (gamma L_light + delta L_sign)
        + l_wc L_wc

L_wp: L1 between predicted and expert waypoints. L_heat: CenterNet's penalty-reduced focal loss
(a cross-entropy that down-weights easy negatives and pixels near a centre), L_reg: smooth L1 at
object centres. L_M: cross-entropy with class weights (`TrainConfig.bev_class_weights`, thin
lane markings weigh more). L_wc: cross-entropy. L_light, L_sign: binary cross-entropy, positives weighted by
`TrainConfig.traffic_pos_weight` (red lights and stop signs are the minority). A head switched
off (an ablation) has no output, so its term is absent from the sum. Ours, not the paper's:
with `ModelConfig.camera_traffic`, the same traffic-rule loss on the camera encoder alone,
weighted `TrainConfig.lambda_camera_tf`. Every term is computed in
float32, also under bf16 autocast.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from training.config import TrainConfig
from training.targets import gather_centres, split_density

TERMS = {
    "planning": ("wp", "total"),
    "detection": ("heat", "reg", "det"),
    "bev": ("bev",),
    "traffic": ("light", "stop", "tf"),
    "weather": ("weather",),
}
"""The terms `compute_losses` returns for each head present ("total" always)."""


def loss_terms(heads: tuple[str, ...], camera_traffic: bool = False) -> tuple[str, ...]:
    """Names of the terms `compute_losses` returns for a model with these heads (and the
    camera-only traffic-rule head, `ModelConfig.has_camera_traffic`)."""
    return tuple(t for h in heads for t in TERMS[h]) + (("camera_tf",) if camera_traffic else ())


STOPPED_MPS = 0.5
"""Below this ego speed (m/s) a frame counts as stopped for `context_weights`."""


def context_weights(truth: torch.Tensor, speed: torch.Tensor, weight: float) -> torch.Tensor:
    """(B, 2) per-frame weights of L_light and L_sign (ours, TrainConfig.traffic_context_weight):
    `weight` where the ego's speed contradicts what the label usually goes with, i.e. a red
    light or a stop sign while moving, or neither while stopped (speed (B,) m/s below
    STOPPED_MPS); 1 elsewhere. Every head sees the speed (TransFuser's velocity embedding), and
    on a 16k build "stopped" alone predicts a red light with F1 ~0.5 (39 % of stopped frames
    are red, 6 % of moving ones), so the frames where that shortcut fails count more."""
    stopped = (speed < STOPPED_MPS)[:, None]
    hard = (truth > 0.5) != stopped
    return torch.where(hard, torch.full_like(truth, weight), torch.ones_like(truth))


def traffic_rule_loss(
    logits: torch.Tensor, truth: torch.Tensor, cfg: TrainConfig, speed: torch.Tensor | None = None
):
    """L_light, L_sign and gamma L_light + delta L_sign of (B, 2) logits against 0/1 truth;
    with the ego speed (B,) m/s, each frame weighted by `context_weights`."""
    logits = logits.float()
    pos = torch.tensor(cfg.traffic_pos_weight, device=logits.device)
    w = None
    if speed is not None and cfg.traffic_context_weight != 1.0:
        w = context_weights(truth, speed.float(), cfg.traffic_context_weight)
    bce = F.binary_cross_entropy_with_logits
    light = bce(logits[:, 0], truth[:, 0], pos_weight=pos[0], weight=None if w is None else w[:, 0])
    stop = bce(logits[:, 1], truth[:, 1], pos_weight=pos[1], weight=None if w is None else w[:, 1])
    return light, stop, cfg.gamma * light + cfg.delta * stop


def focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet's focal loss (alpha 2, beta 4) over heatmaps, normalised by the object count.

    logits, target: (B, T, R, R); target is 1 at centres and a Gaussian in [0, 1) around them.
    """
    logits, target = logits.float(), target.float()
    pos = target.eq(1).float()
    log_p = F.logsigmoid(logits)
    log_not_p = F.logsigmoid(-logits)
    p = log_p.exp()
    pos_loss = (1 - p) ** 2 * log_p * pos
    neg_loss = (1 - target) ** 4 * p**2 * log_not_p * (1 - pos)
    return -(pos_loss.sum() + neg_loss.sum()) / pos.sum().clamp(min=1)


def centre_smooth_l1(
    regression: torch.Tensor, index: torch.Tensor, target: torch.Tensor, mask: torch.Tensor
) -> torch.Tensor:
    """Smooth L1 over the 6 regression channels at object centres, averaged per object.

    regression: (B, T, 6, R, R) predicted maps; index (B, T, K) flat centre pixels; target
    (B, T, K, 6); mask (B, T, K), 1 for real entries.
    """
    pred = gather_centres(regression.float(), index)  # (B, T, K, 6)
    loss = F.smooth_l1_loss(pred, target, reduction="none").sum(dim=3)
    return (loss * mask).sum() / mask.sum().clamp(min=1)


def compute_losses(
    out: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], cfg: TrainConfig
) -> dict[str, torch.Tensor]:
    """Every loss term for the heads present in `out`, and their weighted sum as "total".

    Args:
        out: the model's outputs (training/model.py).
        batch: targets from the loader: waypoints (B, 4, 2) m; heatmap (B, 3, R, R);
            centre_index, centre_mask (B, 3, K), centre_reg (B, 3, K, 6) (training/targets.py);
            bev (B, R, R) uint8 class ids; traffic (B, 2) 0/1 float32
            (red light, stop sign); weather (B,) int64; speed (B,) m/s (the model's input,
            which weights the traffic terms: `context_weights`).
    Returns:
        scalar tensors: wp, and as present heat, reg, det, bev, light, stop, tf, weather,
        camera_tf; total.
    """
    terms = {"wp": F.l1_loss(out["planning"].float(), batch["waypoints"])}
    total = cfg.lambda_wp * terms["wp"]
    if "detection" in out:
        heat, reg = split_density(out["detection"])
        terms["heat"] = focal_loss(heat, batch["heatmap"])
        terms["reg"] = centre_smooth_l1(
            reg, batch["centre_index"], batch["centre_reg"], batch["centre_mask"]
        )
        terms["det"] = cfg.alpha * terms["heat"] + cfg.beta * terms["reg"]
        total = total + cfg.lambda_o * terms["det"]
    if "bev" in out:
        weight = torch.tensor(cfg.bev_class_weights, device=out["bev"].device)
        terms["bev"] = F.cross_entropy(out["bev"].float(), batch["bev"].long(), weight=weight)
        total = total + cfg.lambda_m * terms["bev"]
    if "traffic" in out:
        terms["light"], terms["stop"], terms["tf"] = traffic_rule_loss(
            out["traffic"], batch["traffic"], cfg, batch.get("speed")
        )
        total = total + cfg.lambda_tf * terms["tf"]
    if "camera_traffic" in out:  # ours: the same rule from the camera encoder alone
        terms["camera_tf"] = traffic_rule_loss(
            out["camera_traffic"], batch["traffic"], cfg, batch.get("speed")
        )[2]
        total = total + cfg.lambda_camera_tf * terms["camera_tf"]
    if "weather" in out:
        terms["weather"] = F.cross_entropy(out["weather"].float(), batch["weather"])
        total = total + cfg.lambda_wc * terms["weather"]
    terms["total"] = total
    return terms
