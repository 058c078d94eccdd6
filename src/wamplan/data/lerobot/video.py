"""Camera streams as MP4 files through PyAV: one writer appends episodes to a file (v3.0's shared files, v2.1's one
file an episode), one reader returns the frames of a time span.

Codec: LeRobot encodes AV1 with SVT-AV1 (``libsvtav1``, yuv420p, CRF 30, a key frame every 2 frames so that a
frame is found quickly). PyAV's wheels ship that encoder; where a build lacks it, ``auto`` falls back to H.264
(``libx264``), which every LeRobot reader decodes as well. Frame ``k`` of a file is shown at ``k / fps`` seconds.
"""

from __future__ import annotations

import logging
import os
from fractions import Fraction
from pathlib import Path

import numpy as np

from wamplan.data.lerobot.layout import LeRobotError
from wamplan.errors import reason

CODECS = ("auto", "libsvtav1", "libx264")
# SVT-AV1 prints its configuration to stderr on every file unless told otherwise (1: errors only)
os.environ.setdefault("SVT_LOG", "1")


def encoder_available(name: str) -> bool:
    import av

    try:
        av.codec.Codec(name, "w")
    except (av.codec.codec.UnknownCodecError, ValueError):
        return False
    return True


def pick_codec(name: str = "auto") -> str:
    """``name`` if PyAV can encode it; ``auto``: AV1 (SVT-AV1) where present, else H.264."""
    if name == "auto":
        return next((c for c in CODECS[1:] if encoder_available(c)), "libx264")
    if not encoder_available(name):
        raise LeRobotError(f"--vcodec {name}: this PyAV build has no such encoder; pass --vcodec auto")
    return name


class VideoWriter:
    """Frames of one camera appended to one MP4 file at ``fps``; ``frames`` counts them, so the next episode's span
    starts at ``frames / fps`` seconds."""

    def __init__(self, path: Path, fps: int, width: int, height: int, codec: str, crf: int = 30, gop: int = 2):
        import av

        if width % 2 or height % 2:
            raise LeRobotError(f"{path}: views of {width}x{height} px cannot be encoded in yuv420p (even sizes "
                               f"only); pass an even --image-size")
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path, self.fps, self.frames = path, fps, 0
        self.container = av.open(str(path), "w")
        self.stream = self.container.add_stream(codec, rate=fps, options={"crf": str(crf), "g": str(gop)})
        self.stream.width, self.stream.height, self.stream.pix_fmt = width, height, "yuv420p"
        self.time_base = self.stream.time_base = Fraction(1, fps)  # the muxer may change the stream's on its header

    def add(self, frames: np.ndarray) -> None:
        """(N, H, W, 3) uint8, appended in order."""
        import av

        for img in frames:
            f = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format="rgb24")
            f.pts, f.time_base = self.frames, self.time_base
            self.container.mux(self.stream.encode(f))
            self.frames += 1

    def size_mb(self) -> float:
        return self.path.stat().st_size / 2**20 if self.path.exists() else 0.0

    def close(self) -> None:
        self.container.mux(self.stream.encode())
        self.container.close()


def video_info(path: Path) -> dict:
    """What LeRobot records of a video feature (``info`` of the feature in info.json)."""
    import av

    with av.open(str(path)) as c:
        s = c.streams.video[0]
        return {"video.height": s.height, "video.width": s.width, "video.codec": s.codec.canonical_name,
                "video.pix_fmt": s.pix_fmt, "video.is_depth_map": False, "video.fps": int(s.base_rate),
                "video.channels": 3, "has_audio": bool(c.streams.audio)}


def read_span(path: Path, start: float, end: float | None, fps: float, what: str) -> np.ndarray:
    """The frames of ``path`` shown at ``start <= t < end`` (end None: to the file's end), (N, H, W, 3) uint8; one
    :class:`LeRobotError` naming the file if it is missing or cannot be decoded."""
    import av

    if not path.is_file():
        raise LeRobotError(f"{path} is missing ({what}); the dataset is incomplete")
    half = 0.5 / fps  # a frame belongs to the span its presentation time falls in, to half a frame
    out = []
    logging.getLogger("libav").setLevel(logging.ERROR)
    try:
        with av.open(str(path)) as c:
            stream = c.streams.video[0]
            if start > half and stream.time_base:
                c.seek(int(max(0.0, start - half) / stream.time_base), stream=stream, backward=True)
            for frame in c.decode(stream):
                t = float(frame.time if frame.time is not None else 0.0)
                if end is not None and t >= end - half:
                    break
                if t >= start - half:
                    out.append(frame.to_ndarray(format="rgb24"))  # (H, W, 3)
    except (av.error.FFmpegError, IndexError, ValueError) as e:
        raise LeRobotError(f"{path} cannot be decoded ({what}: {reason(e)}); the dataset is damaged") from None
    if not out:
        return np.zeros((0, 0, 0, 3), np.uint8)
    return np.stack(out)  # (N, H, W, 3)
