"""Orientation plots for one trial: Euler angles and their errors over time, BROAD's errors over
time, 3-D key frames, 3-D animation.

Every function returns the matplotlib ``Figure`` and, given ``out``/``path``, saves it (format
from the suffix: ``.png``, ``.svg``, ...; animations ``.mp4`` with ffmpeg, else ``.gif``).
The module leaves the backend alone (inline in a notebook); the ``togglecf plot`` commands switch
to Agg, which renders without a display (matplotlib also falls back to it on a headless
machine). Quaternions are ``[w, x, y, z]``, sensor -> ENU (``togglecf.core.quaternion``); Euler angles are ZYX roll/pitch/yaw in degrees.
Every filter is drawn in its colour and line style from ``report.style`` (the same in every figure).

Command line (``togglecf.cli.plot``)::

    togglecf plot euler --trial 05 [--filters madgwick,cf] [--models DIR] [--data DIR] --out euler.png
    togglecf plot error --trial 05 --filters madgwick,vqf_core[,toggling --models DIR] --out error.png
    togglecf plot 3d --trial 05 --filter madgwick [--models DIR] --out anim.gif|anim.mp4|frames.png
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from togglecf.core import quaternion as quat
from togglecf.core.extras import deferred, require
from togglecf.metrics.broad import error_angles_rad, error_quaternion
from togglecf.report.style import style

#: matplotlib (the ``plot`` extra), imported on first use
plt = deferred("matplotlib.pyplot", extra="plot", what="togglecf.report.plots")
art3d = deferred("mpl_toolkits.mplot3d.art3d", extra="plot", what="togglecf.report.plots")

AXIS_COLORS = ("#e41a1c", "#4daf4a", "#377eb8")  # sensor x, y, z
EULER_NAMES = ("roll", "pitch", "yaw")
#: BROAD's per-sample errors drawn by ``plot_error`` (``metrics.error_angles_rad``)
ERROR_NAMES = ("total", "heading", "inclination")

# IMU box half-extents (a flat board, x longest) and its 8 corners / 6 faces
_HALF = np.array([0.5, 0.3, 0.1])
_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * _HALF
_FACES = ((0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5))
_OFFSET = 0.9  # estimate drawn at -x, truth at +x (east)


def _save(fig, out):
    if out is not None:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=fig.dpi)
    return fig


def euler_deg(q) -> np.ndarray:
    """Roll, pitch, yaw [deg] ``(N, 3)``; NaN rows (missing truth) stay NaN."""
    q = np.asarray(q, float)
    out = np.full(q.shape[:-1] + (3,), np.nan)
    ok = np.all(np.isfinite(q), axis=-1)
    out[ok] = np.degrees(quat.to_euler_zyx(q[ok]))
    return out


def _break_wraps(y, limit=180.0):
    """NaN where an angle jumps by more than ``limit`` (±180° wrap): no vertical lines."""
    y = np.array(y, float)
    jump = np.zeros(y.shape, bool)
    jump[1:] = np.abs(np.diff(y)) > limit
    y[jump] = np.nan
    return y


def wrap_deg(d):
    """Angles [deg] wrapped to [-180, 180)."""
    return (np.asarray(d, float) + 180.0) % 360.0 - 180.0


def _check_estimates(trial, estimates):
    n = trial.n_samples
    for name, q in estimates.items():
        if np.shape(q) != (n, 4):
            raise ValueError(f"estimate {name!r}: expected shape ({n}, 4), got {np.shape(q)}")


def _time_selection(trial, t_range):
    t = np.arange(trial.n_samples) / trial.fs
    sel = np.ones(trial.n_samples, bool) if t_range is None else (t >= t_range[0]) & (t <= t_range[1])
    return t, sel


def _robust_limit(curves, floor=1.0, q=99.0):
    """Symmetric y limit that shows the bulk of ``curves`` (the ``q``-th percentile of |y|, +20 %):
    rare spikes (gimbal lock near pitch ±90°) are cut off instead of flattening the rest."""
    vals = np.concatenate([np.abs(c[np.isfinite(c)]) for c in curves] + [np.zeros(1)])
    return max(floor, 1.2 * float(np.percentile(vals, q)))


def plot_euler(trial, estimates: dict, out=None, t_range=None, title=None, figsize=(13, 7), dpi=100,
               errors: bool = True):
    """Roll/pitch/yaw [deg] of each estimate (name -> ``(N, 4)``) against the ground truth
    ``trial.opt_quat`` over time [s]; ``t_range=(t0, t1)`` crops. One Axes per angle (the first
    three Axes of the figure); each line's label is the estimate's name (``"truth"`` for the
    reference), its colour and style ``report.style.style(name)``. Roll and yaw wrap at ±180°: the
    sample after a wrap is left out of the line (NaN), no vertical jumps.

    ``errors`` (default): a second column (Axes 4-6) with each estimate's error per angle,
    estimate − truth wrapped to ±180°, on a scale that shows differences of a few degrees (the
    99th percentile of |error| over the shown estimates; rarer spikes, e.g. near pitch ±90° where
    roll and yaw are ill-defined, run off the panel)."""
    _check_estimates(trial, estimates)
    t, sel = _time_selection(trial, t_range)
    fig = plt.figure(figsize=figsize if errors else (11, 7), dpi=dpi)
    gs = fig.add_gridspec(3, 2 if errors else 1, width_ratios=(3, 2) if errors else None)
    axes = [fig.add_subplot(gs[0, 0])]
    axes += [fig.add_subplot(gs[i, 0], sharex=axes[0]) for i in (1, 2)]
    truth = euler_deg(trial.opt_quat)
    est = {name: euler_deg(q) for name, q in estimates.items()}
    for i, ax in enumerate(axes):
        ax.plot(t[sel], _break_wraps(truth[sel, i]), label="truth", **style("truth"))
        for name, e in est.items():
            ax.plot(t[sel], _break_wraps(e[sel, i]), label=name, **style(name))
        ax.set_ylabel(f"{EULER_NAMES[i]} [°]")
        ax.set_ylim(-185 if i != 1 else -95, 185 if i != 1 else 95)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", ncol=len(estimates) + 1, fontsize="small")
    axes[-1].set_xlabel("time [s]")
    if errors:
        diffs = {name: wrap_deg(e[sel] - truth[sel]) for name, e in est.items()}
        err_axes = [fig.add_subplot(gs[i, 1], sharex=axes[0]) for i in range(3)]
        for i, ax in enumerate(err_axes):
            ax.axhline(0.0, color=style("truth")["color"], lw=0.6)
            for name, d in diffs.items():
                ax.plot(t[sel], _break_wraps(d[:, i]), label=name, **style(name))
            lim = _robust_limit([d[:, i] for d in diffs.values()])
            ax.set_ylim(-lim, lim)
            ax.set_ylabel(f"{EULER_NAMES[i]} error [°]")
            ax.grid(alpha=0.3)
        err_axes[0].set_title("estimate − truth (wrapped to ±180°)", fontsize="medium")
        err_axes[-1].set_xlabel("time [s]")
    fig.suptitle(title or f"{trial.name}: Euler angles (ZYX), estimate vs truth")
    fig.tight_layout()
    return _save(fig, out)


def error_series_deg(q_est, q_ref) -> dict:
    """BROAD's per-sample total, heading and inclination errors [deg] of ``q_est`` against
    ``q_ref`` (``metrics.error_angles_rad`` of the earth-frame error ``q_est ⊗ q_ref*``); NaN where
    either is NaN."""
    q_est, q_ref = np.asarray(q_est, float), np.asarray(q_ref, float)
    ok = np.all(np.isfinite(q_est), axis=1) & np.all(np.isfinite(q_ref), axis=1)
    out = {k: np.full(q_est.shape[0], np.nan) for k in ERROR_NAMES}
    if ok.any():
        e = error_angles_rad(error_quaternion(q_est[ok], q_ref[ok]))
        for k in ERROR_NAMES:
            out[k][ok] = np.degrees(e[k])
    return out


def plot_error(trial, estimates: dict, out=None, t_range=None, title=None, figsize=(11, 7), dpi=100):
    """BROAD's total, heading and inclination error [deg] over time [s] of each estimate (name ->
    ``(N, 4)``) against ``trial.opt_quat``: one Axes per error (in ``ERROR_NAMES`` order), one line
    per estimate labelled with its name in its ``report.style`` colour. Samples outside BROAD's
    ``movement`` (not scored) are shaded; each Axes' title gives every estimate's RMSE over the
    movement samples shown (``metrics.rmse_deg``). ``t_range=(t0, t1)`` crops."""
    _check_estimates(trial, estimates)
    t, sel = _time_selection(trial, t_range)
    series = {name: error_series_deg(q, trial.opt_quat) for name, q in estimates.items()}
    mov = np.asarray(trial.movement, bool)[sel]
    fig, axes = plt.subplots(3, 1, sharex=True, figsize=figsize, dpi=dpi)
    for ax, metric in zip(axes, ERROR_NAMES):
        ax.fill_between(t[sel], 0, 1, where=~mov, transform=ax.get_xaxis_transform(), color="0.92", lw=0,
                        label="not scored (no movement)")
        rmse = []
        for name, s in series.items():
            y = s[metric][sel]
            ax.plot(t[sel], y, label=name, **style(name))
            e = y[mov & np.isfinite(y)]
            rmse.append(f"{name} {np.sqrt(np.mean(e * e)):.2f}°" if e.size else f"{name} n/a")
        ax.set_ylabel(f"{metric} error [°]")
        ax.set_ylim(0, _robust_limit([s[metric][sel] for s in series.values()]))
        ax.set_title("RMSE over movement: " + ", ".join(rmse), fontsize="small", loc="left")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", ncol=len(estimates) + 1, fontsize="small")
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(title or f"{trial.name}: BROAD's errors over time")
    fig.tight_layout()
    return _save(fig, out)


# -- 3-D ----------------------------------------------------------------------------------------
def _box_polys(q, center):
    """The 6 faces of the IMU box rotated by ``q`` (sensor -> ENU) around ``center``."""
    c = quat.rotate(np.broadcast_to(q, (8, 4)), _CORNERS) + center
    return [c[list(f)] for f in _FACES]


def _axis_segments(q, center, length=0.75):
    d = quat.rotate(np.broadcast_to(q, (3, 4)), np.eye(3) * length)
    return [(center, center + d[i]) for i in range(3)]


class _Scene:
    """One 3-D Axes with the estimate's box (left) and the truth's box (right), updatable."""

    def __init__(self, ax, label_est="estimate"):
        self.ax = ax
        self.centers = (np.array([-_OFFSET, 0, 0]), np.array([_OFFSET, 0, 0]))
        self.boxes, self.axes_lines = [], []
        for j, color in enumerate((style(label_est)["color"], style("truth")["color"])):
            poly = art3d.Poly3DCollection(_box_polys(quat.IDENTITY, self.centers[j]), facecolor=color, alpha=0.35,
                                          edgecolor="k", linewidths=0.5)
            ax.add_collection3d(poly)
            self.boxes.append(poly)
            lines = [ax.plot(*np.transpose(s), color=AXIS_COLORS[i], lw=2)[0]
                     for i, s in enumerate(_axis_segments(quat.IDENTITY, self.centers[j]))]
            self.axes_lines.append(lines)
        ax.text(-_OFFSET, 0, 1.0, label_est, ha="center", fontsize=8)
        self.truth_label = ax.text(_OFFSET, 0, 1.0, "truth", ha="center", fontsize=8)
        lim = 1.6
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_zlim(-lim / 2, lim / 2)
        ax.set_box_aspect((2, 2, 1))
        ax.set_xlabel("E")
        ax.set_ylabel("N")
        ax.set_zlabel("U")
        ax.tick_params(labelsize=6)

    def set(self, q_est, q_true):
        for j, q in enumerate((q_est, q_true)):
            ok = bool(np.all(np.isfinite(q)))
            q = np.asarray(q, float) if ok else quat.IDENTITY
            self.boxes[j].set_verts(_box_polys(q, self.centers[j]))
            self.boxes[j].set_visible(ok)
            if j == 1:
                self.truth_label.set_text("truth" if ok else "truth n/a")
            for line, (a, b) in zip(self.axes_lines[j], _axis_segments(q, self.centers[j])):
                line.set_data_3d(*np.transpose([a, b]))
                line.set_visible(ok)


def plot_3d_frames(trial, q_est, times, out=None, ncols=4, name="estimate", dpi=100):
    """A grid of key frames at ``times`` [s]: the IMU box rotated by ``q_est`` ``(N, 4)`` (in the
    colour of the filter ``name``) beside the ground truth (the truth's colour; hidden where the
    truth is NaN). Sensor axes x/y/z red/green/blue."""
    q_est = np.asarray(q_est, float)
    times = np.atleast_1d(np.asarray(times, float))
    idx = np.clip(np.round(times * trial.fs).astype(int), 0, trial.n_samples - 1)
    ncols = max(1, min(ncols, len(idx)))
    nrows = -(-len(idx) // ncols)
    fig = plt.figure(figsize=(3.2 * ncols, 2.8 * nrows), dpi=dpi)
    for k, i in enumerate(idx):
        ax = fig.add_subplot(nrows, ncols, k + 1, projection="3d")
        _Scene(ax, label_est=name).set(q_est[i], trial.opt_quat[i])
        ax.set_title(f"t = {i / trial.fs:.1f} s", fontsize=9)
    fig.suptitle(f"{trial.name}: {name} (left) vs truth (right)")
    fig.subplots_adjust(top=0.82 if nrows == 1 else 0.9)
    return _save(fig, out)


def ffmpeg_available() -> bool:
    animation = require("matplotlib.animation", extra="plot", what="togglecf.report.plots")
    return animation.writers.is_available("ffmpeg")


def animation_path(path) -> Path:
    """Where ``animate_3d`` writes: ``path``, or with ``.gif`` when it asks for ``.mp4`` and
    ffmpeg is missing."""
    path = Path(path)
    if path.suffix.lower() == ".mp4" and not ffmpeg_available():
        return path.with_suffix(".gif")
    return path


def animate_3d(trial, q_est, path, fps: int = 10, duration: float | None = None, t_range=None,
               name="estimate", dpi=72):
    """Animate the estimate beside the truth and write ``path``: MP4 (``FFMpegWriter``) when
    ffmpeg is available, else GIF (``PillowWriter``; ``animation_path`` says which).

    The trial (or ``t_range``) is subsampled to ``fps * duration`` frames (default: the real
    time span, at most 8 s of animation: ~0.1 s of rendering per frame) so it renders in
    seconds. Returns the Figure."""
    animation = require("matplotlib.animation", extra="plot", what="togglecf.report.plots")
    q_est = np.asarray(q_est, float)
    t0, t1 = (0.0, trial.duration) if t_range is None else t_range
    i0, i1 = int(max(0, t0 * trial.fs)), int(min(trial.n_samples, t1 * trial.fs))
    if i1 <= i0:
        raise ValueError(f"empty time range {t_range}")
    if duration is None:
        duration = min(8.0, (i1 - i0) / trial.fs)
    n_frames = max(2, int(round(fps * duration)))
    idx = np.unique(np.linspace(i0, i1 - 1, n_frames).astype(int))
    fig = plt.figure(figsize=(5, 3.6), dpi=dpi)
    ax = fig.add_subplot(projection="3d")
    scene = _Scene(ax, label_est=name)
    title = ax.set_title("")

    def frame(k):
        i = idx[k]
        scene.set(q_est[i], trial.opt_quat[i])
        title.set_text(f"{trial.name[:30]}  t = {i / trial.fs:5.1f} s")
        return []

    anim = animation.FuncAnimation(fig, frame, frames=len(idx), blit=False)
    out = animation_path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = animation.FFMpegWriter(fps=fps) if out.suffix.lower() == ".mp4" else animation.PillowWriter(fps=fps)
    anim.save(out, writer=writer, dpi=dpi)
    return fig


