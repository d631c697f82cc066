"""plot_mean_std: curves as mean lines with a std band over runs (benchmarks/table1.py's figures)."""
import cv2
import numpy as np

from trakdis.utils.plot import nice_ticks, plot_mean_std


def test_mean_std_bands_png(tmp_path):
    x = [0, 50, 100]
    curves = {"TraKDis": (x, np.array([[0.1, 0.3, 0.5], [0.2, 0.4, 0.45]])),
              "No-Aug": (x, np.array([[0.0, 0.1, 0.2], [0.1, np.nan, 0.3]])),  # a missing point is left out
              "one run": (x, np.array([0.3, 0.3, 0.3]))}
    path = plot_mean_std(curves, tmp_path / "c.png", title="ClothFold", ylabel="score", xlabel="updates")
    img = cv2.imread(str(path))
    assert img is not None and img.shape == (420, 640, 3)
    blue = np.array([180, 119, 31])  # the first curve's colour (BGR), its mean line
    assert (np.abs(img.astype(int) - blue).sum(-1) < 10).sum() > 50
    empty = plot_mean_std({}, tmp_path / "e.png", title="nothing")
    assert cv2.imread(str(empty)) is not None


def test_explicit_xticks_one_mark_each(tmp_path):
    """Noise levels 0, 1e-5, 1e-3 at positions 0, 1, 2: one tick mark per given label, none else."""
    curves = {"TraKDis": ([0, 1, 2], np.array([0.5, 0.45, 0.2]))}

    def marks(**kw):
        img = cv2.imread(str(plot_mean_std(curves, tmp_path / "t.png", **kw)))
        row = img[382, :, :].astype(int).sum(-1) < 100  # just under the plot's bottom edge (y = 380)
        return int((row[1:] & ~row[:-1]).sum())  # runs of dark pixels: one per tick mark

    assert marks(xticks=[(0, "0"), (1, "1e-5"), (2, "1e-3")]) == 3
    assert marks(xticks=[(0, "0"), (2, "1e-3")]) == 2
    assert marks() == len(nice_ticks(0, 2, 6))  # without xticks: evenly spaced numbers
