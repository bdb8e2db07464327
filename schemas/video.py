"""Frames -> a video file that plays in browsers, for `datagen inspect` and `train show`.

    with VideoWriter("episode.mp4", fps=8.0) as video:
        for rgb in frames:                 # (H, W, 3) uint8 RGB, all of one size
            video.write(rgb)

`.mp4` is H.264 (yuv420p, `+faststart`), `.webm` is VP9, both through PyAV (`pip install
'iidsu[viz]'`; its wheels ship FFmpeg with libx264 and libvpx). Without PyAV the writer falls
back to OpenCV, whose pip wheel cannot encode H.264 (measured: `avc1` fails to open): `.mp4`
then holds MPEG-4 Part 2 (`mp4v`), which VLC and ffplay play but browsers do not, and a warning
says so. It lives in `schemas/` because both halves draw datasets and `training/` may not
import `datagen/`.

The file appears under its name only when `close()` has finished it (written to a hidden
`.NAME.partial.EXT` beside it, then renamed); on an error nothing is left under either name.
`prepare_output` gives the same rule to the PNGs and Rerun recordings the viewers write.
"""

from __future__ import annotations

import os
import sys
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

from schemas.outputs import check_file, partial_path  # noqa: F401  (partial_path: re-exported)

# suffix -> (PyAV codec, OpenCV fallback fourcc, fallback's description)
CODECS = {
    ".mp4": ("libx264", "mp4v", "MPEG-4 Part 2 (mp4v): plays in VLC/ffplay, not in browsers"),
    ".webm": ("libvpx-vp9", "VP90", "VP9 through OpenCV"),
}
# libx264's default quality; "veryfast" encoded a 360-frame inspect video 2.5x faster than the
# default "medium" (5.5 s vs 13-16 s on a loaded 2-core box) for a 1 % larger file.
X264_OPTIONS = {"crf": "23", "preset": "veryfast"}


class VideoError(ValueError):
    """An output path that cannot take the file (suffix, folder); one-line message."""


def prepare_output(path: Path) -> Path:
    """Check that `path` can be written (schemas.outputs.check_file: UserError in one line if
    not), create its folder and return its `partial_path`."""
    path = check_file(path, flag=None)
    path.parent.mkdir(parents=True, exist_ok=True)
    return partial_path(path)


class VideoWriter:
    """Writes (H, W, 3) uint8 RGB frames at `fps` frames per second to `path` (.mp4 or .webm).

    Odd frame sizes are padded by one black row/column (yuv420p needs even sides)."""

    def __init__(self, path: str | Path, fps: float, quiet: bool = False):
        self.path = Path(path)
        suffix = self.path.suffix.lower()
        if suffix not in CODECS:
            raise VideoError(f"{self.path}: a video must end in {' or '.join(CODECS)}")
        if not fps > 0:
            raise VideoError(f"frame rate must be > 0, got {fps}")
        self.fps, self.quiet, self.frames = fps, quiet, 0
        self.partial = prepare_output(self.path)
        self._container = self._stream = self._cv = None
        self.codec = self._open_av(suffix)

    def _open_av(self, suffix: str) -> str:
        try:
            import av
        except ImportError:
            if not self.quiet:
                print(
                    f"note: PyAV is not installed (pip install 'iidsu[viz]'), so {self.path.name} "
                    f"is {CODECS[suffix][2]}",
                    file=sys.stderr,
                )
            return CODECS[suffix][1]
        self._av = av
        try:
            self._container = av.open(
                str(self.partial),
                "w",
                options={"movflags": "+faststart"} if suffix == ".mp4" else {},
            )
        except OSError as e:
            raise VideoError(f"{self.path}: cannot write here ({e.strerror or e})") from None
        return CODECS[suffix][0]

    def write(self, rgb: np.ndarray) -> None:
        """Append one (H, W, 3) uint8 RGB frame; the first one fixes the size."""
        h, w = rgb.shape[:2]
        rgb = np.pad(rgb, ((0, h % 2), (0, w % 2), (0, 0)))
        if self.frames == 0:
            self._start(rgb.shape[1], rgb.shape[0])
        if self._container is not None:
            frame = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
            for packet in self._stream.encode(frame):
                self._container.mux(packet)
        else:
            self._cv.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        self.frames += 1

    def _start(self, width: int, height: int) -> None:
        if self._container is not None:
            rate = Fraction(self.fps).limit_denominator(1000)
            self._stream = self._container.add_stream(self.codec, rate=rate)
            self._stream.width, self._stream.height = width, height
            self._stream.pix_fmt = "yuv420p"  # what browsers decode
            self._stream.options = X264_OPTIONS if self.codec == "libx264" else {}
        else:
            fourcc = cv2.VideoWriter_fourcc(*self.codec)
            self._cv = cv2.VideoWriter(str(self.partial), fourcc, self.fps, (width, height))
            if not self._cv.isOpened():
                raise VideoError(f"{self.path}: OpenCV cannot open a {self.codec} writer here")

    def close(self) -> None:
        """Finish the file and move it to its name."""
        if self.frames == 0:
            self.abort()
            raise VideoError(f"{self.path}: no frames to write")
        if self._container is not None:
            for packet in self._stream.encode():
                self._container.mux(packet)
            self._container.close()
        else:
            self._cv.release()
        os.replace(self.partial, self.path)

    def abort(self) -> None:
        """Drop the unfinished file."""
        try:
            if self._container is not None:
                self._container.close()
            elif self._cv is not None:
                self._cv.release()
        except Exception:  # noqa: BLE001  (closing a broken stream: the file goes anyway)
            pass
        self.partial.unlink(missing_ok=True)

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
