"""Structured-light conditions of real captures the generator reproduces (DESIGN §9).

A real two-camera Gray-code capture (issue 34) broke facegeo in two ways; the generator can make
both, at every preset:

* **Lost frames.** One camera lost four structured-light frames, declared in the manifest as
  ``[structured_light.cameras.<camera>] missing = [...]``. ``generate_scan(...,
  sl_missing={camera: [frame, ...]})`` leaves those frames unwritten and declares them;
  :data:`LOST_FRAME_PATTERNS` names ready-made sets (``"issue34"``: the real capture's, for any
  number of bits, :func:`issue34_lost_frames`).
* **Cameras that out-resolve the projector.** 4896 × 3264 cameras and a 1024 × 768 projector:
  many camera pixels share one projector pixel, so its code. ``generate_scan(...,
  projector_scale=N)`` resizes the projector so one of its pixels covers about N × N camera
  pixels on the face (:func:`camera_px_per_projector_px`, :func:`projector_size_for_scale`);
  :func:`shared_code_fraction` measures the result.

Conventions: projector coordinates ``q = (x, y)`` in projector pixels, integer coordinates at
pixel centres (docs/conventions.md), so the projector pixel — the integer code a perfect
decoder gives — is ``floor(q + 0.5)``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from facegeo.checks import as_array, fmt_value
from facegeo.errors import InputError

__all__ = [
    "LOST_FRAME_PATTERNS",
    "camera_px_per_projector_px",
    "check_projector_scale",
    "check_sl_phase_steps",
    "issue34_lost_frames",
    "projector_coordinates",
    "resolve_lost_frames",
    "projector_size_for_scale",
    "shared_code_fraction",
]


# ---------------------------------------------------------------------------- lost frames


def issue34_lost_frames(spec) -> list[str]:
    """The frames issue 34's camera lost, for the bits of ``spec``.

    The real capture (10 column and 10 row bits, MSB = bit 0) lost column bit 9's pattern frame,
    both frames of row bit 8 and row bit 9's inverse: the last column bit's pattern frame, both
    frames of the second-to-last row bit and the last row bit's inverse. With ``n_x`` / ``n_y``
    bits, in capture order::

        {c}_x_{n_x-1}, {c}_y_{n_y-2}, {c}_y_{n_y-2}_inv, {c}_y_{n_y-1}_inv

    ``c`` the first code family of ``spec.codes`` (``"gray"`` by default).

    Parameters
    ----------
    spec : facegeo.geometry.structured_light.PatternSpec

    Returns
    -------
    list of str
        Frame names, each one of ``pattern_names(spec)``.

    Raises
    ------
    InputError
        ``spec`` has no inverse frames, no column bit or fewer than two row bits.
    """
    n_x, n_y = spec.n_bits("x"), spec.n_bits("y")
    if not spec.inverse or n_x < 1 or n_y < 2:
        raise InputError(
            f"sl_missing 'issue34': needs Gray code with inverse frames, >= 1 column bit and >= 2 "
            f"row bits; the pattern spec has inverse={spec.inverse}, {n_x} column and {n_y} row "
            "bits")
    c = spec.codes[0]
    return [f"{c}_x_{n_x - 1:02d}", f"{c}_y_{n_y - 2:02d}", f"{c}_y_{n_y - 2:02d}_inv",
            f"{c}_y_{n_y - 1:02d}_inv"]


#: Named sets of lost structured-light frames: name → function(PatternSpec) → frame names.
#: ``generate_scan(..., sl_missing={camera: NAME})`` uses one.
LOST_FRAME_PATTERNS: dict[str, Callable[..., list[str]]] = {
    "issue34": issue34_lost_frames,
}


def resolve_lost_frames(sl_missing, camera_names: Sequence[str],
                        frame_names: Sequence[str], spec) -> dict[str, list[str]]:
    """Check ``generate_scan``'s ``sl_missing`` and expand its named patterns.

    Parameters
    ----------
    sl_missing : mapping of str to (sequence of str or str), or None
        Camera name → the structured-light frames it lost: frame names, or the name of a
        pattern in :data:`LOST_FRAME_PATTERNS`.
    camera_names : sequence of str
        The rig's capture cameras.
    frame_names : sequence of str
        The structured-light frames in capture order (``pattern_names(spec)``).
    spec : PatternSpec
        The patterns (for the named sets).

    Returns
    -------
    dict of str to list of str
        Camera → lost frames in capture order; cameras that lose none are left out.

    Raises
    ------
    InputError
        Not a mapping; an unknown camera or frame (the message lists the valid ones), an unknown
        pattern name, a repeated frame, or a camera that would lose every frame.
    """
    if sl_missing is None:
        return {}
    if not isinstance(sl_missing, Mapping):
        raise InputError(f"sl_missing: expected a mapping camera -> frame names, got "
                         f"{type(sl_missing).__name__}")
    order = {f: i for i, f in enumerate(frame_names)}
    out: dict[str, list[str]] = {}
    for cam, frames in sl_missing.items():
        if cam not in camera_names:
            raise InputError(f"sl_missing: unknown camera {fmt_value(cam)}; the rig's cameras are "
                             f"{', '.join(camera_names)}")
        if isinstance(frames, str):
            if frames not in LOST_FRAME_PATTERNS:
                raise InputError(
                    f"sl_missing[{cam!r}]: unknown pattern {fmt_value(frames)}; expected a list of "
                    f"frame names or one of {', '.join(LOST_FRAME_PATTERNS)}")
            frames = LOST_FRAME_PATTERNS[frames](spec)
        elif not isinstance(frames, Sequence) or not all(isinstance(f, str) for f in frames):
            raise InputError(f"sl_missing[{cam!r}]: expected a list of frame names or a pattern "
                             f"name ({', '.join(LOST_FRAME_PATTERNS)}), got {fmt_value(frames)}")
        unknown = [f for f in frames if f not in order]
        if unknown:
            raise InputError(
                f"sl_missing[{cam!r}]: unknown frame(s) {', '.join(map(repr, unknown))}; this "
                f"scan's structured-light frames are {', '.join(frame_names)}")
        if len(set(frames)) != len(frames):
            raise InputError(f"sl_missing[{cam!r}]: a frame is listed twice in {list(frames)}")
        if len(frames) == len(order):
            raise InputError(f"sl_missing[{cam!r}]: every structured-light frame is listed; a "
                             "camera must keep at least one")
        if frames:
            out[cam] = sorted(frames, key=order.__getitem__)
    return out


# ---------------------------------------------------------------------------- projector resolution


def check_projector_scale(value) -> float | None:
    """``generate_scan``'s ``projector_scale``: None, or a finite number > 0."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) \
            or not math.isfinite(float(value)) or float(value) <= 0:
        raise InputError(f"projector_scale: expected a finite number > 0 (camera pixels per "
                         f"projector pixel, linear), got {fmt_value(value)}")
    return float(value)


def check_sl_phase_steps(value) -> int | None:
    """``generate_scan``'s ``sl_phase_steps``: None (the preset's), 0 or an integer >= 3."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) \
            or int(value) in (1, 2) or not 0 <= int(value) <= 64:
        raise InputError(f"sl_phase_steps: expected 0 (Gray code only) or an integer in [3, 64] "
                         f"(an N-step phase shift), got {fmt_value(value)}")
    return int(value)


def projector_coordinates(view, projector) -> np.ndarray:
    """True projector coordinates of the surface point at each pixel centre of a camera.

    Parameters
    ----------
    view : facegeo.synth.render.SurfaceView
        What the camera sees (pixel-centre rays: ``supersample = 1``).
    projector : facegeo.geometry.camera.Camera

    Returns
    -------
    (H, W, 2) float64, projector px
        NaN off the head and where the point is behind the projector.
    """
    if view.samples_per_pixel != 1:
        raise InputError(f"view: expected pixel-centre samples (supersample 1), got "
                         f"{view.samples_per_pixel} per pixel")
    q, front = projector.project(view.p_world)
    q = np.where(front[:, None], q, np.nan)
    return view.to_image(q, np.nan).astype(np.float64)


def camera_px_per_projector_px(q_proj) -> float:
    """How many camera pixels one projector pixel spans on the surface, linear, median.

    Per pixel ``1 / sqrt(|det J|)``, ``J = ∂q_proj/∂(col, row)`` by central differences (a
    projector pixel covers ``1 / |det J|`` camera pixels, so about N × N at N); the median over
    the pixels where ``J`` is finite (the head, less a one-pixel rim), so occlusion edges, where
    ``q_proj`` jumps, do not move it.

    Parameters
    ----------
    q_proj : (H, W, 2) float64, projector px
        True projector coordinates of each camera pixel (NaN off the surface).

    Returns
    -------
    float
        NaN when no pixel has a finite Jacobian.
    """
    q = as_array(q_proj, "q_proj", shape=(None, None, 2), finite=False)
    if min(q.shape[:2]) < 3:
        return float("nan")
    c = q[1:-1, 2:] - q[1:-1, :-2]  # 2 ∂q/∂col
    r = q[2:, 1:-1] - q[:-2, 1:-1]  # 2 ∂q/∂row
    det = np.abs(c[..., 0] * r[..., 1] - c[..., 1] * r[..., 0]) / 4.0
    with np.errstate(divide="ignore"):
        n = 1.0 / np.sqrt(det[np.isfinite(det)])
    return float(np.median(n)) if n.size else float("nan")


def shared_code_fraction(q_proj) -> float:
    """Fraction of surface pixels whose true projector pixel equals a 4-neighbour's.

    The projector pixel of camera pixel ``(row, col)`` is ``floor(q_proj + 0.5)`` (both
    coordinates: the column and row codes a perfect decoder gives); a pixel *shares* its code
    when its left, right, upper or lower neighbour is on the surface with the same one. Issue
    34's camera: 0.97.

    Parameters
    ----------
    q_proj : (H, W, 2) float64, projector px
        True projector coordinates of each camera pixel; NaN (either coordinate) off the surface.

    Returns
    -------
    float
        Over the pixels with finite ``q_proj``; NaN when there are none.
    """
    q = as_array(q_proj, "q_proj", shape=(None, None, 2), finite=False)
    on = np.isfinite(q).all(axis=-1)
    code = np.where(on[..., None], np.floor(q + 0.5), np.nan)
    same = np.zeros(on.shape, bool)
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        eq = (code[a] == code[b]).all(axis=-1)  # NaN never equals: off-surface never shares
        same[a] |= eq
        same[b] |= eq
    n = int(on.sum())
    return float(same[on].sum() / n) if n else float("nan")


def projector_size_for_scale(size: tuple[int, int], ratio: float,
                             projector_scale: float) -> tuple[int, int]:
    """The projector size at which one projector pixel spans ``projector_scale`` camera pixels.

    A projector of ``size`` measured ``ratio`` camera pixels per projector pixel
    (:func:`camera_px_per_projector_px`); resizing it by ``f`` (focal lengths with it) makes that
    ``ratio / f``, so ``f = ratio / projector_scale``. The size is the nearest to ``f × size``
    that keeps the aspect ratio exactly: ``size / g · k``, ``g = gcd(width, height)``,
    ``k = round(g · f)`` (a 256 × 192 projector comes in steps of 4 × 3), so
    ``Camera.scaled(k / g)`` gives integer sizes.

    Parameters
    ----------
    size : (int, int)
        Projector (width, height), pixels.
    ratio : float > 0
        Camera pixels per projector pixel at ``size``, linear.
    projector_scale : float > 0
        The camera pixels per projector pixel wanted, linear.

    Returns
    -------
    (int, int)

    Raises
    ------
    InputError
        ``projector_scale`` so large the projector rounds to no pixel.
    """
    w, h = (int(s) for s in size)
    g = math.gcd(w, h)
    f = float(ratio) / float(projector_scale)
    if not math.isfinite(f) or f <= 0:
        raise InputError(f"projector_scale: cannot resize the projector: {ratio} camera pixels "
                         "per projector pixel measured on the head (does the head face the "
                         "cameras and the projector?)")
    k = round(g * f)
    if k < 1:
        raise InputError(
            f"projector_scale: {fmt_value(projector_scale)} camera pixels per projector pixel "
            f"needs a {w * f:.3g} × {h * f:.3g} px projector, below the smallest of its aspect "
            f"ratio ({w // g} × {h // g}, {ratio * g:.3g} camera pixels per projector pixel); "
            f"use a projector_scale below {2 * ratio * g:.3g}")
    return (w // g * k, h // g * k)
