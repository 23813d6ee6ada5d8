"""What one camera's structured-light decode can use: :func:`plan_camera_decode`.

A real capture loses frames: a camera's manifest declares some missing
(``[structured_light.cameras.<camera>] missing``, ``bits_x`` / ``bits_y``), and a camera that
only saw the calibration board has none. The plan says, from the scan's
:class:`~facegeo.geometry.structured_light.PatternSpec` and the frame names one camera has,
which pattern set that camera decodes and what was done to get there — per axis and code
family (docs/structured-light.md, *Cameras with lost frames*):

* a bit with both frames of its pair is used as it is;
* a bit with one frame of its pair left is decoded against the mid level ``(white + black) / 2``
  (needs the white and black frames): the decoder is fed a stand-in partner
  ``white + black - frame`` (:func:`with_stand_in_partners`), so the pair's difference is
  ``2 (frame - (white + black) / 2)`` — its sign the threshold test, its magnitude the usual
  pair margin; without white / black the bit is lost;
* from the first lost bit of an axis on, the Gray code's bits are dropped: a reflected Gray code
  of ``n' < n`` bits is the first ``n'`` planes of the ``n``-bit one (``gray(c) >> s ==
  gray(c >> s)``), so the camera decodes ``PatternSpec(n_bits = n')`` and its codes name blocks
  of ``2**(n - n')`` of the scan's codes — the decoded coordinate is the block's centre, in the
  full set's projector pixels, with ``sigma = block / sqrt(12)``; a camera's declared ``bits_x``
  / ``bits_y`` cap ``n'`` the same way;
* the other code families (``"xor02"``, ``"xor04"``, ``"minsw"``) have no such prefix: a family
  that lost a bit, or any family beside a Gray code that lost one (one pattern set has one bit
  count per axis), is dropped on that camera;
* an axis's phase frames are used only when all are there, and only while the camera's code
  blocks stay within half a phase period (what unwrapping needs); else phase is dropped on
  that axis;
* a camera with no structured-light frame at all is skipped (``action == "skip"``); one left
  with nothing to decode — no code bit on any axis of a coded set, or no phase axis of a
  phase-only set — is ``"undecodable"``, with the reason.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from facegeo.checks import fmt_value
from facegeo.errors import InputError
from facegeo.geometry._sl_patterns import (
    _AXES,
    PatternSpec,
    _bits_for,
    _check_spec,
    _pattern_table,
    pattern_names,
)

__all__ = ["CameraDecodePlan", "MID_LEVEL", "plan_camera_decode", "with_stand_in_partners"]

#: What a half pair's remaining frame is decoded against.
MID_LEVEL = "(white + black) / 2"


@dataclass(frozen=True)
class CameraDecodePlan:
    """One camera's decode of a scan's pattern set (:func:`plan_camera_decode`).

    Attributes
    ----------
    camera : str or None
        The camera's name, when given (used in messages only).
    action : {"decode", "skip", "undecodable"}
        ``"skip"``: the camera has no structured-light frame (a calibration-only camera);
        ``"undecodable"``: it has frames but nothing decodable is left (``reason`` says why).
    reason : str
        Why the camera is skipped or undecodable ("" when it is decoded).
    spec : PatternSpec or None
        The camera's own pattern set (None unless ``action == "decode"``): the scan's with the
        camera's bits, phase axes, code families and white / black frames.
    frames : tuple of str
        The frames the decode reads, in feeding order (white and black first).
    stand_ins : dict str -> str
        ``{present frame: missing partner}`` of each half pair: the partner is fed as
        ``white + black - frame`` right after the present frame (:func:`with_stand_in_partners`).
    axes : dict axis -> dict
        Per axis of the scan's set: ``bits_scan`` (the scan's bits), ``bits`` (the camera's),
        ``block_px`` (projector pixels one of the camera's codes spans, ``2**s`` of its
        :meth:`PatternSpec.stripe_shift`), ``codes_per_block`` (``2**(bits_scan - bits)``, the
        scan's codes one camera code covers), ``limited_by`` (None, or what capped the bits),
        ``phase`` (None without phase on the axis, else ``"used"`` or why it was dropped).
    half_pairs : tuple of dict
        ``{"axis", "bit", "code", "decoded_against": MID_LEVEL, "present", "missing"}`` per
        bit decoded from one frame of its pair.
    lost_bits : tuple of dict
        ``{"axis", "bit", "code", "missing": [frames], "present": [frames]}`` (and ``"why"``)
        per bit the camera cannot decode at all.
    dropped : tuple of dict
        ``{"what", "why", "frames": [frames the camera has but does not read]}``: Gray bits
        after a lost one, code families, phase axes, a lone white or black frame.
    """

    camera: str | None
    action: str
    reason: str = ""
    spec: PatternSpec | None = None
    frames: tuple[str, ...] = ()
    stand_ins: dict[str, str] = field(default_factory=dict)
    axes: dict[str, dict] = field(default_factory=dict)
    half_pairs: tuple[dict, ...] = ()
    lost_bits: tuple[dict, ...] = ()
    dropped: tuple[dict, ...] = ()

    @property
    def unused_frames(self) -> list[str]:
        """Frames the camera has that the decode does not read."""
        return [f for d in self.dropped for f in d["frames"]]

    @property
    def complete(self) -> bool:
        """True when the camera decodes the scan's set as it is (nothing half, lost, dropped)."""
        return (self.action == "decode" and not self.half_pairs and not self.lost_bits
                and not self.dropped)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (the decode stage's per-camera ``plan`` metric)."""
        out: dict[str, Any] = {"action": self.action}
        if self.reason:
            out["reason"] = self.reason
        out["axes"] = {a: dict(v) for a, v in self.axes.items()}
        out["bits"] = {a: v["bits"] for a, v in self.axes.items()}
        out["block_px"] = {a: v["block_px"] for a, v in self.axes.items() if v["bits"]}
        out["half_pairs"] = [dict(h) for h in self.half_pairs]
        out["lost_bits"] = [dict(b) for b in self.lost_bits]
        out["dropped"] = [dict(d) for d in self.dropped]
        if self.spec is not None:
            out["patterns"] = self.spec.to_dict()
            out["frames_read"] = len(self.frames)
        return out


def _frame_names(available: Iterable[str], table: Mapping, camera: str | None) -> set[str]:
    if isinstance(available, str):
        raise InputError(f"available: expected a collection of frame names, got the string "
                         f"{fmt_value(available)}")
    have = set(available)
    unknown = sorted(str(f) for f in have if f not in table)
    if unknown:
        who = f"camera {camera!r}: " if camera else ""
        raise InputError(f"available: {who}frame(s) {unknown[:8]} are not in the pattern set "
                         f"(its {len(table)} frames are {list(table)[:6]} ...)")
    return have


def _check_max_bits(max_bits: Mapping[str, int] | None, spec: PatternSpec) -> dict[str, int]:
    caps = {a: spec.n_bits(a) for a in _AXES}
    if max_bits is None:
        return caps
    if not isinstance(max_bits, Mapping):
        raise InputError(f"max_bits: expected a mapping axis -> bits, got {fmt_value(max_bits)}")
    for a, v in max_bits.items():
        if a not in _AXES:
            raise InputError(f"max_bits: unknown axis {fmt_value(a)}; expected 'x' or 'y'")
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise InputError(f"max_bits[{a!r}]: expected an integer >= 0, got {fmt_value(v)}")
        caps[a] = min(caps[a], int(v))
    return caps


def _bit_status(spec: PatternSpec, have: set[str], wb: bool):
    """Per (code, axis): a list over bits of ``("pair" | "half" | "single" | "lost", info)``."""
    status: dict[tuple[str, str], list] = {}
    for code in spec.codes:
        for axis in _AXES:
            row = []
            for i in range(spec.n_bits(axis)):
                pos = f"{code}_{axis}_{i:02d}"
                names = (pos, pos + "_inv") if spec.inverse else (pos,)
                present = [n for n in names if n in have]
                missing = [n for n in names if n not in have]
                if not missing:
                    row.append(("pair" if spec.inverse else "single", present))
                elif present and wb:
                    row.append(("half", (present[0], missing[0])))
                else:
                    info = {"missing": missing, "present": present}
                    if present:
                        info["why"] = ("one frame of the pair left and no white / black frames "
                                       f"to decode it against {MID_LEVEL}")
                    row.append(("lost", info))
            status[(code, axis)] = row
    return status


def plan_camera_decode(spec: PatternSpec, available: Iterable[str], *,
                       max_bits: Mapping[str, int] | None = None,
                       camera: str | None = None) -> CameraDecodePlan:
    """The pattern set one camera decodes, given the frames it has (module docstring).

    Parameters
    ----------
    spec : PatternSpec
        The scan's pattern set.
    available : collection of str
        The frame names this camera has (:func:`pattern_names` of ``spec``, any order; e.g.
        :meth:`facegeo.capture.scan.Scan.camera_frames`).
    max_bits : mapping {"x", "y"} -> int, optional
        Gray-code bits the camera resolves per axis (the manifest's ``bits_x`` / ``bits_y``,
        :meth:`facegeo.capture.scan.Scan.sl_bits`); larger values than the set's are ignored.
    camera : str, optional
        Name, for messages.

    Returns
    -------
    CameraDecodePlan
        ``action`` says whether the camera is decoded, skipped or undecodable; the plan never
        raises for missing frames.

    Raises
    ------
    InputError
        ``spec`` is not a PatternSpec; ``available`` names a frame not in the set; bad
        ``max_bits``.
    """
    spec = _check_spec(spec)
    table = _pattern_table(spec)
    have = _frame_names(available, table, camera)
    caps = _check_max_bits(max_bits, spec)
    if not have:
        return CameraDecodePlan(camera, "skip", "no structured-light frames (a camera of the "
                                "calibration only)")
    dropped: list[dict] = []
    wb = spec.white_black and {"white", "black"} <= have
    if spec.white_black and not wb and have & {"white", "black"}:
        lone = sorted(have & {"white", "black"})
        dropped.append({"what": "white_black", "frames": lone,
                        "why": f"{'black' if 'white' in have else 'white'} frame missing"})
    status = _bit_status(spec, have, wb)
    for axis in _AXES:  # Gray bits beyond the declared ones are not expected: neither lost nor half
        row = status.get(("gray", axis), [])
        row[caps[axis]:] = [("beyond", None)] * len(row[caps[axis]:])
    half_pairs, lost_bits = [], []
    for (code, axis), row in status.items():
        for i, (kind, info) in enumerate(row):
            if kind == "half":
                half_pairs.append({"axis": axis, "bit": i, "code": code,
                                   "decoded_against": MID_LEVEL, "present": info[0],
                                   "missing": info[1]})
            elif kind == "lost":
                lost_bits.append({"axis": axis, "bit": i, "code": code, **info})

    # Gray: the bits before the first lost one (and within the camera's declared bits)
    bits, limited = {}, {}
    for axis in _AXES:
        n = spec.n_bits(axis)
        bits[axis], limited[axis] = n, None
        if "gray" in spec.codes and n:
            row = status[("gray", axis)]
            first = next((i for i, (k, _) in enumerate(row) if k in ("lost", "beyond")), n)
            if first < caps[axis]:
                bits[axis], limited[axis] = first, f"gray bit {first} lost"
            elif caps[axis] < n:
                bits[axis], limited[axis] = caps[axis], f"bits_{axis} = {caps[axis]} (declared)"
    gray_cut = any(bits[a] < spec.n_bits(a) for a in _AXES)
    codes = []
    for code in spec.codes:
        if code == "gray":
            codes.append(code)
            continue
        lost = [b for b in lost_bits if b["code"] == code]
        capped = [a for a in _AXES if caps[a] < spec.n_bits(a)]
        why = (f"bit {lost[0]['bit']} of {lost[0]['axis']} lost" if lost else
               f"the camera resolves fewer bits on {capped[0]} (bits_{capped[0]} = "
               f"{caps[capped[0]]})" if capped else
               "the Gray code keeps fewer bits on this camera" if gray_cut else None)
        if why is None:
            codes.append(code)
            continue
        frames = [n for n in table if table[n].kind == "gray" and table[n].code == code
                  and n in have]
        dropped.append({"what": f"code {code}", "frames": frames,
                        "why": f"{why}; a {code} code has no shorter prefix"})
    if not codes:  # every family dropped (the kept ones are complete at the scan's bits)
        bits = {a: 0 for a in _AXES}
    binary = spec.gray and any(bits[a] for a in _AXES)
    for axis in _AXES:  # Gray bits after the first lost one the camera still has
        if "gray" in codes and bits[axis] < spec.n_bits(axis):
            frames = [n for n in table if table[n].kind == "gray" and table[n].code == "gray"
                      and table[n].axis == axis and table[n].index >= bits[axis] and n in have]
            if frames:
                dropped.append({"what": f"gray {axis} bits {bits[axis]}..{spec.n_bits(axis) - 1}",
                                "frames": frames, "why": limited[axis]})

    # phase: complete axes whose codes still unwrap them
    phase_axes, phase_note = [], {}
    for axis in spec.phase_axes if spec.phase_steps else ():
        names = [f"phase_{axis}_{k}" for k in range(spec.phase_steps)]
        gone = [n for n in names if n not in have]
        size = spec.width if axis == "x" else spec.height
        period = size / spec.phase_periods(axis)
        block = 2 ** max(_bits_for(size) - bits[axis], 0)
        why = None
        if gone:
            why = f"frames {gone} missing"
        elif spec.gray and spec.n_bits(axis) and bits[axis] < spec.n_bits(axis):
            if not binary or not bits[axis]:
                why = "no code bit left on this axis to unwrap it"
            elif block > period / 2.0:
                why = (f"{bits[axis]} bits leave {block}-px blocks, wider than half the "
                       f"{period:g}-px period (unwrapping needs <= {period / 2.0:g})")
        if why is None:
            phase_axes.append(axis)
            phase_note[axis] = "used"
        else:
            phase_note[axis] = f"dropped: {why}"
            present = [n for n in names if n in have]
            dropped.append({"what": f"phase {axis}", "frames": present, "why": why})

    axes = {}
    for axis in _AXES:
        size = spec.width if axis == "x" else spec.height
        n = bits[axis] if binary else 0
        axes[axis] = {
            "bits_scan": spec.n_bits(axis), "bits": n,
            "block_px": 2 ** max(_bits_for(size) - n, 0) if n else None,
            "codes_per_block": 2 ** (spec.n_bits(axis) - n) if n else None,
            "limited_by": limited[axis],
            "phase": phase_note.get(axis),
        }
    plan_kw = {"axes": axes, "half_pairs": tuple(half_pairs), "lost_bits": tuple(lost_bits)}
    scan_binary = spec.gray and any(spec.n_bits(a) for a in _AXES)
    if scan_binary and not binary:
        gone = sorted({f for b in lost_bits for f in b["missing"]}, key=list(table).index)
        return CameraDecodePlan(
            camera, "undecodable", f"no code bit left on any axis (missing {gone[:8]}"
            f"{' ...' if len(gone) > 8 else ''})", dropped=tuple(dropped), **plan_kw)
    if not scan_binary and spec.phase_steps and not phase_axes:
        return CameraDecodePlan(camera, "undecodable", "no complete phase axis left",
                                dropped=tuple(dropped), **plan_kw)
    try:
        cam_spec = PatternSpec(
            width=spec.width, height=spec.height, gray=binary,
            n_bits_x=bits["x"] if binary else 0, n_bits_y=bits["y"] if binary else 0,
            inverse=spec.inverse, white_black=wb, phase_steps=spec.phase_steps if phase_axes else 0,
            phase_periods_x=spec.phase_periods_x, phase_periods_y=spec.phase_periods_y,
            phase_axes=tuple(phase_axes) or spec.phase_axes,
            codes=tuple(codes) if binary else ("gray",))
    except InputError as exc:
        return CameraDecodePlan(camera, "undecodable", f"no pattern set left ({exc})",
                                dropped=tuple(dropped), **plan_kw)
    cam_table = _pattern_table(cam_spec)
    stand_ins = {h["present"]: h["missing"] for h in half_pairs if h["missing"] in cam_table}
    frames = tuple(n for n in pattern_names(cam_spec) if n in have)
    plan_kw["half_pairs"] = tuple(h for h in half_pairs if h["missing"] in cam_table)
    return CameraDecodePlan(camera, "decode", "", cam_spec, frames, stand_ins,
                            dropped=tuple(dropped), **plan_kw)


def with_stand_in_partners(frames: Iterable, plan: CameraDecodePlan, *,
                           full_scale: float | None = None) -> Iterator[tuple[str, Any]]:
    """The camera's frames for ``decode_stream(..., plan.spec)``, half pairs completed.

    Passes each ``(name, frame)`` through; after the present frame of a half pair
    (``plan.stand_ins``) it yields the missing partner as ``white + black - frame``: float32
    ``(H, W)`` luminance (the decoder's channel mean, in fractions of full scale, times
    ``full_scale`` when given), so the decoder's pair difference is ``2 (frame - (white +
    black) / 2)``. The white and black frames must come before the first half pair (the plan's
    ``frames`` order); their sum is held as one plane until the last stand-in is made, then
    released. Frames still stream one at a time.

    Parameters
    ----------
    frames : iterable of (str, (H, W) or (H, W, C) array)
        ``plan.frames``, e.g. ``scan.iter_sl(camera, plan.frames)``; linear intensities.
    plan : CameraDecodePlan
        With ``action == "decode"``.
    full_scale : float, optional, frame units
        As :func:`~facegeo.geometry.structured_light.decode_stream`'s (pass the same).

    Yields
    ------
    (str, array)

    Raises
    ------
    InputError
        A half pair's frame before the white or black frame; a plan that does not decode.
    """
    from facegeo.geometry._sl_stream import _luminance

    if not isinstance(plan, CameraDecodePlan) or plan.action != "decode":
        raise InputError(f"plan: expected a CameraDecodePlan whose action is 'decode', got "
                         f"{getattr(plan, 'action', type(plan).__name__)!r}")
    todo = dict(plan.stand_ins)
    unit = 1.0 if full_scale is None else float(full_scale)
    wb: dict[str, Any] = {}
    mid2 = None  # white + black, luminance
    for item in frames:
        name, frame = item[0], item[1]
        partner = todo.pop(name, None)
        stand_in = None
        if todo or partner is not None:
            if name in ("white", "black") and mid2 is None:
                wb[name] = _luminance(frame, name, None, full_scale)
                if len(wb) == 2:
                    mid2 = wb.pop("white")
                    mid2 += wb.pop("black")
            if partner is not None:
                if mid2 is None:
                    raise InputError(f"frames: {name!r} (half of a pair) came before the white "
                                     "and black frames its stand-in partner is made from; feed "
                                     "plan.frames in order")
                stand_in = mid2 - _luminance(frame, name, None, full_scale)
                if unit != 1.0:
                    stand_in *= unit
                if not todo:
                    mid2 = None  # the last stand-in: white + black no longer needed
        yield name, frame
        if stand_in is not None:
            yield partner, stand_in
    if todo:
        raise InputError(f"frames: ended before {sorted(todo)} (half pairs of the plan) came")
