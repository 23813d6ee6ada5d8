"""The projector's joint or separate solve, chosen per scan by held-out projector corners.

``facegeo.pipeline._calibrate_projector.projector_rig`` refines the projector jointly with the
cameras or keeps its separate solve (pose only in the rig), whichever predicts the projector's
corners of a held-out pose better from the board the cameras place (leave one projector pose
out; the separate solve only when its gain exceeds one standard error). Corner-level synthetic
rigs (no images): two 640 × 480 cameras with 10 board views of their own, a 800 × 600 projector
seeing ``n`` more poses with the cameras, a 9 × 6 board at 0.7 m, tilts up to ±0.5 rad.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from facegeo.frames import Pose, look_at
from facegeo.geometry.camera import Camera

#: cameras' corners, px RMS
CAMERA_NOISE_PX = 0.1
#: the unbiased rig: projector corners' noise, px (4 views of it leave focal and distance
#: traded in a separate solve)
PROJECTOR_NOISE_PX = 0.2
#: the biased rig: projector corners' noise, px (its separate solve is exact to 1e-4) ...
PRECISE_PROJECTOR_NOISE_PX = 0.01
#: ... and the cameras' corners of each projector pose shifted together by a random offset of
#: this σ per axis, px (a board the cameras mis-locate per view: the joint solve pulls the
#: projector's intrinsics after it)
CAMERA_VIEW_BIAS_PX = 2.0
#: the separate solve kept (seed 2: gain 3.0 standard errors): its focal within this of the
#: truth, max |f/f_true − 1| (measured 1.4e-4) while the joint solve's is off by more than
#: JOINT_OFF_REL (measured 3.4e-3). The held-out corners' noise floor is the held-out board's
#: own offset (≈ 2–3 px RMS here), so on other draws of this rig the gain stays within its
#: noise and the joint solve is kept although its focal is 2–7 % off (seeds 0, 1, 3 of 4):
#: the choice answers for the camera-to-projector correspondence, not for the focal alone
SEPARATE_FOCAL_REL = 1e-3
JOINT_OFF_REL = 2e-3
#: ... and its pose solved in the rig: centre against the truth's in camera a's frame, metres
#: (measured 0.027: the cameras' own focal is 4 % off through the offset boards; left at its
#: separate solve's frame the centre would be 0.14 m off)
PROJECTOR_CENTRE_M = 0.05

PROJ_K = np.array([[1000.0, 0.0, 395.0], [0.0, 998.0, 310.0], [0.0, 0.0, 1.0]])
MODELS = {"a": "pinhole", "b": "pinhole", "proj": "pinhole"}


def _board(nx=9, ny=6, square=0.03):
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny)), -1).reshape(-1, 2) * square
    return np.c_[g - g.mean(0), np.zeros(len(g))]


def _rig(seed, n_proj, proj_noise, view_bias):
    """``(obs, init, true projector)`` for :func:`projector_rig`: the cameras' own views
    ``v*``, projector poses ``p*`` seen by both cameras and the projector; ``init`` the
    cameras' and the projector's separate pinhole solves."""
    from facegeo.geometry.calibration import calibrate_camera

    rng = np.random.default_rng(seed)
    K = np.array([[900.0, 0, 322.0], [0, 903.0, 238.0], [0, 0, 1]])
    cams = [Camera("a", 640, 480, K, None, look_at([-0.12, 0, 0], [0, 0, 0.7])),
            Camera("b", 640, 480, K * [[1.01], [1], [1]], None,
                   look_at([0.12, 0, 0], [0, 0, 0.7]))]
    proj = Camera("proj", 800, 600, PROJ_K, None, look_at([0.0, -0.08, 0.0], [0, 0, 0.7]))
    P = _board()
    obs = {c.name: {} for c in cams + [proj]}

    def add(key, who, bias):
        while True:  # a pose every device sees whole
            R = cv2.Rodrigues(rng.uniform(-0.5, 0.5, 3))[0]
            T = Pose(R, np.array([0, 0, 0.7]) + rng.uniform(-0.06, 0.06, 3))
            qs = [c.project(T.apply(P)) for c in who]
            if all(f.all() and c.in_image(q).all() for c, (q, f) in zip(who, qs)):
                break
        for c, (q, _) in zip(who, qs):
            if c is proj:
                obs[c.name][key] = (P, q + rng.normal(0, proj_noise, q.shape))
            else:
                obs[c.name][key] = (P, q + rng.normal(0, CAMERA_NOISE_PX, q.shape)
                                    + rng.normal(0, bias, 2))

    for v in range(10):
        add(f"v{v}", cams, 0.0)
    for v in range(n_proj):
        add(f"p{v}", cams + [proj], view_bias)
    init = {}
    for c in cams + [proj]:
        vs = list(obs[c.name].values())
        init[c.name] = calibrate_camera([p for p, _ in vs], [q for _, q in vs], c.size,
                                        model="pinhole", name=c.name,
                                        reject_views=c is not proj).camera
    return obs, init, proj


def _choose(obs, init):
    from facegeo.pipeline._calibrate_projector import projector_rig

    return projector_rig(obs, init, "proj", "pinhole", reference="a", loss="linear",
                         models=MODELS, refine={"a", "b"})


def _focal_rel(c) -> float:
    fx, fy = (c["fx"], c["fy"]) if isinstance(c, dict) else (c.fx, c.fy)
    return max(abs(fx / PROJ_K[0, 0] - 1), abs(fy / PROJ_K[1, 1] - 1))


def test_separate_solve_kept_when_the_cameras_mislocate_the_boards():
    """Cameras whose board of each projector pose is off by a per-view offset: the joint solve
    pulls the projector's focal off, the held-out corners say so (the separate solve's gain
    exceeds its standard error), and the rig keeps the separate intrinsics exactly, solving the
    projector's pose only."""
    obs, init, proj = _rig(2, 6, PRECISE_PROJECTOR_NOISE_PX, CAMERA_VIEW_BIAS_PX)
    rig, ch = _choose(obs, init)
    assert ch["solve"] == "separate", ch["solve_reason"]
    assert ch["solve_held_out_poses"] == 6
    sc = ch["solve_held_out_rms_px"]
    assert sc["separate"] < sc["joint"]
    assert ch["solve_gain_px2"] > ch["solve_gain_se_px2"] > 0
    out = rig.camera("proj")
    np.testing.assert_array_equal(out.K, init["proj"].K)  # not refined
    assert _focal_rel(out) < SEPARATE_FOCAL_REL
    assert _focal_rel(ch["joint_intrinsics"]) > JOINT_OFF_REL
    # the pose was solved in the rig (camera a's frame): the projector's centre near the truth's
    c_true = look_at([-0.12, 0, 0], [0, 0, 0.7]).apply(proj.center_world)
    assert np.linalg.norm(rig.camera("a").T_cam_world.apply(out.center_world) - c_true) \
        < PROJECTOR_CENTRE_M
    assert ch["solve_reason"].startswith("separate: held-out projector corners")


def test_joint_solve_kept_on_a_sound_rig():
    """Unbiased cameras and a projector seen in few noisy poses (its separate solve trades
    focal and distance): the joint solve predicts the held-out corners better and is kept —
    the rig's projector is the joint one, and its focal beats the separate solve's."""
    obs, init, proj = _rig(0, 4, PROJECTOR_NOISE_PX, 0.0)
    rig, ch = _choose(obs, init)
    assert ch["solve"] == "joint", ch["solve_reason"]
    sc = ch["solve_held_out_rms_px"]
    assert sc["joint"] < sc["separate"] and ch["solve_gain_px2"] < 0
    out = rig.camera("proj")
    assert {k: float(getattr(out, k)) for k in ("fx", "fy", "cx", "cy")} \
        == ch["joint_intrinsics"]
    assert _focal_rel(out) < _focal_rel(init["proj"])  # measured 1.5e-3 against 2.3e-3
    assert "not above the noise" in ch["solve_reason"]


def test_too_few_projector_poses_keep_the_joint_solve_unscored():
    """Three projector poses (holding one out would leave the separate solve two): joint,
    unscored, said so."""
    from facegeo.pipeline._calibrate_projector import CHOICE_MIN_VIEWS

    obs, init, _ = _rig(1, CHOICE_MIN_VIEWS - 1, PROJECTOR_NOISE_PX, 0.0)
    rig, ch = _choose(obs, init)
    assert ch["solve"] == "joint" and ch["solve_held_out_poses"] == 0
    assert ch["solve_held_out_rms_px"] == {"joint": None, "separate": None}
    assert "not scored" in ch["solve_reason"]


@pytest.mark.parametrize("bias", [0.0, CAMERA_VIEW_BIAS_PX])
def test_choice_is_the_lower_held_out_score(bias):
    """Whatever it chooses, the choice follows the recorded scores: separate only where its
    per-pose gain exceeds the noise."""
    obs, init, _ = _rig(3, 6, PRECISE_PROJECTOR_NOISE_PX, bias)
    _, ch = _choose(obs, init)
    g, se = ch["solve_gain_px2"], ch["solve_gain_se_px2"]
    assert ch["solve"] == ("separate" if g > se else "joint")
    sc = ch["solve_held_out_rms_px"]
    if ch["solve"] == "separate":
        assert sc["separate"] < sc["joint"]


def test_a_fold_that_does_not_solve_is_left_out_of_the_score(monkeypatch):
    """A separate solve that fails without one pose (here by hand: ``InputError``) leaves that
    pose unscored; the others decide, and the stage does not stop."""
    import facegeo.geometry.calibration as gc
    from facegeo.errors import InputError

    obs, init, _ = _rig(0, 5, PROJECTOR_NOISE_PX, 0.0)
    orig = gc.calibrate_camera

    def failing(P, Q, size, **kw):
        if kw.get("name") == "proj" and len(P) == 4 and not any(
                np.array_equal(q, obs["proj"]["p0"][1]) for q in Q):
            raise InputError("no solve without p0 (the test's)")
        return orig(P, Q, size, **kw)

    monkeypatch.setattr(gc, "calibrate_camera", failing)
    _, ch = _choose(obs, init)
    assert ch["solve_held_out_poses"] == 4
    assert ch["solve"] in ("joint", "separate") and ch["solve_held_out_rms_px"]["joint"] > 0
