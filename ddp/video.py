"""Rollout videos with the controller's state drawn on every frame.

A base env that can render colour images exposes ``render_rgb(width, height,
camera=None) -> uint8 [H, W, 3]`` (a camera it does not have: ``ValueError``,
one line naming its cameras). :class:`EpisodeRecorder` collects one
frame per simulated step (``ChunkedEnv`` feeds it) and labels each frame with
what the DDP controller decided for the chunk being executed:

* a coloured border: green = ID, acting from real latents; orange = OOD but
  acting from real latents (the tracking-only ablation); red = imagining
  (acting from imagined latents); blue flash = a tracking / recovery shift of
  the end-effector was executed before the chunk;
* a caption: chunk index, mode, D_R-I (when the world model forecast it) and
  "success" once the task is solved.

Videos are MP4 when imageio with its ffmpeg plugin is installed
(``pip install "ddp[video]"``) and animated GIF otherwise (Pillow, which
matplotlib already needs). Beside each video, ``<name>_sheet.png`` shows the
episode at a glance: the last frame of every chunk, labelled the same way,
eight to a row (small enough to commit with a run's results).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ddp.atomic_file import atomic_write

__all__ = ["ChunkLabel", "EpisodeRecorder", "VideoSettings", "annotate", "contact_sheet", "write_video"]

ID_COLOUR = (40, 170, 70)
OOD_REAL_COLOUR = (235, 140, 20)
IMAGINED_COLOUR = (210, 40, 40)
SHIFT_COLOUR = (40, 90, 220)


@dataclass(frozen=True)
class VideoSettings:
    """Where and how ``ChunkedEnv`` records: the first ``episodes`` episodes of each env (only episodes that end:
    one cut short by a reset or by closing the env is not written)."""

    directory: str
    episodes: int = 2
    size: int = 256
    fps: int = 20
    camera: str | None = None  # the env's default video camera
    prefix: str = "seed"
    first_seed: int = 0  # name of the first episode's file: <prefix><first_seed + n>


@dataclass
class ChunkLabel:
    """What the controller did for one chunk (read from the action tensordict)."""

    chunk: int
    mode: int | None = None  # 0 ID, 1 OOD; None: a policy without the DDP controller
    imagined: bool = False
    discrepancy: float = float("nan")
    shifted: bool = False
    success: bool = False

    @classmethod
    def from_tensordict(cls, td, chunk: int, success: bool) -> "ChunkLabel":
        def get(key, default):
            value = td.get(("ddp", key), None)
            return default if value is None else value.reshape(-1)[0].item()

        shift = td.get("ee_shift", None)
        return cls(
            chunk=chunk,
            mode=None if td.get(("ddp", "mode"), None) is None else int(get("mode", 0)),
            imagined=bool(get("imagined", False)),
            discrepancy=float(get("discrepancy", float("nan"))),
            shifted=shift is not None and bool(shift.abs().max() > 0),
            success=success,
        )

    def colour(self) -> tuple[int, int, int]:
        if self.imagined:
            return IMAGINED_COLOUR
        return OOD_REAL_COLOUR if self.mode == 1 else ID_COLOUR

    def caption(self) -> str:
        if self.mode is None:
            state = "policy"
        elif self.imagined:
            state = "OOD: imagining"
        else:
            state = "OOD: real latents" if self.mode == 1 else "ID"
        parts = [f"chunk {self.chunk}", state]
        if not math.isnan(self.discrepancy):
            parts.append(f"D={self.discrepancy:.2g}")
        if self.success:
            parts.append("success")
        return "  ".join(parts)


def annotate(frame: np.ndarray, caption: str, colour: tuple[int, int, int], border: int = 4,
             flash: tuple[int, int, int] | None = None) -> np.ndarray:
    """A copy of ``frame`` with a coloured border (``flash`` as an inner ring) and a caption bar."""
    from PIL import Image, ImageDraw

    out = np.ascontiguousarray(frame[..., :3], dtype=np.uint8).copy()
    h, w = out.shape[:2]
    b = max(1, min(border, h // 8, w // 8))
    out[:b], out[-b:], out[:, :b], out[:, -b:] = colour, colour, colour, colour
    if flash is not None:
        out[b : 2 * b], out[-2 * b : -b], out[:, b : 2 * b], out[:, -2 * b : -b] = flash, flash, flash, flash
    image = Image.fromarray(out)
    draw = ImageDraw.Draw(image)
    bar = 12
    draw.rectangle([b, h - b - bar, w - b - 1, h - b - 1], fill=(0, 0, 0))
    draw.text((b + 2, h - b - bar), caption, fill=colour)
    return np.asarray(image)


def gif_frame_ms(fps: int) -> int:
    """A GIF frame's duration for ``fps``: GIFs count in 10 ms units and viewers slow frames under 20 ms
    to about 100 ms, so the nearest multiple of 10 ms, at least 20 ms (50 fps at most)."""
    return max(20, 10 * round(100 / fps))


def _even(frame: np.ndarray) -> np.ndarray:
    """``frame`` with its last row / column repeated where height / width are odd (libx264 encodes even
    sizes only; an odd one wrote an empty file without an error)."""
    h, w = frame.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return frame
    return np.pad(frame, ((0, h % 2), (0, w % 2)) + ((0, 0),) * (frame.ndim - 2), mode="edge")


def write_video(frames: list[np.ndarray], path: str | Path, fps: int = 20) -> Path:
    """Write frames as MP4 (imageio + ffmpeg) or, without them, as GIF next to ``path``; returns the file.
    Odd frame sizes are padded by one row / column for the MP4 encoder; a GIF plays at most 50 fps."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not frames:
        raise ValueError(f"{path}: no frames to write")
    try:
        import imageio.v2 as imageio
        import imageio_ffmpeg  # noqa: F401 - the mp4 writer's backend
    except ImportError:
        from PIL import Image

        images = [Image.fromarray(f) for f in frames]
        return atomic_write(path.with_suffix(".gif"), lambda f: images[0].save(
            f, format="GIF", save_all=True, append_images=images[1:], duration=gif_frame_ms(fps), loop=0))
    mp4 = path.with_suffix(".mp4")
    tmp = mp4.with_name(f".{mp4.stem}.tmp.mp4")  # ffmpeg writes to a path: renamed once whole
    try:
        with imageio.get_writer(tmp, fps=fps, codec="libx264", quality=7, macro_block_size=1) as writer:
            for f in frames:
                writer.append_data(_even(f))
        if not tmp.is_file() or tmp.stat().st_size == 0:  # ffmpeg can fail without imageio raising
            raise RuntimeError(f"{mp4}: the video encoder wrote nothing (ffmpeg's log above says why)")
        tmp.replace(mp4)
    finally:
        tmp.unlink(missing_ok=True)  # a writer that failed part-way leaves no hidden half-file behind
    return mp4


def contact_sheet(frames: list[np.ndarray], path: str | Path, columns: int = 8, width: int = 160) -> Path:
    """Write ``frames`` (one per chunk, already labelled) as one PNG grid, each scaled to ``width`` px."""
    from PIL import Image

    if not frames:
        raise ValueError(f"{path}: no frames for a contact sheet")
    tiles = []
    for f in frames:
        img = Image.fromarray(np.ascontiguousarray(f[..., :3], dtype=np.uint8))
        tiles.append(img.resize((width, max(1, round(img.height * width / img.width))), Image.LANCZOS))
    cols = min(columns, len(tiles))
    rows = math.ceil(len(tiles) / cols)
    h = max(t.height for t in tiles)
    sheet = Image.new("RGB", (cols * width, rows * h), (255, 255, 255))
    for i, t in enumerate(tiles):
        sheet.paste(t, ((i % cols) * width, (i // cols) * h))
    return atomic_write(path, lambda f: sheet.save(f, format="PNG", optimize=True))


class EpisodeRecorder:
    """Collects labelled frames episode by episode and writes the first ``settings.episodes`` of them."""

    def __init__(self, settings: VideoSettings):
        if settings.episodes < 0:
            raise ValueError(f"video episodes must be >= 0; got {settings.episodes}")
        self.settings = settings
        self.frames: list[np.ndarray] = []
        self.chunk_ends: dict[int, int] = {}  # chunk -> index of its last frame (the contact sheet's frames)
        self.episode = -1  # episodes started so far - 1
        self.seed: int | None = None  # the current episode's seed (its file's name), when the env tells it
        self.written: list[Path] = []

    @property
    def recording(self) -> bool:
        return 0 <= self.episode < self.settings.episodes

    def start_episode(self, seed: int | None = None) -> None:
        """A new episode (``seed``: its seed, the file's name; else ``first_seed`` + its number). An episode
        that did not end (the env was reset before its last chunk) is dropped, not written."""
        self.discard()
        self.episode += 1
        self.seed = seed

    def discard(self) -> None:
        """Forget the current episode's frames without writing them (it did not end)."""
        self.frames, self.chunk_ends = [], {}

    def add(self, frame: np.ndarray, label: ChunkLabel | None) -> None:
        if not self.recording:
            return
        if label is None:  # the reset frame, before any decision
            self.frames.append(annotate(frame, "chunk 0  reset", (128, 128, 128)))
        else:
            flash = SHIFT_COLOUR if label.shifted else None
            self.frames.append(annotate(frame, label.caption(), label.colour(), flash=flash))
            self.chunk_ends[label.chunk] = len(self.frames) - 1

    def finish(self) -> Path | None:
        """Write the current episode (if recorded) and forget its frames."""
        if not self.recording or not self.frames:
            self.discard()
            return None
        s = self.settings
        name = Path(s.directory) / f"{s.prefix}{s.first_seed + self.episode if self.seed is None else self.seed}"
        path = write_video(self.frames, name, s.fps)
        ends = [self.chunk_ends[c] for c in sorted(self.chunk_ends)] or [len(self.frames) - 1]
        contact_sheet([self.frames[i] for i in ends], name.with_name(f"{name.name}_sheet.png"))
        self.discard()
        self.written.append(path)
        return path
