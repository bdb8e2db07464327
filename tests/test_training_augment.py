import numpy as np

from tests.synthetic import write_shards
from training import data
from training.augment import zoom_out, zoom_scale


def _dot(row: int, col: int) -> np.ndarray:
    image = np.zeros((3, 256, 256), np.uint8)
    image[0, row - 2 : row + 2, col - 2 : col + 2] = 255  # a 4 px red lamp
    return image


def _centre_of_red(image: np.ndarray) -> tuple[float, float]:
    rows, cols = np.nonzero(image[0] > 32)
    return rows.mean(), cols.mean()


def test_zoom_out_shrinks_about_the_image_centre():
    image = _dot(64, 200)
    out = zoom_out(image, 0.5)
    assert out.shape == image.shape and out.dtype == np.uint8
    row, col = _centre_of_red(out)
    # 64 px above and 72 px right of the centre (128, 128) become 32 and 36
    assert abs(row - (128 - 32)) < 1.5 and abs(col - (128 + 36)) < 1.5
    assert (out[0] > 32).sum() < (image[0] > 32).sum()  # the lamp got smaller
    assert zoom_out(image, 1.0) is image


def test_zoom_out_fills_the_margin_with_the_edge_pixels():
    image = np.zeros((3, 256, 256), np.uint8)
    image[:, 128:] = 200  # a bright lower half (road) under a dark sky
    out = zoom_out(image, 0.6)
    assert (out[:, -1] == 200).all() and (out[:, 0] == 0).all()


def test_zoom_scale_depends_only_on_its_arguments():
    draws = [zoom_scale(3, 2, f"ep-{k % 7}", k, 0.55, 0.5) for k in range(4000)]
    assert draws == [zoom_scale(3, 2, f"ep-{k % 7}", k, 0.55, 0.5) for k in range(4000)]
    zoomed = np.array([s for s in draws if s < 1])
    assert 0.45 < len(zoomed) / len(draws) < 0.55
    assert zoomed.min() >= 0.55 and zoomed.max() < 1
    other_epoch = [zoom_scale(3, 3, f"ep-{k % 7}", k, 0.55, 0.5) for k in range(4000)]
    assert draws != other_epoch


def test_frame_stream_zooms_training_frames_the_same_way_each_time(tmp_path):
    index = data.scan(write_shards(tmp_path, episodes=2, frames=6))

    def images(zoom):
        stream = data.FrameStream(index, 64, shuffle=True, seed=1, zoom_out=zoom)
        stream.set_epoch(1)
        return {(s["episode_id"], s["frame"]): s["image"] for s in stream}

    plain, zoomed, again = images(None), images((0.5, 1.0)), images((0.5, 1.0))
    assert plain.keys() == zoomed.keys()
    assert all(np.array_equal(zoomed[k], again[k]) for k in zoomed)  # exact on --resume
    assert all(not np.array_equal(zoomed[k], plain[k]) for k in zoomed)  # probability 1


def test_runs_from_before_the_augmentation_resume_without_it():
    import dataclasses

    from training.config import PRESETS, TrainConfig, preset

    assert PRESETS["tiny"][1].zoom_out == 1.0  # the paper names no augmentation
    saved = dataclasses.asdict(preset("tiny", "ours")[1])  # ours zooms out
    assert TrainConfig.from_dict(saved).zoom_out == 0.55
    del saved["zoom_out"]
    assert TrainConfig.from_dict(saved).zoom_out == 1.0
