"""Benchmark drawing one episode: PNG frames, H.264 and mp4v videos, a Rerun recording.

    .venv/bin/python bench/video.py runs/figure/data --episode downtown-5-0000   # after make figure

Times, for one episode of a built dataset: reading its rows, drawing every frame
(`datagen.dataset.inspect.draw`), encoding the drawn frames to H.264 (PyAV, libx264) and to mp4v
(OpenCV, the fallback), and writing the Rerun recording; prints seconds, ms per frame and the
file sizes. Prints figures, asserts nothing.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from datagen.dataset import inspect, recording  # noqa: E402
from schemas import dataset  # noqa: E402
from schemas.video import VideoWriter  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("path", help="dataset directory")
    p.add_argument("--episode", default=None, help="episode id (default: the first)")
    p.add_argument("--fps", type=float, default=8.0, help="video frame rate (default 8: 4x)")
    args = p.parse_args()
    episode = args.episode or dataset.episode_ids(args.path)[0]
    rows_out = []

    def stage(name, fn, path=None):
        start = time.perf_counter()
        result = fn()
        seconds = time.perf_counter() - start
        size = f"{path.stat().st_size / 1e6:7.1f} MB" if path else ""
        rows_out.append((name, seconds, size))
        return result

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        table = stage("read episode", lambda: dataset.read_episode(args.path, episode))
        rows = table.to_pylist()
        frames = stage("draw frames", lambda: [inspect.draw(r) for r in rows])

        def encode(path, quiet=False):
            with VideoWriter(path, args.fps, quiet=quiet) as video:
                for f in frames:
                    video.write(f)

        h264 = tmp / "h264.mp4"
        stage("encode H.264 (PyAV)", lambda: encode(h264), h264)
        import builtins

        real_import = builtins.__import__

        def no_av(name, *a, **kw):
            if name == "av":
                raise ImportError(name)
            return real_import(name, *a, **kw)

        builtins.__import__ = no_av
        try:
            mp4v = tmp / "mp4v.mp4"
            stage("encode mp4v (OpenCV)", lambda: encode(mp4v, quiet=True), mp4v)
        finally:
            builtins.__import__ = real_import
        rrd = tmp / "episode.rrd"
        stage("rerun recording", lambda: recording.write(table, rrd), rrd)

    n = len(rows)
    print(f"episode {episode}: {n} frames, video at {args.fps:g} fps")
    print(f"{'stage':24} {'s':>7} {'ms/frame':>9} {'size':>10}")
    for name, seconds, size in rows_out:
        print(f"{name:24} {seconds:7.2f} {1000 * seconds / n:9.1f} {size:>10}")
    total = sum(s for name, s, _ in rows_out if name in ("read episode", "draw frames")) + next(
        s for name, s, _ in rows_out if name.startswith("encode H.264")
    )
    print(f"{'inspect --video total':24} {total:7.2f} {1000 * total / n:9.1f}")


if __name__ == "__main__":
    main()
