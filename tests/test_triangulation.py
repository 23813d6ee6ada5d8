"""Triangulation of decode maps (facegeo.geometry.triangulation).

Fixtures: the default rig at 1/6 scale (80 × 120 cameras, asymmetric intrinsics and
distortion, cameras ±15° about the projector) looking at an analytic sphere; decode maps are the
sphere's true points projected into the projector, plus Gaussian noise where stated. The tiny
synthetic scan (procedural head) supplies the hard cases with a real projector shadow.
"""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.errors import InputError, ShapeError
from facegeo.frames import look_at
from facegeo.geometry import triangulation as tr
from facegeo.geometry.camera import Camera
from facegeo.geometry.rig import default_rig

#: Noise-free triangulation, worst case over all pixels, metres (float64 GN to rounding).
TOL_EXACT_M = 1e-7
#: Noise-free camera–camera triangulation through codes, RMS, metres: the local affine inverse
#: map's interpolation error, ≈ 1/8 of the 6 mm footprint of an 80 × 120 camera's pixel.
TOL_PAIR_RMS_M = 0.8e-3
#: Reported σ against the observed error: |std(err / σ) − 1| (2,000+ points).
TOL_SIGMA_CALIBRATION = 0.15
#: "No wild point": worst distance of any surviving point to the true surface, metres.
TOL_WILD_M = 5e-3

SPHERE_C = np.array([0.004, -0.003, 0.01])
SPHERE_R = 0.09


def _rig(scale=1 / 6):
    rig = default_rig().scaled(scale)
    proj = rig.projector.scaled(0.5)  # 512 × 384
    return rig.cameras, proj


def _sphere_hits(cam: Camera):
    o, d = cam.pixel_rays()
    oc = o - SPHERE_C
    b = np.einsum("...i,...i->...", oc, d)
    c = np.einsum("...i,...i->...", oc, oc) - SPHERE_R**2
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    hit = disc > 0
    p = np.where(hit[..., None], o + t[..., None] * d, np.nan)
    return p, hit


def _decode(cam, proj, noise=0.0, seed=0, with_y=True):
    p, hit = _sphere_hits(cam)
    q, front = proj.project(np.where(hit[..., None], p, 0))
    n = (p - SPHERE_C) / SPHERE_R
    with np.errstate(invalid="ignore"):
        lit = hit & front & proj.in_image(q) & (np.einsum("...i,...i->...", n, proj.center_world - p) > 0)
    rng = np.random.default_rng(seed)
    q = q + rng.normal(0, noise, q.shape) if noise else q
    x = np.where(lit, q[..., 0], np.nan)
    y = np.where(lit & with_y, q[..., 1], np.nan)
    return x, y, lit, p


def _dist_to_sphere(p):
    return np.abs(np.linalg.norm(p - SPHERE_C, axis=-1) - SPHERE_R)


@pytest.mark.parametrize("with_y", [True, False], ids=["ray", "plane"])
def test_noise_free_decode_triangulates_exactly(with_y):
    cams, proj = _rig()
    for cam in cams:
        x, y, lit, p = _decode(cam, proj, with_y=with_y)
        pm = tr.triangulate_maps(cam, proj, x, y)
        assert pm.valid.sum() > 0.9 * lit.sum()
        err = np.linalg.norm(pm.p_world - p, axis=-1)[pm.valid]
        assert err.max() < TOL_EXACT_M, f"{cam.name}: worst {err.max():.3g} m"


def test_plane_against_distorted_projector_is_exact():
    """x only, projector with strong distortion: a column is a curved sheet; GN follows it."""
    cams, proj = _rig()
    proj = proj.replace(dist=np.array([-0.2, 0.05, 0.001, -0.002, 0.0]))
    x, _, lit, p = _decode(cams[0], proj)
    pm = tr.triangulate_maps(cams[0], proj, x, None)
    err = np.linalg.norm(pm.p_world - p, axis=-1)[pm.valid]
    assert pm.valid.sum() > 0.9 * lit.sum()
    assert err.max() < TOL_EXACT_M


@pytest.mark.parametrize("with_y", [True, False], ids=["ray", "plane"])
def test_sigma_predicts_the_error(with_y):
    """σ from the intersection geometry: err/σ along the ray has unit standard deviation."""
    cams, proj = _rig(scale=1 / 3)
    noise = 0.2
    ratios = []
    for cam in cams:
        x, y, _lit, p = _decode(cam, proj, noise=noise, seed=3, with_y=with_y)
        pm = tr.triangulate_maps(cam, proj, x, y, sigma_x=np.full(x.shape, noise),
                                 sigma_y=np.full(x.shape, noise), footprint_ratio=None)
        v = pm.valid
        signed = np.linalg.norm(pm.p_world - cam.center_world, axis=-1) - np.linalg.norm(
            p - cam.center_world, axis=-1)
        ratios.append(signed[v] / pm.sigma[v])
    r = np.concatenate(ratios)
    assert r.size > 2000
    assert abs(np.std(r) - 1) < TOL_SIGMA_CALIBRATION, np.std(r)
    # and σ is not a constant: it follows the geometry (further / more oblique → larger)
    assert np.ptp(pm.sigma[pm.valid]) > 0.1 * np.median(pm.sigma[pm.valid])


def test_ray_nearly_parallel_to_projector_plane_is_rejected():
    """A camera displaced along the projector's columns sees every column plane edge-on."""
    cams, proj = _rig()
    cam = cams[0]
    # put the camera 20 cm above the projector (along the projector's -y axis, i.e. inside its
    # central column plane's family): rays through the sphere run almost along column planes
    c_proj = proj.center_world
    up = -proj.T_cam_world.R[1]  # projector's -y axis in world
    eye = c_proj + 0.2 * up
    side = look_at(eye, SPHERE_C)
    cam_bad = cam.replace(T_cam_world=side)
    x, _, lit, _p = _decode(cam_bad, proj)
    fit_only = tr.triangulate_maps(cam_bad, proj, x, None, min_angle_deg=0.0,
                                   max_sigma_ratio=np.inf)
    good_cam = tr.triangulate_maps(cam, proj, *_decode(cam, proj)[:2])
    # the geometry says so: σ per projector pixel is far larger than for the ±15° cameras
    assert np.nanmedian(fit_only.sigma) > 20 * np.nanmedian(good_cam.sigma)
    pm = tr.triangulate_maps(cam_bad, proj, x, None)
    assert lit.sum() > 100
    assert pm.valid.sum() == 0
    # rejected for its geometry (or the ill-posed solve left the ray), never placed anywhere
    assert np.isin(pm.reason[lit], [tr.UNCERTAIN, tr.BEHIND]).all()
    assert pm.reason_counts()["uncertain"] > 0.5 * lit.sum()


def test_solve_along_rays_on_the_plane_gives_infinite_sigma():
    _, proj = _rig()
    # a ray inside the column plane x = cx (through the projector centre's column)
    o = proj.center_world + 0.1 * proj.T_cam_world.R[1]
    d = proj.T_cam_world.R[2]  # projector's optical axis: stays on column x = cx
    fit = tr.solve_along_rays(o[None], d[None], proj, np.array([[proj.cx, np.nan]]),
                              np.array([[0.3, 0.3]]))
    assert not np.isfinite(fit.sigma_t[0]) or fit.sigma_t[0] > 1e3


def test_wrong_y_codes_are_inconsistent():
    """x right, y off by 6 projector px in a patch: the camera–projector residual catches it."""
    cams, proj = _rig()
    cam = cams[1]
    x, y, lit, _p = _decode(cam, proj, noise=0.05)
    patch = np.zeros(lit.shape, bool)
    patch[50:60, 30:45] = True
    patch &= lit
    y = y.copy()
    y[patch] += 6.0
    pm = tr.triangulate_maps(cam, proj, x, y, sigma_x=np.full(x.shape, 0.05),
                             sigma_y=np.full(x.shape, 0.05))
    assert patch.sum() > 50
    assert not pm.valid[patch].any()
    assert (pm.reason[patch] == tr.INCONSISTENT).mean() > 0.9
    assert pm.valid[lit & ~patch].mean() > 0.9


def test_isolated_wrong_codes_give_no_wild_points():
    """Random codes at 2 % of pixels with full confidence (a decoder's wrong bits)."""
    cams, proj = _rig()
    cam = cams[0]
    x, _, lit, _p = _decode(cam, proj, noise=0.1)
    rng = np.random.default_rng(1)
    bad = lit & (rng.random(lit.shape) < 0.02)
    x = x.copy()
    x[bad] = rng.uniform(0, proj.width, bad.sum())
    pm = tr.triangulate_maps(cam, proj, x, None)
    d = _dist_to_sphere(pm.p_world[pm.valid])
    assert d.max() < TOL_WILD_M, d.max()
    wrong_px = bad & (np.abs(x - _decode(cam, proj)[0]) > 3)
    assert (~pm.valid[wrong_px]).mean() > 0.9


def test_low_confidence_pixels_get_no_point():
    """Saturated / unreliable pixels: the decoder's confidence decides, not the code."""
    cams, proj = _rig()
    x, y, lit, _ = _decode(cams[0], proj)
    conf = np.ones(x.shape, np.float32)
    conf[:, :40] = 0.05
    pm = tr.triangulate_maps(cams[0], proj, x, y, confidence=conf)
    assert not pm.valid[:, :40].any()
    assert (pm.reason[:, :40][lit[:, :40]] == tr.NO_CODE).all()
    assert pm.valid[:, 40:].sum() > 0.9 * lit[:, 40:].sum()


def test_depth_discontinuity_is_down_weighted_by_the_footprint():
    cams, proj = _rig()
    cam = cams[0]
    x, y, lit, _ = _decode(cam, proj, noise=0.05)
    pm = tr.triangulate_maps(cam, proj, x, y, max_sigma_ratio=np.inf, spike_sigmas=np.inf,
                             spike_floor=np.inf)
    # silhouette pixels (a lit pixel beside an unlit one) vs the interior
    from scipy.ndimage import binary_erosion

    interior = binary_erosion(lit, iterations=3)
    s_int = np.median(pm.sigma[interior & pm.valid])
    jump = x.copy()
    jump[:, 40:] += 30.0  # a code jump of 30 px between columns 39 and 40 (an occlusion)
    pj = tr.triangulate_maps(cam, proj, jump, None, max_sigma_ratio=np.inf,
                             spike_sigmas=np.inf, spike_floor=np.inf)
    edge = lit[:, 39] & lit[:, 40]
    assert edge.sum() > 5
    assert np.all(pj.sigma[edge, 39] > 5 * s_int)
    assert np.all(tr.triangulate_maps(cam, proj, jump, None).reason[edge, 39:41] != tr.OK)


@pytest.mark.parametrize("shift", [40.0, -40.0])
def test_fusion_rejects_wrong_patches_and_averages_agreeing_points(shift):
    cams, proj = _rig()
    maps = []
    for i, cam in enumerate(cams):
        x, y, _lit, _ = _decode(cam, proj, noise=0.1, seed=i, with_y=i != 0)
        if i == 0:  # a patch of camera 0 decoded 40 px off (a flipped Gray bit), x only
            x = x.copy()
            x[40:60, 30:50] += shift
        maps.append(tr.triangulate_maps(cam, proj, x, y, spike_sigmas=np.inf,
                                        spike_floor=np.inf))
    before = [m.valid.copy() for m in maps]
    d_before = _dist_to_sphere(maps[0].p_world[before[0]])
    assert d_before.max() > 10e-3  # the bad patch made wild points ...
    fused = tr.fuse_cameras(maps, cams)
    d = _dist_to_sphere(fused.p_world)
    assert d.max() < TOL_WILD_M  # ... that fusion removed (or they were never kept)
    assert ((maps[0].reason == tr.OCCLUDED_VIEW) | (maps[0].reason == tr.OUTLIER)).sum() > 100
    # averaging: confirmed points are closer to the surface than single-camera ones
    single = np.concatenate([_dist_to_sphere(m.p_world[m.valid]) for m in maps])
    assert fused.confirmed.mean() > 0.5
    assert np.sqrt(np.mean(d[fused.confirmed] ** 2)) < 0.85 * np.sqrt(np.mean(single**2))
    assert np.all(fused.sigma[fused.confirmed] < maps[0].sigma[maps[0].valid].max())
    # normals would be oriented toward these cameras
    assert np.all(np.einsum("ij,ij->i", fused.view_dirs, fused.p_world - SPHERE_C) > 0)


def test_camera_pair_through_codes_without_projector_calibration():
    cams, proj = _rig()
    xa, ya, lita, pa = _decode(cams[0], proj)
    xb, yb, _, _ = _decode(cams[1], proj)
    pm = tr.triangulate_camera_pair(cams[0], cams[1], xa, ya, xb, yb)
    v = pm.valid
    assert v.sum() > 0.7 * lita.sum()
    err = np.linalg.norm(pm.p_world - pa, axis=-1)[v]
    assert np.sqrt(np.mean(err**2)) < TOL_PAIR_RMS_M, np.sqrt(np.mean(err**2))
    assert _dist_to_sphere(pm.p_world[v]).max() < TOL_WILD_M


def test_swapped_cameras_fail():
    """Using camera 1's maps with camera 0's pose does not reproduce the surface."""
    cams, proj = _rig()
    x, y, lit, _p = _decode(cams[1], proj)
    pm = tr.triangulate_maps(cams[0].replace(K=cams[1].K, dist=cams[1].dist), proj, x, y)
    d = _dist_to_sphere(pm.p_world[pm.valid])
    assert pm.valid.sum() < 0.5 * lit.sum() or np.median(d) > 1e-3


def test_bad_inputs_name_the_argument():
    cams, proj = _rig()
    x, y, _, _ = _decode(cams[0], proj)
    with pytest.raises(ShapeError, match="x: expected the camera"):
        tr.triangulate_maps(cams[0], proj, x[:-1], None)
    with pytest.raises(ShapeError, match="y: expected shape"):
        tr.triangulate_maps(cams[0], proj, x, y[:, :-1])
    with pytest.raises(InputError, match="default_sigma_px"):
        tr.triangulate_maps(cams[0], proj, x, y, default_sigma_px=0)
    with pytest.raises(InputError, match="maps, cameras"):
        tr.fuse_cameras([], [])
    with pytest.raises(InputError, match="k: expected >= 3"):
        tr.match_projector_codes(x, y, x, y, k=2)


# ---------------------------------------------------------------- the tiny synthetic scan


@pytest.fixture(scope="module")
def tiny_scan(tmp_path_factory):
    from facegeo.capture.scan import load_scan
    from facegeo.synth.capture import generate_scan

    root = tmp_path_factory.mktemp("tri") / "tiny"
    generate_scan(root, "tiny")
    return load_scan(root)


def test_projector_shadow_with_garbage_codes_gives_no_wild_point(tiny_scan):
    """Beside the nose the projector casts a shadow; a decoder may emit garbage there."""
    from facegeo.geometry.mesh import surface_errors
    from facegeo.geometry.rig import Rig
    from facegeo.pipeline.mesh import _load_gt_mesh, ground_truth_decode

    rig = Rig.load(tiny_scan.ground_truth_path("rig"))
    V, F = _load_gt_mesh(tiny_scan)
    rng = np.random.default_rng(0)
    maps, cams, n_shadow = [], [], 0
    for name in tiny_scan.camera_names:
        d = ground_truth_decode(tiny_scan, name, noise_px=0.1)
        sh = d["shadow"]
        n_shadow += int(sh.sum())
        x, y = d["x"].copy(), d["y"].copy()
        x[sh] = rng.uniform(0, rig.projector.width, sh.sum())
        y[sh] = rng.uniform(0, rig.projector.height, sh.sum())
        cam = rig.camera(name)
        pm = tr.triangulate_maps(cam, rig.projector, x, y, sigma_x=d["sigma_x"],
                                 sigma_y=d["sigma_y"])
        assert (pm.valid & sh).sum() <= 0.02 * sh.sum()
        maps.append(pm)
        cams.append(cam)
    assert n_shadow > 20
    fused = tr.fuse_cameras(maps, cams)
    dist = surface_errors(fused.p_world, V, F)
    assert dist.max() < TOL_WILD_M, dist.max()


def test_grazing_pixels_have_honest_sigma(tiny_scan):
    """Where the surface turns away from the camera, surviving points' errors stay within 5 σ."""
    from facegeo.geometry.rig import Rig
    from facegeo.pipeline.mesh import ground_truth_decode

    rig = Rig.load(tiny_scan.ground_truth_path("rig"))
    name = tiny_scan.camera_names[0]
    cam = rig.camera(name)
    d = ground_truth_decode(tiny_scan, name, noise_px=0.1, seed=2)
    with np.load(tiny_scan.ground_truth_path(f"geometry_{name}")) as g:
        n = g["n_world"]
    v = cam.center_world - d["p_world"]
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore"):
        grazing = d["valid"] & (np.einsum("...i,...i->...", n, v) < np.cos(np.radians(75)))
    pm = tr.triangulate_maps(cam, rig.projector, d["x"], d["y"], sigma_x=d["sigma_x"],
                             sigma_y=d["sigma_y"])
    assert grazing.sum() > 10
    keep = grazing & pm.valid
    err = np.linalg.norm(pm.p_world - d["p_world"], axis=-1)
    assert np.all(err[keep] < 5 * pm.sigma[keep] + 1e-4)
    # grazing points carry more uncertainty than the face on average
    assert np.median(pm.sigma[keep]) > np.median(pm.sigma[pm.valid & ~grazing]) or keep.sum() == 0
