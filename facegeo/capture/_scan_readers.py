"""Frame readers of a scan: linearised OLAT, structured-light and projector-calibration frames,
one at a time (:class:`facegeo.capture.scan.Scan`'s reading methods, kept in their own module).

Every frame is read through :func:`facegeo.capture.imageio.read_image` and linearised with the
group's response; ``return_mask`` adds the clipped/saturated sample mask; ``luminance=True``
returns Rec. 709 luminance (:data:`LUMINANCE_WEIGHTS`). OLAT frames read with
``subtract_ambient=True`` are ``max(frame − ambient, 0)`` (:func:`subtract_ambient_frame`), the
clipped pixels counted (:meth:`_ScanReaders.ambient_clipped`). See ``docs/scan-format.md``
(*Streaming*).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from facegeo.capture._scan_files import _size_error
from facegeo.capture._scan_schema import _err
from facegeo.capture.imageio import read_image
from facegeo.capture.response import clipped_mask, saturated_mask
from facegeo.checks import check_choice
from facegeo.errors import InputError

#: Linear-RGB → luminance weights (Rec. 709 / sRGB primaries, the library's RGB; ITU-R BT.709
#: item 3.2): ``Y = 0.2126 R + 0.7152 G + 0.0722 B``.
LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def subtract_ambient_frame(frame: np.ndarray, ambient: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``max(frame − ambient, 0)`` and where the clip acted.

    Parameters
    ----------
    frame, ambient : (H, W, C) float32, linear radiance, same shape

    Returns
    -------
    difference : (H, W, C) float32, ≥ 0 (NaN stays NaN)
    clipped : (H, W) bool
        Pixels where ``frame − ambient < 0`` in some channel (set to 0 there).
    """
    d = np.subtract(frame, ambient, dtype=np.float32)
    neg = d < 0  # False at NaN: NaN stays NaN
    d[neg] = 0.0
    clipped = neg.any(axis=-1) if neg.ndim == 3 else neg
    return d, clipped


def _luminance(lin: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32 luminance of a linear frame (grey frames pass through)."""
    if lin.ndim == 2:
        return lin
    return np.dot(lin[..., :3], LUMINANCE_WEIGHTS).astype(np.float32, copy=False)


class _ScanReaders:
    """Reading methods mixed into :class:`~facegeo.capture.scan.Scan`."""

    def _read(self, group: str, camera: str, path: Path, *, return_mask: bool,
              clipped_valid: bool = False):
        raw = read_image(path)
        cam = self.camera(camera)
        h, w = raw.shape[:2]
        if (w, h) != (cam.width, cam.height):
            raise _size_error(path, group, camera, (w, h), (cam.width, cam.height))
        try:
            lin = self.response(group).linearize(raw)
        except InputError as exc:
            raise _err(f"{exc}", key=f"{group}.response", path=path) from exc
        if not return_mask:
            return lin, None
        if raw.dtype.kind == "f":
            valid = np.isfinite(raw) if raw.ndim == 2 else np.isfinite(raw).all(axis=-1)
        elif clipped_valid:
            valid = ~saturated_mask(raw)
        else:
            valid = ~(saturated_mask(raw) | clipped_mask(raw))
        return lin, valid

    def olat_frame(self, camera: str, light: int | str, *, return_mask: bool = False,
                   subtract_ambient: bool = False, black_clipped: str = "masked",
                   return_clipped: bool = False):
        """One OLAT frame, linear.

        Parameters
        ----------
        camera : str
        light : int or str
            Light index (``l = j·n_theta + i`` for the grid; the list position for a light
            list) or a light list's light name.
        return_mask : bool
            Also return where the samples can be trusted.
        subtract_ambient : bool
            Subtract :meth:`ambient_frame` (needs ``olat.ambient``) and clip the difference at
            0 (:func:`subtract_ambient_frame`): noise, or an ambient frame a little brighter
            than the flash frame, would leave negative radiance where the light adds nothing,
            which no reflectance fit accepts. The pixels clipped are counted per frame
            (:meth:`ambient_clipped`) and returned with ``return_clipped``.
        black_clipped : {"masked", "dark"}
            With ``return_mask``: ``"masked"`` (the convention) flags black-clipped samples of
            integer frames as untrusted; ``"dark"`` counts them as measured dark values (the
            true value lies below one code value) and flags only saturated ones — what the
            projection of a one-light-at-a-time frame wants, where most of the head is in
            shadow (:func:`facegeo.pipeline.project.run_project`).
        return_clipped : bool
            Also return the ``(H, W)`` bool mask of pixels where the ambient subtraction was
            clipped at 0 in some channel (all False without ``subtract_ambient``). A clipped
            sample is a measured dark value (0), not an untrusted one: ``valid`` is unchanged.

        Returns
        -------
        frame : (H, W, 3) float32, linear radiance
            The linearised pixel values divided by ``[olat] exposure``; ≥ 0 with
            ``subtract_ambient`` (for integer frames). Grey frames are repeated to three
            channels; alpha is dropped.
        valid : (H, W) bool, only with ``return_mask``
            False where a sample is saturated or black-clipped (integer frames) or non-finite
            (float frames).
        clipped : (H, W) bool, only with ``return_clipped``, last
            Where ``frame − ambient`` was negative in some channel and was set to 0.
        """
        check_choice(black_clipped, "black_clipped", ("masked", "dark"))
        lin, valid = self._olat_read(camera, self.olat_path(camera, light), return_mask,
                                     clipped_valid=black_clipped == "dark")
        clipped = None
        if subtract_ambient:
            lin, clipped = subtract_ambient_frame(lin, self.ambient_frame(camera))
            counts = self.__dict__.setdefault("_ambient_clipped", {})
            counts[(camera, self._light_index(light))] = int(np.count_nonzero(clipped))
        elif return_clipped:
            clipped = np.zeros(lin.shape[:2], bool)
        out = (lin,) + ((valid,) if return_mask else ()) + ((clipped,) if return_clipped else ())
        return out[0] if len(out) == 1 else out

    def ambient_clipped(self, camera: str | None = None) -> dict:
        """Pixels clipped at 0 by the ambient subtraction, per frame read so far with
        ``subtract_ambient=True``: ``{(camera, light index): pixels}`` (only ``camera``'s frames
        when given). A frame read again replaces its count. Empty before any such read."""
        counts = dict(self.__dict__.get("_ambient_clipped", {}))
        return counts if camera is None else {k: v for k, v in counts.items() if k[0] == camera}

    def _olat_read(self, camera: str, path: Path, return_mask: bool, *,
                   clipped_valid: bool = False):
        lin, valid = self._read("olat", camera, path, return_mask=return_mask,
                                clipped_valid=clipped_valid)
        exposure = float(self._section("olat").get("exposure", 1.0))
        if exposure != 1.0:
            lin = lin / np.float32(exposure)
        if lin.ndim == 2:
            lin = np.repeat(lin[..., None], 3, axis=-1)
        elif lin.shape[-1] == 4:
            lin = np.ascontiguousarray(lin[..., :3])
        return lin, valid

    def ambient_frame(self, camera: str) -> np.ndarray:
        """``camera``'s ambient frame (no light on), ``(H, W, 3)`` float32 linear, divided by
        ``olat.exposure`` like the OLAT frames; read once and cached.

        Raises
        ------
        ScanFormatError
            The scan declares no ``olat.ambient``.
        """
        a = self._ambient.get(camera)
        if a is None:
            p = self.ambient_path(camera)
            if p is None:
                raise _err("this scan has no ambient frame (olat.ambient)", key="olat.ambient",
                           path=self.manifest_path)
            a = self._olat_read(camera, p, False)[0]
            a.setflags(write=False)
            self._ambient[camera] = a
        return a

    def iter_olat(self, camera: str, lights: Sequence[int] | None = None, *,
                  return_mask: bool = False, subtract_ambient: bool = False,
                  read_ahead: int = 0, black_clipped: str = "masked",
                  return_clipped: bool = False) -> Iterator[tuple]:
        """Yield ``(light, frame)`` (or ``(light, frame, valid)``; ``return_clipped`` adds the
        ambient-clipped mask last) for ``lights`` (default the lights ``camera`` has, in
        light-index order), reading one frame at a time.

        ``read_ahead=N`` (N ≥ 2) reads and decodes the next frames on N threads while the caller
        works on this one (:func:`facegeo.fsutil.read_ahead`; a few frames in flight, bounded
        in bytes). Image reads keep only native libraries' own failure messages off the
        console (``imageio``); what other threads print meanwhile reaches the terminal.
        ``black_clipped``, ``subtract_ambient``: see :meth:`olat_frame`."""
        from facegeo.fsutil import read_ahead as ahead

        def read(light):
            out = self.olat_frame(camera, light, return_mask=return_mask,
                                  subtract_ambient=subtract_ambient, black_clipped=black_clipped,
                                  return_clipped=return_clipped)
            return (light, *out) if isinstance(out, tuple) else (light, out)

        yield from ahead(read, self.camera_frames("olat", camera) if lights is None else lights,
                         workers=int(read_ahead))

    def sl_frame(self, camera: str, frame: str, *, return_mask: bool = False,
                 luminance: bool = False):
        """One structured-light frame, linear.

        Parameters
        ----------
        camera, frame : str
        return_mask : bool
            Also return where the samples can be trusted.
        luminance : bool
            Return single-channel luminance ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` of the
            linear frame (:data:`LUMINANCE_WEIGHTS`): a third of the memory of RGB, all a
            Gray-code or phase decoder needs.

        Returns
        -------
        frame : (H, W) or (H, W, 3) float32, linear, channels as stored (alpha dropped);
            ``(H, W)`` with ``luminance``
        valid : (H, W) bool, only with ``return_mask`` (see :meth:`olat_frame`)
        """
        return self._sl_like("structured_light", camera, self.sl_path(camera, frame),
                             return_mask, luminance)

    def _sl_like(self, group, camera, path, return_mask, luminance):
        lin, valid = self._read(group, camera, path, return_mask=return_mask)
        if luminance:
            lin = _luminance(lin)
        elif lin.ndim == 3 and lin.shape[-1] == 4:
            lin = np.ascontiguousarray(lin[..., :3])
        return (lin, valid) if return_mask else lin

    def iter_sl(self, camera: str, frames: Sequence[str] | None = None, *,
                luminance: bool = False, return_mask: bool = False,
                read_ahead: int = 0) -> Iterator[tuple]:
        """Yield ``(name, frame)`` (or ``(name, frame, valid)``) for ``frames`` (default the
        frames ``camera`` has, in capture order), reading one frame at a time: only the frame
        being yielded is held (with ``read_ahead``, also the few read ahead, bounded in bytes:
        see :meth:`iter_olat`), so a decoder that accumulates bit planes never holds the group.
        See :meth:`sl_frame` for ``luminance``."""
        from facegeo.fsutil import read_ahead as ahead

        def read(name):
            out = self.sl_frame(camera, name, return_mask=return_mask, luminance=luminance)
            return (name, *out) if return_mask else (name, out)

        yield from ahead(read, self.camera_frames("structured_light", camera)
                         if frames is None else frames, workers=int(read_ahead))

    def projector_frame(self, camera: str, view: int, frame: str, *, return_mask: bool = False,
                        luminance: bool = False):
        """One projector-calibration frame (the board in view ``view`` under pattern
        ``frame``), linearised with ``calib.response``; see :meth:`sl_frame` for the options."""
        paths = self.projector_view_paths(camera, view)
        check_choice(frame, "frame", list(paths))
        return self._sl_like("calib.projector", camera, paths[frame], return_mask, luminance)

    def iter_projector(self, camera: str, view: int, *, luminance: bool = False,
                       return_mask: bool = False) -> Iterator[tuple]:
        """Yield ``(name, frame)`` over the patterns of projector-calibration view ``view``,
        one frame at a time (see :meth:`projector_frame`)."""
        for name in self.projector_frames:
            out = self.projector_frame(camera, view, name, return_mask=return_mask,
                                       luminance=luminance)
            yield (name, *out) if return_mask else (name, out)

    # ------------------------------------------------------------------ validation
