"""Validation of a scan against its rig and the files on disk (:meth:`Scan.validate`).

A mixin of :class:`facegeo.capture.scan.Scan`, kept apart so the loader's own module stays
readable; see ``docs/scan-format.md`` (*Validation*).
"""

from __future__ import annotations

import logging
from typing import Self

from facegeo.capture._scan_files import FrameCheck, _check_group_files
from facegeo.capture._scan_schema import _err
from facegeo.checks import check_choice, fmt_value
from facegeo.errors import InputError, ScanFormatError

log = logging.getLogger("facegeo.capture.scan")

#: Levels of :meth:`Scan.validate`.
CHECKS = ("quick", "full")


class _ScanValidation:
    """:meth:`validate` and its parts (mixed into :class:`~facegeo.capture.scan.Scan`)."""

    def validate(self, check: str = "quick") -> Self:
        """Check the scan against its rig and the files on disk.

        Parameters
        ----------
        check : {"quick", "full"}
            ``"quick"``: the rig (and its cross-checks), response tables, ground-truth entries,
            that every expected frame exists inside the scan, and the header of **every**
            frame, read without decoding pixels: size against the rig, channel count, sample
            type against the declared response and against the group's first frame, and a file
            that ends before its data does (truncated; see
            :func:`~facegeo.capture.imageio.read_image_info`). ``"full"``: additionally the
            board file, and a decode of every frame whose pixels are checked: NaN or inf are
            errors; negative radiance, an all-black frame and a mostly saturated one are
            warnings, kept in :attr:`frame_check` and not raised.

        Returns
        -------
        Scan
            ``self``.

        Raises
        ------
        ScanFormatError
            The first problem found, naming the file and/or key and what would be right (with
            the number and first names of the other frames that fail).

        Notes
        -----
        After the frame checks ran, :attr:`frame_check` (a
        :class:`~facegeo.capture._scan_files.FrameCheck`) says how many headers were read, how
        many frames decoded, and lists every problem per frame, warnings included.
        """
        check_choice(check, "check", CHECKS)
        where = self.manifest_path
        rig = self.rig
        cameras = list(rig.cameras)
        if self.groups and not cameras:
            raise _err(
                "the rig has no cameras, but the scan lists frames", key="scan.rig", path=where
            )
        names = [c.name for c in cameras]
        if len(names) > 1:
            for group in self.groups:
                for k in ("files", "ambient", "corners"):
                    t = self._section(group).get(k)
                    if isinstance(t, str) and "{camera" not in t:
                        raise _err(f"template {t!r} has no {{camera}} but the rig has "
                                   f"{len(names)} cameras, whose files would collide; only a "
                                   "one-camera rig may leave {camera} out",
                                   key=f"{group}.{k}", path=where)
        if len(set(names)) != len(names):
            raise _err(
                f"the rig's camera names are not unique: {names}", key="scan.rig", path=where
            )
        if self.has("olat"):
            self._validate_olat(rig, where)
        if self.has("structured_light"):
            proj = getattr(rig, "projector", None)
            if proj is None:
                raise _err(
                    "[structured_light] is present but the rig has no projector",
                    key="structured_light.projector",
                    path=where,
                )
            if self.sl_projector != proj.name:
                raise _err(
                    f"projector = {fmt_value(self.sl_projector)} but the rig's projector is {fmt_value(proj.name)}",
                    key="structured_light.projector",
                    path=where,
                )
        for sect in ("calib", "structured_light", "olat"):
            if self.has(sect):
                self.response(sect)
        self._validate_cameras_tables(names, where)
        if self.has("structured_light"):
            self._validate_patterns("structured_light", self.sl_frames, where)
        if self.has("calib.projector") and "frames" in self._section("calib.projector"):
            self._validate_patterns("calib.projector", self.projector_frames, where)
        self._validate_world(names, where)
        if self.has("calib") and "corners" in self._section("calib"):
            for cam in names:
                if self.calib_views(cam):  # a camera that saw no view needs no corner list
                    self.calib_corners(cam)
        for key in self.reference_keys:
            p = self.reference_path(key)
            if not p.exists():
                raise _err(f"reference file not found: {p}", key=f"reference.{key}", path=where)
        if self.has("calib"):
            spec = self._m["calib"]["board"]
            if isinstance(spec, str):
                board = self._resolve(spec, key="calib.board", where=where)
                if not board.is_file():
                    raise _err(f"board file not found: {board}", key="calib.board", path=where)
            if check == "full" or not isinstance(spec, str):
                self.__dict__.pop("board", None)
                _ = self.board
        for key in self.ground_truth_keys:
            p = self.ground_truth_path(key)
            if not p.exists():
                raise _err(f"ground-truth file not found: {p}", key=f"ground_truth.{key}",
                           path=where)
        report = FrameCheck()
        for group in self.groups:
            for cam in cameras:
                _check_group_files(
                    self.expected_files(group, cam.name), self.response(group), group, cam,
                    full=(check == "full"), report=report,
                )
        self.frame_check = report
        report.raise_first_error()
        return self

    def _validate_olat(self, rig, where) -> None:
        lights = getattr(rig, "lights", None)
        if lights is None:
            raise _err("[olat] is present but the rig has no lights (rig.json lights = null)",
                       key="olat", path=where)
        grid = hasattr(lights, "n_theta")
        if self.n_lights != lights.n_lights:
            what = (f"light stage has {lights.n_lights} lights ({lights.n_theta} × "
                    f"{lights.n_phi})" if grid else f"light list has {lights.n_lights} lights")
            raise _err(
                f"n_lights = {self.n_lights} but the rig's {what}; "
                "they must be equal",
                key="olat.n_lights",
                path=where,
            )
        sect = self._section("olat")
        if not grid and sect["light_order"] != "theta-fastest":
            raise _err("light_order applies to the θ × φ grid; a light list's file order is its "
                       "list order (leave light_order out)", key="olat.light_order", path=where)
        if grid and "{light_name" in sect["files"]:
            raise _err("{light_name} needs a light list with names in the rig (rig.json lights "
                       "kind = \"list\"); the θ × φ grid has light numbers ({light})",
                       key="olat.files", path=where)

    def _validate_cameras_tables(self, names: list[str], where) -> None:
        """``[<group>.cameras.<camera>]``: known cameras, known views / frames / lights, bits
        within the pattern spec's."""
        for group in self.groups:
            tables = self._section(group).get("cameras", {})
            for cam, t in tables.items():
                key = f"{group}.cameras.{cam}"
                if cam not in names:
                    raise _err(f"no camera {cam!r} in the rig; cameras: {', '.join(names)}",
                               key=key, path=where)
                if group in ("calib", "calib.projector"):
                    n = self._section(group)["views"]
                    for k in ("views", "missing"):
                        bad = [v for v in t.get(k, ()) if v >= n]
                        if bad:
                            raise _err(f"view {bad[0]} is out of range: {group}.views = {n} "
                                       f"(views 0 … {n - 1})", key=f"{key}.{k}", path=where)
                elif group == "structured_light":
                    frames = self.sl_frames
                    bad = [f for f in t.get("missing", ()) if f not in frames]
                    if bad:
                        raise _err(f"{bad[0]!r} is not one of structured_light.frames",
                                   key=f"{key}.missing", path=where)
                    for axis in ("x", "y"):
                        if f"bits_{axis}" not in t:
                            continue
                        spec = self.pattern_spec()
                        if spec is None:
                            raise _err("per-camera bits need a pattern spec "
                                       "([structured_light.patterns])", key=f"{key}.bits_{axis}",
                                       path=where)
                        if t[f"bits_{axis}"] > spec.n_bits(axis):
                            raise _err(f"bits_{axis} = {t[f'bits_{axis}']} but the patterns "
                                       f"code {spec.n_bits(axis)} bits on {axis}",
                                       key=f"{key}.bits_{axis}", path=where)
                else:
                    for x in t.get("missing", ()):
                        try:
                            self._light_index(x)
                        except InputError as exc:
                            raise _err(f"{exc}", key=f"{key}.missing", path=where) from exc

    def _validate_patterns(self, group: str, frames: list[str], where) -> None:
        """The pattern spec must produce exactly the frame list (a missing inverse frame is a
        load error naming it)."""
        from facegeo.geometry.structured_light import pattern_names

        try:
            spec = self.pattern_spec(group)
        except ScanFormatError:
            if self.version == 1:  # version 1's patterns table was free-form, never parsed
                log.debug("%s: version-1 patterns table is not a PatternSpec; not checked",
                          self.manifest_path)
                return
            raise
        if spec is None:
            return
        if group == "structured_light":
            proj = getattr(self.rig, "projector", None)
            if proj is not None and (spec.width, spec.height) != (proj.width, proj.height):
                raise _err(f"patterns are for a {spec.width}×{spec.height} projector but the rig's "
                           f"projector is {proj.width}×{proj.height}",
                           key=f"{group}.patterns", path=where)
        want = pattern_names(spec)
        fkey = f"{group}.frames"
        missing = [n for n in want if n not in frames]
        if missing:
            raise _err(f"the pattern spec ({group}.patterns) projects frame {missing[0]!r}, which "
                       f"{fkey} does not list ({len(missing)} missing: "
                       f"{', '.join(missing[:4])}{', ...' if len(missing) > 4 else ''})",
                       key=fkey, path=where)
        extra = [f for f in frames if f not in want]
        if extra:
            raise _err(f"frame {extra[0]!r} is not a pattern of {group}.patterns (it projects "
                       f"{', '.join(want[:6])}{', ...' if len(want) > 6 else ''})",
                       key=fkey, path=where)

    def _validate_world(self, names: list[str], where) -> None:
        w = self._m["scan"].get("world")
        if w is None or "transform" in w:
            return
        if not self.has("calib"):
            raise _err("world = { camera, board_view } needs a [calib] section",
                       key="scan.world", path=where)
        if w["camera"] not in names:
            raise _err(f"no camera {w['camera']!r} in the rig; cameras: {', '.join(names)}",
                       key="scan.world.camera", path=where)
        if w["board_view"] not in self.calib_views(w["camera"]):
            raise _err(f"camera {w['camera']!r} has no calibration view {w['board_view']} (its "
                       f"views: {self.calib_views(w['camera'])})", key="scan.world.board_view",
                       path=where)

# =========================================================================== entry points
