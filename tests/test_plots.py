"""``togglecf.report.plots``: figures render headless (Agg), files are valid PNG/SVG/GIF, and what is
drawn is the data (line data in the Axes, the curves' colours in the PNG's pixels)."""
import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.image as mpimg  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.colors import to_rgb  # noqa: E402

from togglecf.cli.plot import add_plot_parser  # noqa: E402
from togglecf.report import plots  # noqa: E402
from togglecf.core import quaternion as quat  # noqa: E402
from togglecf import simulate as sim  # noqa: E402

FS = 100.0
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def trial():
    return sim.imu_from_orientation(sim.gimbal_trajectory(FS, 12.0), FS)


@pytest.fixture(scope="module")
def q_offset(trial):
    """The truth turned by 40° about the vertical: a yaw curve clearly apart from the truth's."""
    return quat.multiply(quat.from_rotvec([0.0, 0.0, np.radians(40.0)]), trial.opt_quat)


def _near(img, color, tol=0.12):
    return np.all(np.abs(img[..., :3] - np.array(to_rgb(color))) < tol, axis=-1)


def test_plot_euler_lines_and_pixels(tmp_path, trial, q_offset):
    out = tmp_path / "euler.png"
    fig = plots.plot_euler(trial, {"offset": q_offset}, out=out)
    assert out.read_bytes()[:8] == PNG_MAGIC
    t = np.arange(trial.n_samples) / FS
    truth = np.degrees(quat.to_euler_zyx(trial.opt_quat))
    est = np.degrees(quat.to_euler_zyx(q_offset))
    axes = fig.axes[:3]
    assert [ax.get_ylabel() for ax in axes] == ["roll [°]", "pitch [°]", "yaw [°]"]
    for i, ax in enumerate(axes):
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        assert set(lines) == {"truth", "offset"}
        np.testing.assert_allclose(lines["truth"].get_xdata(), t)
        np.testing.assert_allclose(lines["truth"].get_ydata(), truth[:, i])
        np.testing.assert_allclose(lines["offset"].get_ydata(), est[:, i])
    # yaw differs by 40° (mod 360); roll/pitch equal
    d = (axes[2].get_lines()[1].get_ydata() - axes[2].get_lines()[0].get_ydata()) % 360
    np.testing.assert_allclose(d, 40.0, atol=1e-9)
    # the PNG shows both curves: in the yaw panel (bottom third) black and red pixels, apart
    img = mpimg.imread(out)
    h = img.shape[0]
    yaw_panel = img[int(0.68 * h):int(0.92 * h), int(0.1 * img.shape[1]):int(0.95 * img.shape[1])]
    black = _near(yaw_panel, plots.TRUTH_COLOR)
    red = _near(yaw_panel, plots.EST_COLORS[0])
    assert black.sum() > 500 and red.sum() > 500
    # red pixels mostly above the black ones (yaw + 40°, the panel's y axis points up)
    rows = np.arange(yaw_panel.shape[0])[:, None]
    assert (rows * red).sum() / red.sum() < (rows * black).sum() / black.sum()
    plt.close(fig)


def test_plot_euler_svg_and_crop(tmp_path, trial, q_offset):
    out = tmp_path / "euler.svg"
    fig = plots.plot_euler(trial, {"a": q_offset, "b": trial.opt_quat}, out=out, t_range=(2.0, 4.0))
    assert b"<svg" in out.read_bytes()[:500]
    x = fig.axes[0].get_lines()[0].get_xdata()
    assert x.min() >= 2.0 and x.max() <= 4.0 and len(x) == 201
    with pytest.raises(ValueError, match="expected shape"):
        plots.plot_euler(trial, {"bad": q_offset[:10]})
    plt.close("all")


def test_plot_3d_frames(tmp_path, trial, q_offset):
    out = tmp_path / "frames.png"
    times = [0.0, 3.0, 6.0, 9.0, 11.0]
    fig = plots.plot_3d_frames(trial, q_offset, times, out=out, ncols=3)
    assert out.read_bytes()[:8] == PNG_MAGIC
    axes3d = [ax for ax in fig.axes if ax.name == "3d"]
    assert len(axes3d) == len(times)
    # the estimate's sensor x axis (first line) points along q_est ⊗ e_x, drawn at the left box
    ax = axes3d[1]
    i = int(round(3.0 * FS))
    xs, ys, zs = ax.get_lines()[0].get_data_3d()
    d = np.array([xs[1] - xs[0], ys[1] - ys[0], zs[1] - zs[0]])
    np.testing.assert_allclose(d / np.linalg.norm(d), quat.rotate(q_offset[i], [1.0, 0, 0]), atol=1e-12)
    assert xs[0] < 0  # estimate left of the truth
    xs_t, ys_t, zs_t = ax.get_lines()[3].get_data_3d()  # truth's x axis
    d_t = np.array([xs_t[1] - xs_t[0], ys_t[1] - ys_t[0], zs_t[1] - zs_t[0]])
    np.testing.assert_allclose(d_t / np.linalg.norm(d_t), quat.rotate(trial.opt_quat[i], [1.0, 0, 0]), atol=1e-12)
    plt.close(fig)


def test_animate_3d_gif(tmp_path, trial, q_offset, monkeypatch):
    from PIL import Image

    monkeypatch.setattr(plots, "ffmpeg_available", lambda: False)
    path = tmp_path / "anim.mp4"
    assert plots.animation_path(path).suffix == ".gif"  # no ffmpeg -> GIF
    fig = plots.animate_3d(trial, q_offset, path, fps=5, duration=2.0)
    gif = tmp_path / "anim.gif"
    assert gif.read_bytes()[:6] == b"GIF89a"
    with Image.open(gif) as im:
        assert im.n_frames == 10
    plt.close(fig)


@pytest.mark.skipif(not plots.ffmpeg_available(), reason="ffmpeg not installed")
def test_animate_3d_mp4(tmp_path, trial, q_offset):
    path = tmp_path / "anim.mp4"
    plots.animate_3d(trial, q_offset, path, fps=5, duration=1.0)
    assert path.stat().st_size > 1000 and path.read_bytes()[4:8] == b"ftyp"


def _cli(argv):
    p = argparse.ArgumentParser(prog="togglecf")
    add_plot_parser(p.add_subparsers(dest="command"))
    args = p.parse_args(argv)
    return args.func(args)


@pytest.mark.broad
def test_cli_plot_real_trial(tmp_path, broad_index):
    data = str(broad_index.root)
    out = tmp_path / "euler.png"
    _cli(["plot", "euler", "--trial", "05", "--filters", "madgwick,cf", "--data", data, "--end", "30",
          "--out", str(out)])
    assert out.read_bytes()[:8] == PNG_MAGIC
    frames = tmp_path / "frames.png"
    _cli(["plot", "3d", "--trial", "05", "--filter", "madgwick", "--data", data, "--frames", "4",
          "--start", "10", "--end", "40", "--out", str(frames)])
    assert frames.read_bytes()[:8] == PNG_MAGIC
    gif = tmp_path / "anim.gif"
    _cli(["plot", "3d", "--trial", "05", "--filter", "madgwick", "--data", data, "--fps", "4",
          "--duration", "2", "--out", str(gif)])
    assert gif.read_bytes()[:6] == b"GIF89a"
    plt.close("all")
