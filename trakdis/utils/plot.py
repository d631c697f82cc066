"""Learning-curve PNGs drawn with OpenCV (matplotlib is not a dependency).

One panel per logged column (``train/loss_nll``, ``eval/normalized_performance``, ...) against
``step``, with tick labels, NaN gaps skipped and sparse columns (evaluations) drawn with
markers. Refresh a run's figure from its CSV at any time::

    python -m trakdis.utils.plot runs/online_dt/<name>/log.csv            # -> curves.png beside it
    python -m trakdis.utils.plot log.csv -o out.png --columns eval/normalized_performance
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import pandas as pd

from .checkpoint import atomic_write_bytes

__all__ = ["plot_curves", "plot_csv", "plot_mean_std", "nice_ticks"]

_COLORS = [(180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140)]
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """About ``n`` round tick values covering ``[lo, hi]``."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return []
    if hi <= lo:
        return [lo]
    raw = (hi - lo) / max(n - 1, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    ticks, t = [], first
    while t <= hi + 1e-9 * step:
        ticks.append(0.0 if abs(t) < step * 1e-9 else t)
        t += step
    return ticks


def _fmt(v: float) -> str:
    if v == 0:
        return "0"
    if abs(v) >= 1e4 or abs(v) < 1e-3:
        return f"{v:.1e}"
    return f"{v:.4g}"


def _panel(x: np.ndarray, y: np.ndarray, title: str, size: tuple[int, int], color) -> np.ndarray:
    h, w = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 62, 12, 26, 34
    cv2.putText(img, title, (left, 18), _FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    pw, ph = w - left - right, h - top - bottom
    cv2.rectangle(img, (left, top), (left + pw, top + ph), (0, 0, 0), 1)
    if len(x) == 0:
        cv2.putText(img, "no data", (left + pw // 3, top + ph // 2), _FONT, 0.45, (128, 128, 128), 1, cv2.LINE_AA)
        return img
    x0, x1 = float(x.min()), float(x.max())
    y0, y1 = float(y.min()), float(y.max())
    if x1 == x0:
        x0, x1 = x0 - 1, x1 + 1
    if y1 == y0:
        pad = abs(y0) * 0.1 or 1.0
        y0, y1 = y0 - pad, y1 + pad
    pad = (y1 - y0) * 0.05
    y0, y1 = y0 - pad, y1 + pad

    def px(xv, yv):
        return (
            np.round(left + (np.asarray(xv) - x0) / (x1 - x0) * pw).astype(np.int32),
            np.round(top + ph - (np.asarray(yv) - y0) / (y1 - y0) * ph).astype(np.int32),
        )

    for t in nice_ticks(y0, y1, 5):
        _, ty = px(x0, t)
        cv2.line(img, (left, int(ty)), (left + pw, int(ty)), (230, 230, 230), 1)
        cv2.putText(img, _fmt(t), (4, int(ty) + 4), _FONT, 0.35, (60, 60, 60), 1, cv2.LINE_AA)
    for t in nice_ticks(x0, x1, 5):
        tx, _ = px(t, y0)
        cv2.line(img, (int(tx), top + ph), (int(tx), top + ph + 4), (0, 0, 0), 1)
        label = _fmt(t)
        cv2.putText(img, label, (int(tx) - 4 * len(label), top + ph + 16), _FONT, 0.35, (60, 60, 60), 1, cv2.LINE_AA)
    cv2.putText(img, "step", (left + pw - 30, h - 4), _FONT, 0.35, (60, 60, 60), 1, cv2.LINE_AA)
    order = np.argsort(x, kind="stable")
    xs, ys = px(x[order], y[order])
    pts = np.stack([xs, ys], axis=1).reshape(-1, 1, 2)
    if len(x) > 1:
        cv2.polylines(img, [pts], False, color, 2 if len(x) < 200 else 1, cv2.LINE_AA)
    if len(x) <= 60:
        for p in pts[:, 0]:
            cv2.circle(img, (int(p[0]), int(p[1])), 3, color, -1, cv2.LINE_AA)
    return img


def plot_curves(
    frame: pd.DataFrame,
    path: str | Path,
    *,
    columns: Sequence[str] | None = None,
    x: str = "step",
    panel_size: tuple[int, int] = (240, 360),
    ncols: int = 3,
    title: str | None = None,
) -> Path:
    """Draw one panel per numeric column of ``frame`` against ``x`` and write a PNG."""
    if x not in frame.columns:
        raise KeyError(f"column {x!r} not in the log; columns are {list(frame.columns)}")
    if columns is None:
        columns = [c for c in frame.columns if c != x and pd.api.types.is_numeric_dtype(frame[c])]
    else:
        missing = [c for c in columns if c not in frame.columns]
        if missing:
            raise KeyError(f"columns {missing} not in the log; columns are {list(frame.columns)}")
    xs = pd.to_numeric(frame[x], errors="coerce").to_numpy(float)
    panels = [
        _panel(xs, pd.to_numeric(frame[c], errors="coerce").to_numpy(float), c, panel_size, _COLORS[i % len(_COLORS)])
        for i, c in enumerate(columns)
    ]
    if not panels:
        panels = [_panel(np.array([]), np.array([]), "(no metrics)", panel_size, _COLORS[0])]
    ncols = max(1, min(ncols, len(panels)))
    nrows = math.ceil(len(panels) / ncols)
    blank = np.full_like(panels[0], 255)
    panels += [blank] * (nrows * ncols - len(panels))
    grid = np.vstack([np.hstack(panels[r * ncols : (r + 1) * ncols]) for r in range(nrows)])
    if title:
        head = np.full((28, grid.shape[1], 3), 255, np.uint8)
        cv2.putText(head, title, (8, 20), _FONT, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
        grid = np.vstack([head, grid])
    ok, png = cv2.imencode(".png", grid)
    if not ok:  # pragma: no cover - OpenCV without PNG support
        raise RuntimeError("OpenCV could not encode a PNG")
    return atomic_write_bytes(path, png.tobytes())


def plot_csv(csv_path: str | Path, out: str | Path | None = None, **kwargs) -> Path:
    """Read a ``log.csv`` and write its curves (default: ``curves.png`` beside the CSV)."""
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        raise FileNotFoundError(f"log file {csv_path} does not exist")
    frame = pd.read_csv(csv_path)
    out = Path(out) if out is not None else csv_path.with_name("curves.png")
    kwargs.setdefault("title", str(csv_path.parent))
    return plot_curves(frame, out, **kwargs)


def plot_mean_std(
    curves: "dict[str, tuple[Sequence[float], np.ndarray]]",
    path: str | Path,
    *,
    title: str = "",
    xlabel: str = "step",
    ylabel: str = "",
    size: tuple[int, int] = (420, 640),
    xticks: "Sequence[tuple[float, str]] | None" = None,
) -> Path:
    """One panel of several curves, each a mean line with a +-1 std band: ``curves[label] = (x [T],
    values [S, T])`` (``S`` runs, e.g. seeds; NaN entries are left out of that point's mean/std).
    The legend gives each label with its number of runs. ``xticks``: ``(position, label)`` pairs
    instead of evenly spaced numbers (e.g. noise levels 0, 1e-5, ... drawn at positions 0, 1, ...).
    Writes a PNG and returns its path."""
    h, w = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 62, 160, 30, 40
    pw, ph = w - left - right, h - top - bottom
    head = f"{title}: {ylabel}" if title and ylabel else (title or ylabel)
    cv2.putText(img, head, (left, 20), _FONT, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(img, (left, top), (left + pw, top + ph), (0, 0, 0), 1)
    stats = {}
    for label, (x, values) in curves.items():
        x = np.asarray(x, dtype=float)
        v = np.asarray(values, dtype=float).reshape(-1, len(x))
        with np.errstate(all="ignore"):
            n = np.isfinite(v).sum(0)
            mean = np.where(n > 0, np.nansum(v, 0) / np.maximum(n, 1), np.nan)
            std = np.where(n > 0, np.sqrt(np.nansum((v - mean) ** 2, 0) / np.maximum(n, 1)), np.nan)
        ok = np.isfinite(x) & np.isfinite(mean)
        stats[label] = (x[ok], mean[ok], std[ok], v.shape[0])
    xs = np.concatenate([s[0] for s in stats.values()]) if stats else np.array([])
    lo = np.concatenate([s[1] - s[2] for s in stats.values()]) if stats else np.array([])
    hi = np.concatenate([s[1] + s[2] for s in stats.values()]) if stats else np.array([])
    if xs.size == 0:
        cv2.putText(img, "no data", (left + pw // 3, top + ph // 2), _FONT, 0.5, (128, 128, 128), 1, cv2.LINE_AA)
    else:
        x0, x1 = float(xs.min()), float(xs.max())
        y0, y1 = float(lo.min()), float(hi.max())
        if x1 == x0:
            x0, x1 = x0 - 1, x1 + 1
        if y1 == y0:
            y0, y1 = y0 - 0.5, y1 + 0.5
        pad = (y1 - y0) * 0.05
        y0, y1 = y0 - pad, y1 + pad

        def px(xv, yv):
            return np.stack([np.round(left + (np.asarray(xv) - x0) / (x1 - x0) * pw),
                             np.round(top + ph - (np.asarray(yv) - y0) / (y1 - y0) * ph)], -1).astype(np.int32)

        for t in nice_ticks(y0, y1, 6):
            ty = int(px(x0, t)[1])
            cv2.line(img, (left, ty), (left + pw, ty), (230, 230, 230), 1)
            cv2.putText(img, _fmt(t), (4, ty + 4), _FONT, 0.35, (60, 60, 60), 1, cv2.LINE_AA)
        ticks = [(t, _fmt(t)) for t in nice_ticks(x0, x1, 6)] if xticks is None else list(xticks)
        for t, text in ticks:
            tx = int(px(t, y0)[0])
            cv2.line(img, (tx, top + ph), (tx, top + ph + 4), (0, 0, 0), 1)
            cv2.putText(img, text, (tx - 4 * len(text), top + ph + 16), _FONT, 0.35, (60, 60, 60), 1, cv2.LINE_AA)
        for i, (label, (x, mean, std, n_runs)) in enumerate(stats.items()):
            color = _COLORS[i % len(_COLORS)]
            if len(x):
                band = np.concatenate([px(x, mean + std), px(x[::-1], (mean - std)[::-1])])
                overlay = img.copy()
                cv2.fillPoly(overlay, [band.reshape(-1, 1, 2)], color, cv2.LINE_AA)
                cv2.addWeighted(overlay, 0.2, img, 0.8, 0, dst=img)
                pts = px(x, mean).reshape(-1, 1, 2)
                cv2.polylines(img, [pts], False, color, 2, cv2.LINE_AA)
                for p in pts[:, 0]:
                    cv2.circle(img, (int(p[0]), int(p[1])), 3, color, -1, cv2.LINE_AA)
            ly = top + 14 + 18 * i
            cv2.line(img, (left + pw + 10, ly - 4), (left + pw + 30, ly - 4), color, 2, cv2.LINE_AA)
            cv2.putText(img, f"{label} (n={n_runs})", (left + pw + 34, ly), _FONT, 0.38, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, xlabel, (left + pw // 2 - 4 * len(xlabel), h - 6), _FONT, 0.4, (60, 60, 60), 1, cv2.LINE_AA)
    ok, png = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV without PNG support
        raise RuntimeError("OpenCV could not encode a PNG")
    return atomic_write_bytes(path, png.tobytes())


def main(argv: Sequence[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(prog="python -m trakdis.utils.plot", description=__doc__.split("\n\n")[0])
    parser.add_argument("csv", help="a run's log.csv")
    parser.add_argument("-o", "--out", default=None, help="output PNG (default: curves.png beside the CSV)")
    parser.add_argument("--columns", nargs="*", default=None, help="columns to plot (default: all numeric)")
    parser.add_argument("--ncols", type=int, default=3, help="panels per row")
    args = parser.parse_args(argv)
    path = plot_csv(args.csv, args.out, columns=args.columns, ncols=args.ncols)
    print(f"wrote {path}")
    return path


if __name__ == "__main__":
    main()
