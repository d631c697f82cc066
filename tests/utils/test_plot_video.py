import subprocess
import sys

import cv2
import numpy as np
import pandas as pd
import pytest

from trakdis.utils.plot import nice_ticks, plot_csv
from trakdis.utils.video import VideoWriter, side_by_side, write_video


def test_nice_ticks():
    assert nice_ticks(0, 1, 5) == [0.0, 0.25, 0.5, 0.75, 1.0]
    t = nice_ticks(-3.7, 12.2)
    assert t[0] >= -3.7 and t[-1] <= 12.2 and len(t) >= 3


def test_plot_csv_cli(tmp_path):
    steps = np.arange(50)
    frame = pd.DataFrame({"step": steps, "train/loss_nll": np.exp(-steps / 10),
                          "eval/normalized_performance": np.where(steps % 10 == 0, steps / 50, np.nan)})
    csv = tmp_path / "log.csv"
    frame.to_csv(csv, index=False)
    out = subprocess.run([sys.executable, "-m", "trakdis.utils.plot", str(csv)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    img = cv2.imread(str(tmp_path / "curves.png"))
    assert img is not None and img.shape[0] > 200 and img.shape[1] >= 2 * 360
    # The curve colour is actually drawn (not a blank canvas).
    assert (img != 255).any(axis=2).mean() > 0.02
    with pytest.raises(KeyError, match="nope"):
        plot_csv(csv, tmp_path / "x.png", columns=["nope"])


def test_side_by_side_and_video(tmp_path):
    big = np.zeros((64, 96, 3), np.uint8)
    small = np.zeros((32, 32, 3), np.uint8)
    small[:16] = 255
    frame = side_by_side(big, small, labels=None)
    assert frame.shape == (64, 96 + 4 + 64, 3)
    assert (frame[:32, 100:] == 255).all() and (frame[32:, 100:] == 0).all()  # nearest upscaling
    path = write_video(tmp_path / "v.mp4", [frame] * 5, fps=5)
    assert path.exists() and path.stat().st_size > 0
    cap = cv2.VideoCapture(str(path))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 5


def test_video_fallbacks(tmp_path):
    w = VideoWriter(tmp_path / "v.mp4", codecs=[(".mp4", "XXXX"), (".avi", "MJPG")])
    for _ in range(3):
        w.write(np.zeros((10, 10, 3), np.uint8))
    assert w.close().suffix == ".avi" and w.kind == "MJPG"
    w = VideoWriter(tmp_path / "p.mp4", codecs=[])
    for _ in range(3):
        w.write(np.zeros((10, 10, 3), np.float32))
    assert w.kind == "png" and len(list(w.close().glob("*.png"))) == 3
    with pytest.raises(ValueError, match="shape"):
        side_by_side(np.zeros((4, 4)), np.zeros((2, 2, 5)))
