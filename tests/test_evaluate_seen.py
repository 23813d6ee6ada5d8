"""What the capture could have shown: ``facegeo.evaluate.views.seen_fraction`` and the seen
figures of a view (the co-visibility mask of novel-view benchmarks, issue 37)."""

from __future__ import annotations

import numpy as np
import pytest

#: Pixels this close (metres) to the source camera's horizon on the sphere (z = r²/d: 1 cm for
#: a 10 cm sphere seen from 1 m) are left out of the half-sphere comparison: there its rays
#: graze the surface, and which side a pixel's nine rays fall on is the sub-pixel grid's and
#: the tessellation's.
BOUNDARY_M = 0.01


def _camera(name, eye, size=96, f=220.0):
    from facegeo.frames import look_at
    from facegeo.geometry.camera import Camera

    K = np.array([[f, 0.0, (size - 1) / 2], [0.0, f, (size - 1) / 2], [0.0, 0.0, 1.0]])
    return Camera(name, size, size, K, np.zeros(0), look_at(np.asarray(eye, float), np.zeros(3)))


def _renderer(*spheres):
    """A reference renderer of spheres ``(centre, radius)`` (one mesh)."""
    import trimesh

    from facegeo.synth.render import ReferenceRenderer
    from facegeo.synth.skin import SkinField

    parts = [trimesh.creation.icosphere(subdivisions=4, radius=r).apply_translation(c)
             for c, r in spheres]
    m = trimesh.util.concatenate(parts)
    v = np.asarray(m.vertices)
    return ReferenceRenderer(v, np.asarray(m.faces, np.int64), SkinField.for_mesh(v, seed=0))


def test_a_source_camera_sees_the_half_of_a_sphere_facing_it():
    """Seen from +X, a sphere whose only source camera is on +Z: the pixels on the cap that
    camera sees (z > r²/d) are seen, the others are not; the source's own view is seen whole (but for its
    grazing rim); a pixel's share counts its rays on the surface only."""
    from facegeo.evaluate.views import seen_fraction

    r = _renderer(((0.0, 0.0, 0.0), 0.1))
    source = _camera("src", (0.0, 0.0, 1.0))
    view = r.surface_view(_camera("novel", (1.0, 0.0, 0.0)), supersample=3)
    seen = seen_fraction(view, r.rays, [source])
    assert seen.shape == view.mask.shape and seen.dtype == np.float32
    assert not seen[~view.mask].any()
    z = view.to_image(view.p_world[:, 2])  # the pixel's mean z
    horizon = 0.1 ** 2 / 1.0
    front = view.mask & (z > horizon + BOUNDARY_M)
    back = view.mask & (z < horizon - BOUNDARY_M)
    assert front.sum() > 500 and back.sum() > 500
    assert (seen[front] == 1.0).all() and (seen[back] == 0.0).all()
    own = r.surface_view(source, supersample=3)
    assert seen_fraction(own, r.rays, [source])[own.mask].mean() > 0.99
    # no camera: nothing seen; a second source behind the sphere sees the cap z < −r²/d, and
    # the band between the two horizons stays unseen
    assert not seen_fraction(view, r.rays, []).any()
    both = seen_fraction(view, r.rays, [source, _camera("behind", (0.0, 0.0, -1.0))])
    assert (both[front | (view.mask & (z < -horizon - BOUNDARY_M))] == 1.0).all()
    band = view.mask & (np.abs(z) < 0.003)
    assert band.sum() > 20 and (both[band] == 0.0).all()


def test_surface_hidden_from_the_source_behind_another_is_unseen():
    """A small sphere between the source camera and a large one hides a disc of the large
    sphere from it: exactly the points whose segment to the camera passes through the small
    sphere are unseen (checked analytically, away from the disc's edge)."""
    from facegeo.evaluate.views import seen_fraction

    big, small = ((0.0, 0.0, 0.0), 0.1), ((0.0, 0.0, 0.3), 0.04)
    eye = np.array([0.0, 0.0, 1.0])
    source = _camera("src", eye)
    r = _renderer(big, small)
    view = r.surface_view(_camera("novel", (0.5, 0.2, 0.85)), supersample=1)
    seen = seen_fraction(view, r.rays, [source])
    p = view.p_world
    on_big = np.linalg.norm(p, axis=1) < 0.1 + 1e-3
    # distance from the small sphere's centre to the segment p → eye
    d = eye - p
    t = np.clip(np.einsum("ij,ij->i", np.asarray(small[0]) - p, d) / np.einsum("ij,ij->i", d, d),
                0.0, 1.0)
    dist = np.linalg.norm(p + t[:, None] * d - np.asarray(small[0]), axis=1)
    # facing the camera, not within ≈ 6° of grazing (where the tessellated sphere may hide a
    # point from a camera its interpolated normal faces)
    facing = np.einsum("ij,ij->i", d, view.n_world) > 0.1 * np.linalg.norm(d, axis=1)
    pix = view.pixel_index  # one ray a pixel
    got = seen.ravel()[pix]
    hidden = on_big & facing & (dist < small[1] - 0.004)
    clear = on_big & facing & (dist > small[1] + 0.004)
    assert hidden.sum() > 50 and clear.sum() > 500
    assert (got[hidden] == 0.0).all() and (got[clear] == 1.0).all()
    # without the small sphere, the same points are seen
    alone = _renderer(big)
    assert seen_fraction(alone.surface_view(_camera("novel", (0.5, 0.2, 0.85))), alone.rays,
                         [source]).ravel()[pix][hidden].all()


def test_seen_figures_split_the_error_by_what_the_capture_saw():
    """``view_figures(..., seen=)``: the gain over the seen pixels, the unseen pixels' count
    and their share of the render's squared error, and the summary's worst seen gain."""
    from facegeo.evaluate.views import view_figures, views_summary

    mask = np.zeros((10, 20), bool)
    mask[2:8, 2:18] = True  # 96 px
    seen = np.zeros((10, 20), np.float32)
    seen[2:8, 2:10] = 1.0  # 48 px seen
    seen[2:8, 10] = 0.5  # 6 px partly
    ref = np.where(mask[..., None], np.float32(0.5), np.float32(0.0))
    image, naive = ref.copy(), ref.copy()
    image[2:8, 2:10] += 0.01  # seen: the render 0.01 off, the naive 0.1
    naive[2:8, 2:10] += 0.1
    image[2:8, 11:18] += 0.2  # unseen (42 px): both 0.2 off
    naive[2:8, 11:18] += 0.2
    v = {"image": image, "covered": mask, "texture": None, "naive": naive,
         "naive_texture": None, "paper": None}
    got = view_figures(v, ref, mask, head_mask=True, seen=seen)
    assert got["seen_pixels"] == 48 and got["unseen_head_pixels"] == 42
    err_seen, err_unseen = 48 * 3 * 0.01 ** 2, 42 * 3 * 0.2 ** 2
    assert got["unseen_error_share"] == pytest.approx(err_unseen / (err_seen + err_unseen),
                                                      abs=1e-5)
    assert got["psnr_gain_db_seen"] == pytest.approx(20.0, abs=1e-3)  # 10 × smaller error
    # over the whole mask the unseen pixels' shared error dilutes it to ≈ 1 dB
    whole = 10 * np.log10((48 * 3 * 0.1 ** 2 + err_unseen) / (err_seen + err_unseen))
    assert got["psnr_gain_db"] == pytest.approx(whole, abs=1e-3) and whole < 1.1
    assert "seen_pixels" not in view_figures(v, ref, mask, head_mask=True)
    s = views_summary({"a": got, "b": {**got, "psnr_gain_db_seen": 3.0}})
    assert s["psnr_gain_db_seen_min"] == 3.0
