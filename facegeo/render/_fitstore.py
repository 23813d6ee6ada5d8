"""Per-camera skin-model fits on disk: what :func:`facegeo.appearance.skin.resynthesize` needs.

Private module behind :mod:`facegeo.render`. A camera's folder ``<dest>/<camera>/`` holds

    fit.npz   per fitted function: ``rows`` (row of the camera's projected field),
              ``texel_index``, the SkinFit's per-function parameters (view, normals, d_0,
              α_0, α_1, ρ_d, ρ_s, flags, valid, lobe misfits), its shadow / cast-shadow /
              saturation maps bit-packed, eta and single_channel
    D.npy     ``(N, L, C)`` the diffuse component D of the final separation (float16 by
              default, float32 on request), memory-mapped when read

The specular component is not stored: S = R − D with R the projected field (the fit's own
definition, so D + S reproduces the measured function exactly and a view equal to the source
view returns it unchanged). With float16 D, S differs from the fit's by at most D's rounding
(2⁻¹¹ of D). :meth:`FitStore.relit_rows` reads float16 R and D in the compiled pass of
:func:`facegeo.appearance._skin_resynth.relit_stored` (no float32 copies; S formed there as
:meth:`FitStore.skin_fit` forms it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facegeo.errors import InputError
from facegeo.fsutil import NpyRowFile, aligned_empty

FIT_FILE = "fit.npz"
DIFFUSE_FILE = "D.npy"

_PER_FUNCTION = ("view", "normal", "normal_moment", "normal_initial", "lobe_misfit_moment",
                 "lobe_misfit", "d_0", "alpha_0", "alpha_1", "rho_d", "rho_s", "flags", "valid")
_MAPS = ("shadow", "cast_shadow", "saturated")


def light_set(stage):
    """The :class:`facegeo.appearance.skin.LightSet` of a rig's lights.

    Directions are the stage's (toward each light from the stage centre); near-field lights
    are treated as distant from the surface point, as :func:`fit_reflectance` requires (the
    direction error is at most the head radius over the stage radius, ≈ 6° at 1.5 m). A
    light-stage grid (:class:`facegeo.geometry.rig.LightStage`) keeps its grid (bilinear
    interpolation in Eq. 9, the compiled grid kernels, ``light_step``); a free list
    (:class:`facegeo.geometry.lights.LightList`: a real rig's measured positions) gives a free
    light set with the list's δA and intensities (Eq. 9 interpolates between the three
    nearest lights; ``light_step`` must be 1).
    """
    from facegeo.appearance.skin import LightSet

    if hasattr(stage, "n_theta"):
        return LightSet.from_grid(stage.n_theta, stage.n_phi, stage.color)
    dark = np.flatnonzero(np.any(np.asarray(stage.intensities) <= 0, axis=1))
    if dark.size:
        names = ", ".join(stage.names[i] for i in dark[:5]) + (", ..." if dark.size > 5 else "")
        raise InputError(f"lights: the skin model needs every light brighter than 0 in every "
                         f"channel; {dark.size} are not ({names}): leave them out of the rig's "
                         "light list")
    return LightSet.from_directions(stage.directions, stage.solid_angles, stage.intensities)


class FitWriter:
    """Write a camera's fits chunk by chunk (bounded memory: one chunk's D at a time).

    D goes to ``D.npy`` block by block (:class:`facegeo.fsutil.NpyRowFile`: a preallocated
    file, direct writes for aligned blocks; a memory map written in place cost ≈ 4 s of
    kernel time per GB here, 10 s of a 200 k-function camera's fit).

    Parameters
    ----------
    directory : path
        The camera's folder (created).
    n : int
        Functions that will be written.
    n_lights, channels : int
    dtype : {"float16", "float32"}
        Storage of D.
    """

    def __init__(self, directory, n: int, n_lights: int, channels: int = 3,
                 dtype: str = "float16"):
        if dtype not in ("float16", "float32"):
            raise InputError(f"diffuse_dtype: expected 'float16' or 'float32', got {dtype!r}")
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.n = int(n)
        self.dtype = np.dtype(dtype)
        self.row_shape = (int(n_lights), int(channels))
        self._file = NpyRowFile(self.dir / DIFFUSE_FILE, (self.n,) + self.row_shape, self.dtype)
        self._slot = aligned_empty((0,) + self.row_shape, self.dtype)  # reused, grown on demand
        self.parts: dict[str, list] = {k: [] for k in _PER_FUNCTION + _MAPS}
        self.rows: list[np.ndarray] = []
        self.texels: list[np.ndarray] = []
        self.done = 0
        self.eta = 1.4
        self.single = False

    def diffuse_slot(self, k: int) -> np.ndarray:
        """A buffer for the next ``k`` fits' D (``(k, L, C)`` of the store's dtype): pass it as
        ``fit_reflectance(diffuse_out=…)`` and :meth:`write` stores it without a copy. The same
        memory is lent again by the next call (one chunk in flight)."""
        k = int(k)
        if not 0 <= k <= self.n - self.done:
            raise InputError(f"{self.dir}: {k} more fits do not fit ({self.done} of {self.n} "
                             "written)")
        if self._slot.shape[0] < k:
            self._slot = aligned_empty((k,) + self.row_shape, self.dtype)
        return self._slot[:k]

    def write(self, rows, texel_index, fit) -> None:
        """Append the fits of field rows ``rows`` (texels ``texel_index``)."""
        k = len(rows)
        if k > self.n - self.done:
            raise InputError(f"{self.dir}: {k} more fits do not fit ({self.done} of {self.n} "
                             "written)")
        d = fit.diffuse
        if not (isinstance(d, np.ndarray) and d.dtype == self.dtype and d.flags.c_contiguous):
            d = np.ascontiguousarray(d, dtype=self.dtype)  # else the fit wrote a slot
        if d.shape != (k,) + self.row_shape:
            raise InputError(f"{self.dir}: expected D of shape {(k,) + self.row_shape}, got "
                             f"{d.shape}")
        self._file.write(self.done, d)
        self.done += k
        self.rows.append(np.asarray(rows, np.int64))
        self.texels.append(np.asarray(texel_index, np.int64))
        for name in _PER_FUNCTION:
            self.parts[name].append(np.asarray(getattr(fit, name)))
        for name in _MAPS:
            self.parts[name].append(np.packbits(np.asarray(getattr(fit, name), bool), axis=1))
        self.eta = float(fit.eta)
        self.single = bool(fit.single_channel)

    def close(self) -> Path:
        """Flush D and write ``fit.npz``; returns its path."""
        if self.done != self.n:
            raise InputError(f"{self.dir}: {self.done} fits written, {self.n} announced")
        self._file.close()
        L = self.row_shape[0]
        arrays = {k: (np.concatenate(v) if v else np.zeros((0,)))
                  for k, v in self.parts.items()}
        path = self.dir / FIT_FILE
        np.savez(path, rows=np.concatenate(self.rows) if self.rows else np.zeros(0, np.int64),
                 texel_index=(np.concatenate(self.texels) if self.texels
                              else np.zeros(0, np.int64)),
                 eta=np.array(self.eta), single_channel=np.array(self.single),
                 n_lights=np.array(L), **arrays)
        return path


@dataclass
class FitStore:
    """A camera's fits, loaded from its folder (parameters in memory, D memory-mapped).

    Attributes
    ----------
    directory : Path
    rows : (N,) int64 — row of the camera's projected field of each fit (increasing)
    texel_index : (N,) int64
    params : dict of str -> array — per-function parameters and packed maps
    D : (N, L, C) memmap
    eta : float
    single_channel : bool
    """

    directory: Path
    rows: np.ndarray
    texel_index: np.ndarray
    params: dict
    D: np.ndarray
    eta: float
    single_channel: bool

    @classmethod
    def load(cls, directory) -> FitStore:
        d = Path(directory)
        if not (d / FIT_FILE).is_file() or not (d / DIFFUSE_FILE).is_file():
            raise InputError(f"{d}: no skin-model fit here ({FIT_FILE}, {DIFFUSE_FILE}); run "
                             f"'facegeo fit SCAN' first")
        with np.load(d / FIT_FILE) as z:
            params = {k: z[k] for k in _PER_FUNCTION + _MAPS}
            rows, tex = z["rows"].astype(np.int64), z["texel_index"].astype(np.int64)
            eta, single = float(z["eta"]), bool(z["single_channel"])
        D = np.load(d / DIFFUSE_FILE, mmap_mode="r")
        if D.shape[0] != rows.size:
            raise InputError(f"{d}: {DIFFUSE_FILE} holds {D.shape[0]} functions, {FIT_FILE} "
                             f"{rows.size} (re-run 'facegeo fit')")
        order = np.argsort(rows, kind="stable")
        if np.any(order != np.arange(rows.size)):
            raise InputError(f"{d}: fitted rows are not in field order (re-run 'facegeo fit')")
        return cls(d, rows, tex, params, D, eta, single)

    def __len__(self) -> int:
        return int(self.rows.size)

    def locate(self, field_rows) -> tuple[np.ndarray, np.ndarray]:
        """Fit index of each field row, and whether the row was fitted."""
        field_rows = np.asarray(field_rows, np.int64)
        pos = np.searchsorted(self.rows, field_rows)
        pos_c = np.minimum(pos, max(len(self) - 1, 0))
        found = (pos < len(self)) & (self.rows[pos_c] == field_rows) if len(self) else \
            np.zeros(field_rows.shape, bool)
        return pos_c, found

    def skin_fit(self, idx, R, lights):
        """The :class:`facegeo.appearance.skin.SkinFit` of fits ``idx`` with measured functions R.

        Parameters
        ----------
        idx : (n,) int, fit indices (increasing, for memory-map locality)
        R : (n, L, C) float32, the projected field's rows of these fits
        lights : LightSet
        """
        from facegeo.appearance.skin import SkinFit

        idx = np.asarray(idx, np.int64)
        L = R.shape[1]
        p = {k: self.params[k][idx] for k in _PER_FUNCTION}
        maps = {k: np.unpackbits(self.params[k][idx], axis=1, count=L).astype(bool)
                for k in _MAPS}
        D = np.asarray(self.D[idx], np.float32)
        S = np.asarray(R, np.float32) - D
        return SkinFit(lights=lights, view=p["view"], normal=p["normal"],
                       normal_moment=p["normal_moment"], normal_initial=p["normal_initial"],
                       lobe_misfit_moment=p["lobe_misfit_moment"], lobe_misfit=p["lobe_misfit"],
                       d_0=p["d_0"], alpha_0=p["alpha_0"], alpha_1=p["alpha_1"],
                       rho_d=p["rho_d"], rho_s=p["rho_s"], diffuse=D, specular=S,
                       shadow=maps["shadow"], cast_shadow=maps["cast_shadow"],
                       saturated=maps["saturated"], flags=p["flags"].astype(np.int32),
                       valid=p["valid"].astype(bool), eta=self.eta,
                       single_channel=self.single_channel)

    def relit_rows(self, field, field_rows, idx, todo, v_n, weights, lights, light_step=1):
        """Eq. 4 of measured functions and of the same functions resynthesised for v_n, read
        and resynthesised in one compiled pass over the float16 field and D
        (:func:`facegeo.appearance._skin_resynth.relit_stored`; R, D and S are not built as
        float32 arrays). Only where ``uses_stored_kernel``.

        Parameters
        ----------
        field : (T, L, 3) float16 memmap — the camera's projected field
        field_rows : (n,) int — rows of ``field``; idx : (n,) int — their fit indices
        todo : (n,) bool — rows to resynthesise (fitted, not the source view)
        v_n : (n, 3) float64, unit, the light set's frame; weights : (L, 3); lights : LightSet
        light_step : int ≥ 1 — resynthesis on k × k blocks of the grid (``relit_stored``)

        Returns
        -------
        naive, relit : (n, 3) float64 — as ``relit_stored`` (NaN naive where a sample is not
            finite; relit 0 where not resynthesised)
        finite : (n,) bool
        back : (n,) bool — the fit's FLAG_BACKFACING or n·v_n ≤ 0 (the caller keeps the
            naive value there)
        """
        from facegeo.appearance._skin_resynth import relit_stored
        from facegeo.appearance.skin import FLAG_BACKFACING

        idx = np.asarray(idx, np.int64)
        L = field.shape[1]
        p = {k: self.params[k][idx] for k in ("view", "normal", "alpha_0", "alpha_1", "flags")}
        cast = np.unpackbits(self.params["cast_shadow"][idx], axis=1, count=L).astype(bool)
        naive, relit, finite = relit_stored(
            field, field_rows, self.D, idx, todo, normal=p["normal"], view=p["view"],
            alpha_0=p["alpha_0"], alpha_1=p["alpha_1"], cast_shadow=cast, eta=self.eta,
            lights=lights, v_n=v_n, weights=weights, light_step=light_step)
        back = (((p["flags"].astype(np.int32) & FLAG_BACKFACING) != 0)
                | (np.einsum("ni,ni->n", p["normal"], np.asarray(v_n, np.float64)) <= 0))
        return naive, relit, finite, back

    def uses_stored_kernel(self, field, lights) -> bool:
        """Whether :meth:`relit_rows` serves this camera (float16 field and D, a 3-channel fit
        on the light-stage grid; any number of lights with energy, any ``light_step``)."""
        from facegeo.appearance._skin_resynth import stored_kernel_applies

        return stored_kernel_applies(field, self.D, lights, self.single_channel)
