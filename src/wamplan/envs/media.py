"""Pictures and videos of the task's cameras: the views side by side (in ``CAMERAS`` order unless told), labelled
grids of views, and videos: MP4 (imageio) or VP9 in WebM (PyAV), which browsers play."""

from __future__ import annotations

import functools
import io
from pathlib import Path
from typing import Sequence

import numpy as np

from wamplan.envs.contract import CAMERAS

WEBM_CODEC = "libvpx-vp9"  # VP9: Chromium and Firefox play it from a WebM file


def side_by_side(views: dict[str, np.ndarray], cameras: Sequence[str] | None = None) -> np.ndarray:
    """camera -> (H, W, 3) uint8 images -> one (H, V * W, 3) image, ``cameras`` left to right (default: the cube
    task's front | side | wrist)."""
    return np.concatenate([views[c] for c in (cameras or CAMERAS)], axis=1)


def resize_view(img: np.ndarray, size: int) -> np.ndarray:
    """(H, W, 3) uint8, or float in [0, 1] -> (size, size, 3) uint8 (area filter when shrinking)."""
    from PIL import Image

    if img.dtype != np.uint8:
        img = (np.clip(img, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
    if img.shape[:2] == (size, size):
        return img
    return np.asarray(Image.fromarray(img).resize((size, size), Image.Resampling.BOX))


def labelled_grid(columns: Sequence[tuple[str, Sequence[np.ndarray | None]]], size: int,
                  rows: Sequence[str] = (), header: int = 26) -> np.ndarray:
    """Columns of views under one-line (or two-line) labels -> one (header + R * size, C * size, 3) uint8 image.
    Each column is (label, R views, each (h, w, 3) uint8 or float in [0, 1], or None for an empty grey cell);
    ``rows`` names the R rows in small print at each row's top-left corner. ``size`` and the image width must be
    even for a video."""
    from PIL import Image, ImageDraw

    n_rows = max(len(views) for _, views in columns)
    img = np.full((header + n_rows * size, len(columns) * size, 3), 255, np.uint8)
    for j, (_, views) in enumerate(columns):
        for i, v in enumerate(views):
            cell = np.full((size, size, 3), 200, np.uint8) if v is None else resize_view(v, size)
            img[header + i * size: header + (i + 1) * size, j * size:(j + 1) * size] = cell
    pic = Image.fromarray(img)
    draw, font = ImageDraw.Draw(pic), _font()
    for j, (label, _) in enumerate(columns):
        draw.multiline_text((j * size + 3, 1), label, fill=(0, 0, 0), spacing=1, font=font)
        if j:
            draw.line([(j * size, 0), (j * size, img.shape[0])], fill=(255, 255, 255), width=1)
    for i, name in enumerate(rows):
        draw.text((3, header + i * size + 2), name, fill=(255, 255, 0), font=font)
    return np.asarray(pic)


@functools.cache
def _font(size: int = 11):
    """DejaVu Sans at ``size`` px (the font matplotlib ships), else Pillow's own."""
    from PIL import ImageFont

    try:
        import matplotlib

        return ImageFont.truetype(str(Path(matplotlib.get_data_path()) / "fonts" / "ttf" / "DejaVuSans.ttf"), size)
    except (ImportError, OSError):  # no matplotlib, or a Pillow without FreeType
        return ImageFont.load_default()


def save_views(images: dict[str, np.ndarray], path: str | Path) -> None:
    """Write the views of one step side by side as an image file (format from the suffix)."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, side_by_side(images))


def write_video(path: str | Path, frames: Sequence[dict[str, np.ndarray] | np.ndarray], fps: int = 20,
                steps: Sequence[int] | None = None, hold: int = 0) -> None:
    """Write one video of ``frames`` (per-step views, camera -> (H, W, 3) uint8, put side by side, or whole
    (H, W, 3) uint8 images): MP4 through imageio, or, for a ``.webm`` path, VP9 (see :func:`encode_webm`, which
    ``steps`` and ``hold`` are for)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    pictures = [side_by_side(f) if isinstance(f, dict) else f for f in frames]
    if path.suffix == ".webm":
        path.write_bytes(encode_webm(pictures, fps, steps, hold))
        return
    import imageio.v2 as imageio

    with imageio.get_writer(path, fps=fps, macro_block_size=1) as w:
        for p in pictures:
            w.append_data(p)


def require_webm() -> None:
    """One line naming the package to install when VP9/WebM cannot be written here (PyAV missing, or an FFmpeg
    build without libvpx)."""
    from wamplan.errors import UserError

    try:
        import av
    except ImportError:
        raise UserError("videos need PyAV to write VP9/WebM: pip install av (or pass --videos none)") from None
    try:
        av.codec.Codec(WEBM_CODEC, "w")
    except Exception:  # PyAV raises its own UnknownCodecError (a ValueError) across versions
        raise UserError(f"PyAV {av.__version__} has no {WEBM_CODEC} encoder; reinstall the PyAV wheel (pip install "
                        f"--force-reinstall av), which ships one, or pass --videos none") from None


def encode_webm(pictures: Sequence[np.ndarray], fps: int = 20, steps: Sequence[int] | None = None,
                hold: int = 0) -> bytes:
    """(H, W, 3) uint8 pictures of one size -> the bytes of a VP9 WebM file. ``steps``: each picture's time in
    frames of 1/``fps`` s (increasing; default 0, 1, 2, ...), so pictures taken every few control steps play at
    their real times; ``hold``: frames of 1/``fps`` s the last picture stays on screen. Odd sizes are padded to
    even (VP9's 4:2:0)."""
    import av

    if not pictures:
        raise ValueError("encode_webm needs at least one picture")
    steps = list(range(len(pictures))) if steps is None else [int(s) for s in steps]
    if len(steps) != len(pictures) or any(b <= a for a, b in zip(steps, steps[1:])):
        raise ValueError(f"encode_webm's steps must increase, one per picture; got {steps} for {len(pictures)}")
    h, w = pictures[0].shape[:2]
    H, W = h + h % 2, w + w % 2
    buf = io.BytesIO()
    with av.open(buf, "w", format="webm") as out:
        stream = out.add_stream(WEBM_CODEC, rate=fps)
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        stream.thread_count = 1  # the evaluation's cores run episodes
        # realtime speed: a few ms a picture (the 'good' deadline costs ~4x for a ~20 % smaller file)
        stream.options = {"deadline": "realtime", "cpu-used": "8", "crf": "32", "b": "0", "lag-in-frames": "0"}
        times = steps + ([steps[-1] + hold] if hold > 0 else [])
        for t, p in zip(times, [*pictures, pictures[-1]]):
            if p.shape[:2] != (h, w):
                raise ValueError(f"encode_webm's pictures must share one size; got {p.shape[:2]} after {(h, w)}")
            frame = av.VideoFrame.from_ndarray(np.pad(p, ((0, H - h), (0, W - w), (0, 0)), mode="edge"), format="rgb24")
            frame.pts = t - steps[0]
            out.mux(stream.encode(frame))
        out.mux(stream.encode())
    return buf.getvalue()


def read_video(path: str | Path, fps: int = 20) -> tuple[list[np.ndarray], list[int]]:
    """A video's pictures ((H, W, 3) uint8 each) and their times in frames of 1/``fps`` s (what
    :func:`encode_webm` wrote as ``steps``, counted from the first)."""
    import av

    with av.open(str(path)) as f:
        pairs = [(f_.to_ndarray(format="rgb24"), round(float(f_.time or 0.0) * fps)) for f_ in f.decode(video=0)]
    return [p for p, _ in pairs], [t for _, t in pairs]


def caption(img: np.ndarray, text: str, height: int = 14) -> np.ndarray:
    """(H, W, 3) uint8 -> (height + H, W, 3): one line of ``text`` on a white strip above the picture."""
    from PIL import Image, ImageDraw

    strip = Image.new("RGB", (img.shape[1], height), (255, 255, 255))
    ImageDraw.Draw(strip).text((3, 1), text, fill=(0, 0, 0), font=_font())
    return np.concatenate([np.asarray(strip), img], axis=0)
