"""Structured-light patterns and their decoding: Gray code (with inverses) and N-step phase shift.

Debevec et al. 2000 (Sec. 3) build the face geometry from structured light projected by a video
projector beside the cameras. This module makes the projector's patterns, samples them at
continuous projector coordinates (for the synthetic renderer) and decodes camera frames into
projector coordinates per camera pixel. Triangulation is a later stage.

Conventions
-----------
* **Pixels** (DESIGN §3): ``(x, y)`` = (column, row); integer coordinates are projector pixel
  *centres*; projector pixel ``c`` covers ``[c - 0.5, c + 0.5)``. Images are ``[row, col]``.
* **Projection order** (:func:`pattern_names`)::

      "white", "black",                                   if spec.white_black
      "gray_x_00", "gray_x_00_inv", ..., "gray_x_{n-1}",  column bits, MSB first
      "gray_y_00", "gray_y_00_inv", ...,                  row bits, MSB first
      "phase_x_0", ..., "phase_x_{N-1}", "phase_y_0", ... for each axis in spec.phase_axes

  The ``_inv`` frame follows its pattern only when ``spec.inverse``. With ``white_black=False``
  and ``inverse=True`` the Gray frames are in exactly the order and polarity of OpenCV's
  ``cv2.structured_light.GrayCodePattern.generate()`` (columns then rows, MSB first, each
  pattern followed by its inverse; white = bit 1).
* **Gray code**: bit ``i`` (``i = 0`` is the MSB) of frame ``gray_x_i`` is bit ``n-1-i`` of
  ``gray_encode(col >> s)``, where ``s = max(ceil(log2(width)) - n_bits_x, 0)``. With the
  default ``n_bits_x = ceil(log2(width))``, ``s = 0`` and every column has its own code; with
  fewer bits the codes name stripes ``2**s`` pixels wide (the MSBs of the full code, since
  ``gray(c) >> s == gray(c >> s)``) and the decoded coordinate is the stripe's centre.
* **Phase shift**: frame ``phase_x_k`` is
  ``0.5 + 0.5 cos(phi(x) - 2 pi k / N)`` with ``phi(x) = 2 pi P_x (x + 0.5) / width``,
  ``P_x`` = ``phase_periods_x`` periods across the projector (rows and ``P_y`` for ``y``).
  :func:`decode_phase` returns ``phi mod 2 pi``; :func:`unwrap_with_gray` picks the period from
  the Gray-code decode and returns sub-pixel projector coordinates.
* **Frames** are intensities, ``(H, W)`` or ``(H, W, C)``; colour frames are reduced to the
  channel mean. Every frame is read relative to its **full scale**: the dtype's maximum for
  integer frames (255 for uint8, 65535 for uint16), 1.0 for float frames, or the
  ``full_scale`` argument when given (e.g. float radiance with another exposure). Thresholds
  (``min_contrast``, ``shadow_threshold``, ``threshold``, ``min_modulation``) and the returned
  ``contrast`` / ``modulation`` are fractions of full scale, so the uint8, uint16 and float
  versions of one capture decode to the same codes and the same shadow mask. Bit decisions
  (``frame > inverse``) do not depend on the scale or on a monotonic response curve; the
  thresholds do, so 8/16-bit frames of a non-linear camera are best linearised first
  (:mod:`facegeo.capture.response`).

References
----------
Debevec, Hawkins, Tchou, Duiker, Sarokin, Sagar. Acquiring the Reflectance Field of a Human
Face. SIGGRAPH 2000, Sec. 3. — Inokuchi, Sato, Matsuda. Range imaging system for 3-D object
recognition. ICPR 1984 (Gray-code structured light). — Srinivasan, Liu, Halioua. Automated
phase-measuring profilometry of 3-D diffuse objects. Appl. Opt. 23(18), 1984 (N-step phase).
"""

from __future__ import annotations

from facegeo.geometry._sl_patterns import (  # noqa: F401 (re-exported)
    _AXES,
    _CHUNK_PIXELS,
    PatternSpec,
    _check_spec,
    _pattern_table,
    gray_decode,
    gray_encode,
    pattern_image,
    pattern_names,
    pattern_value_at,
)

__all__ = [
    "CameraDecodePlan",
    "GrayDecode",
    "PatternSpec",
    "PhaseDecode",
    "decode_gray",
    "decode_phase",
    "decode_stream",
    "gray_decode",
    "gray_encode",
    "pattern_image",
    "pattern_names",
    "pattern_value_at",
    "plan_camera_decode",
    "unwrap_with_gray",
    "with_stand_in_partners",
]

# --------------------------------------------------------------------------- decoders
# Whole-set decoders live in _sl_decode (they need PatternSpec above): re-exported here.
from facegeo.geometry._sl_decode import (
    GrayDecode,
    PhaseDecode,
    decode_gray,
    decode_phase,
    unwrap_with_gray,
)

# --------------------------------------------------------------------------- per-camera plans
# A camera's own pattern set from the frames it has (lost frames): _sl_plan, re-exported.
from facegeo.geometry._sl_plan import (  # noqa: E402
    CameraDecodePlan,
    plan_camera_decode,
    with_stand_in_partners,
)

# --------------------------------------------------------------------------- streaming decode


def decode_stream(frames, spec: PatternSpec, *, full_scale: float | None = None,
                  min_contrast: float = 0.005, rel_contrast: float = 0.15,
                  shadow_threshold: float = 0.02, min_modulation: float = 0.3,
                  noise_sigma: float = 0.005, max_coarse_px: float | None = None,
                  vote_tolerance_px: float = 0.0, saturation: float = 0.98,
                  threads: int = 1):
    """Decode structured-light frames in one streaming pass, robust to skin's global light.

    Frames arrive one at a time as ``(name, frame)`` pairs, in any order; each is reduced to
    float32 luminance (channel mean, fraction of full scale) and folded into per-pixel
    accumulators, so memory is bounded by a few planes per pixel (``_sl_stream`` module
    docstring), never the whole set.

    **Bits relative to the pixel's own light.** Each binary plane's decision is ``pattern >
    inverse`` (without inverse frames, ``pattern > (white + black) / 2``, or ``> (L_max +
    L_min) / 2`` over the pixel's binary frames when there are no white / black frames either).
    Its margin (``|pattern - inverse|``, or twice the distance to the threshold) is *reliable*
    when ``margin >= max(min_contrast, rel_contrast * L_d)``, with ``L_d = L_max - L_min`` the
    pixel's direct light from its binary frames (Nayar et al. 2006, Sec. 3: ``L_max = L_d +
    L_g/2``, ``L_min = L_g/2`` under half-on high-frequency patterns; the global part
    ``L_g = 2 L_min`` is returned too). All binary planes are used, coarse ones included: under
    interreflection this overestimates ``L_d`` (and the thresholds err on the strict side);
    restricting to the fine planes was measured worse on skin, where subsurface scattering
    blurs stripes of a few millimetres and the "direct" light they show is too small. A pixel keeps the planes it resolves: its coordinate
    comes from the prefix of reliable planes (a block of ``2**k`` stripes, centre and
    ``σ = w / sqrt(12)``), or, when exactly one plane is unresolved and the two candidate
    codes are neighbours, from the stripe boundary between them. The coordinate is valid when
    the block is at most ``max_coarse_px`` wide — by default half a phase period when the axis
    has phase frames (enough to unwrap), else one stripe (exact codes only). Per bit, the
    result counts the lit pixels that leave that plane unresolved and those it invalidates.
    The long-run code (``"minsw"``) has no prefix: it decodes through its code → stripe table;
    with one unresolved plane it takes the boundary (or the phase's pick) of the two table
    candidates, otherwise the pixel is invalid on that axis (docs/structured-light.md).

    **Ensemble of codes** (Gupta et al. 2013): with several ``spec.codes`` families, each is
    decoded independently and a family's coordinate stands when another agrees within
    ``vote_tolerance_px`` (plus half their block widths); disagreeing pixels are invalid.

    **Phase** (Srinivasan et al. 1984): ``phi = atan2(S, C)``, ``B = (2/N) sqrt(S^2 + C^2)``,
    unwrapped with the Gray coordinate as in :func:`unwrap_with_gray`; used where the fringe
    contrast ``2 B / L_d >= min_modulation``, with ``σ = noise_sigma sqrt(2/N) / B`` radians
    turned into projector pixels.

    Parameters
    ----------
    frames : iterable of (str, (H, W) or (H, W, C) array) or mapping str -> array
        Linear intensities named as :func:`pattern_names`; every frame of the set exactly once.
    spec : PatternSpec
    full_scale : float, optional, frame units
        White level (default: dtype maximum for integers, 1 for floats).
    min_contrast : float, fraction of full scale
        Absolute floor of a reliable bit margin.
    rel_contrast : float
        Reliable bit margin relative to the pixel's direct light ``L_d``.
    shadow_threshold : float, fraction of full scale
        Pixels with ``white - black`` (else ``L_d``) below this are projector shadow.
    min_modulation : float
        Smallest fringe contrast ``2 B / L_d`` for the phase to be used.
    noise_sigma : float, fraction of full scale
        1-σ intensity noise assumed for the phase ``σ`` estimate.
    max_coarse_px : float, optional, projector pixels
        Widest block a binary code may leave a pixel in (default above).
    vote_tolerance_px : float, projector pixels
        Agreement tolerance of the code-family vote beyond half the two block widths (0: exact
        codes must be equal; a stripe-boundary coordinate agrees with either neighbour).
    saturation : float, fraction of full scale
        Pixels whose brightest phase frame reaches this have a clipped fringe: their phase is
        not used (they keep an exact code if they have one).
    threads : int
        Threads of the tile-major pair kernel and of the finish, 1 … ``NUMBA_NUM_THREADS``
        (default 1: two threads were faster only on an idle machine; the result is identical).

    Returns
    -------
    StreamDecode

    Raises
    ------
    InputError
        Unknown, repeated or missing frames (the count must match the pattern set); NaN / inf;
        all-dark frames (no pixel lit by the projector); bad settings.
    ShapeError
        Frames of different sizes or not images.

    References
    ----------
    Nayar, Krishnan, Grossberg, Raskar. Fast separation of direct and global components of a
    scene using high frequency illumination. SIGGRAPH 2006. — Gupta, Agrawal, Veeraraghavan,
    Narasimhan. A Practical Approach to 3D Scanning in the Presence of Interreflections,
    Subsurface Scattering and Defocus. IJCV 102, 2013.
    """
    from facegeo.geometry._sl_stream import decode_frames

    return decode_frames(frames, _check_spec(spec), full_scale=full_scale,
                         min_contrast=min_contrast, rel_contrast=rel_contrast,
                         shadow_threshold=shadow_threshold, min_modulation=min_modulation,
                         noise_sigma=noise_sigma, max_coarse_px=max_coarse_px,
                         vote_tolerance_px=vote_tolerance_px, saturation=saturation,
                         threads=threads)
