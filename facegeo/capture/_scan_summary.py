"""The human summary of a scan that ``facegeo info`` prints (:func:`summarize`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any


def _fmt_bytes(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"  # pragma: no cover


def _du(path: Path, skip: Path | None = None, seen: set | None = None) -> int:
    """Bytes in the files under ``path`` (symlinks not followed), each inode counted once:
    hard links (a scan that links frames from another, say) do not double the size."""
    total = 0
    seen = set() if seen is None else seen
    for dirpath, dirnames, filenames in os.walk(path):
        if skip is not None:
            dirnames[:] = [d for d in dirnames if Path(dirpath, d) != skip]
        for f in filenames:
            try:
                st = os.lstat(os.path.join(dirpath, f))
            except OSError:
                continue
            ident = (st.st_dev, st.st_ino)
            if ident in seen:
                continue
            seen.add(ident)
            total += st.st_size
    return total


def _fmt_response(r: Any) -> str:
    if isinstance(r, str):
        return r
    if r.get("kind") == "gamma":
        return f"gamma {r['gamma']}"
    if r.get("kind") == "table":
        return f"table {r['file']}"
    return str(r.get("kind"))


def _fmt_keys(keys: list, limit: int = 4) -> str:
    shown = [f"view {k[0]} {k[1]}" if isinstance(k, tuple) else str(k) for k in keys[:limit]]
    return ", ".join(shown) + (f", ... ({len(keys)} in all)" if len(keys) > limit else "")


def summarize(scan) -> str:  # scan: facegeo.capture.scan.Scan
    """A human-readable summary of a scan: name and version, cameras, projector, lights, frame
    groups, what each camera has and lacks per group, board, world frame, responses, reference
    answers, ground truth and size on disk (hard links counted once).

    This is what ``facegeo info`` prints."""
    m = scan._m
    lines = [(f"scan {scan.name!r} ({'synthetic' if scan.synthetic else 'real capture'}, "
              f"format version {scan.version})"),
             f"  root: {scan.root}"]
    if scan.description:
        lines.append(f"  description: {scan.description}")
    rig = scan.rig
    lines.append(f"  rig: {m['scan']['rig']}, {len(rig.cameras)} camera(s)")
    for c in rig.cameras:
        lines.append(f"    camera {c.name}: {c.width}×{c.height} px")
    proj = getattr(rig, "projector", None)
    if proj is None:
        lines.append("  projector: none")
    else:
        cal = "" if getattr(rig, "projector_calibrated", True) else " (uncalibrated: intrinsics unknown)"
        lines.append(f"  projector: {proj.name} {proj.width}×{proj.height} px{cal}")
    lights = getattr(rig, "lights", None)
    if lights is None:
        lines.append("  lights: none")
    elif hasattr(lights, "n_theta"):
        lines.append(
            f"  light stage: {lights.n_lights} lights ({lights.n_theta} azimuths × "
            f"{lights.n_phi} inclinations)"
        )
    else:
        where = "directions" if lights.is_distant else "near-field positions"
        cover = ("a dome clipped at the horizon" if lights.horizon_axis is not None
                 else "the full sphere")
        lines.append(f"  light list: {lights.n_lights} lights ({where}), Voronoi solid angles "
                     f"over {cover}: sum {lights.solid_angles.sum():.3f} sr")
    world = m["scan"].get("world")
    if world is not None:
        lines.append("  world frame: " + ("explicit transform T_world_rig" if "transform" in world
                                          else f"board in view {world['board_view']} seen by "
                                               f"{world['camera']}"))
    lines.append("  frame groups:" if scan.groups else "  frame groups: none")
    cams = scan.camera_names
    for g in scan.groups:
        s = scan._section(g)
        total = sum(len(scan.expected_files(g, c)) for c in cams)
        if g == "calib":
            per, what = s["views"], "view(s)"
            board = s["board"] if isinstance(s["board"], str) else f"inline {s['board']['kind']}"
            extra = f", response {_fmt_response(s['response'])}, board {board}"
            if "corners" in s:
                extra += f", corner lists {s['corners']}"
            if not scan.calib_images:
                extra += ", no images"
        elif g == "calib.projector":
            nf = len(scan.projector_frames)
            per = s["views"] * nf
            what = f"file(s) ({s['views']} view(s) × {nf} frames)"
            extra = f", response {_fmt_response(m['calib']['response'])}"
        elif g == "structured_light":
            per, what = len(s["frames"]), "frame(s)"
            extra = f", response {_fmt_response(s['response'])}, projector {s['projector']!r}"
        else:
            per, what = s["n_lights"], "light(s)"
            extra = f", response {_fmt_response(s['response'])}"
            if hasattr(lights, "n_theta"):
                extra += f", order {s['light_order']}"
            if "ambient" in s:
                extra += ", ambient frame"
        lines.append(f"    {g}: {per} {what} per camera, {total} files{extra}")
        lines.append(f"      files: {s['files']}")
        for c in cams:
            have = scan.camera_frames(g, c)
            lack = scan.missing_frames(g, c)
            line = f"      {c}: {len(have)} of {per}"
            if lack:
                if g == "olat" and scan.light_names is not None:
                    lack = [scan.light_names[k] for k in lack]
                elif g == "calib":
                    lack = [f"view {k}" for k in lack]
                line += f"; lacks {_fmt_keys(lack)}"
            if g == "structured_light" and "cameras" in s and c in s["cameras"]:
                bits = {k: v for k, v in s["cameras"][c].items() if k.startswith("bits_")}
                if bits:
                    line += "; resolves " + ", ".join(f"{k} = {v}" for k, v in bits.items())
            lines.append(line)
    for title, flat in (("reference", scan._ref or {}), ("ground truth", scan._gt or {})):
        if flat:
            lines.append(f"  {title}: {len(flat)} entr{'y' if len(flat) == 1 else 'ies'}")
            for k, v in flat.items():
                lines.append(f"    {k} = {v}")
    out = scan.root / "out"
    seen: set = set()
    size_in = _du(scan.root, skip=out, seen=seen)
    size_out = _du(out, seen=seen) if out.is_dir() else 0
    lines.append(f"  size on disk (hard links counted once): {_fmt_bytes(size_in)} (inputs), "
                 f"{_fmt_bytes(size_out)} (out/)")
    return "\n".join(lines)
