"""OpenCV's legacy ChArUco pattern in the board description (issue 35): the ``legacy`` key,
and a set of views read both ways where the description leaves it open."""

from __future__ import annotations

import json

import numpy as np
import pytest

from facegeo.errors import InputError
from facegeo.frames import Pose
from facegeo.geometry.board import CharucoBoard, random_board_poses
from facegeo.geometry.calibration import charuco_reading, detect_boards
from facegeo.geometry.camera import Camera

#: views rendered per test set, and the corners a legacy board's correct reading must find
#: in each (of 7 × 5 = 35 inner corners; measured 35 in every view)
N_VIEWS = 2
MIN_CORNERS_RIGHT_READING = 30
#: the wrong reading interpolates at most this fraction of the right one's corners (measured 0)
WRONG_READING_MAX_FRACTION = 0.2


def _views(board, n=N_VIEWS, seed=3):
    cam = Camera("cam", 800, 600, np.array([[900.0, 0, 401.5], [0, 905.0, 297.2], [0, 0, 1]]),
                 np.zeros(0), Pose.identity())
    poses = random_board_poses(cam, n, np.random.default_rng(seed), board=board,
                               tilt_deg=(5.0, 25.0), fill=(0.5, 0.7))
    return [board.render(cam, T, supersample=2).to_uint8() for T in poses]


def test_legacy_key_round_trips_and_auto_is_undeclared():
    b = CharucoBoard(8, 6, 0.03, 0.022, "DICT_4X4_50", legacy=True)
    d = b.to_dict()
    assert d["legacy"] is True and CharucoBoard.from_dict(json.loads(json.dumps(d))) == b
    plain = CharucoBoard(8, 6, 0.03, 0.022, "DICT_4X4_50")
    assert "legacy" not in plain.to_dict()  # version-1 files unchanged
    assert CharucoBoard.from_dict({**plain.to_dict(), "legacy": "auto"}).legacy is None
    with pytest.raises(InputError, match="legacy: expected true, false or \"auto\""):
        CharucoBoard.from_dict({**plain.to_dict(), "legacy": "yes"})
    with pytest.raises(InputError, match="legacy"):
        CharucoBoard(8, 6, 0.03, 0.022, "DICT_4X4_50", legacy="yes")


def test_reading_follows_setting_then_description_then_row_parity():
    even = CharucoBoard(8, 6, 0.03, 0.022, "DICT_4X4_50")
    odd = CharucoBoard(8, 5, 0.03, 0.022, "DICT_4X4_50")
    assert even.legacy_matters and not odd.legacy_matters
    assert charuco_reading(even) is None  # open: read both ways
    assert charuco_reading(odd) is False  # the same board either way
    assert charuco_reading(even.with_legacy(True)) is True
    assert charuco_reading(even.with_legacy(True), legacy=False) is False  # the setting wins


@pytest.mark.parametrize("printed_legacy", [True, False])
def test_undeclared_even_row_board_is_read_the_way_it_was_printed(printed_legacy):
    """Views of a 8 × 6 board printed in either pattern, described without ``legacy``: the
    set is read both ways and the right reading kept (every detection says which); the
    description that states the wrong pattern finds (next to) nothing — what auto-detection
    saves a user from."""
    printed = CharucoBoard(8, 6, 0.03, 0.022, "DICT_4X4_50", legacy=printed_legacy)
    images = _views(printed)
    described = printed.with_legacy(None)
    dets = detect_boards(images, described)
    assert all(d.found and d.legacy is printed_legacy for d in dets), [d.reason for d in dets]
    assert min(d.n_corners for d in dets) >= MIN_CORNERS_RIGHT_READING
    wrong = detect_boards(images, described.with_legacy(not printed_legacy))
    n_wrong = sum(d.n_corners for d in wrong if d.found)
    assert n_wrong <= WRONG_READING_MAX_FRACTION * sum(d.n_corners for d in dets)
    # the declared right pattern reads the same corners without the second reading
    right = detect_boards(images, described.with_legacy(printed_legacy))
    for a, b in zip(dets, right):
        assert np.array_equal(a.ids, b.ids) and np.array_equal(a.q, b.q)
