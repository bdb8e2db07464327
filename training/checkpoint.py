"""Checkpoints: one `torch.save`d dict per file, written atomically, loadable without pickle code.

Keys: model (state dict), optimizer (state dict), model_config and train_config (dicts,
`training/config.py`), epoch (epochs completed), step (optimizer steps taken; the learning-rate
schedule is a pure function of it), rng (per DDP rank, the torch CPU and CUDA generator states),
val_episodes (the held-out episode ids), metrics (the last epoch's `metrics.jsonl` line),
sensor_config (the shards' iidsu.config_json, what closed-loop driving checks its sensors against).
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import torch

from schemas import sensor_part
from training.config import ModelConfig
from training.errors import UserError
from training.model import IIDSU


def save_checkpoint(path: Path, state: dict) -> None:
    """Write `state` to `path` through a temporary file and a rename, so that a reader (or a
    crash) never sees half a checkpoint."""
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: str | Path) -> dict:
    """A checkpoint written by `train fit`; UserError if there is none or it is something else."""
    p = Path(path)
    if not p.is_file():
        raise UserError(f"{path}: no such checkpoint")
    try:
        with warnings.catch_warnings():  # e.g. "Detected pickle protocol 4": a foreign file
            warnings.simplefilter("ignore")
            state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception:  # torch raises a variety of types for a foreign or truncated file
        # torch's own message (six lines) advises weights_only=False: unsafe on a foreign file
        # and no help for ours; what the user needs to know is what the file is not
        state = None
    if not isinstance(state, dict) or not {"model", "model_config"} <= state.keys():
        raise UserError(f"{path}: not a checkpoint written by `train fit`")
    return state


def check_sensors(state: dict, sensors: dict | None, what: str, where: str | Path) -> None:
    """UserError naming the differing fields if checkpoint `state` was trained on data from
    other sensors than `sensors` (`what`: whose, e.g. "this world's"; `where`: the checkpoint).
    Checkpoints from before sensor_config was stored, and data that records none, pass: a
    model reads images and sweeps of the sizes it was trained on, nothing else."""
    trained = state.get("sensor_config")
    if trained is None or sensors is None:
        return
    # what shapes only the labels (recovery frames, who drove) is no difference of the sensors
    a, b = (json.loads(json.dumps(sensor_part(c), sort_keys=True)) for c in (trained, sensors))
    if a != b:
        keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        raise UserError(
            f"{where}: trained on data from other sensors than {what} (differs in "
            f"{', '.join(keys)}); evaluate with the sensors the data was recorded with"
        )


def model_from_checkpoint(state: dict, device: torch.device | str = "cpu") -> IIDSU:
    """The checkpoint's model in eval mode on `device`."""
    model = IIDSU(ModelConfig.from_dict(state["model_config"]))
    model.load_state_dict(state["model"])
    return model.to(device).eval()
