"""Calibration of the camera–camera route's reported σ (facegeo.geometry.triangulation).

The metric is the z-score, a point's error over its reported σ, whose RMS is 1 when σ is
honest: for one camera's points (one pair, or merged over partners) the signed depth error along
the camera ray; for a fused point the 3-D distance to the point it estimates — the same
inverse-variance mean of the averaged cameras' *true* points (partners found as
:func:`fuse_cameras` finds them, :func:`_fused_truth`) — over the fused σ.

Fixtures: the default rig at 1/3 scale (160 × 240 cameras, fx ≠ fy, cx ≠ cy, distortion, ±15°
about the projector), the projector at 512 × 384; where stated a third camera 25 cm above the
projector, or camera 1 rolled 30° about its optical axis (its image axes turned against the
projector's, so a code axis's noise lands in both of its pixel axes). Decode maps: the true
projector coordinates of each pixel's surface point plus seeded Gaussian noise. Surfaces:

* a tilted plane disc, 8 cm radius: the code → pixel map between cameras is nearly affine, so
  the code-noise model of σ is all there is to test (tight band);
* the analytic sphere of ``tests/test_triangulation.py``, seen to its limb: at grazing incidence
  the local affine code match has a misfit σ does not carry (RMS z 1.2–1.5 on those points,
  ``docs/mesh.md``), hence the wider band.

Measured (this version / the previous one, which these tests fail): single pairs on the sphere,
three cameras, 0.1 px: RMS z 1.08 / 1.4e11 (degenerate matches reported σ ≈ 1e-17 m); plane,
two cameras, 0.1 px, fused: 1.024 / 1.118 (1.01 / 1.10 of the single-pair z); plane, three
cameras, merged per camera: 1.009 / 0.884; rolled camera, 0.08 / 0.3 px codes: depth RMS
0.181 / 0.239 mm.
"""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.frames import look_at
from facegeo.geometry import triangulation as tr
from facegeo.geometry.rig import default_rig

#: RMS z on the plane (no affine misfit), > 10,000 points per test.
Z_RMS_PLANE = (0.9, 1.1)
#: RMS z on the sphere, limb included (grazing incidence carries misfit σ does not model).
Z_RMS_SPHERE = (0.8, 1.25)
#: Fused RMS z over the RMS z of the per-camera maps it fuses, same decodes: fusing neither
#: loses nor gains calibration (counted as independent, the shared code maps made it ≈ 1.10).
FUSED_OVER_MAPS_Z = (0.95, 1.05)
#: Rolled camera, 0.08 / 0.3 px codes: single-pair depth RMS, metres (per-axis σ: 0.239 mm).
ROLLED_PAIR_DEPTH_RMS_M = 0.21e-3
#: Smallest σ a match may report, metres (a degenerate match reported ≈ 1e-17 m).
MIN_SIGMA_M = 1e-6
#: Gain ∂t/∂q of :func:`solve_along_rays` against finite differences of re-solves, relative.
TOL_GAIN_REL = 1e-4

SPHERE_C = np.array([0.004, -0.003, 0.01])
SPHERE_R = 0.09
DISC_R = 0.08


def _cameras(n: int = 2, roll_deg: float = 0.0):
    rig = default_rig().scaled(1 / 3)
    proj = rig.projector.scaled(0.5)
    cams = list(rig.cameras)
    if roll_deg:
        th = np.radians(roll_deg)
        cams[1] = cams[1].replace(T_cam_world=look_at(cams[1].center_world, SPHERE_C,
                                                      up=(np.sin(th), np.cos(th), 0.0)))
    if n == 3:
        cams.append(cams[0].replace(
            name="cam_top", T_cam_world=look_at(proj.center_world + [0.0, 0.25, 0.0], SPHERE_C)))
    return cams, proj


def _plane_normal(proj):
    n = proj.center_world - SPHERE_C
    n = n / np.linalg.norm(n) + np.array([0.25, -0.15, 0.0])  # tilted off every axis
    return n / np.linalg.norm(n)


def _decode(cam, proj, surface, sigma_xy, rng):
    """``x, y`` maps (NaN unlit) and the true points ``(H, W, 3)`` of ``surface``."""
    o, d = cam.pixel_rays()
    with np.errstate(invalid="ignore", divide="ignore"):
        if surface == "plane":
            n = _plane_normal(proj)
            t = ((SPHERE_C - o) @ n) / (d @ n)
            p = o + t[..., None] * d
            hit = (t > 0) & (np.linalg.norm(p - SPHERE_C, axis=-1) < DISC_R)
            hit &= ((cam.center_world - p) @ n) > 0
        else:
            oc = o - SPHERE_C
            b = np.einsum("...i,...i->...", oc, d)
            disc = b * b - (np.einsum("...i,...i->...", oc, oc) - SPHERE_R**2)
            hit = disc > 0
            p = o + (-b - np.sqrt(disc))[..., None] * d
            n = (p - SPHERE_C) / SPHERE_R
        p = np.where(hit[..., None], p, 0.0)
        q, front = proj.project(p)
        lit = hit & front & proj.in_image(q)
        lit &= np.einsum("...i,...i->...", np.broadcast_to(n, p.shape), proj.center_world - p) > 0
    q = q + rng.normal(0.0, 1.0, q.shape) * np.asarray(sigma_xy)
    return (np.where(lit, q[..., 0], np.nan), np.where(lit, q[..., 1], np.nan),
            np.where(lit[..., None], p, np.nan))


def _decodes(cams, proj, surface, sigma_xy, seed=0):
    rng = np.random.default_rng(seed)
    dec = [_decode(c, proj, surface, sigma_xy, rng) for c in cams]
    sig = {"sigma_x": [np.full(d[0].shape, sigma_xy[0]) for d in dec],
           "sigma_y": [np.full(d[0].shape, sigma_xy[1]) for d in dec]}
    return dec, sig


def _rms(z):
    return float(np.sqrt(np.mean(np.square(z))))


def _map_z(pm, cam, p_true):
    """Signed depth error over σ of a point map's points."""
    err = pm.depth - np.linalg.norm(p_true - cam.center_world, axis=-1)
    return (err / pm.sigma)[pm.valid], err[pm.valid]


def _fused_truth(maps, cams, p_true, tol_sigmas=4.0, tol_floor=1e-3):
    """``{(camera, column, row): true point}`` each fused point estimates: the inverse-variance
    mean of the true points :func:`fuse_cameras` averages (its partner rule, before fusion)."""
    depth_med = [tr._median3(m.depth) for m in maps]
    out = {}
    for a, ma in enumerate(maps):
        rows, cols = np.nonzero(ma.valid)
        p, s = ma.p_world[rows, cols], ma.sigma[rows, cols]
        num, den = p_true[a][rows, cols] / s[:, None] ** 2, 1.0 / s**2
        for b, (mb, cb) in enumerate(zip(maps, cams)):
            if b == a:
                continue
            qi, ok = tr._pixel_of(cb, p)
            D = np.where(ok, depth_med[b][qi[:, 1], qi[:, 0]], np.nan)
            sb = mb.sigma[qi[:, 1], qi[:, 0]]
            sb = np.where(np.isfinite(sb), sb, s)
            tau = tol_sigmas * np.sqrt(s**2 + sb**2) + tol_floor
            with np.errstate(invalid="ignore"):
                have = np.abs(np.linalg.norm(p - cb.center_world, axis=1) - D) <= tau
            have &= mb.valid[qi[:, 1], qi[:, 0]]
            wb = 1.0 / sb[have] ** 2
            num[have] += p_true[b][qi[have, 1], qi[have, 0]] * wb[:, None]
            den[have] += wb
        for r, c, v in zip(rows, cols, num / den[:, None]):
            out[(a, int(c), int(r))] = v
    return out


def _fused_z(maps, cams, p_true):
    truth = _fused_truth(maps, cams, p_true)
    fused = tr.fuse_cameras(maps, cams)
    ref = np.array([truth[(int(a), int(c), int(r))] for a, (c, r) in zip(fused.camera,
                                                                          fused.pixel)])
    z = np.linalg.norm(fused.p_world - ref, axis=1) / fused.sigma
    return z[fused.confirmed]


def test_pair_sigma_on_the_sphere_has_no_degenerate_match():
    """Every ordered pair of three cameras: a match whose B neighbours lie on one pixel row
    claimed zero variance across it (σ ≈ 1e-17 m, RMS z ≈ 1e11); it is now refused."""
    cams, proj = _cameras(3)
    dec, sig = _decodes(cams, proj, "sphere", (0.1, 0.1))
    z, sigmas = [], []
    for a, ca in enumerate(cams):
        for b, cb in enumerate(cams):
            if a != b:
                pm = tr.triangulate_camera_pair(ca, cb, dec[a][0], dec[a][1], dec[b][0],
                                                dec[b][1], sigma_x=sig["sigma_x"][a],
                                                sigma_y=sig["sigma_y"][a])
                z.append(_map_z(pm, ca, dec[a][2])[0])
                sigmas.append(pm.sigma[pm.valid])
    z = np.concatenate(z)
    assert z.size > 20000
    assert np.concatenate(sigmas).min() > MIN_SIGMA_M
    assert Z_RMS_SPHERE[0] <= _rms(z) <= Z_RMS_SPHERE[1], _rms(z)


def test_merged_sigma_counts_each_partner_on_its_own_code_axis():
    """Three cameras on the plane: A's pairs share A's code noise, but a horizontal partner
    reads mostly the column code and the vertical one the row code — propagated as one
    sensitivity vector, not as perfectly correlated (RMS z was 0.88)."""
    cams, proj = _cameras(3)
    dec, sig = _decodes(cams, proj, "plane", (0.1, 0.1))
    maps, _ = tr.triangulate_camera_pairs(cams, [d[0] for d in dec], [d[1] for d in dec], **sig)
    z = np.concatenate([_map_z(m, c, d[2])[0] for m, c, d in zip(maps, cams, dec)])
    assert z.size > 10000
    assert Z_RMS_PLANE[0] <= _rms(z) <= Z_RMS_PLANE[1], _rms(z)


@pytest.mark.parametrize("n_cameras", [2, 3])
def test_fused_sigma_counts_the_shared_code_maps(n_cameras):
    """Camera A's and B's points of one surface point come from the same two code maps (each
    camera's own code enters the other's local fit): fused as independent, RMS z read 1.118
    with two cameras, 1.10 of the per-camera maps' z."""
    cams, proj = _cameras(n_cameras)
    dec, sig = _decodes(cams, proj, "plane", (0.1, 0.1))
    maps, _ = tr.triangulate_camera_pairs(cams, [d[0] for d in dec], [d[1] for d in dec], **sig)
    z_maps = _rms(np.concatenate([_map_z(m, c, d[2])[0] for m, c, d in zip(maps, cams, dec)]))
    z = _fused_z(maps, cams, [d[2] for d in dec])
    assert z.size > 10000
    assert Z_RMS_PLANE[0] <= _rms(z) <= Z_RMS_PLANE[1], _rms(z)
    ratio = _rms(z) / z_maps
    assert FUSED_OVER_MAPS_Z[0] <= ratio <= FUSED_OVER_MAPS_Z[1], (_rms(z), z_maps)


def test_fused_sigma_on_the_sphere_limb_included():
    cams, proj = _cameras(3)
    dec, sig = _decodes(cams, proj, "sphere", (0.1, 0.1))
    maps, _ = tr.triangulate_camera_pairs(cams, [d[0] for d in dec], [d[1] for d in dec], **sig)
    z = _fused_z(maps, cams, [d[2] for d in dec])
    assert z.size > 10000
    assert Z_RMS_SPHERE[0] <= _rms(z) <= Z_RMS_SPHERE[1], _rms(z)


def test_rolled_camera_weighs_the_correlated_pixel_axes():
    """Camera B rolled 30°, a fine column code beside a coarse row code: the row code's noise
    lands in both of B's pixel axes, correlated; weighted per axis the points were 32 % worse
    (depth RMS 0.239 mm against 0.181) and σ 9 % pessimistic."""
    cams, proj = _cameras(2, roll_deg=30.0)
    dec, sig = _decodes(cams, proj, "plane", (0.08, 0.3))
    z, err = [], []
    for a, b in ((0, 1), (1, 0)):
        pm = tr.triangulate_camera_pair(cams[a], cams[b], dec[a][0], dec[a][1], dec[b][0],
                                        dec[b][1], sigma_x=sig["sigma_x"][a],
                                        sigma_y=sig["sigma_y"][a])
        za, ea = _map_z(pm, cams[a], dec[a][2])
        z.append(za)
        err.append(ea)
    z, err = np.concatenate(z), np.concatenate(err)
    assert z.size > 10000
    assert _rms(err) <= ROLLED_PAIR_DEPTH_RMS_M, _rms(err)
    assert Z_RMS_PLANE[0] <= _rms(z) <= Z_RMS_PLANE[1], _rms(z)


def test_solve_along_rays_with_a_covariance():
    """``cov_other``: diagonal reproduces ``sigma_other``; σ_t is ``(jᵀ·Σ⁻¹·j)^(-1/2)``; the
    gain ``dt_dq`` matches re-solving with a perturbed target; a correlation moves the point."""
    cams, proj = _cameras(2)
    x, y, p = _decode(cams[0], proj, "sphere", (0.0, 0.0), np.random.default_rng(0))
    sel = np.flatnonzero(np.isfinite(x).ravel())[::97]
    o, d = cams[0].pixel_rays(cams[0].pixel_grid().reshape(-1, 2)[sel])
    q = np.stack([x.ravel()[sel], y.ravel()[sel]], 1) + np.random.default_rng(1).normal(
        0, 0.3, (sel.size, 2))
    s = np.column_stack([np.full(sel.size, 0.1), np.full(sel.size, 0.4)])
    diag = tr.solve_along_rays(o, d, proj, q, s)
    cov = tr.solve_along_rays(o, d, proj, q, cov_other=s[:, :, None] * np.eye(2) * s[:, None])
    assert np.max(np.abs(cov.t - diag.t)) < 1e-12
    assert np.max(np.abs(cov.sigma_t / diag.sigma_t - 1)) < 1e-9
    C = np.array([[0.04, 0.035], [0.035, 0.09]])
    fit = tr.solve_along_rays(o, d, proj, q, cov_other=np.broadcast_to(C, (sel.size, 2, 2)))
    assert np.median(np.abs(fit.t - diag.t)) > 1e-6  # the correlation is used
    # σ_t from the projection's derivative along the ray, independently
    h = 1e-7
    qp, _ = proj.project(o + (fit.t + h)[:, None] * d)
    qm, _ = proj.project(o + (fit.t - h)[:, None] * d)
    j = (qp - qm) / (2 * h)
    sig = 1 / np.sqrt(np.einsum("ni,ij,nj->n", j, np.linalg.inv(C), j))
    assert np.max(np.abs(fit.sigma_t / sig - 1)) < TOL_GAIN_REL
    for axis in (0, 1):
        dq = np.zeros(2)
        dq[axis] = 1e-3
        moved = tr.solve_along_rays(o, d, proj, q + dq, cov_other=np.broadcast_to(C, (sel.size,
                                                                                      2, 2)))
        numeric = (moved.t - fit.t) / dq[axis]
        assert np.max(np.abs(numeric / fit.dt_dq[:, axis] - 1)) < TOL_GAIN_REL
