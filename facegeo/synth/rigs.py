"""The synthetic capture's rigs: the cameras of a multi-camera band, the true rig's seeded
errors (cameras, projector, and on request the lights' calibration error), the calibration-only
witness camera, and which cameras see the projector-calibration views.

:mod:`facegeo.synth.capture` builds its scans with these; they are public for tests and
benchmarks that need the same rigs without writing a scan.
"""

from __future__ import annotations

import numbers

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError
from facegeo.frames import Pose, look_at, rotation_from_rvec

__all__ = ["LIGHT_PERTURBATION", "PROJECTOR_VIEW_MAX_ANGLE_DEG", "RIG_PERTURBATION", "RING_BAND",
           "WITNESS_ANGLE_DEG", "WITNESS_ENV", "WITNESS_NAME", "WITNESS_SUPERSAMPLE",
           "perturbed_lights", "perturbed_rig", "projector_view_cameras", "ring_cameras",
           "witness_camera", "witness_weights"]

#: Band of :func:`ring_cameras`: yaw of the outermost cameras from +Z (degrees; a shared
#: calibration board must stay within 75° of every camera's view, so ±56° rather than a full
#: ring), distance from the head centre (m) and the two rows' elevations (degrees).
RING_BAND = {"yaw_deg": 56.0, "distance_m": 1.10, "elevation_deg": (7.0, -5.0)}

#: How far the true rig departs from the nominal one (1 σ): what a calibration must recover.
RIG_PERTURBATION = {"position_m": 0.002, "rotation_deg": 0.2, "focal_rel": 0.005,
                    "principal_px": 3.0, "k1": 0.01}


def perturbed_rig(rig, seed: int):
    """The rig as built: the nominal ``rig`` with seeded errors of the sizes in
    :data:`RIG_PERTURBATION` in every camera's and the projector's pose and intrinsics.

    The synthetic capture renders with this true rig and writes the nominal one as the scan's
    ``rig.json`` — what a real rig's owner knows before calibration — and the true one to
    ``ground_truth/rig.json``, so calibration has something real to recover. The lights stay
    exact here; ``generate_scan(light_error_deg=…)`` gives ``rig.json`` a light list off by a
    light-stage calibration error (:func:`perturbed_lights`).
    """
    from facegeo.geometry.rig import Rig

    rng = np.random.default_rng([seed, 7])
    cams = [_jittered_camera(c, rng, distortion=True) for c in rig.cameras]
    proj = (None if rig.projector is None
            else _jittered_camera(rig.projector, rng, distortion=False))
    return Rig(cameras=cams, projector=proj, lights=rig.lights)


def _jittered_camera(cam, rng, *, distortion: bool):
    """``cam`` with seeded errors of the sizes in :data:`RIG_PERTURBATION` (draws from ``rng``
    in a fixed order: fx, fy, principal point, k1, rotation, position)."""
    P = RIG_PERTURBATION
    K = cam.K.copy()
    K[0, 0] *= 1 + P["focal_rel"] * rng.standard_normal()
    K[1, 1] *= 1 + P["focal_rel"] * rng.standard_normal()
    # principal_px is at a 480-px-wide image; scale to this image
    K[:2, 2] += P["principal_px"] * (cam.width / 480.0) * rng.standard_normal(2)
    dist = cam.dist.copy()
    if distortion and dist.size:
        dist[0] += P["k1"] * rng.standard_normal()
    # perturb the camera's pose in the world: rotate about and move its centre
    dR = rotation_from_rvec(np.deg2rad(P["rotation_deg"]) * rng.standard_normal(3))
    c = cam.center_world + P["position_m"] * rng.standard_normal(3)
    R = dR @ cam.T_cam_world.R
    return cam.replace(K=K, dist=dist, T_cam_world=Pose(R, -R @ c))


#: A light-stage calibration error (1 σ) for ``generate_scan(light_error_deg=…)``: the order
#: a mirror-ball or arm-encoder light calibration leaves, ≈ 0.5° of direction per tangent axis
#: and 5 mm of distance for lights at 1.5 m (an assumption of this generator, not a figure
#: measured on a particular stage).
LIGHT_PERTURBATION = {"direction_deg": 0.5, "radius_m": 0.005}


def perturbed_lights(lights, seed: int, direction_deg: float, radius_m: float | None = None):
    """The light-stage grid ``lights`` as a light list whose every light is moved by a seeded
    calibration error: its direction rotated by ``direction_deg`` (1 σ per tangent axis) and,
    for near-field lights, its distance changed by ``radius_m`` (1 σ; default
    ``LIGHT_PERTURBATION["radius_m"] × direction_deg / LIGHT_PERTURBATION["direction_deg"]``).

    Names ``"0000"`` … in light-index order (the grid's theta-fastest order, so file numbers are
    unchanged), the grid's colour as every light's intensity, δA the list's own (Voronoi cells
    of the perturbed directions, what every stage integrating over a list uses; the grid's
    ``"paper"`` δA sum to more than 4π, 12.65 sr at 16 × 8, which a list refuses). The scan's
    ``rig.json`` carries this list — what the owner believes — and ``ground_truth/rig.json``
    the grid the frames were rendered with.
    """
    from facegeo.geometry.lights import LightList

    if (isinstance(direction_deg, bool) or not isinstance(direction_deg, numbers.Real)
            or not np.isfinite(float(direction_deg)) or float(direction_deg) < 0):
        raise InputError(f"light_error_deg: expected a finite number >= 0, got "
                         f"{fmt_value(direction_deg)}")
    P = LIGHT_PERTURBATION
    if radius_m is None:
        radius_m = P["radius_m"] * float(direction_deg) / P["direction_deg"]
    rng = np.random.default_rng([seed, 11])
    v = lights.directions
    # rotate each direction about a random tangent axis: a 2-D Gaussian angle in its tangent plane
    a = np.where(np.abs(v[:, 1:2]) < 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(v, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(v, t1)
    d = np.radians(float(direction_deg)) * rng.standard_normal((len(v), 2))
    v2 = v + d[:, :1] * t1 + d[:, 1:] * t2
    v2 /= np.linalg.norm(v2, axis=1, keepdims=True)
    n = lights.n_lights
    common = {"intensities": np.tile(lights.color_rgb, (n, 1)),
              "names": [f"{l:04d}" for l in range(n)],
              "center": lights.center}
    if lights.is_distant:
        return LightList(directions=v2, **common)
    r = lights.radius + float(radius_m) * rng.standard_normal(n)
    return LightList(positions=np.asarray(lights.center) + r[:, None] * v2, **common)


#: Name of the calibration-only witness camera (``generate_scan(witness=True)``).
WITNESS_NAME = "witness"
#: Smallest angle between the witness camera's direction from the head and every capture
#: camera's (degrees): a viewpoint the capture cameras do not share (issue 37: 35–45°).
WITNESS_ANGLE_DEG = 40.0
#: The environment of the witness camera's reference images: the render stage's default
#: built-in map (``facegeo.pipeline.render.builtin_env("axis_lobes")``, a 64-row lat-long
#: :func:`facegeo.lighting.envmap.axis_lobe_map`; the generator sits below ``pipeline`` and
#: builds the same map, ``tests/test_witness_camera.py`` checks they are equal).
WITNESS_ENV = "axis_lobes"
WITNESS_ENV_HEIGHT = 64
#: Rays per pixel side of the reference images: the ``reconstruct`` render stage's
#: ``RENDER_SUPERSAMPLE`` (a camera's pixel integrates its footprint; checked by the test).
WITNESS_SUPERSAMPLE = 3


def witness_camera(rig, name: str = WITNESS_NAME, angle_deg: float = WITNESS_ANGLE_DEG):
    """A camera at a viewpoint the rig's capture cameras do not share, facing the face.

    Aimed at the point where the capture cameras' optical axes meet (least squares), from
    their mean distance to it, in the direction of their mean direction tilted up (toward +Y)
    by the smallest elevation that puts it ``angle_deg`` from every capture camera's direction
    (default rig: 37.5° up, 40° from both cameras). Intrinsics and distortion: the first
    capture camera's (the same image size).
    """
    from facegeo.geometry.camera import Camera

    cams = list(rig.cameras)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cams:
        d = c.T_cam_world.R[2]
        P_perp = np.eye(3) - np.outer(d, d)
        A += P_perp
        b += P_perp @ c.center_world
    aim = np.linalg.lstsq(A, b, rcond=None)[0]
    off = np.array([c.center_world - aim for c in cams])
    dist = float(np.linalg.norm(off, axis=1).mean())
    dirs = off / np.linalg.norm(off, axis=1, keepdims=True)
    u = dirs.mean(axis=0)
    u /= np.linalg.norm(u)
    up = np.array([0.0, 1.0, 0.0]) - u[1] * u
    up /= np.linalg.norm(up)
    cos_max = np.cos(np.radians(angle_deg))
    for e in np.radians(np.arange(0.0, 80.0, 0.1)):
        v = np.cos(e) * u + np.sin(e) * up
        if (dirs @ v).max() <= cos_max:
            break
    ref = cams[0]
    return Camera(name, ref.width, ref.height, ref.K.copy(), ref.dist.copy(),
                  look_at(aim + dist * v, aim))


def _with_witness(nominal_rig, rig, seed: int):
    """The nominal and true rigs with the witness camera appended: nominal at
    :func:`witness_camera`'s pose, true with its own seeded errors (a stream apart from the
    other cameras', so theirs are unchanged)."""
    from facegeo.geometry.rig import Rig

    w = witness_camera(nominal_rig)
    w_true = _jittered_camera(w, np.random.default_rng([seed, 7, 1]), distortion=True)
    return (Rig(cameras=list(nominal_rig.cameras) + [w], projector=nominal_rig.projector,
                lights=nominal_rig.lights),
            Rig(cameras=list(rig.cameras) + [w_true], projector=rig.projector,
                lights=rig.lights))


def witness_weights(lights) -> np.ndarray:
    """Eq. (4) weights ``(L, 3)`` of :data:`WITNESS_ENV` on ``lights``, computed as the render
    stage computes them (``light_weights(env, lights, solid_angle="paper")`` then
    ``field_weights``), so reference and render agree on the lighting."""
    from facegeo.lighting import envmap as E

    env = E.axis_lobe_map(WITNESS_ENV_HEIGHT)
    return E.field_weights(E.light_weights(env, lights, solid_angle="paper"), lights)


def ring_cameras(n: int) -> list:
    """``n`` capture cameras on a band around the head, full size (480 × 720 px), world frame.

    Camera ``cam_XX`` (``XX`` = 00 … n−1) sits at yaw ``−Y + 2Y·i/(n−1)`` about +Y from +Z
    (``Y`` = :data:`RING_BAND` ``yaw_deg``; one camera: yaw 0), alternately on the upper and
    the lower row (``elevation_deg``), :data:`RING_BAND` ``distance_m`` from the head centre,
    aimed at it: the front cameras see the face, the outer ones the cheek and the side of the
    head. Intrinsics are the default rig's ``cam_left``'s (f ≈ 2200 px) with small
    deterministic per-camera differences (fx ±1 %, fy/fx 1.003, principal point a few pixels
    off-centre, the same mild distortion scaled ±10 %), so no two cameras are identical and
    no axis is symmetric (house style: asymmetric fixtures).

    Raises
    ------
    InputError
        ``n`` is not a positive integer.
    """
    import math

    from facegeo.geometry.camera import Camera
    from facegeo.geometry.rig import default_rig

    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InputError(f"n_cameras: expected a positive integer, got {fmt_value(n)}")
    base = default_rig().cameras[0]
    Y, d = RING_BAND["yaw_deg"], RING_BAND["distance_m"]
    rows = RING_BAND["elevation_deg"]
    cams = []
    for i in range(int(n)):
        yaw = math.radians(0.0 if n == 1 else -Y + 2.0 * Y * i / (n - 1))
        el = math.radians(rows[i % len(rows)])
        eye = d * np.array([math.cos(el) * math.sin(yaw), math.sin(el),
                            math.cos(el) * math.cos(yaw)])
        fx = base.fx * (1.0 + 0.01 * math.sin(1.3 * i + 0.4))
        K = np.array([[fx, 0.0, 240.0 + 3.0 * math.cos(1.7 * i)],
                      [0.0, fx * 1.003, 360.0 + 4.0 * math.sin(2.3 * i + 0.2)],
                      [0.0, 0.0, 1.0]])
        dist = base.dist * (1.0 + 0.1 * math.cos(0.9 * i))
        cams.append(Camera(f"cam_{i:02d}", base.width, base.height, K, dist,
                           look_at(eye, np.zeros(3))))
    return cams


#: A camera sees the projector-calibration views when its optical axis is within this angle of
#: the projector's (degrees): both of the default rig's cameras (≈ 16°), the six middle ones of
#: a 16-camera :func:`ring_cameras` band (a board seen whole by the projector and cameras
#: ±56° apart cannot be placed).
PROJECTOR_VIEW_MAX_ANGLE_DEG = 25.0


def projector_view_cameras(rig, *, exclude=()) -> list:
    """The capture cameras that see the projector-calibration views: optical axis within
    :data:`PROJECTOR_VIEW_MAX_ANGLE_DEG` of the projector's, names in ``exclude`` left out
    (a calibration-only camera). At least one: the nearest camera if none is that close."""
    z_p = rig.projector.T_cam_world.R[2]
    cands = [c for c in rig.cameras if c.name not in set(exclude)]
    ang = [float(np.degrees(np.arccos(np.clip(c.T_cam_world.R[2] @ z_p, -1.0, 1.0))))
           for c in cands]
    out = [c for c, a in zip(cands, ang) if a <= PROJECTOR_VIEW_MAX_ANGLE_DEG]
    return out or [cands[int(np.argmin(ang))]]
