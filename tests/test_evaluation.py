"""BROAD metrics on constructed cases with known answers."""
import numpy as np
import pytest

from togglecf.core import quaternion as quat
from togglecf.metrics.broad import (ErrorReference, error_angles_rad, error_quaternion, group_means,
                                    remove_heading_offset, rmse_deg, tagp, trial_errors)
from conftest import random_quats


def rot(axis, deg):
    return quat.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis))


@pytest.fixture
def ref(rng):
    return random_quats(rng, 2000)


def test_constant_yaw_offset(ref):
    est = quat.multiply(rot([0, 0, 1], 10), ref)  # earth-frame rotation about up
    e = trial_errors(est, ref, np.ones(len(ref), bool))
    assert e["total"] == pytest.approx(10, abs=1e-9)
    assert e["heading"] == pytest.approx(10, abs=1e-9)
    assert e["inclination"] == pytest.approx(0, abs=1e-6)


def test_constant_tilt_offset(ref):
    est = quat.multiply(rot([1, 1, 0], 5), ref)  # earth-frame rotation about a horizontal axis
    e = trial_errors(est, ref, np.ones(len(ref), bool))
    assert e["total"] == pytest.approx(5, abs=1e-9)
    assert e["inclination"] == pytest.approx(5, abs=1e-9)
    assert e["heading"] == pytest.approx(0, abs=1e-6)


def test_heading_and_inclination_combined():
    # q_err = yaw 30° ⊗ tilt 40°: BROAD's decomposition gives each part back
    q_err = quat.multiply(rot([0, 0, 1], 30), rot([1, 0, 0], 40))
    a = {k: np.degrees(v) for k, v in error_angles_rad(q_err[None]).items()}
    assert a["inclination"][0] == pytest.approx(40, abs=1e-9)
    # heading = 2 atan(|z/w|) with w = cos15 cos20, z = sin15 cos20 -> exactly 30°
    assert a["heading"][0] == pytest.approx(30, abs=1e-9)
    assert a["total"][0] == pytest.approx(np.degrees(quat.angle_between(q_err, quat.IDENTITY)), abs=1e-9)


def test_sign_and_normalisation_do_not_matter(ref):
    est = quat.multiply(rot([0, 0, 1], 10), ref)
    e1 = trial_errors(est, ref, np.ones(len(ref), bool))
    e2 = trial_errors(-3.0 * est, 0.5 * ref, np.ones(len(ref), bool))
    assert e1 == pytest.approx(e2)


def test_rmse_over_movement_ignoring_nan_reference(ref):
    est = ref.copy()
    est[:1000] = quat.multiply(rot([0, 0, 1], 20), ref[:1000])
    movement = np.zeros(len(ref), bool)
    movement[500:1500] = True  # 500 samples with 20° error, 500 with 0
    e = trial_errors(est, ref, movement)
    assert e["total"] == pytest.approx(np.sqrt(0.5 * 20**2), abs=1e-9)
    ref_nan = ref.copy()
    ref_nan[1000:1500] = np.nan  # the error-free half has no reference: only 20° samples remain
    assert trial_errors(est, ref_nan, movement)["total"] == pytest.approx(20, abs=1e-9)


def test_roll_pitch_yaw_rmse(ref):
    ref = quat.from_euler_zyx(np.column_stack([np.zeros(100), np.zeros(100), np.linspace(-3, 3, 100)]))
    est = quat.from_euler_zyx(np.column_stack([np.full(100, 0.1), np.zeros(100), np.linspace(-3, 3, 100) + 0.2]))
    e = trial_errors(est, ref, np.ones(100, bool))
    assert e["roll"] == pytest.approx(np.degrees(0.1), abs=1e-9)
    assert e["pitch"] == pytest.approx(0, abs=1e-9)
    assert e["yaw"] == pytest.approx(np.degrees(0.2), abs=1e-9)  # wrapped across ±180°


def test_six_d_removes_constant_heading_only(ref):
    est = quat.multiply(rot([0, 0, 1], 70), quat.multiply(rot([1, 0, 0], 3), ref))
    mov = np.ones(len(ref), bool)
    assert trial_errors(est, ref, mov)["heading"] > 60
    e = trial_errors(est, ref, mov, six_d=True)
    assert e["inclination"] == pytest.approx(3, abs=1e-6)
    assert e["total"] == pytest.approx(3, abs=0.05)  # residual: heading part of the tilted error
    fixed = remove_heading_offset(est, ref, mov)
    assert np.all(np.isfinite(fixed))


def _errors_by_definition(est, ref, movement, six_d):
    """BROAD's errors computed on every sample, then averaged over ``movement`` (the metrics doc's
    recipe; ``ErrorReference`` computes the scored samples alone)."""
    if six_d:
        est = remove_heading_offset(est, ref, movement)
    out = {k: rmse_deg(v, movement) for k, v in error_angles_rad(error_quaternion(est, ref)).items()}
    d = np.angle(np.exp(1j * (quat.to_euler_zyx(est) - quat.to_euler_zyx(ref))))
    return out | {k: rmse_deg(d[:, i], movement) for i, k in enumerate(("roll", "pitch", "yaw"))}


@pytest.mark.parametrize("six_d", [False, True])
def test_error_reference_equals_the_definition_bit_for_bit(ref, rng, six_d):
    # the study's numbers must not move when a grid scores through one ErrorReference: every error is
    # per sample, so the scored rows alone give the same floats (same values, same order into each mean)
    est = quat.normalize(ref + 0.05 * rng.standard_normal(ref.shape)) * rng.uniform(0.5, 2.0, (len(ref), 1))
    ref = ref.copy()
    ref[100:140] = np.nan  # a reference gap inside the scored samples
    movement = rng.random(len(ref)) < 0.6
    reference = ErrorReference(ref, movement)
    for q in (est, quat.multiply(rot([0, 0, 1], 25), est)):
        want = _errors_by_definition(q, ref, movement, six_d)
        assert reference.errors(q, six_d) == want
        assert trial_errors(q, ref, movement, six_d) == want
    assert all(np.isnan(v) for v in ErrorReference(ref, np.zeros(len(ref), bool)).errors(est, six_d).values())
    with pytest.raises(ValueError, match="q_est"):
        reference.errors(est[:-1])


def test_error_quaternion_is_earth_frame():
    ref = rot([0, 1, 0], 90)
    est = quat.multiply(rot([0, 0, 1], 10), ref)
    np.testing.assert_allclose(np.abs(error_quaternion(est, ref)), np.abs(rot([0, 0, 1], 10)), atol=1e-12)


def test_group_means_and_tagp():
    per_trial = {"a": {"total": 1.0}, "b": {"total": 3.0}, "c": {"total": 5.0}}
    g = group_means(per_trial, {"all": ["a", "b", "c", "d"], "x": ["a", "b"], "none": ["d"]})
    assert g["all"]["total"] == 3.0 and g["all"]["n_trials"] == 3 and g["all"]["n_listed"] == 4
    assert g["x"]["total"] == 2.0 and "none" not in g
    grid = {"k": [1, 2, 3]}
    res = {(1,): {"a": {"total": 4.0}, "b": {"total": 4.0}},
           (2,): {"a": {"total": 1.0}, "b": {"total": 5.0}},  # mean 3: the TAGP
           (3,): {"a": {"total": 0.5}, "b": {"total": 7.0}}}  # best single trial, worse mean
    t = tagp(grid, res)
    assert t.params == {"k": 2} and t.index == (1,)
    np.testing.assert_allclose(t.mean_total, [4.0, 3.0, 3.75])
    with pytest.raises(KeyError, match="no results"):
        tagp({"k": [1, 2, 9]}, res)
