"""The generator's calibration views reach the image's corners (issue 35):
``synth.boards.rig_calibration_views(corner_per_camera=...)``. Poses only (no rendering)."""

from __future__ import annotations

import numpy as np
import pytest

from facegeo.errors import InputError
from facegeo.synth.boards import board_coverage, rig_calibration_views

#: fraction of a 16 × 16 grid of each camera's image holding an inner board corner of some
#: view: without corner views at most ... (measured 0.36–0.45, seeds 0/1) ...
COVERAGE_WITHOUT_MAX = 0.5
#: ... and with 4 corner views per camera at least (measured 0.56–0.63)
COVERAGE_WITH_MIN = 0.53
#: a corner view's nearest inner corner from its image corner, fraction of the image size per
#: axis (CORNER_VIEWS["corner_cell"]); measured 0.08–0.099
CORNER_REACH = 0.1
#: views per camera the chain calibrates from with 12 shared views + 4 close + 4 corner views
MIN_VIEWS_PER_CAMERA = 15


@pytest.fixture(scope="module")
def rig_and_board():
    from facegeo.synth.capture import Preset, _board_for_rig, build_rig, perturbed_rig

    preset = Preset("views", 1 / 2, 4, 2, 3, (256, 192), 12, 4, 0, olat_half=False,
                    sl_supersample=1)
    rig = perturbed_rig(build_rig(preset), 0)
    return rig, _board_for_rig(rig)


def _in_image_views(board, cam, poses):
    from facegeo.geometry.board import board_points

    P = board_points(board)
    out = []
    for T in poses:
        q, front = cam.project_cam((cam.T_cam_world @ T).apply(P))
        ok = front & cam.in_image(q)
        if ok.sum() >= 6:
            out.append(q[ok])
    return out


def test_corner_views_cover_the_image_to_its_corners(rig_and_board):
    rig, board = rig_and_board
    base = rig_calibration_views(board, rig.cameras, 12, 0)
    more = rig_calibration_views(board, rig.cameras, 12, 0, corner_per_camera=4)
    # the shared and close views are drawn first and do not change
    assert all(np.allclose(a.matrix, b.matrix) for a, b in zip(base, more))
    assert len(more) == len(base) + 4 * len(rig.cameras)
    corner_views = more[len(base):]
    for cam in rig.cameras:
        w = [cam.T_cam_world @ T for T in base]
        m = [cam.T_cam_world @ T for T in more]
        assert board_coverage(board, cam, w, grid=(16, 16)) <= COVERAGE_WITHOUT_MAX
        assert board_coverage(board, cam, m, grid=(16, 16)) >= COVERAGE_WITH_MIN
        assert len(_in_image_views(board, cam, more)) >= MIN_VIEWS_PER_CAMERA
        # each image corner is reached by a corner view of this camera
        mine = corner_views[rig.cameras.index(cam)::len(rig.cameras)]
        size = np.array(cam.size, float)
        for corner in ([-0.5, -0.5], [size[0] - 0.5, -0.5], [-0.5, size[1] - 0.5],
                       size - 0.5):
            d = min(np.max(np.abs(q - corner) / size, axis=1).min()
                    for q in _in_image_views(board, cam, mine))
            assert d <= CORNER_REACH, (cam.name, corner, d)


def test_corner_views_count_is_checked(rig_and_board):
    rig, board = rig_and_board
    with pytest.raises(InputError, match="corner_per_camera: expected an integer >= 0"):
        rig_calibration_views(board, rig.cameras, 3, 0, close_per_camera=0,
                              corner_per_camera=-1)
