"""Rollout videos with OpenCV.

:class:`VideoWriter` writes MP4 (``mp4v`` codec). OpenCV cannot write GIF, so when the MP4
encoder is unavailable it falls back to Motion-JPEG AVI (``MJPG``, available in every OpenCV
build), and as a last resort to a directory of numbered PNG frames. The path actually written
is :attr:`VideoWriter.path` (returned by :func:`write_video`).

:func:`side_by_side` puts a large render next to the agent's small (e.g. 32x32) view, upscaled
with nearest-neighbour so the pixels the agent sees stay visible.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterable, Sequence

import cv2
import numpy as np

__all__ = ["VideoWriter", "write_video", "side_by_side", "to_uint8_frame"]

_FONT = cv2.FONT_HERSHEY_SIMPLEX


def to_uint8_frame(frame) -> np.ndarray:
    """An ``[H, W, 3]`` uint8 RGB numpy frame from a tensor/array (``[3, H, W]`` or floats in [0, 1] accepted)."""
    if hasattr(frame, "detach"):
        frame = frame.detach().cpu().numpy()
    frame = np.asarray(frame)
    if frame.ndim == 3 and frame.shape[0] in (1, 3) and frame.shape[-1] not in (1, 3):
        frame = np.transpose(frame, (1, 2, 0))
    if frame.ndim == 2:
        frame = frame[..., None]
    if frame.ndim != 3 or frame.shape[-1] not in (1, 3):
        raise ValueError(f"expected an image of shape [H, W, 3] (or [3, H, W]), got {frame.shape}")
    if frame.shape[-1] == 1:
        frame = np.repeat(frame, 3, axis=-1)
    if frame.dtype != np.uint8:
        if np.issubdtype(frame.dtype, np.floating) and frame.size and float(np.nanmax(frame)) <= 1.0:
            frame = frame * 255.0
        frame = np.clip(np.nan_to_num(frame), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(frame)


def side_by_side(
    large, small, *, labels: Sequence[str] | None = ("render", "agent view"), text: str | None = None
) -> np.ndarray:
    """``[large | small upscaled to large's height]`` as one RGB uint8 frame, with optional captions."""
    large, small = to_uint8_frame(large), to_uint8_frame(small)
    h = large.shape[0]
    scale = h / small.shape[0]
    up = cv2.resize(small, (max(1, round(small.shape[1] * scale)), h), interpolation=cv2.INTER_NEAREST)
    sep = np.full((h, 4, 3), 255, np.uint8)
    frame = np.ascontiguousarray(np.concatenate([large, sep, up], axis=1))
    if labels:
        for (x0, label) in zip((0, large.shape[1] + 4), labels):
            _caption(frame, label, x0, 0)
    if text:
        _caption(frame, text, 0, h - 18)
    return frame


def _caption(frame: np.ndarray, text: str, x0: int, y0: int) -> None:
    """White text on a dark strip (readable on any background, survives video compression)."""
    (tw, _), _ = cv2.getTextSize(text, _FONT, 0.4, 1)
    x1, y1 = min(frame.shape[1], x0 + tw + 8), min(frame.shape[0], y0 + 18)
    frame[y0:y1, x0:x1] = (frame[y0:y1, x0:x1] * 0.35).astype(np.uint8)
    cv2.putText(frame, text, (x0 + 4, y0 + 13), _FONT, 0.4, (255, 255, 255), 1, cv2.LINE_AA)


class VideoWriter:
    """Write RGB frames to ``path`` (``.mp4``); see the module doc for the fallbacks.

    The frame size is fixed by the first frame; later frames of another size are resized.
    """

    def __init__(self, path: str | Path, fps: float = 10.0, *, codecs: Sequence[tuple[str, str]] | None = None):
        self.requested = Path(path)
        self.fps = float(fps)
        self.codecs = list(codecs) if codecs is not None else [(".mp4", "mp4v"), (".avi", "MJPG")]
        self.path: Path | None = None
        self.kind: str | None = None
        self._writer = None
        self._size: tuple[int, int] | None = None
        self.frames = 0

    def _open(self, w: int, h: int) -> None:
        self.requested.parent.mkdir(parents=True, exist_ok=True)
        for suffix, fourcc in self.codecs:
            path = self.requested.with_suffix(suffix)
            writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), self.fps, (w, h))
            if writer.isOpened():
                self._writer, self.path, self.kind = writer, path, fourcc
                return
            writer.release()
        # No working encoder: a directory of PNG frames.
        self.path = self.requested.with_suffix("")
        self.path = self.path.with_name(self.path.name + "_frames")
        self.path.mkdir(parents=True, exist_ok=True)
        self.kind = "png"

    def write(self, frame) -> None:
        frame = to_uint8_frame(frame)
        h, w = frame.shape[:2]
        if self._size is None:
            # Several codecs require even dimensions.
            self._size = (w + w % 2, h + h % 2)
            self._open(*self._size)
        if (w, h) != self._size:
            frame = cv2.resize(frame, self._size, interpolation=cv2.INTER_NEAREST)
        bgr = cv2.cvtColor(frame, cv2.COLOR_RGB2BGR)
        if self.kind == "png":
            cv2.imwrite(str(self.path / f"{self.frames:05d}.png"), bgr)
        else:
            self._writer.write(bgr)
        self.frames += 1

    def close(self) -> Path | None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        return self.path

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_video(path: str | Path, frames: Iterable, fps: float = 10.0) -> Path:
    """Write all ``frames`` and return the path actually written (``.mp4``, ``.avi`` or a frame dir)."""
    with VideoWriter(path, fps) as writer:
        for frame in frames:
            writer.write(frame)
    if writer.path is None:
        raise ValueError(f"no frames given for video {path}")
    return writer.path
