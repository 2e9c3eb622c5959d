"""Quaternion core against scipy.spatial.transform.Rotation (scalar-last [x,y,z,w], active,
Hamilton): our [w,x,y,z] maps to scipy's via a roll of the last axis."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from togglecf.core import quaternion as quat
from conftest import random_quats

ATOL = 1e-12  # pure float64 algebra on unit inputs: rounding only


def to_scipy(q):
    return Rotation.from_quat(np.roll(q, -1, axis=-1))


def from_scipy(r):
    return np.roll(r.as_quat(), 1, axis=-1)


def same_rotation(p, q, atol=1e-10):
    return np.all(np.abs(np.abs(np.sum(p * q, axis=-1)) - 1.0) < atol)


@pytest.fixture
def special_quats():
    """Near-singular cases: identity, 180° turns, tiny angles, gimbal lock (pitch ±90°)."""
    cases = [quat.IDENTITY, [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0.6, 0.8, 0],
             quat.from_rotvec(np.array([1e-9, -2e-9, 3e-10])),
             quat.from_rotvec(np.array([0, 0, np.pi - 1e-9])),
             quat.from_euler_zyx(np.array([0.3, np.pi / 2, -1.0])),
             quat.from_euler_zyx(np.array([-0.7, -np.pi / 2, 2.0])),
             quat.from_euler_zyx(np.array([0.1, np.pi / 2 - 1e-9, 0.5]))]
    return quat.normalize(np.array(cases, float))


def test_multiply_matches_scipy(rng):
    p, q = random_quats(rng, 500), random_quats(rng, 500)
    expected = from_scipy(to_scipy(p) * to_scipy(q))
    assert same_rotation(quat.multiply(p, q), expected)


def test_rotate_and_matrix_match_scipy(rng, special_quats):
    q = np.concatenate([random_quats(rng, 500), special_quats])
    v = rng.standard_normal((len(q), 3))
    np.testing.assert_allclose(quat.rotate(q, v), to_scipy(q).apply(v), atol=ATOL)
    np.testing.assert_allclose(quat.to_matrix(q), to_scipy(q).as_matrix(), atol=ATOL)


def test_from_matrix_round_trip(rng, special_quats):
    q = np.concatenate([random_quats(rng, 500), special_quats])
    back = quat.from_matrix(to_scipy(q).as_matrix())
    assert np.all(back[:, 0] >= 0)
    assert same_rotation(back, q)


def test_rotvec_matches_scipy_and_round_trips(rng, special_quats):
    q = np.concatenate([random_quats(rng, 500), special_quats])
    rv = quat.to_rotvec(q)
    np.testing.assert_allclose(quat.from_rotvec(rv), np.where(q[:, :1] < 0, -q, q), atol=1e-9)
    # scipy's rotvec is ambiguous at exactly π (±axis); compare the rotations instead there
    assert same_rotation(quat.from_rotvec(to_scipy(q).as_rotvec()), q)
    np.testing.assert_allclose(np.linalg.norm(rv, axis=1), to_scipy(q).magnitude(), atol=1e-9)


def test_euler_zyx_matches_scipy(rng):
    q = random_quats(rng, 500)
    np.testing.assert_allclose(quat.to_euler_zyx(q), to_scipy(q).as_euler("ZYX")[:, ::-1], atol=1e-9)
    assert same_rotation(quat.from_euler_zyx(quat.to_euler_zyx(q)), q)


def test_euler_at_gimbal_lock_still_represents_the_rotation(special_quats):
    rpy = quat.to_euler_zyx(special_quats)
    assert np.all(np.isfinite(rpy))
    assert same_rotation(quat.from_euler_zyx(rpy), special_quats, atol=1e-9)
    lock = np.abs(np.abs(rpy[:, 1]) - np.pi / 2) < 1e-6
    assert lock.sum() >= 2 and np.all(rpy[lock, 0] == 0.0)  # roll set to zero, as scipy does


def test_slerp_matches_scipy(rng):
    from scipy.spatial.transform import Slerp
    p, q = random_quats(rng, 50), random_quats(rng, 50)
    for t in (0.0, 0.25, 0.5, 0.9, 1.0):
        out = quat.slerp(p, q, t)
        for i in range(len(p)):
            ref = Slerp([0, 1], to_scipy(np.stack([p[i], q[i]])))([t])
            assert same_rotation(out[i], from_scipy(ref)[0], atol=1e-9)


def test_slerp_and_lerp_handle_nearly_equal_quaternions():
    p = quat.from_rotvec(np.array([0.1, 0.2, 0.3]))
    q = quat.multiply(p, quat.from_rotvec(np.array([1e-10, 0, 0])))
    for fn in (quat.slerp, quat.lerp):
        out = fn(p, -q, 0.5)  # opposite sign: same rotation, must take the short arc
        assert np.all(np.isfinite(out)) and quat.angle_between(out, p) < 1e-9


def test_from_acc_mag_recovers_orientation(rng):
    q = random_quats(rng, 200)
    g = np.array([0, 0, 9.81])
    m = np.array([0.0, 20.0, -45.0])  # north and down, as in Europe
    acc = quat.rotate(quat.conjugate(q), np.tile(g, (200, 1)))
    mag = quat.rotate(quat.conjugate(q), np.tile(m, (200, 1)))
    assert same_rotation(quat.from_acc_mag(acc, mag), q, atol=1e-9)
    ok = []
    for a, mm, qq in zip(acc, mag, q):
        good, qs = quat.from_acc_mag_scalar(*a, *mm)
        ok.append(good and same_rotation(np.array(qs), qq, atol=1e-9))
    assert all(ok)


def test_from_acc_mag_degenerate_gives_nan_not_garbage():
    out = quat.from_acc_mag(np.array([[0, 0, 9.81], [0, 0, 0]]), np.array([[0, 0, 40.0], [0, 20, -40]]))
    assert np.all(np.isnan(out))
    assert quat.from_acc_mag_scalar(0.0, 0.0, 9.81, 0.0, 0.0, 40.0)[0] is False


def test_from_acc_is_pure_tilt(rng):
    q = quat.from_euler_zyx(np.array([0.4, -0.3, 0.0]))
    acc = quat.rotate(quat.conjugate(q), np.array([0, 0, 9.81]))
    out = quat.from_acc(acc)
    np.testing.assert_allclose(quat.rotate(out, acc), [0, 0, 9.81], atol=1e-9)
    assert abs(out[3]) < 1e-12  # no rotation about the vertical component of the quaternion


def test_scalar_versions_equal_vectorised(rng):
    p, q = random_quats(rng, 100), random_quats(rng, 100)
    v = rng.standard_normal((100, 3))
    for i in range(100):
        np.testing.assert_allclose(quat.multiply_scalar(tuple(p[i]), tuple(q[i])), quat.multiply(p[i], q[i]), atol=ATOL)
        np.testing.assert_allclose(quat.rotate_scalar(tuple(p[i]), tuple(v[i])), quat.rotate(p[i], v[i]), atol=ATOL)
        np.testing.assert_allclose(quat.rotate_inverse_scalar(tuple(p[i]), tuple(v[i])),
                                   quat.rotate(quat.conjugate(p[i]), v[i]), atol=ATOL)
        np.testing.assert_allclose(quat.from_rotvec_scalar(*v[i]), quat.from_rotvec(v[i]), atol=ATOL)
        R = quat.to_matrix(p[i])
        assert same_rotation(np.array(quat.from_matrix_scalar(*R.ravel())), p[i])


def test_frame_conversions():
    # a sensor aligned with NED (x north, y east, z down) seen from ENU
    q_ned_identity = quat.IDENTITY
    q_enu = quat.from_frame(q_ned_identity, "NED")
    np.testing.assert_allclose(quat.rotate(q_enu, [1, 0, 0]), [0, 1, 0], atol=ATOL)  # sensor x -> north
    np.testing.assert_allclose(quat.rotate(q_enu, [0, 0, 1]), [0, 0, -1], atol=ATOL)  # sensor z -> down
    q_enu = quat.from_frame(quat.IDENTITY, "NWU")
    np.testing.assert_allclose(quat.rotate(q_enu, [1, 0, 0]), [0, 1, 0], atol=ATOL)  # NWU x = north
    np.testing.assert_allclose(quat.rotate(q_enu, [0, 1, 0]), [-1, 0, 0], atol=ATOL)  # NWU y = west
    q = quat.from_rotvec(np.array([0.3, -0.2, 1.0]))
    for frame in ("NED", "NWU", "ENU"):
        np.testing.assert_allclose(quat.from_frame(quat.to_frame(q, frame), frame), q, atol=ATOL)
    with pytest.raises(ValueError, match="unknown earth frame"):
        quat.to_frame(q, "XYZ")


def test_bad_shapes_raise_clear_errors():
    with pytest.raises(ValueError, match=r"expected shape \(\.\.\., 4\)"):
        quat.multiply(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match=r"expected shape \(\.\.\., 3\)"):
        quat.rotate(quat.IDENTITY, np.zeros(4))
