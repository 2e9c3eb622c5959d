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

from togglecf import simulate as sim  # noqa: E402
from togglecf.cli.plot import add_plot_parser  # noqa: E402
from togglecf.core import quaternion as quat  # noqa: E402
from togglecf.report import plots, study_report  # noqa: E402
from togglecf.report.style import FILTER_STYLE, style  # noqa: E402

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
    fig = plots.plot_euler(trial, {"madgwick": q_offset}, out=out)
    assert out.read_bytes()[:8] == PNG_MAGIC
    t = np.arange(trial.n_samples) / FS
    truth = np.degrees(quat.to_euler_zyx(trial.opt_quat))
    est = np.degrees(quat.to_euler_zyx(q_offset))
    axes = fig.axes[:3]
    assert [ax.get_ylabel() for ax in axes] == ["roll [°]", "pitch [°]", "yaw [°]"]
    for i, ax in enumerate(axes):
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        assert set(lines) == {"truth", "madgwick"}
        np.testing.assert_allclose(lines["truth"].get_xdata(), t)
        np.testing.assert_allclose(lines["truth"].get_ydata(), truth[:, i])
        np.testing.assert_allclose(lines["madgwick"].get_ydata(), est[:, i])
    # yaw differs by 40° (mod 360); roll/pitch equal
    d = (axes[2].get_lines()[1].get_ydata() - axes[2].get_lines()[0].get_ydata()) % 360
    np.testing.assert_allclose(d, 40.0, atol=1e-9)
    # the PNG shows both curves: in the yaw panel (bottom third, left column) black and red pixels, apart
    img = mpimg.imread(out)
    h, w = img.shape[:2]
    yaw_panel = img[int(0.68 * h):int(0.92 * h), int(0.08 * w):int(0.55 * w)]
    black = _near(yaw_panel, style("truth")["color"])
    red = _near(yaw_panel, style("madgwick")["color"])
    assert black.sum() > 300 and red.sum() > 300
    # red pixels mostly above the black ones (yaw + 40°, the panel's y axis points up)
    rows = np.arange(yaw_panel.shape[0])[:, None]
    assert (rows * red).sum() / red.sum() < (rows * black).sum() / black.sum()
    plt.close(fig)


def test_plot_euler_error_panel_shows_small_differences(trial):
    """Estimate − truth per angle, wrapped: a 3° roll offset and a 40° yaw offset are 3 and 40 in the
    error panels (Axes 4-6), whose scale shows a few degrees (not ±180°)."""
    small = quat.multiply(trial.opt_quat, quat.from_rotvec([np.radians(3.0), 0.0, 0.0]))  # body-frame roll
    big = quat.multiply(quat.from_rotvec([0.0, 0.0, np.radians(-170.0)]), trial.opt_quat)  # yaw −170°: wraps
    fig = plots.plot_euler(trial, {"cf": small, "madgwick": big})
    err_axes = fig.axes[3:6]
    assert [ax.get_ylabel() for ax in err_axes] == ["roll error [°]", "pitch error [°]", "yaw error [°]"]
    truth = np.degrees(quat.to_euler_zyx(trial.opt_quat))
    for i, ax in enumerate(err_axes):
        lines = {ln.get_label(): ln for ln in ax.get_lines() if not ln.get_label().startswith("_")}
        assert set(lines) == {"cf", "madgwick"}
        for name, q in (("cf", small), ("madgwick", big)):
            y = lines[name].get_ydata()
            ok = np.isfinite(y)
            want = plots.wrap_deg(np.degrees(quat.to_euler_zyx(q))[:, i] - truth[:, i])
            assert ok.mean() > 0.95 and np.all((y[ok] >= -180) & (y[ok] < 180))
            np.testing.assert_allclose(y[ok], want[ok], atol=1e-9)
    yaw_big = err_axes[2].get_lines()[-1].get_ydata()
    np.testing.assert_allclose(np.nanmedian(yaw_big), -170.0, atol=1e-6)
    # roll: the 3° offset fills a visible part of the panel (the scale is not ±180°)
    roll_cf = [ln for ln in err_axes[0].get_lines() if ln.get_label() == "cf"][0].get_ydata()
    assert np.nanmax(np.abs(roll_cf)) > 1.0
    plt.close(fig)
    fig = plots.plot_euler(trial, {"cf": small})
    lo, hi = fig.axes[3].get_ylim()
    assert 3.0 < hi < 10.0 and lo == -hi
    assert len(plots.plot_euler(trial, {"cf": small}, errors=False).axes) == 3
    plt.close("all")


def test_plot_error_broad_errors_over_time(tmp_path, trial):
    """Total/heading/inclination [deg] per sample, per filter: a 5° heading offset is 5° total and
    heading, 0 inclination; a 3° tilt is 3° total and inclination, 0 heading."""
    heading5 = quat.multiply(quat.from_rotvec([0.0, 0.0, np.radians(5.0)]), trial.opt_quat)
    tilt3 = quat.multiply(quat.from_rotvec([np.radians(3.0), 0.0, 0.0]), trial.opt_quat)
    out = tmp_path / "error.png"
    fig = plots.plot_error(trial, {"madgwick": heading5, "vqf_core": tilt3}, out=out, t_range=(1.0, 9.0))
    assert out.read_bytes()[:8] == PNG_MAGIC
    axes = fig.axes[:3]
    assert [ax.get_ylabel() for ax in axes] == ["total error [°]", "heading error [°]", "inclination error [°]"]
    want = {"madgwick": (5.0, 5.0, 0.0), "vqf_core": (3.0, 0.0, 3.0)}
    for i, ax in enumerate(axes):
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        assert set(lines) == {"madgwick", "vqf_core"}
        for name, vals in want.items():
            x, y = lines[name].get_xdata(), lines[name].get_ydata()
            assert x.min() >= 1.0 and x.max() <= 9.0
            np.testing.assert_allclose(y, vals[i], atol=1e-4)  # arccos near 1: ~1e-6° rounding
        assert "madgwick 5.00°" in ax.get_title(loc="left") or i == 2
    assert "vqf_core 3.00°" in axes[0].get_title(loc="left")
    with pytest.raises(ValueError, match="expected shape"):
        plots.plot_error(trial, {"bad": heading5[:5]})
    plt.close("all")


def _colors_by_label(fig) -> dict:
    """label -> RGBA of every labelled line, bar and 3-D box (first occurrence per Axes kept as a list)."""
    from matplotlib.colors import to_rgba
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    found = {}
    for ax in fig.axes:
        for ln in ax.get_lines():
            found.setdefault(ln.get_label(), set()).add(to_rgba(ln.get_color()))
        for c in ax.containers:  # bars
            for patch in c.patches:
                found.setdefault(c.get_label(), set()).add(to_rgba(patch.get_facecolor(), 1.0)[:3] + (1.0,))
        for coll in ax.collections:
            if isinstance(coll, Poly3DCollection):
                found.setdefault(coll.get_label() or "_box", set()).add(tuple(coll.get_facecolor()[0][:3]) + (1.0,))
    return found


def test_same_filter_same_colour_in_every_figure(tmp_path, trial):
    """One palette: every figure function draws a filter in ``style(name)`` (colour and line style)."""
    import pandas as pd
    from matplotlib.colors import to_rgba

    names = ["toggling", "madgwick", "cf", "vqf"]
    q = {n: quat.multiply(quat.from_rotvec([0.0, 0.0, np.radians(2.0 + k)]), trial.opt_quat)
         for k, n in enumerate(names)}
    t = trial
    figs = {
        "plot_euler": plots.plot_euler(t, q),
        "plot_error": plots.plot_error(t, q),
        "error_figure": study_report.error_figure("x", t, {n: np.full(t.n_samples, 1.0 + k)
                                                          for k, n in enumerate(names)}),
        "groups_figure": study_report.groups_figure(pd.DataFrame({n: [1.0 + k, 2.0] for k, n in enumerate(
            names + ["mahony", "aqua", "ekf"])}, index=["g1", "g2"])),
        "timeline_figure": study_report.timeline_figure("x", t, {"alpha_acc": np.full(t.n_samples, 0.01),
                                                                "p": np.tile([0.7, 0.1, 0.1, 0.1], (t.n_samples, 1)),
                                                                "states": ("rest", "a", "b", "c")},
                                                        np.zeros(t.n_samples, int)),
    }
    seen = {}
    for fname, fig in figs.items():
        for label, cols in _colors_by_label(fig).items():
            base = label.split(" ")[0] if label.startswith("predicted") is False else "toggling"
            if label == "ground truth":
                base = "truth"
            if base in FILTER_STYLE:
                assert cols == {to_rgba(style(base)["color"])}, (fname, label, cols)
                seen.setdefault(base, set()).add(fname)
    for n in names:
        assert {"plot_euler", "plot_error", "error_figure", "groups_figure"} <= seen[n], (n, seen[n])
    assert "timeline_figure" in seen["toggling"] and "timeline_figure" in seen["truth"]
    # the groups figure keeps to its few filters (11 bars per group hid the one the eye looks for)
    shown = {lb for lb in _colors_by_label(figs["groups_figure"]) if lb in FILTER_STYLE}
    assert shown == set(names) and not shown & {"mahony", "aqua", "ekf"}
    # line styles too: the same in the Euler plot and the error plot
    for fname in ("plot_euler", "plot_error", "error_figure"):
        for ax in figs[fname].axes:
            for ln in ax.get_lines():
                if ln.get_label() in FILTER_STYLE:
                    assert ln.get_linestyle() == {"-": "-", "--": "--", ":": ":", "-.": "-."}[
                        style(ln.get_label())["linestyle"]], (fname, ln.get_label())
    # the 3-D boxes: the estimate's box in its filter's colour, the truth's in the truth's
    for n in ("madgwick", "toggling"):
        fig = plots.plot_3d_frames(t, q[n], [1.0], name=n)
        boxes = [c for c in fig.axes[0].collections if c.__class__.__name__ == "Poly3DCollection"]
        assert tuple(boxes[0].get_facecolor()[0][:3]) == to_rgba(style(n)["color"])[:3]
        assert tuple(boxes[1].get_facecolor()[0][:3]) == to_rgba(style("truth")["color"])[:3]
    plt.close("all")


def test_palette_keeps_every_filter_apart():
    """Any two named filters differ by at least 0.25 in RGB (0-1 per channel, Euclidean): the learned VQF
    and the toggling CF were two blues 0.17 apart; the learned VQF and its pretrained model share one."""
    from matplotlib.colors import to_rgb

    rgb = {n: np.array(to_rgb(s["color"])) for n, s in FILTER_STYLE.items()}
    assert rgb["learned_vqf"].tolist() == rgb["vqf_toggling"].tolist()
    names = sorted(n for n in rgb if n != "learned_vqf")
    close = [(a, b, round(float(np.linalg.norm(rgb[a] - rgb[b])), 3)) for i, a in enumerate(names)
             for b in names[i + 1:] if np.linalg.norm(rgb[a] - rgb[b]) < 0.25]
    assert not close, close


def test_groups_figure_labels_every_bar_and_never_clips():
    import pandas as pd

    g = pd.DataFrame({"vqf_toggling": [2.0, 41.5], "vqf": [2.4, 40.0], "toggling": [3.0, 55.2]}, index=["a", "b"])
    fig = study_report.groups_figure(g)
    ax = fig.axes[0]
    assert ax.get_ylim()[1] > 55.2  # the largest bar is inside the axes
    texts = sorted(t.get_text() for t in ax.texts)
    assert texts == sorted(["2.0", "41.5", "2.4", "40.0", "3.0", "55.2"])


def test_style_fallbacks():
    assert style("madgwick") == FILTER_STYLE["madgwick"] and style("madgwick") is not FILTER_STYLE["madgwick"]
    v = style("toggling_6d")  # a variant: the base colour, dash-dotted
    assert v["color"] == FILTER_STYLE["toggling"]["color"] and v["linestyle"] == "-."
    assert style("vqf_6d")["color"] == FILTER_STYLE["vqf"]["color"]
    u = style("my_new_filter")  # unknown: a fixed colour not used by any filter, dotted
    assert u == style("my_new_filter") and u["linestyle"] == ":"
    assert u["color"] not in {s["color"] for s in FILTER_STYLE.values()}
    colors = [s["color"] for n, s in FILTER_STYLE.items() if n != "learned_vqf"]  # the pretrained vqf_toggling
    assert len(set(colors)) == len(colors)  # no two filters share a colour


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


def test_cli_plot_error_and_euler_on_mini_data(tmp_path, mini_index, capsys):
    data = str(mini_index.root)
    out = tmp_path / "error.png"
    _cli(["plot", "error", "--trial", "24", "--filters", "madgwick,vqf_core", "--data", data, "--out", str(out)])
    assert out.read_bytes()[:8] == PNG_MAGIC
    out = tmp_path / "euler.svg"
    _cli(["plot", "euler", "--trial", "24", "--filters", "cf", "--data", data, "--start", "4", "--out", str(out)])
    assert b"<svg" in out.read_bytes()[:500]
    with pytest.raises(ValueError, match="needs --models"):
        _cli(["plot", "error", "--trial", "24", "--filters", "madgwick,toggling", "--data", data, "--out", str(out)])
    with pytest.raises(ValueError, match="unknown filter 'nope'"):
        _cli(["plot", "error", "--trial", "24", "--filters", "nope", "--data", data, "--out", str(out)])
    plt.close("all")


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


def test_cli_plot_takes_several_data_directories(tmp_path, mini_index, mini_names, monkeypatch):
    """``--data A --data B``: the trials of both directories reach the plot (names ``<dir>/<trial>``),
    and a trial name found in both is refused with the candidates named."""
    import shutil

    import togglecf.cli.plot as cli_plot

    for d in ("alpha", "beta"):
        shutil.copytree(mini_index.root, tmp_path / d)
    plotted = []
    monkeypatch.setattr(cli_plot, "plot_error", lambda trial, est, **kw: plotted.append((trial.name, sorted(est))))
    data = ["--data", str(tmp_path / "alpha"), "--data", str(tmp_path / "beta")]
    for which in ("alpha", "beta"):
        _cli(["plot", "error", "--trial", f"{which}/{mini_names[2]}", "--filters", "madgwick", *data,
              "--out", str(tmp_path / "e.png")])
    assert plotted == [(f"alpha/{mini_names[2]}", ["madgwick"]), (f"beta/{mini_names[2]}", ["madgwick"])]
    with pytest.raises(ValueError, match=r"matches 2 trials \(alpha/.*beta/.*\); give one as <dir name>/<trial>"):
        _cli(["plot", "error", "--trial", "24", "--filters", "madgwick", *data, "--out", str(tmp_path / "e.png")])
