"""Conventions: poses, look_at, the light-stage grid, input checks, atomic output."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from facegeo.checks import as_array, check_choice, check_positive, check_unit_vectors
from facegeo.errors import InputError, ShapeError
from facegeo.frames import (
    Pose,
    direction_angles,
    light_directions,
    light_grid_angles,
    light_grid_indices,
    light_index,
    light_solid_angles,
    look_at,
    nearest_light_index,
    rotation_from_rvec,
    rvec_from_rotation,
    stratified_light_subset,
)
from facegeo.fsutil import atomic_path, atomic_write_text

SOLID_ANGLE_REL_TOL = 1e-3  # paper's Eq. (4) weights sum to 4π within 0.1 % at 64 × 32
EXACT_SOLID_ANGLE_TOL = 1e-12  # exact cell areas, relative
ROT_TOL = 1e-12  # rotation matrices, max abs element difference
POSE_TOL_M = 1e-12  # metres


def random_pose(rng) -> Pose:
    return Pose.from_rvec_tvec(rng.normal(size=3), rng.normal(size=3))


def test_solid_angles_sum_to_4pi_at_paper_grid():
    total = light_solid_angles(64, 32).sum()
    assert abs(total / (4 * np.pi) - 1) < SOLID_ANGLE_REL_TOL, f"Σ δA / 4π - 1 = {total / (4 * np.pi) - 1}"


@pytest.mark.parametrize("grid", [(64, 32), (16, 8), (3, 1)])
def test_exact_solid_angles_sum_to_4pi(grid):
    total = light_solid_angles(*grid, exact=True).sum()
    assert abs(total / (4 * np.pi) - 1) < EXACT_SOLID_ANGLE_TOL


@pytest.mark.parametrize("grid,k", [((32, 16), 32), ((64, 32), 16), ((16, 8), 16), ((64, 32), 32)])
def test_stratified_light_subset_covers_inclinations_and_azimuths(grid, k):
    n_theta, n_phi = grid
    L = n_theta * n_phi
    sel = stratified_light_subset(L, k)
    assert sel.size == k and np.all(np.diff(sel) > 0) and sel.min() >= 0 and sel.max() < L
    # one light in each stratum of consecutive indices
    assert np.array_equal(sel * k // L, np.arange(k))
    i, j = light_grid_indices(sel, n_theta)
    rows_per_stratum = max(1, L // k // n_theta)
    assert np.unique(j).size >= min(n_phi, k) // rows_per_stratum
    # azimuths spread over the circle, unlike a stride of n_theta / 2 (two azimuths)
    assert np.unique(i).size >= min(k, n_theta) // 2
    assert np.abs(np.exp(2j * np.pi * (i + 0.5) / n_theta).mean()) < 0.25


@pytest.mark.parametrize("n,k", [(20, 7), (2048, 100), (13, 12), (5, 1)])
def test_stratified_light_subset_one_light_per_stratum_when_k_does_not_divide(n, k):
    sel = stratified_light_subset(n, k)
    s = np.arange(k)
    assert sel.size == k and np.all(np.diff(sel) > 0)
    assert np.all((s * n // k <= sel) & (sel < (s + 1) * n // k))


def test_stratified_light_subset_all_lights_and_bad_input():
    assert np.array_equal(stratified_light_subset(20, 20), np.arange(20))
    assert np.array_equal(stratified_light_subset(20, 64), np.arange(20))
    for bad in ((0, 4), (10, 0), (10, 2.5), (True, 3)):
        with pytest.raises(InputError):
            stratified_light_subset(*bad)


def test_light_index_round_trip_and_directions():
    n_theta, n_phi = 64, 32
    l = np.arange(n_theta * n_phi)
    i, j = light_grid_indices(l, n_theta)
    assert np.array_equal(light_index(i, j, n_theta), l)
    theta, phi = light_grid_angles(n_theta, n_phi)
    assert np.allclose(theta, 2 * np.pi * (i + 0.5) / n_theta, atol=0, rtol=1e-15)
    assert np.allclose(phi, np.pi * (j + 0.5) / n_phi, atol=0, rtol=1e-15)
    omega = light_directions(n_theta, n_phi)
    assert np.abs(np.linalg.norm(omega, axis=1) - 1).max() < 1e-15
    # (θ, φ) recovered from the direction, and the direction's cell is the light itself
    t2, p2 = direction_angles(omega)
    assert np.abs(t2 - theta).max() < 1e-12 and np.abs(p2 - phi).max() < 1e-12
    assert np.array_equal(nearest_light_index(omega, n_theta, n_phi), l)


def test_light_grid_orientation():
    """φ from +Y (light 0 near the zenith), θ from +Z toward +X."""
    omega = light_directions(4, 2)
    assert omega[0, 1] > 0.7  # first row: upper hemisphere
    assert omega[-1, 1] < -0.7
    # i = 0 (θ = π/4): +X and +Z both positive; i = 1 (θ = 3π/4): +X positive, +Z negative
    assert omega[0, 0] > 0 and omega[0, 2] > 0
    assert omega[1, 0] > 0 and omega[1, 2] < 0


@pytest.mark.parametrize("bad", [[0.0, 0.0, 0.0], [np.inf, 0.0, 0.0], [0.0, -np.inf, 1.0],
                                 [np.nan, 1.0, 0.0], [np.inf, np.inf, np.inf]])
def test_nearest_light_invalid_direction_is_flagged_or_refused(bad):
    """Zero, NaN and inf directions name no cell: an InputError by default, or −1 with
    valid = False on request — never a usable index (inf used to land in a real cell)."""
    from facegeo.errors import InputError

    v = np.array([[0.3, 0.5, 0.8], bad, [0.0, -1.0, 0.0]])
    with pytest.raises(InputError, match=r"v: 1 direction\(s\) name no light cell.*index \(1,\)"):
        nearest_light_index(v, 8, 4)
    idx, valid = nearest_light_index(v, 8, 4, return_valid=True)
    assert valid.tolist() == [True, False, True], "only the bad row is invalid"
    assert idx[1] == -1, "invalid entries hold -1"
    assert np.array_equal(idx[valid], nearest_light_index(v[valid], 8, 4)), "valid rows unchanged"
    assert idx[2] // 8 == 3, "straight down is in the last row"


def test_pose_apply_invert_compose():
    rng = np.random.default_rng(1)
    T_a_b, T_b_c = random_pose(rng), random_pose(rng)
    p_c = rng.normal(size=(10, 3))
    p_a = (T_a_b @ T_b_c).apply(p_c)
    assert np.abs(p_a - T_a_b.apply(T_b_c.apply(p_c))).max() < POSE_TOL_M
    back = T_b_c.inverse().apply(T_a_b.inverse().apply(p_a))
    assert np.abs(back - p_c).max() < 1e-12
    ident = T_a_b @ T_a_b.inverse()
    assert np.abs(ident.matrix - np.eye(4)).max() < 1e-12
    # directions ignore translation
    assert np.abs(T_a_b.apply_direction(p_c) - p_c @ T_a_b.R.T).max() < 1e-15


def test_pose_matches_opencv_rvec_tvec():
    rng = np.random.default_rng(2)
    for _ in range(20):
        rvec = rng.normal(size=3)
        R_cv, _ = cv2.Rodrigues(rvec)
        assert np.abs(rotation_from_rvec(rvec) - R_cv).max() < ROT_TOL
        assert np.abs(rotation_from_rvec(rvec_from_rotation(R_cv)) - R_cv).max() < 1e-10
    # near π and near 0
    for theta in (np.pi - 1e-7, 1e-9, 0.0):
        axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
        R = rotation_from_rvec(axis * theta)
        assert np.abs(rotation_from_rvec(rvec_from_rotation(R)) - R).max() < 1e-8


def test_pose_rejects_non_rotation_and_dict_round_trip():
    with pytest.raises(InputError, match="not a rotation"):
        Pose(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(ShapeError, match=r"R: expected shape \(3, 3\)"):
        Pose(np.eye(2), np.zeros(3))
    T = Pose.from_rvec_tvec([0.1, 0.2, 0.3], [1, 2, 3])
    assert Pose.from_dict(T.to_dict()) == T
    with pytest.raises(InputError, match="keys 'R' and 't'"):
        Pose.from_dict({"R": np.eye(3).tolist()})


def test_look_at_opencv_frame():
    eye = np.array([0.31, 0.12, 1.05])
    T_cam_world = look_at(eye, np.zeros(3))
    assert np.abs(T_cam_world.origin_of_a_in_b - eye).max() < 1e-12
    p = T_cam_world.apply(np.zeros(3))
    assert abs(p[0]) < 1e-12 and abs(p[1]) < 1e-12 and p[2] > 0  # target on the optical axis
    up_cam = T_cam_world.apply_direction(np.array([0.0, 1.0, 0.0]))
    assert up_cam[1] < 0  # world up is image up: camera y points down
    right_cam = T_cam_world.apply_direction(np.array([1.0, 0.0, 0.0]))
    assert right_cam[0] > 0  # a camera on +Z looking at the face sees world +X to its right
    with pytest.raises(InputError):
        look_at([0, 1, 0], [0, 0, 0], up=[0, 1, 0])


def test_as_array_errors_name_argument_and_shapes():
    with pytest.raises(ShapeError, match=r"points: expected shape \(\.\.\., 3\), got \(4, 2\)"):
        as_array(np.zeros((4, 2)), "points", shape=(..., 3))
    x = np.zeros((3, 3))
    x[1, 2] = np.nan
    with pytest.raises(InputError, match=r"first at index \(1, 2\)"):
        as_array(x, "K")
    assert as_array(np.zeros((2, 5, 3)), "p", shape=(..., 3)).shape == (2, 5, 3)
    assert as_array(np.zeros(3), "p", shape=(..., 3)).shape == (3,)
    with pytest.raises(InputError, match="expected one of 'a', 'b'"):
        check_choice("c", "mode", ["a", "b"])
    with pytest.raises(InputError, match="> 0"):
        check_positive(-1, "radius")
    with pytest.raises(InputError, match="unit vectors"):
        check_unit_vectors([[1.0, 1.0, 0.0]], "n")


def test_atomic_write_keeps_previous_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    atomic_write_text(target, "first")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half-written")
            raise RuntimeError("boom")
    assert target.read_text() == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]  # temp file removed


def test_atomic_write_uses_default_permissions(tmp_path):
    import os

    umask = os.umask(0)
    os.umask(umask)
    target = tmp_path / "perm.txt"
    atomic_write_text(target, "x")
    assert (target.stat().st_mode & 0o777) == (0o666 & ~umask)
