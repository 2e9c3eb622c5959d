"""The classical filter suite (gyro, accmag, madgwick, mahony, aqua, ekf; cf where it applies):
framework contracts on real data, agreement with the ``ahrs`` package and with the papers'
equations, robustness to bad samples (hypothesis) and convergence on simulated data with
exact ground truth."""
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from togglecf.core import quaternion as Q
from togglecf import simulate as sim
from togglecf.filters import FILTERS, make_filter
from togglecf.filters.aqua import adaptive_gain, scale_delta_quat
from togglecf.filters.timeconst import tau_from_gain

ALL = sorted(FILTERS)
SUITE = ["gyro", "accmag", "madgwick", "mahony", "aqua", "ekf"]
FS = 285.714  # BROAD's rate, so that the default (BROAD-tuned) gains are the ones tested


def _incl_deg(q_est, q_ref):
    """Inclination error [deg] of (N, 4) estimates: angle between the estimated and true up
    directions expressed in the sensor frame."""
    up = np.array([0.0, 0.0, 1.0])
    a = Q.rotate(Q.conjugate(q_est), up)
    b = Q.rotate(Q.conjugate(q_ref), up)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def _heading_deg(q_est, q_ref):
    """BROAD's heading error [deg] (rotation about the vertical of q_est ⊗ q_ref*)."""
    e = Q.multiply(q_est, Q.conjugate(q_ref))
    return np.degrees(2.0 * np.arctan2(np.abs(e[..., 3]), np.abs(e[..., 0])))


def _segment(trial, n=2000, start=5000):
    s = slice(start, start + n)
    return trial.gyr[s], trial.acc[s], trial.mag[s]


# ---------------------------------------------------------------------------------------------
# Framework contracts on real data
# ---------------------------------------------------------------------------------------------

@pytest.mark.broad
@pytest.mark.parametrize("use_mag", [True, False], ids=["9D", "6D"])
@pytest.mark.parametrize("name", ALL)
def test_update_loop_equals_batch_bit_for_bit(broad_trial, name, use_mag):
    """``update`` per sample and ``update_batch`` run the same compiled step: identical bits,
    quaternions and diagnostics, on 2000 real samples."""
    g, a, m = _segment(broad_trial)
    fb = make_filter(name, broad_trial.fs, use_mag=use_mag)
    out = fb.update_batch(g, a, m if use_mag else None)
    fl = make_filter(name, broad_trial.fs, use_mag=use_mag)
    quats = np.empty_like(out.quat)
    diags = np.empty((len(g), len(fl.diagnostic_names)))
    for k in range(len(g)):
        quats[k] = fl.update(g[k], a[k], m[k] if use_mag else None)
        diags[k] = list(fl.last_diagnostics.values())
    assert np.array_equal(quats, out.quat)
    assert np.array_equal(diags, np.stack([out.diagnostics[n] for n in fl.diagnostic_names], axis=1))
    assert np.array_equal(fl.get_state(), fb.get_state())
    assert np.all(np.isfinite(out.quat))
    np.testing.assert_allclose(np.linalg.norm(out.quat, axis=1), 1.0, atol=1e-12)  # unit norm to rounding


@pytest.mark.broad
@pytest.mark.parametrize("use_mag", [True, False], ids=["9D", "6D"])
@pytest.mark.parametrize("name", ALL)
def test_save_restore_splits_a_run_exactly(broad_trial, name, use_mag):
    """The whole filter memory is in the state vector: run half, save, continue in a *new*
    filter from the saved state; the two halves equal one full run bit for bit."""
    g, a, m = _segment(broad_trial)
    m = m if use_mag else None
    full = make_filter(name, broad_trial.fs, use_mag=use_mag).update_batch(g, a, m).quat
    f1 = make_filter(name, broad_trial.fs, use_mag=use_mag)
    first = f1.update_batch(g[:1000], a[:1000], None if m is None else m[:1000]).quat
    f2 = make_filter(name, broad_trial.fs, use_mag=use_mag)
    f2.set_state(f1.get_state())
    second = f2.update_batch(g[1000:], a[1000:], None if m is None else m[1000:]).quat
    assert np.array_equal(np.concatenate([first, second]), full)


def test_registry_and_settings():
    """Every suite filter is registered under its CLI name, documents its settings, and names
    its state entries and diagnostics consistently with the arrays it allocates."""
    for name in SUITE:
        cls = FILTERS[name]
        assert cls.name == name
        assert cls.Settings.__doc__ and cls.step is not None
        f = cls(100.0)
        assert f.state.shape == (5 + len(cls.state_names),)
        assert set(f.state_dict()) >= set(cls.state_names)
        out = f.update_batch(np.zeros((3, 3)), np.tile([0.0, 0.0, 9.81], (3, 1)), np.tile([0.0, 20.0, -40.0], (3, 1)))
        assert set(out.diagnostics) == set(cls.diagnostic_names)
    with pytest.raises(TypeError):
        make_filter("madgwick", 100.0, gain=0.1)  # unknown setting names fail loudly
    with pytest.raises(ValueError):
        make_filter("aqua", 100.0, err_low=0.3, err_high=0.2)


def test_gyro_integrates_per_sample_dt_exactly():
    """A constant rate integrated over irregular Δt must give exactly rate × Σ Δt (the
    framework passes dt per sample; exp-map integration is exact for a constant rate)."""
    rng = np.random.default_rng(1)
    n = 500
    dt = rng.uniform(0.001, 0.02, n)
    w = np.array([0.3, -0.2, 0.5])
    f = make_filter("gyro", 100.0, use_mag=False)
    out = f.update_batch(np.tile(w, (n, 1)), np.tile([0.0, 0.0, 9.81], (n, 1)), dt=dt)
    expected = Q.from_rotvec(w * dt[1:].sum())  # sample 0 initialises (identity), 1.. integrate
    assert Q.angle_between(out.quat[-1], expected) < 1e-12  # rounding over 500 products


# ---------------------------------------------------------------------------------------------
# Agreement with the ahrs package and the papers' equations
# ---------------------------------------------------------------------------------------------

def _ahrs_run(ref, q0, g, a, m, use_mag):
    q = q0.copy()
    out = [q]
    for k in range(1, len(g)):
        q = np.asarray(ref.updateMARG(q, g[k], a[k], m[k]) if use_mag else ref.updateIMU(q, g[k], a[k]), float)
        out.append(q)
    return np.array(out)


@pytest.mark.broad
@pytest.mark.parametrize("use_mag", [True, False], ids=["9D", "6D"])
def test_madgwick_matches_ahrs(broad_trial, use_mag):
    """ahrs.filters.Madgwick implements the report (incl. eq. 46 for b, not the C code's half
    b) in the NWU frame (d = [0,0,1] up, b = [b_x, 0, b_z] north): with the same β, the same
    initial quaternion (ours converted ENU -> NWU) and its output converted NWU -> ENU, the two
    agree to rounding. ahrs returns q unchanged for a gyro sample that is exactly zero (9 such
    rows in this trial); ours then still applies the correction, so those samples are given
    an invalid Δt here, which makes ours skip them the same way."""
    ahrs_filters = pytest.importorskip("ahrs.filters")
    g, a, m = _segment(broad_trial, n=5000, start=10000)
    dt = np.where(np.linalg.norm(g, axis=1) == 0.0, np.nan, 1.0 / broad_trial.fs)
    f = make_filter("madgwick", broad_trial.fs, use_mag=use_mag, beta=0.1)
    ours = f.update_batch(g, a, m if use_mag else None, dt=dt).quat
    ref = ahrs_filters.Madgwick(frequency=broad_trial.fs, gain=0.1)
    theirs = Q.from_frame(_ahrs_run(ref, Q.to_frame(ours[0], "NWU"), g, a, m, use_mag), "NWU")
    assert np.abs(theirs - ours).max() < 1e-6  # observed ~1e-14: same equations, rounding only


@pytest.mark.broad
@pytest.mark.parametrize("use_mag", [True, False], ids=["9D", "6D"])
def test_mahony_matches_ahrs(broad_trial, use_mag):
    """ahrs.filters.Mahony uses the explicit complementary filter with bias integral and the
    reference b = [0, |h_xy|, h_z] (y north, z up: ENU), so no frame conversion is needed.
    Same Kp, Ki, initial quaternion and zero initial bias; exactly-zero gyro samples are
    skipped by ahrs, hence the invalid Δt there (see the Madgwick test)."""
    ahrs_filters = pytest.importorskip("ahrs.filters")
    g, a, m = _segment(broad_trial, n=5000, start=10000)
    dt = np.where(np.linalg.norm(g, axis=1) == 0.0, np.nan, 1.0 / broad_trial.fs)
    f = make_filter("mahony", broad_trial.fs, use_mag=use_mag, Kp=0.7, Ki=0.01)
    out = f.update_batch(g, a, m if use_mag else None, dt=dt)
    ref = ahrs_filters.Mahony(frequency=broad_trial.fs, k_P=0.7, k_I=0.01)
    theirs = _ahrs_run(ref, out.quat[0], g, a, m, use_mag)
    assert np.abs(theirs - out.quat).max() < 1e-6  # observed ~1e-15
    np.testing.assert_allclose(ref.b, f.get_state()[5:8], rtol=0, atol=1e-12)  # same integral state


def _madgwick_reference(q_nwu, g, a, m, beta, dt, bscale):
    """Slow, readable numpy version of the report's equations (NWU, matrices as printed)."""
    out = [q_nwu]
    q = q_nwu.copy()
    for k in range(1, len(g)):
        qdot = 0.5 * Q.multiply(q, np.r_[0.0, g[k]])  # eq. 12
        an, mn = a[k] / np.linalg.norm(a[k]), m[k] / np.linalg.norm(m[k])
        h = Q.rotate(q, mn)  # eq. 45
        bx, bz = bscale * np.hypot(h[0], h[1]), bscale * h[2]  # eq. 46 (bscale 0.5: the C code)
        qc = Q.conjugate(q)
        f = np.r_[Q.rotate(qc, [0.0, 0.0, 1.0]) - an, Q.rotate(qc, [bx, 0.0, bz]) - mn]  # eq. 31
        w, x, y, z = q
        J = np.array([[-2 * y, 2 * z, -2 * w, 2 * x], [2 * x, 2 * w, 2 * z, 2 * y], [0, -4 * x, -4 * y, 0],
                      [-2 * bz * y, 2 * bz * z, -4 * bx * y - 2 * bz * w, -4 * bx * z + 2 * bz * x],
                      [-2 * bx * z + 2 * bz * x, 2 * bx * y + 2 * bz * w, 2 * bx * x + 2 * bz * z, -2 * bx * w + 2 * bz * y],
                      [2 * bx * y, 2 * bx * z - 4 * bz * x, 2 * bx * w - 4 * bz * y, 2 * bx * x]])  # eq. 32
        grad = J.T @ f  # eq. 34
        qdot = qdot - beta * grad / np.linalg.norm(grad)  # eq. 33
        q = q + qdot * dt  # eq. 13
        q = q / np.linalg.norm(q)
        out.append(q)
    return np.array(out)


@pytest.mark.broad
@pytest.mark.parametrize("c_code", [False, True], ids=["report", "c_code"])
def test_madgwick_marg_matches_report_equations(broad_trial, c_code):
    """Independent of ahrs: the MARG step against a numpy transcription of the report with
    the Jacobian as printed (eq. 32); with ``c_code_mag_step`` the reference b is halved as in
    MadgwickAHRS.c (BROAD issue 1), and the two variants really differ."""
    g, a, m = _segment(broad_trial, n=2000, start=20000)
    f = make_filter("madgwick", broad_trial.fs, beta=0.1, c_code_mag_step=c_code)
    ours = f.update_batch(g, a, m).quat
    ref = Q.from_frame(_madgwick_reference(Q.to_frame(ours[0], "NWU"), g, a, m, 0.1, 1.0 / broad_trial.fs,
                                           0.5 if c_code else 1.0), "NWU")
    assert np.abs(ref - ours).max() < 1e-9  # rounding only (observed ~1e-14)
    other = make_filter("madgwick", broad_trial.fs, beta=0.1, c_code_mag_step=not c_code).update_batch(g, a, m).quat
    assert np.degrees(Q.angle_between(other, ours)).max() > 0.01  # the b scale matters


def test_aqua_adaptive_gain():
    """Eq. 60-61: full gain for e_m ≤ 0.1, linear fall to 0 at 0.2, zero beyond and for NaN."""
    g = 9.81
    cases = {g: 1.0, 1.05 * g: 1.0, 0.9 * g: 1.0, 1.15 * g: 0.5, 0.85 * g: 0.5, 1.2 * g: 0.0, 3 * g: 0.0, 0.0: 0.0}
    for norm, factor in cases.items():
        assert adaptive_gain(0.02, norm, g, 0.1, 0.2) == pytest.approx(0.02 * factor, abs=1e-15)
    assert adaptive_gain(0.02, math.nan, g, 0.1, 0.2) == 0.0


def test_aqua_scale_delta_quat_lerp_and_slerp():
    """Eq. 50-52: SLERP (Δq_w ≤ ε) equals quaternion.slerp from identity; LERP (Δq_w > ε) is the
    normalised linear blend, within 1e-4 rad of SLERP for these small angles."""
    for angle_deg, expect_slerp in ((60.0, True), (120.0, True), (10.0, False)):
        dq = Q.from_rotvec(np.radians(angle_deg) * np.array([0.6, -0.8, 0.0]))
        for gain in (0.0, 0.01, 0.3, 1.0):
            got, used = scale_delta_quat(tuple(dq), gain, 0.9)
            assert used == expect_slerp
            ref = Q.slerp(Q.IDENTITY, dq, gain)
            tol = 1e-12 if expect_slerp else 1e-4  # LERP vs SLERP at 10°: ~gain(1-gain)θ³/… < 1e-4 rad
            assert Q.angle_between(np.array(got), ref) < tol


@pytest.mark.broad
def test_ekf_covariance_stays_symmetric_positive_definite(broad_trial):
    """P is packed in the state vector; after 20 000 real samples it must still be exactly
    symmetric (the update subtracts a symmetric outer product) and positive definite."""
    f = make_filter("ekf", broad_trial.fs)
    f.update_batch(*_segment(broad_trial, n=20000, start=0))
    P = f.get_state()[16:].reshape(12, 12)
    assert np.array_equal(P, P.T)
    assert np.linalg.eigvalsh(P).min() > 0.0


# ---------------------------------------------------------------------------------------------
# Simulated data with exact ground truth
# ---------------------------------------------------------------------------------------------

def _sim(traj, fs=FS, **kw):
    kw.setdefault("gyro_noise", 0.002)
    kw.setdefault("acc_noise", 0.02)
    kw.setdefault("mag_noise", 0.2)
    return sim.imu_from_orientation(traj, fs, **kw)


CORRECTING = ["cf", "accmag", "madgwick", "mahony", "aqua", "ekf"]


@pytest.mark.parametrize("use_mag", [True, False], ids=["9D", "6D"])
@pytest.mark.parametrize("name", CORRECTING)
def test_tilt_converges_from_wrong_start(name, use_mag):
    """Gimbal motion, default (BROAD-tuned) settings, start 30° off in tilt: after 60 s the
    inclination error over the last 5 s is below 1.5° (the sensor noise alone gives ~0.1-0.5°;
    the slowest filter, the CF with α = 0.0003, has a 12 s time constant: 30°·e⁻⁵ ≈ 0.2°)."""
    traj = sim.gimbal_trajectory(FS, 60.0, amplitude_deg=(15.0, 10.0, 60.0))
    tr = _sim(traj)
    # AQUA without its bias estimator: during the gimbal's slow phases its steady-state test
    # fires (2 % of samples) and the true rate leaks into b (-0.5 °/s here), which leaves a
    # ~4.5° tilt offset; that limitation is the algorithm's, this test checks the correction.
    kw = {"estimate_bias": False} if name == "aqua" else {}
    f = make_filter(name, FS, use_mag=use_mag, **kw)
    f.set_quat(Q.multiply(traj[0], Q.from_rotvec([np.radians(30.0), 0.0, 0.0])))
    out = f.update_batch(tr.gyr, tr.acc, tr.mag if use_mag else None)
    last = slice(-int(5 * FS), None)
    if name != "accmag":  # memoryless: right from the first sample, which is its point
        assert _incl_deg(out.quat[:20], traj[:20]).max() > 20.0  # really started wrong
    assert _incl_deg(out.quat[last], traj[last]).max() < 1.5


@pytest.mark.parametrize("name", ["mahony", "aqua", "ekf"])
def test_gyro_bias_is_estimated(name):
    """Constant bias (0.5, -0.4, 0.3) °/s plus a slow random walk, 9D. Mostly at rest (AQUA
    only learns at rest) with short tilting sweeps: after 120 s the estimate is within
    0.05 °/s per axis (10-17 % of the bias; noise-limited) of the true bias. Mahony runs with
    K_i = 0.05: its BROAD-tuned K_i is so small that the integral needs many minutes; the EKF
    with MATLAB's noise values: its BROAD-tuned gyro_noise (0.02) blames innovations on the
    orientation rather than the bias, and after 120 s it has only ~50 % of the bias."""
    n = int(120 * FS)
    base = sim.static_trajectory((10.0, -5.0, 30.0), n)
    sweep = sim.axis_sweep_trajectory((1, 1, 0), 20.0, FS, 4.0, start=base[0])
    traj = base.copy()
    for t0 in (20.0, 60.0):  # sweep out and back
        k = int(t0 * FS)
        traj[k:k + len(sweep)] = sweep
        traj[k + len(sweep):k + 2 * len(sweep)] = sweep[::-1]
    bias = sim.random_walk_bias(n, FS, sigma=1e-5, initial=np.radians([0.5, -0.4, 0.3]), seed=3)
    tr = _sim(traj, gyro_bias=bias, gyro_noise=0.001)
    kw = {"mahony": {"Kp": 1.0, "Ki": 0.05},
          "ekf": {"gyro_noise": 9.1385e-5, "linacc_noise": 0.0096236, "mag_disturbance_noise": 0.5}}
    f = make_filter(name, FS, **kw.get(name, {}))
    out = f.update_batch(tr.gyr, tr.acc, tr.mag)
    est = np.stack([out.diagnostics[f"bias_{c}"] for c in "xyz"], axis=1)[-1]
    assert np.all(np.abs(np.degrees(est - bias[-1])) < 0.05), np.degrees(est - bias[-1])


@pytest.mark.parametrize("name", ["cf", "madgwick", "mahony", "aqua", "ekf"])
def test_heading_recovers_after_magnetic_disturbance(name):
    """Turntable (30 °/s about the vertical, 20° tilt), 9D; a 40 µT disturbance (almost the
    earth field's strength) from 10 s to 20 s pulls the heading away; 180 s after it ends the
    heading error is below 2°, i.e. close to the undisturbed run's level. The default gains are
    BROAD's TAGPs, so the heading loops are slow: AQUA's tau_mag is 70 s (β̄ = 5e-5 per sample
    at this rate), Mahony's heading loop is ~6.5× slower than its tilt loop (MahonySettings)."""
    traj = sim.turntable_trajectory(FS, 200.0, rate_deg_s=30.0, tilt_deg=20.0)
    n = len(traj)
    dist = sim.mag_disturbance_intervals(n, FS, ((10.0, 20.0, (40.0, 0.0, 0.0)),))
    tr = _sim(traj, mag_disturbance_earth=dist)
    f = make_filter(name, FS)
    out = f.update_batch(tr.gyr, tr.acc, tr.mag)
    head = _heading_deg(out.quat, traj)
    k20 = int(20 * FS)
    assert head[k20 - 10:k20].max() > 2.0  # the disturbance did pull the heading
    assert head[-int(2 * FS):].max() < 2.0


@pytest.mark.parametrize("name", SUITE + ["cf"])
def test_6d_ignores_the_magnetometer(name):
    """use_mag=False: outputs are bit-identical whether mag is garbage, a disturbed field or
    not passed at all."""
    traj = sim.random_smooth_trajectory(FS, 10.0, seed=4)
    tr = _sim(traj)
    ref = make_filter(name, FS, use_mag=False).update_batch(tr.gyr, tr.acc).quat
    rng = np.random.default_rng(0)
    for mag in (tr.mag * 5.0 + 100.0, rng.standard_normal(tr.mag.shape) * 1e3, np.full_like(tr.mag, np.nan)):
        got = make_filter(name, FS, use_mag=False).update_batch(tr.gyr, tr.acc, mag).quat
        assert np.array_equal(got, ref)


# ---------------------------------------------------------------------------------------------
# Robustness: bad samples (hypothesis)
# ---------------------------------------------------------------------------------------------

ROB_FS = 100.0
ROB_N = 6000  # 60 s: the slowest heading correction (EKF defaults) needs ~40 s after a 35° error
BAD_KINDS = ["gyr_nan", "gyr_inf", "gyr_sat", "acc_nan", "acc_inf", "acc_zero", "mag_nan", "mag_zero",
             "mag_inf", "dt_huge", "dt_nan", "dt_neg", "all_nan"]
# gains fast enough to re-converge within ~50 s at 100 Hz (robustness, not accuracy, is tested)
# (per sample at 100 Hz: CF α 0.01, AQUA ᾱ = β̄ = 0.02, as time constants)
ROB_SETTINGS = {"cf": dict(tau=tau_from_gain(0.01, 1 / ROB_FS)), "madgwick": dict(beta=0.1),
                "mahony": dict(Kp=2.0, Ki=0.01),
                "aqua": dict(tau_acc=tau_from_gain(0.02, 1 / ROB_FS), tau_mag=tau_from_gain(0.02, 1 / ROB_FS)),
                "ekf": {}, "accmag": {}, "gyro": {}}
_ROB_TRAJ = sim.random_smooth_trajectory(ROB_FS, ROB_N / ROB_FS, max_rate=1.0, seed=7)
_ROB_TRIAL = sim.imu_from_orientation(_ROB_TRAJ, ROB_FS, gyro_noise=0.002, acc_noise=0.02, mag_noise=0.2, seed=7)


def _apply_bad(kind, k, g, a, m, dt):
    if kind == "gyr_nan":
        g[k, 1] = np.nan
    elif kind == "gyr_inf":
        g[k] = [np.inf, 0.0, -np.inf]
    elif kind == "gyr_sat":
        g[k] = [35.0, -35.0, 35.0]  # a saturated MEMS gyro reads full scale: finite but wrong
    elif kind == "acc_nan":
        a[k, 0] = np.nan
    elif kind == "acc_inf":
        a[k, 2] = np.inf
    elif kind == "acc_zero":
        a[k] = 0.0
    elif kind == "mag_nan":
        m[k, 2] = np.nan
    elif kind == "mag_zero":
        m[k] = 0.0
    elif kind == "mag_inf":
        m[k, 0] = -np.inf
    elif kind == "dt_huge":
        dt[k] = 1e6
    elif kind == "dt_nan":
        dt[k] = np.nan
    elif kind == "dt_neg":
        dt[k] = -0.01
    elif kind == "all_nan":
        g[k] = a[k] = m[k] = np.nan


bad_samples = st.lists(st.tuples(st.sampled_from(BAD_KINDS), st.integers(100, 800)), min_size=1, max_size=40)


@pytest.mark.parametrize("use_mag", [True, False], ids=["9D", "6D"])
@pytest.mark.parametrize("name", SUITE + ["cf"])
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(bad=bad_samples)
def test_bad_samples_are_harmless(name, use_mag, bad):
    """NaN/inf/zero-norm acc and mag, non-finite and saturated (35 rad/s) gyro, huge/NaN/
    negative Δt mixed into 60 s of simulated motion within 1-8 s. Every output is finite and
    unit-norm. Afterwards (last 2 s) the estimate is back within 1.5° of the unharmed run's
    (inclination in 6D, total angle in 9D); a saturated sample can put it 35°+ off. The
    gyro-only filter cannot recover: its error must stay below the rotation it lost (skipped
    samples' |ω|Δt plus the saturated samples' extra rotation)."""
    tr = _ROB_TRIAL
    g, a, m = tr.gyr.copy(), tr.acc.copy(), tr.mag.copy()
    dt = np.full(ROB_N, 1.0 / ROB_FS)
    for kind, k in bad:
        _apply_bad(kind, k, g, a, m, dt)
    kw = ROB_SETTINGS[name]
    clean = make_filter(name, ROB_FS, use_mag=use_mag, **kw).update_batch(tr.gyr, tr.acc, tr.mag if use_mag else None)
    out = make_filter(name, ROB_FS, use_mag=use_mag, **kw).update_batch(g, a, m if use_mag else None, dt=dt)
    assert np.all(np.isfinite(out.quat))
    np.testing.assert_allclose(np.linalg.norm(out.quat, axis=1), 1.0, atol=1e-12)
    last = slice(-200, None)
    if name == "gyro":
        idx = sorted({k for _, k in bad})
        lost = np.linalg.norm(tr.gyr[idx], axis=1).sum() / ROB_FS + np.sqrt(3) * 35.0 * len(idx) / ROB_FS
        err = np.degrees(Q.angle_between(out.quat[last], clean.quat[last])).max()
        assert err <= np.degrees(lost) + 1e-6
        return
    if use_mag:
        err = np.degrees(Q.angle_between(out.quat[last], clean.quat[last])).max()
    else:
        err = _incl_deg(out.quat[last], clean.quat[last]).max()
    assert err < 1.5, err
