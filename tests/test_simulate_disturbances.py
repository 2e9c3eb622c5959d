"""The simulator's trajectories and disturbances (used by the filter-suite tests) do what
their docstrings say, checked against closed forms."""
import numpy as np

from togglecf.core import quaternion as Q
from togglecf import simulate as sim
from togglecf.data.broad import GRAVITY

FS = 200.0


def test_turntable_body_rate_is_constant_vertical_rate():
    """q(t) = Rz(rate·t) ⊗ R(tilt): the gyro (body rate), rotated to the earth frame, is
    (0, 0, rate) at every sample; the tilt is constant (acc at rest makes the same angle)."""
    traj = sim.turntable_trajectory(FS, 10.0, rate_deg_s=45.0, tilt_deg=25.0)
    tr = sim.imu_from_orientation(traj, FS)
    w_earth = Q.rotate(traj[1:-1], tr.gyr[2:])  # gyr[k] carries the rate from q[k-1] to q[k]
    np.testing.assert_allclose(w_earth, np.tile([0.0, 0.0, np.radians(45.0)], (len(w_earth), 1)), atol=1e-9)
    tilt = np.degrees(np.arccos(tr.acc[:, 2] / np.linalg.norm(tr.acc, axis=1)))
    np.testing.assert_allclose(tilt, 25.0, atol=1e-9)


def test_gimbal_follows_its_euler_sinusoids():
    traj = sim.gimbal_trajectory(FS, 20.0, amplitude_deg=(30.0, 20.0, 90.0), freq_hz=(0.1, 0.2, 0.05),
                                 phase=(0.0, 0.0, 0.0))
    t = np.arange(len(traj)) / FS
    rpy = np.degrees(Q.to_euler_zyx(traj))
    np.testing.assert_allclose(rpy[:, 0], 30.0 * np.sin(2 * np.pi * 0.1 * t), atol=1e-9)
    np.testing.assert_allclose(rpy[:, 1], 20.0 * np.sin(2 * np.pi * 0.2 * t), atol=1e-9)
    np.testing.assert_allclose(rpy[:, 2], 90.0 * np.sin(2 * np.pi * 0.05 * t), atol=1e-9)


def test_random_walk_bias_enters_the_gyro_exactly():
    """Per-sample bias (N, 3): gyro − noiseless gyro == bias; the walk starts at ``initial`` and
    its increments have std σ·√Δt (checked to 5 % on 60 000 increments)."""
    n = 20000
    bias = sim.random_walk_bias(n, FS, sigma=0.01, initial=(0.1, -0.2, 0.3), seed=1)
    np.testing.assert_array_equal(bias[0], [0.1, -0.2, 0.3])
    assert abs(np.diff(bias, axis=0).std() / (0.01 * np.sqrt(1 / FS)) - 1.0) < 0.05
    traj = sim.static_trajectory((10, 20, 30), n)
    clean = sim.imu_from_orientation(traj, FS)
    biased = sim.imu_from_orientation(traj, FS, gyro_bias=bias)
    np.testing.assert_allclose(biased.gyr - clean.gyr, bias, atol=1e-15)


def test_linear_acceleration_bursts_and_vibration():
    n = int(10 * FS)
    lin = sim.linear_acceleration_bursts(n, FS, ((2.0, 1.0, (3.0, -1.0, 0.5)), (6.0, 0.5, (0.0, 0.0, 4.0))))
    t = np.arange(n) / FS
    outside = ~(((t >= 2.0) & (t < 3.0)) | ((t >= 6.0) & (t < 6.5)))
    assert np.all(lin[outside] == 0.0)
    np.testing.assert_allclose(lin[int(2.5 * FS)], [3.0, -1.0, 0.5], atol=1e-12)  # raised-cosine peak
    vib = sim.vibration(n, FS, amplitude=2.0, freq_hz=25.0, start=4.0, stop=5.0)
    assert np.all(vib[(t < 4.0) | (t >= 5.0)] == 0.0)
    assert 1.9 < np.abs(vib).max() <= 2.0
    # the accelerometer measures gravity plus the linear acceleration, in the sensor frame
    traj = sim.static_trajectory((0, 0, 90), n)
    tr = sim.imu_from_orientation(traj, FS, lin_acc_earth=lin + vib)
    np.testing.assert_allclose(Q.rotate(traj, tr.acc), lin + vib + [0.0, 0.0, GRAVITY], atol=1e-9)


def test_mag_disturbance_intervals():
    n = int(30 * FS)
    d = sim.mag_disturbance_intervals(n, FS, ((10.0, 20.0, (30.0, 0.0, 0.0)),))
    t = np.arange(n) / FS
    inside = (t >= 10.0) & (t < 20.0)
    assert np.all(d[inside] == [30.0, 0.0, 0.0]) and np.all(d[~inside] == 0.0)
    traj = sim.static_trajectory((0, 0, 0), n)
    tr = sim.imu_from_orientation(traj, FS, mag_disturbance_earth=d)
    np.testing.assert_allclose(tr.mag, sim.EARTH_MAG_ENU + d, atol=1e-12)
