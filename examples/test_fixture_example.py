"""Use facegeo in your own pytest suite: a scan and its reflectance field as fixtures.

Run:  python -m pytest -q examples/test_fixture_example.py

The session-scoped fixtures build a tiny synthetic scan once (a few seconds) and run
``facegeo reconstruct`` on it (atlas → project, cached under ``SCAN/out/``); tests then read the
projected surface reflectance field and the ground truth the generator wrote beside the scan.
To test against a real capture, swap ``generate_scan`` for ``load_scan("path/to/your/scan")``
and leave out what only a synthetic scan has (``ground_truth_path``: the true rig and mesh):
on a real scan ``reconstruct`` also runs the stages its data calls for (calibrate, decode,
mesh) and writes into the scan's ``out/`` (copy the scan first if it must stay untouched).
"""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.capture.scan import load_scan
from facegeo.pipeline.reconstruct import run_reconstruct
from facegeo.synth.capture import generate_scan


@pytest.fixture(scope="session")
def tiny_scan(tmp_path_factory):
    """A validated tiny synthetic scan (2 cameras, 128 lights)."""
    root = tmp_path_factory.mktemp("facegeo") / "scan"
    generate_scan(root, preset="tiny", seed=3)
    return load_scan(root)


@pytest.fixture(scope="session")
def field(tiny_scan):
    """The reconstruct products up to the projected field: ``out/atlas``, ``out/project``,
    on the generator's true rig and mesh (the default, ``"auto"``, is the whole chain: the
    calibrated rig and the reconstructed mesh, calibrate → decode → mesh first)."""
    results = run_reconstruct(tiny_scan.root, rig="ground_truth", mesh="ground_truth",
                              until="project")
    assert [r.name for r in results] == ["atlas", "project"]
    return tiny_scan.out_dir


def test_reconstruct_is_cached(tiny_scan, field):
    # a second run finds every stage current and does no work
    again = run_reconstruct(tiny_scan.root, rig="ground_truth", mesh="ground_truth",
                            until="project")
    assert all(not r.ran for r in again)


def test_field_matches_the_frames(tiny_scan, field):
    """A texel's reflectance function is the OLAT frames sampled where the texel projects:
    bilinearly, except across a cast-shadow edge, where only the taps on the texel's side of
    the edge count (the projection's shadow-consistent taps, docs/surface.md)."""
    import cv2

    from facegeo.surface.atlas import Texels
    from facegeo.surface.reflectance import open_field

    from facegeo.geometry.rig import Rig

    cam = tiny_scan.camera_names[0]
    # A synthetic scan's rig.json is the nominal rig (what a user would measure before
    # calibration); the frames were rendered with the perturbed true rig in ground_truth/, and
    # the fixture projects with that one (rig="ground_truth"; the default "auto" is the
    # calibrated rig when the boards calibrate).
    camera = Rig.load(tiny_scan.ground_truth_path("rig")).camera(cam)
    R = open_field(field / "project" / cam)                 # (T_c, L, 3) float16 memory map
    index = np.load(field / "project" / cam / "texel_index.npy")
    weight = np.load(field / "project" / cam / "weight.npy")
    texels = Texels.load(field / "atlas" / "texels.npz")
    assert R.shape == (index.size, tiny_scan.n_lights, 3)

    # 50 of the most confidently seen texels (head-on, far from silhouettes and occlusions)
    pick = np.argsort(weight)[-5000::100]
    q, ok = camera.project(texels.p_world[index[pick]])
    assert ok.all()
    x0, y0 = np.floor(q[:, 0]).astype(int), np.floor(q[:, 1]).astype(int)
    for light in (0, tiny_scan.n_lights // 2):
        frame = tiny_scan.olat_frame(cam, light)             # (H, W, 3) float32, linear
        sampled = cv2.remap(frame, q[:, 0].astype(np.float32).reshape(-1, 1),
                            q[:, 1].astype(np.float32).reshape(-1, 1), cv2.INTER_LINEAR)[:, 0]
        stored = np.asarray(R[pick, light], np.float32)
        scale = float(np.abs(sampled).max()) or 1.0
        taps = np.stack([frame[y0 + dy, x0 + dx] for dy in (0, 1) for dx in (0, 1)], 1)
        lum = taps.sum(axis=2)
        edge = lum.max(axis=1) > 2 * lum.min(axis=1) + 1e-3 * scale  # lit next to shadowed
        # float16 storage: 2^-11 relative rounding of each stored sample
        np.testing.assert_allclose(stored[~edge], sampled[~edge], rtol=2e-3, atol=2e-3 * scale)
        # at an edge: a weighted mean of some of the four taps
        tol = 2e-3 * scale
        assert (stored[edge] >= taps[edge].min(axis=1) - tol).all()
        assert (stored[edge] <= taps[edge].max(axis=1) + tol).all()
