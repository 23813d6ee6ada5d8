"""The paper's skin reflectance model: separation, normals, chromaticity ramp, shadow maps and
resynthesis of reflectance functions for novel views (Debevec et al. 2000, §4, Eq. 5–9).

This is the paper's model implemented exactly — not the generator's deliberately mismatched
BRDF of :mod:`facegeo.appearance.brdf` (whose RGB α's also change brightness). Pieces:

* :func:`ramp_f`, :func:`ramp_chromaticity` — the diffuse chromaticity ramp, Eq. 6–7;
* :func:`paper_reflectance` — the model evaluated exactly ("paper mode", forward);
* :func:`separate_colour` — the colour-space separation of §4.2;
* :func:`fit_reflectance` — the whole analysis of §4.2 with the shadow maps of §4.4;
* :func:`resynthesize` — new reflectance functions for a novel view, §4.3 with Eq. 9.
* :func:`resynthesize_relit` — Eq. 4 on the resynthesised functions, fused (no (N, L, 3) result).

Reflectance functions are ``(N, L, 3)`` float32 (linear RGB OLAT radiance, one row per texel or
pixel, one column per light of a :class:`LightSet`); directions are unit vectors in the light
set's frame. Per-function numerical trouble never raises and never yields NaN or inf: results
are finite fallbacks with bits set in ``flags`` (:data:`FLAG_NAMES`) and ``valid`` False.

References
----------
.. [1] P. Debevec et al., "Acquiring the Reflectance Field of a Human Face", SIGGRAPH 2000, §4.
.. [2] K. E. Torrance, E. M. Sparrow, "Theory for off-specular reflection from roughened
   surfaces", JOSA 57(9), 1967.
.. [3] W.-C. Ma et al., "Rapid Acquisition of Specular and Diffuse Normal Maps from Polarized
   Spherical Gradient Illumination", EGSR 2007 (first-moment normals).
"""

from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass, replace

import numpy as np

from facegeo.appearance import _skin_fit
from facegeo.appearance._skin_fit import (
    FLAG_BACKFACING,
    FLAG_BLACK,
    FLAG_GRAZING_VIEW,
    FLAG_MASKED,
    FLAG_RAMP_REJECTED,
    FLAG_NAMES,
    FLAG_SATURATED,
    FLAG_SHADOWED,
    FLAG_SINGLE_CHANNEL,
    FLAG_SINGULAR,
    FLAG_SPECULAR_IN_SHADOW,
    FLAG_SPECULAR_SKIPPED,
    GRAZING_COS,
    MIN_SAMPLES,
    SHADOW_THRESHOLD,
    SearchDepth,
    check_mask,
    check_reflectance,
    check_views,
    direct_search,
    fit_lambertian_lobe,
    fit_ramp,
    initial_diffuse_chromaticity,
    moment_normal,
    specular_energy,
)
from facegeo.appearance._skin_model import (
    S_WHITE,
    SINGULAR_SIN2,
    LightSet,
    SkinParams,
    invert_ramp,
    normalize,
    paper_reflectance,
    ramp_chromaticity,
    ramp_f,
    separate_colour,
    specular_sample,
)
from facegeo.appearance._near_field import NearField
from facegeo.appearance._skin_resynth import (
    Resynthesis,
    resynthesize,
    resynthesize_relit,
    view_independent,
)
from facegeo.checks import as_array, check_unit_vectors, fmt_value

log = logging.getLogger(__name__)

__all__ = [
    "LightSet", "SkinParams", "SkinFit", "SearchDepth", "Resynthesis",
    "ramp_f", "ramp_chromaticity", "invert_ramp", "specular_sample", "paper_reflectance",
    "separate_colour", "shadow_map", "fit_reflectance", "fit_reflectance_near", "NearField",
    "resynthesize", "resynthesize_relit",
    "view_independent",
    "direct_search", "flag_names", "check_mask", "FLAG_NAMES", "FLAG_BLACK", "FLAG_SINGULAR", "FLAG_SHADOWED",
    "FLAG_SATURATED", "FLAG_SINGLE_CHANNEL", "FLAG_GRAZING_VIEW", "FLAG_SPECULAR_IN_SHADOW",
    "FLAG_SPECULAR_SKIPPED", "FLAG_BACKFACING", "FLAG_MASKED", "FLAG_RAMP_REJECTED", "S_WHITE", "SHADOW_THRESHOLD", "normalize",
]

#: Samples (functions × lights) per chunk of the analysis. With the compiled kernels
#: (``_skin_fit.KERNELS``) the searches keep their temporaries per function, so the chunk only
#: bounds the numpy steps' (chunk, L, 3) arrays (6 MB at 64 × 2048) and is the unit of work
#: of ``threads=`` (measured under load, 64 functions per chunk were as fast as 16).
CHUNK_SAMPLES = 131072
#: Default functions per chunk at 2048 lights (``CHUNK_SAMPLES // L`` in general, ≥ 64).
CHUNK = 64
#: Default ``chroma_gate`` of :func:`fit_reflectance` (noise σ's of the chromaticity check).
CHROMA_GATE = 3.0


@dataclass
class SkinFit:
    """Result of :func:`fit_reflectance` for N reflectance functions.

    Attributes
    ----------
    lights : LightSet
    view : (N, 3) float64, unit
        v_0, toward the camera that measured each function.
    normal : (N, 3) float64, unit
        n_d: the Lambertian-lobe normal of the final diffuse component (Fig. 14 b).
    normal_moment : (N, 3) float64, unit
        Closed-form first-moment normal Σ D ω δA of the initial diffuse component (Ma 2007).
    normal_initial : (N, 3) float64, unit
        Lobe-search normal of the initial (uniform-d_0) separation, which the ramp fit used.
    lobe_misfit_moment, lobe_misfit : (N,) float64
        Relative misfit 1 − cos² of the Lambertian lobe to the initial diffuse brightness at
        the moment normal and at the searched normal (how much the search improves).
        These four are the fit's starts: above twice ``SearchDepth.sample_lights`` lights
        they are computed on the light subsample (:func:`_skin_fit.light_subsample`).
    d_0 : (N, 3) float64, unit; alpha_0, alpha_1 : (N,) float64
        The chromaticity ramp (Eq. 6–7).
    rho_d : (N, 3) float64
        Diffuse albedo a·d_0 (Fig. 14 c), white-balanced.
    rho_s : (N,) float64
        Specular energy (Fig. 14 d).
    diffuse, specular : (N, L, C) float32
        D and S of the final separation, in the input's units (D + S = R). ``diffuse`` is
        float16 when the caller had it written into a float16 array, ``specular`` None when
        the caller did not ask for it (:func:`fit_reflectance`'s ``diffuse_out``,
        ``specular``).
    shadow : (N, L) bool
        Shadow map (§4.4): thresholded brightness or the caller's visibility; the analysis
        ignores these samples. Includes attached shadows (n·l ≤ 0) and the dark terminator.
    cast_shadow : (N, L) bool
        The part of ``shadow`` that the fitted diffuse lobe says should be lit (brighter than
        twice the threshold), plus every light the caller's visibility hides: occluded lights.
        Resynthesis puts no specular lobe there (§4.4).
    saturated : (N, L) bool
        Samples left out of the analysis as untrusted: saturated (``saturation``) or masked by
        the caller (``masked``; :data:`FLAG_SATURATED` and :data:`FLAG_MASKED` say which).
    flags : (N,) int32; valid : (N,) bool
    eta : float
    single_channel : bool
    near : NearField or None
        Set by :func:`fit_reflectance_near`: each function's point in a near-field light stage;
        :func:`resynthesize` then evaluates Eq. 9 with every light where it is. Not stored by
        :meth:`save` (a loaded fit is resynthesised as distant: pass ``near`` again with
        :func:`dataclasses.replace`).
    """

    lights: LightSet
    view: np.ndarray
    normal: np.ndarray
    normal_moment: np.ndarray
    normal_initial: np.ndarray
    lobe_misfit_moment: np.ndarray
    lobe_misfit: np.ndarray
    d_0: np.ndarray
    alpha_0: np.ndarray
    alpha_1: np.ndarray
    rho_d: np.ndarray
    rho_s: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray | None
    shadow: np.ndarray
    cast_shadow: np.ndarray
    saturated: np.ndarray
    flags: np.ndarray
    valid: np.ndarray
    eta: float
    single_channel: bool
    near: NearField | None = None

    @property
    def reflectance(self) -> np.ndarray:
        """D + S, ``(N, L, C)`` float32: the measured functions (the separation recombines)."""
        self._need_specular("reflectance")
        return self.diffuse + self.specular

    def _need_specular(self, what: str) -> None:
        if self.specular is None:
            from facegeo.errors import InputError

            raise InputError(f"{what}: this fit holds no specular component (fitted with "
                             "specular=False); refit with specular=True")

    def save(self, path) -> None:
        """Write the fit to one ``.npz`` file, atomically (:func:`facegeo.fsutil.atomic_path`).

        Every array attribute is stored under its own name, the light set as ``lights_*``
        arrays, scalars as 0-d arrays (format version :data:`SKINFIT_FORMAT`). No pickles:
        :meth:`load` reads it with ``allow_pickle=False``.

        Parameters
        ----------
        path : path-like
            Destination; conventionally ending ``.npz`` (written as given, never renamed).
        """
        from facegeo.fsutil import atomic_path

        self._need_specular("SkinFit.save")
        arrays = {k: np.asarray(getattr(self, k)) for k in _SKINFIT_ARRAYS}
        lt = self.lights
        arrays.update(lights_directions=lt.directions, lights_solid_angles=lt.solid_angles,
                      lights_intensities=lt.intensities,
                      lights_grid=np.asarray(lt.grid if lt.grid is not None else (-1, -1),
                                             np.int64),
                      eta=np.float64(self.eta), single_channel=np.bool_(self.single_channel),
                      format=np.int64(SKINFIT_FORMAT))
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)

    @classmethod
    def load(cls, path) -> SkinFit:
        """Read a fit written by :meth:`save`.

        Raises
        ------
        ScanFormatError
            The file is missing, not an ``.npz``, of another format version, or lacks an
            array or has one of the wrong shape (the message names the file and the key).
        """
        from facegeo.errors import ScanFormatError

        try:
            z = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ScanFormatError(f"cannot read a skin fit (.npz from SkinFit.save): {exc}",
                                  path=path) from exc
        with z:
            missing = [k for k in (*_SKINFIT_ARRAYS, "lights_directions", "lights_solid_angles",
                                   "lights_intensities", "lights_grid", "eta", "single_channel",
                                   "format") if k not in z.files]
            if missing:
                raise ScanFormatError(f"not a skin fit: missing arrays {missing}", path=path,
                                      key=missing[0])
            if int(z["format"]) != SKINFIT_FORMAT:
                raise ScanFormatError(f"skin fit format {int(z['format'])}, expected "
                                      f"{SKINFIT_FORMAT}", path=path, key="format")
            a = {k: z[k] for k in z.files}
        grid = tuple(int(g) for g in a["lights_grid"])
        lights = LightSet(a["lights_directions"], a["lights_solid_angles"],
                          a["lights_intensities"], None if grid[0] < 0 else grid)
        N, L = a["shadow"].shape if a["shadow"].ndim == 2 else (-1, -1)
        for k in _SKINFIT_ARRAYS:
            lead = a[k].shape[:2] if k in ("diffuse", "specular", "shadow", "cast_shadow",
                                           "saturated") else a[k].shape[:1]
            want = (N, L) if len(lead) == 2 else (N,)
            if lead != want or lights.n_lights != L:
                raise ScanFormatError(f"array shape {a[k].shape} does not match {N} functions "
                                      f"× {lights.n_lights} lights", path=path, key=k)
        return cls(lights=lights, eta=float(a["eta"]), single_channel=bool(a["single_channel"]),
                   **{k: a[k] for k in _SKINFIT_ARRAYS})


#: Version of the ``.npz`` layout written by :meth:`SkinFit.save`.
SKINFIT_FORMAT = 1
_SKINFIT_ARRAYS = ("view", "normal", "normal_moment", "normal_initial", "lobe_misfit_moment",
                   "lobe_misfit", "d_0", "alpha_0", "alpha_1", "rho_d", "rho_s", "diffuse",
                   "specular", "shadow", "cast_shadow", "saturated", "flags", "valid")


def flag_names(flags: int) -> list[str]:
    """Names of the bits set in one flags value."""
    return [name for bit, name in FLAG_NAMES.items() if int(flags) & bit]


def shadow_map(R, *, threshold: float = SHADOW_THRESHOLD, visibility=None, saturated=None):
    """Shadow map of each reflectance function (§4.4), ``(N, L)`` bool, True = shadowed.

    Brightness thresholding as in the paper (Fig. 13): a sample is shadowed when its brightness
    (sum over channels) is below ``threshold`` times the function's 99th-percentile brightness
    over unsaturated samples. Beyond the paper, an externally computed ``visibility`` ``(N, L)``
    bool (e.g. Embree shadow rays toward each light; True = the light is visible) marks every
    invisible light shadowed too. Attached shadows (n·l ≤ 0) are dark and come out shadowed.

    Parameters
    ----------
    R : (N, L, C) array_like, ≥ 0
    threshold : float in (0, 1)
    visibility, saturated : (N, L) bool, optional
    """
    R = np.asarray(R, np.float64)
    if R.ndim == 2:
        R = R[..., None]
    N, L = R.shape[:2]
    if not 0.0 < float(threshold) < 1.0:
        from facegeo.errors import InputError

        raise InputError(f"threshold: expected a fraction in (0, 1), got {fmt_value(threshold)}")
    sat = check_mask(saturated, "saturated", N, L)
    b = R.sum(axis=2)
    ref = np.percentile(np.where(sat, 0.0, b), 99, axis=1)
    shadow = b <= threshold * ref[:, None]
    if visibility is not None:
        shadow |= ~check_mask(visibility, "visibility", N, L)
    return shadow


def fit_reflectance(R, v, lights: LightSet, *, visibility=None, saturation: float | None = None,
                    masked=None,
                    eta: float = 1.4, depth: SearchDepth | None = None,
                    shadow_threshold: float = SHADOW_THRESHOLD, d_0=None, rounds: int = 1,
                    chunk: int | None = None, threads: int = 1,
                    specular_gate: float = 0.0, diffuse_out=None,
                    specular: bool = True, chroma_gate: float = CHROMA_GATE) -> SkinFit:
    """Fit the paper's skin model to reflectance functions (Debevec et al. 2000, §4.2 and §4.4).

    Steps, each vectorised over a chunk of functions:

    1. White-balance by the light intensities; mask saturated samples and the caller's masked
       ones; shadow map (§4.4, :func:`shadow_map`); the analysis runs on unshadowed,
       unsaturated, unmasked samples.
    2. Initial uniform diffuse chromaticity d_0 from the median R/G and G/B ratios in a
       brightness range, and a colour-space separation with it (§4.2, :func:`separate_colour`).
    3. Normal: the closed-form first moment Σ D ω δA (Ma et al. 2007), then the Lambertian-lobe
       fit to |D| by coarse-to-fine direct search started from it (§4.2).
    4. α_0, α_1 (Eq. 7) by coarse-to-fine direct search with samples near the mirror direction
       down-weighted, then a Levenberg–Marquardt polish of α_0, α_1 and the normal together;
       where the lobe leaves the ramp's scale undecided (model mismatch), a second polish
       adds the paper's fit to the observed chromaticities (``SearchDepth.chroma``; see
       :func:`facegeo.appearance._skin_fit.fit_ramp` for the criterion and why).
    5. Final separation with the fitted ramp (Eq. 6 per sample; optionally μ_s gated at the
       noise, ``specular_gate``), normal recomputed from the final D, albedo ρ_d and
       specular energy ρ_s (Fig. 14 b–d).

    Single-channel input (``(N, L)`` or ``(N, L, 1)``) cannot be separated by colour: the whole
    function is taken as diffuse, only the lobe is fitted (``FLAG_SINGLE_CHANNEL``; logged).

    Parameters
    ----------
    R : (N, L, 3), (N, L, 1) or (N, L) array_like, linear radiance ≥ 0
        Reflectance functions: OLAT frame values per function and light.
    v : (3,) or (N, 3) array_like, unit, the light set's frame
        Toward the camera (v_0).
    lights : LightSet
    visibility : (N, L) bool, optional
        True where the light is visible from the point (shadow rays); False lights are shadowed.
    saturation : float, optional
        Samples with any channel ≥ this value (input units) are masked as saturated.
    masked : (N, L) bool, optional
        True where a sample cannot be trusted (a masked pixel: black-clipped, saturated or
        non-finite — the projected field's NaN samples). Its value is ignored (it may be NaN)
        and taken as 0 (so D = S = 0 there); it is left out of the analysis like a saturated
        sample (in ``saturated``) and its function is flagged :data:`FLAG_MASKED`. Black-clipped
        samples are dark, so the shadow map marks them shadowed, as it would the measured
        zeros; a function keeps a valid fit while MIN_SAMPLES lit samples remain.
    eta : float
        Index of refraction for F (ρ_s estimate).
    depth : SearchDepth, optional
        Coarse-to-fine search depth (default ``SearchDepth()``).
    shadow_threshold : float
        Fraction of the 99th-percentile brightness below which a sample is shadowed.
    d_0 : (N, 3) array_like, unit, optional
        Known representative diffuse chromaticity (white balanced), e.g. from a
        cross-polarised frame or the generator; replaces the median-ratio estimate for the
        ramp fit and the final separation. (d_0, α_0, α_1) are only weakly identifiable
        together, so α's are comparable only for the same d_0.
    rounds : int
        Alternations of ramp fit → final separation → normal (the paper does one; with the
        default joint polish a second changes little).
    chunk : int, optional
        Functions per chunk; default ``max(CHUNK, CHUNK_SAMPLES // L)`` (64 at 2048 lights),
        which bounds the memory of the numpy steps. Results do not depend on it (to rounding;
        tested).
    threads : int
        Worker threads, 1 to ``NUMBA_NUM_THREADS``: each fits whole chunks (numpy steps and
        compiled kernels, the kernels on one numba thread), so no thread waits while another
        runs serial numpy code. Default 1; pass 2 where both cores are free: the CPU time per
        function is the same at one and two threads, so two gain what the free core gives
        (paper mode, 2048 lights, one core busy with another job: 1.26× wall; docs/skin.md).
        Results do not depend on it: the chunks are the same and each function is one
        independent problem (bit-identical, tested).

    specular_gate : float
        ≥ 0. With G > 0 a sample's μ_s counts as specular only above G σ, σ the noise
        estimated from the function's negative μ_s
        (:func:`facegeo.appearance._skin_fit.gate_specular`); the rest stays in D. Default 0:
        the paper's ``S = max(μ_s, 0) s``. For noisy captures (3 suits Gaussian noise: small
        preset with 0.5 % noise, resynthesis 2.4× → 3.0× better than naive); on noise-free
        or merely mismatched data it cuts real specular tails.
    chroma_gate : float
        ≥ 0. The check of the light's colour against the albedo's before moving energy into S
        (:func:`facegeo.appearance._skin_fit.gate_chromaticity`): μ_s stays in D where it is
        within ``chroma_gate`` times the colour noise the separation turns into μ_s (the RMS
        of the out-of-plane μ_e: large where the diffuse colour is close to the light's). Default :data:`CHROMA_GATE`; 0 is the
        paper's separation. No effect where the threshold is below 1/1000 of a sample's
        brightness (the generator's exact functions: bit-identical). DiLiGenT cat, every
        10th mask pixel, all 96 lights: mean normal error 15.2° (paper) → 8.66° (Lambertian
        least squares 8.68°), S 18.5 % → 1.2 % of the energy; docs/skin.md, "Colour
        separation on near-grey objects".
    diffuse_out : (N, L, C) float32 or float16 ndarray, optional
        Where to write D instead of a fresh float32 array (the result's ``diffuse`` is then
        this array), e.g. the buffer the fit store writes to disk
        (:meth:`facegeo.render.FitWriter.diffuse_slot`): with float16, D is rounded there by
        the worker threads and S is formed from the rounded D, so D + S = R still holds to one
        float32 rounding. C-contiguous, writable, not overlapping ``R``.
    specular : bool
        Form S = R − D (default). False: the result's ``specular`` is None — for a caller that
        keeps D only (the fit stage stores D; S = R − D is formed again from the field when
        needed), one pass over the samples and ≈ 25 KB of fresh memory per function saved
        (2048 lights; first touches of fresh memory cost a quarter of a 20 k-function call's
        CPU time here, docs/skin.md).

    Returns
    -------
    SkinFit
    """
    R, single = check_reflectance(R, lights, masked)
    N, L, C = R.shape
    # one writable C-contiguous float64 copy (N × 3): a read-only or broadcast view would give
    # the compiled kernels a second type signature, i.e. a second cold compile of each
    v = np.array(check_views(v, N), np.float64, order="C")
    if d_0 is not None:
        d_0 = np.array(check_unit_vectors(as_array(d_0, "d_0", shape=(N, 3)), "d_0", tol=1e-6),
                       np.float64, order="C")
    depth = depth or SearchDepth()
    eta = float(eta)
    if not (np.isfinite(eta) and eta > 1.0):
        from facegeo.errors import InputError

        raise InputError(f"eta: expected an index of refraction > 1, got {fmt_value(eta)}")
    E = lights.intensities if not single else lights.intensities.mean(axis=1, keepdims=True)
    if not 0.0 < float(shadow_threshold) < 1.0:
        from facegeo.errors import InputError

        raise InputError(f"shadow_threshold: expected a fraction in (0, 1), got "
                         f"{fmt_value(shadow_threshold)}")
    specular_gate = float(specular_gate)
    chroma_gate = float(chroma_gate)
    if not (np.isfinite(chroma_gate) and chroma_gate >= 0.0):
        from facegeo.errors import InputError

        raise InputError(f"chroma_gate: expected a finite number >= 0, got "
                         f"{fmt_value(chroma_gate)}")
    if not (np.isfinite(specular_gate) and specular_gate >= 0.0):
        from facegeo.errors import InputError

        raise InputError(f"specular_gate: expected a finite number >= 0 (noise σ's), got "
                         f"{fmt_value(specular_gate)}")
    vis = None if visibility is None else check_mask(visibility, "visibility", N, L)
    mask = None if masked is None else check_mask(masked, "masked", N, L)
    if mask is not None and not mask.any():
        mask = None
    if single:
        log.info("single-channel reflectance functions: colour separation is impossible; "
                 "fitting the diffuse lobe alone")
    out = {k: [] for k in ("n", "nm", "n1", "mm", "m1", "d0", "a0", "a1", "rd", "rs", "flags",
                           "cast")}
    # Everything per chunk, written straight into the outputs: no (N, L, 3) float64 copy of
    # the whole input (those passes cost a third of the fit at 512 functions).
    D = _check_out(diffuse_out, "diffuse_out", (N, L, C), (np.float32, np.float16), R)
    if D.dtype == np.float16:
        from facegeo.surface._half import float32_to_halves
    S = np.empty((N, L, C), np.float32) if specular else None
    shadow = np.empty((N, L), bool)
    sat = np.zeros((N, L), bool)
    if chunk is None:
        chunk = max(CHUNK, CHUNK_SAMPLES // max(L, 1))
    starts = list(range(0, N, max(1, int(chunk))))
    no_vis = np.ones((1, 1), bool)

    def run(i):
        # one chunk, written straight into the outputs (disjoint slices of D, shadow, sat)
        sl = slice(i, min(N, i + int(chunk)))
        # the final separation writes D ⊙ E as float32: into D itself, or a chunk scratch
        D32 = D[sl] if D.dtype == np.float32 else np.empty((sl.stop - i, L, C), np.float32)
        stats = None
        Rs = R[sl]
        m = None if mask is None else mask[sl]
        if m is not None and m.any():
            # masked samples as 0: a value the steps below ignore (saturated) or read as dark
            Rs = np.where(m[..., None], np.zeros((), Rs.dtype), Rs)
        else:
            m = None
        if _skin_fit.KERNELS:
            # white balance, saturation, shadow map and the brightness statistics in one pass
            from facegeo.appearance._skin_kernels_samples import prepare_chunk

            if Rs.dtype not in (np.float32, np.float64):  # float16 maps, integers: one kernel
                Rs = Rs.astype(np.float64)
            # a masked sample's 0 counts in the statistics as a saturated one's does (as 0)
            Rw, sat[sl], shadow[sl], bmax, ref = prepare_chunk(
                np.ascontiguousarray(Rs), np.ascontiguousarray(E, np.float64),
                np.inf if saturation is None else float(saturation), float(shadow_threshold),
                no_vis if vis is None else np.ascontiguousarray(vis[sl]), vis is not None)
            stats = (bmax, ref)
            sat_only = sat[sl].any(axis=1) if m is not None else None
            if m is not None:
                sat[sl] |= m
        else:
            Rc = np.asarray(Rs, np.float64)
            if saturation is not None:
                sat[sl] = (Rc >= float(saturation)).any(axis=2)
            sat_only = sat[sl].any(axis=1) if m is not None else None
            if m is not None:
                sat[sl] |= m
            Rw = Rc / E[None]
            shadow[sl] = shadow_map(Rw, threshold=shadow_threshold,
                                    visibility=None if vis is None else vis[sl],
                                    saturated=sat[sl])
        res = _fit_chunk(Rw, v[sl], lights, shadow[sl], sat[sl], single, eta, depth,
                         shadow_threshold, None if d_0 is None else d_0[sl], rounds,
                         specular_gate, stats, D32 if _skin_fit.KERNELS else None,
                         chroma_gate)
        if m is not None:  # FLAG_SATURATED for saturation only, FLAG_MASKED for the mask
            res["flags"] = (res["flags"] & ~FLAG_SATURATED
                            | np.where(sat_only, FLAG_SATURATED, 0)
                            | np.where(m.any(axis=1), FLAG_MASKED, 0))
        if res["D"] is not None:  # else the final separation wrote D32 itself
            D32[...] = res["D"] * E[None]  # float32 on assignment
        if D.dtype != np.float32:
            float32_to_halves(D32, D[sl])  # rounded as numpy's cast, on the worker (compiled)
        if S is not None:
            # S here, on the worker (not after all chunks, serially), from the stored D: D + S
            # = R up to one float32 rounding (masked samples: 0 − D, D = 0 there)
            np.subtract(Rs, D[sl], out=S[sl], dtype=np.float32)
        return {k: res[k] for k in out}

    for res in _map_chunks(run, starts, threads):
        for k in out:
            out[k].append(res[k])
    cat = {k: np.concatenate(val) if val else np.zeros((0,)) for k, val in out.items()}
    flags = cat["flags"].astype(np.int32)
    hidden = np.zeros((N, L), bool) if vis is None else ~vis
    valid = (flags & (FLAG_BLACK | FLAG_SHADOWED)) == 0
    return SkinFit(lights=lights, view=v, normal=cat["n"], normal_moment=cat["nm"],
                   normal_initial=cat["n1"], lobe_misfit_moment=cat["mm"], lobe_misfit=cat["m1"],
                   d_0=cat["d0"], alpha_0=cat["a0"], alpha_1=cat["a1"], rho_d=cat["rd"],
                   rho_s=cat["rs"], diffuse=D, specular=S, shadow=shadow,
                   cast_shadow=cat["cast"] | hidden, saturated=sat,
                   flags=flags, valid=valid, eta=eta, single_channel=single)


def fit_reflectance_near(R, v, lights: LightSet, near: NearField, *, masked=None,
                         diffuse_out=None, specular: bool = True, **settings) -> SkinFit:
    """:func:`fit_reflectance` for a near-field light stage: each light where it is.

    The paper takes every light as distant (§4.2). Here the functions are first turned into
    what a distant stage would have measured at each point
    (:func:`facegeo.appearance._near_field.distant_equivalent`: divided by the falloff
    (r/|r ω_l − δ|)², resampled at the stage's directions as seen from the point), the model is
    fitted to that (§4.2 unchanged), and the final separation (Eq. 6 per sample, §4.2) is
    applied to the *measured* samples at their true directions
    (:func:`facegeo.appearance._near_field.separate_measured`), so D + S = R holds for the
    measured functions. The result carries ``near``, so :func:`resynthesize` evaluates Eq. 9
    with the true directions and falloffs. Why (docs/skin.md, "Near-field light stages"):
    small preset, 400 exact generator functions, stage radius 1.5 m: median normal error
    0.18° against 1.34°, resynthesis 3.5× / 3.6× better than naive at 30° / 60° (pooled)
    against 0.86× / 1.5×.

    Parameters
    ----------
    R : (N, L, C) array_like, linear radiance ≥ 0 (masked samples any value)
    v : (3,) or (N, 3) — toward the camera
    lights : LightSet — the stage's directions ω_l from its centre, intensities at the centre
    near : NearField — each function's offset from the stage centre, the stage radius
    masked, diffuse_out, specular — as :func:`fit_reflectance`
    **settings — the other keywords of :func:`fit_reflectance` (``eta``, ``depth``, ``threads``,
        ``saturation``, …; ``visibility`` refers to the measured lights and is resampled
        with the samples)

    Returns
    -------
    SkinFit — parameters of the distant-equivalent fit; ``diffuse`` / ``specular`` / ``shadow``
    maps of the measured functions' separation (shadow maps: of the resampled functions)
    """
    from facegeo.appearance._near_field import distant_equivalent, separate_measured

    R, single = check_reflectance(R, lights, masked)
    N, L, C = R.shape
    if near.offsets.shape[0] != N:
        from facegeo.errors import ShapeError

        raise ShapeError(f"near.offsets: expected {N} rows (one per function), got "
                         f"{near.offsets.shape[0]}")
    mask = None if masked is None else check_mask(masked, "masked", N, L)
    R32 = np.asarray(R, np.float32)
    if mask is not None and mask.any():
        R32 = np.where(mask[..., None], np.float32(0.0), R32)
    else:
        mask = None
    Rd, md = distant_equivalent(R32, near, lights, mask)
    if settings.get("visibility") is not None:
        vis, _ = distant_equivalent(
            check_mask(settings["visibility"], "visibility", N, L)[..., None]
            .astype(np.float32), near, lights)
        settings["visibility"] = vis[..., 0] >= 0.5
    fit = fit_reflectance(Rd, v, lights, masked=md, specular=False, **settings)
    D = _check_out(diffuse_out, "diffuse_out", (N, L, C), (np.float32, np.float16), R)
    separate_measured(R32, fit, near, D, masked=mask)
    S = np.subtract(R32, D, dtype=np.float32) if specular else None
    return replace(fit, diffuse=D, specular=S, near=near)


def _check_out(out, name, shape, dtypes, R):
    """A caller's output array for :func:`fit_reflectance` (a fresh float32 one when None):
    a C-contiguous, writable ndarray of ``shape`` and one of ``dtypes`` that does not overlap
    the input ``R``."""
    from facegeo.errors import InputError, ShapeError

    if out is None:
        return np.empty(shape, np.float32)
    if not isinstance(out, np.ndarray):
        raise InputError(f"{name}: expected a numpy array, got {type(out).__name__}")
    if out.shape != tuple(shape):
        raise ShapeError(f"{name}: expected shape {tuple(shape)}, got {out.shape}")
    if out.dtype not in [np.dtype(d) for d in dtypes]:
        raise InputError(f"{name}: expected dtype {' or '.join(np.dtype(d).name for d in dtypes)}"
                         f", got {out.dtype}")
    if not out.flags.writeable:
        raise InputError(f"{name}: the array is read-only")
    if not out.flags.c_contiguous:
        raise InputError(f"{name}: expected a C-contiguous array (a slice of whole rows)")
    if np.may_share_memory(out, R):
        raise InputError(f"{name}: overlaps the reflectance functions R (an input is never "
                         "written over)")
    return out


def _map_chunks(run, starts, threads):
    """``[run(i) for i in starts]``, on ``threads`` worker threads when > 1 (results in order).

    Each worker takes whole chunks and runs the compiled kernels on one numba thread (numba's
    thread count is per calling thread), so the numpy steps of one chunk overlap the kernels of
    another: no thread waits at a parallel region's barrier while the serial steps run (the
    reason ``prange`` over the functions of a chunk measured slower than one thread under
    load). The chunks are the same at any thread count and each is computed by the same code,
    so the results are bit-identical (tested).
    """
    t = _check_threads(threads)
    if t == 1 or len(starts) <= 1:
        with _numba_threads(1):
            return [run(i) for i in starts]
    from concurrent.futures import ThreadPoolExecutor

    def job(i):
        with _numba_threads(1):
            return run(i)

    with ThreadPoolExecutor(max_workers=min(t, len(starts)),
                            thread_name_prefix="facegeo-skin-fit") as pool:
        return list(pool.map(job, starts))


def _check_threads(threads):
    import numba

    t = int(threads)
    if not 1 <= t <= numba.config.NUMBA_NUM_THREADS:
        from facegeo.errors import InputError

        raise InputError(f"threads: expected 1 to {numba.config.NUMBA_NUM_THREADS}, got "
                         f"{fmt_value(threads)}")
    return t


@contextlib.contextmanager
def _numba_threads(threads):
    """numba's thread count for the block (in the calling thread)."""
    import numba

    t = _check_threads(threads)
    old = numba.get_num_threads()
    numba.set_num_threads(t)
    try:
        yield
    finally:
        numba.set_num_threads(old)


def _separate_ramp(R, d0, n, v, lights, a0, a1, out=None):
    """The §4.2 separation of every sample with the ramp chromaticity (the compiled
    ``_skin_kernels.separate_ramp``); ``n`` None: with d_0 itself (the initial separation).
    Returns ``D (n, L, 3)``, ``μ_s (n, L)`` (both with 0 lights when ``n`` is None),
    ``|D| (n, L)``, any-singular ``(n,)``. ``out`` ``(n, L, 3)`` float32: ``D ⊙ E`` (the
    light intensities) is written there instead, and D has 0 lights."""
    from facegeo.appearance._skin_kernels_samples import separate_ramp

    c = np.ascontiguousarray
    uniform = n is None
    N = R.shape[0]
    zeros = np.zeros(N)
    return separate_ramp(c(R, np.float64), c(d0, np.float64), c(v if uniform else n, np.float64),
                         c(v, np.float64), c(lights.directions), zeros if uniform else c(a0),
                         zeros if uniform else c(a1), uniform, SINGULAR_SIN2,
                         c(lights.intensities, np.float64),
                         np.empty((0, 0, 3), np.float32) if out is None else out)


def _fit_chunk(R, v, lights, shadow, sat, single, eta, depth, threshold, d_0, rounds,
               gate=0.0, stats=None, out=None, chroma_gate=0.0):
    """§4.2 on one chunk of white-balanced functions R ``(n, L, C)``; see :func:`fit_reflectance`.
    ``stats``: each function's largest unsaturated brightness and the 99th percentile of its
    ``|R|`` (saturated samples as 0), when the caller has them (``prepare_chunk``). ``out``
    ``(n, L, 3)`` float32: where the final separation can write ``D ⊙ E`` itself (compiled
    kernels, colour, no specular gate), it does, and the result's ``"D"`` is None."""
    n_f, L, C = R.shape
    l = lights.directions
    flags = np.zeros(n_f, np.int64)
    valid_s = ~shadow & ~sat
    flags |= np.where(sat.any(axis=1), FLAG_SATURATED, 0)
    if stats is None:
        bmax = np.where(sat, 0.0, R.sum(axis=2)).max(axis=1)
        ref = np.percentile(np.where(sat, 0.0, np.linalg.norm(R, axis=2)), 99, axis=1)
    else:
        bmax, ref = stats
    black = ~(bmax > 1e-12)
    few = valid_s.sum(axis=1) < MIN_SAMPLES
    flags |= np.where(black, FLAG_BLACK, 0)
    flags |= np.where(few & ~black, FLAG_SHADOWED, 0)
    w = valid_s.astype(np.float64)
    s = S_WHITE
    R0, w0, lights0 = R, w, lights  # the samples of the starting normals (all, or a subsample)
    if single:
        flags |= FLAG_SINGLE_CHANNEL
        d0 = np.broadcast_to(s, (n_f, 3)).copy()
        D0 = R
        y0 = R[..., 0]
    else:
        # the median-ratio estimate only where no d_0 is given (skipped work, not a fallback)
        d0 = d_0 if d_0 is not None else initial_diffuse_chromaticity(R, valid_s)[0]
        # the initial separation, moment and lobe only serve as starts (of the ramp fit and of
        # the final lobe fit on all lights): on the ramp's light subsample where it has one
        sub = _skin_fit.light_subsample(lights, depth.sample_lights)
        if sub is not None:
            idx = np.flatnonzero(sub)
            R0, w0, lights0 = R[:, idx], w[:, idx], lights.subset(idx)
        if _skin_fit.KERNELS:
            _, _, y0, sing0 = _separate_ramp(R0, d0, None, v, lights0, None, None)
        else:
            D0, _, _, _, _, sing = separate_colour(R0, d0[:, None, :], s)
            sing0 = sing[:, 0]
            y0 = np.linalg.norm(D0, axis=2)
        flags |= np.where(sing0, FLAG_SINGULAR, 0)
    nm = moment_normal(y0, w0, lights0, v)
    n1, k, mm, m1 = fit_lambertian_lobe(y0, w0, lights0, nm, depth)
    if single:
        a0 = np.zeros(n_f)
        a1 = np.zeros(n_f)
        D = R
        Smu = np.zeros((n_f, L))
        n = n1
    else:
        n = n1
        for _ in range(max(1, int(rounds))):
            # the polish moves the normal with the ramp; it only serves the ramp fit
            a0, a1, n_ramp, _ = fit_ramp(R, w, lights, n, v, d0, depth)
            a0, a1, n_ramp, rejected = _skin_fit.physical_ramp(a0, a1, n_ramp, n)
            flags |= np.where(rejected, FLAG_RAMP_REJECTED, 0)
            # the colour noise the separation turns into μ_s (the chromaticity check)
            c_sig, c_top = _skin_fit.chroma_noise(R, w, d0)
            if _skin_fit.KERNELS:
                direct = (out is not None and not gate > 0.0
                          and not _skin_fit.chroma_gate_active(c_sig, c_top, chroma_gate).any())
                D, mu_s, y, sing2 = _separate_ramp(R, d0, n_ramp, v, lights, a0, a1,
                                                   out if direct else None)
                D = None if direct else D
            else:
                nl = n_ramp @ l.T
                nv = np.einsum("ni,ni->n", n_ramp, v)
                c = ramp_chromaticity(d0[:, None, :],
                                      ramp_f(nl, nv[:, None], a0[:, None], a1[:, None]))
                D, _, _, mu_s, _, sing2 = separate_colour(R, c, s)
                y = np.linalg.norm(D, axis=2)
                sing2 = sing2.any(axis=1)
            D, mu_s, yg = _skin_fit.gate_specular(D, mu_s, w, gate)
            y = y if yg is None else yg
            D, mu_s, yg = _skin_fit.gate_chromaticity(D, mu_s, c_sig, c_top, chroma_gate)
            y = y if yg is None else yg
            # normal recomputed from the final diffuse component (§4.2, Fig. 14 b)
            n, k, _, _ = fit_lambertian_lobe(y, w, lights, n1, depth)
        sing_any = (flags & FLAG_SINGULAR) != 0
        a0 = np.where(sing_any, 0.0, a0)
        a1 = np.where(sing_any, 0.0, a1)
        flags |= np.where(sing2, FLAG_SINGULAR, 0)
        Smu = np.maximum(mu_s, 0.0) / np.sqrt(3.0)
    # k: the lobe's scale at the final normal (fit_lambertian_lobe, on the final |D|)
    rho_d = np.pi * np.maximum(k, 0.0)[:, None] * d0
    if _skin_fit.KERNELS:
        from facegeo.appearance._skin_kernels_samples import cast_shadow

        cast = cast_shadow(np.ascontiguousarray(shadow), np.ascontiguousarray(n, np.float64),
                           np.ascontiguousarray(l), np.ascontiguousarray(k, np.float64),
                           2.0 * threshold * np.asarray(ref, np.float64))
    else:
        x = np.maximum(n @ l.T, 0.0)
        cast = shadow & (np.maximum(k, 0.0)[:, None] * x > 2.0 * threshold * ref[:, None])
    nv = np.einsum("ni,ni->n", n, v)
    flags |= np.where(nv < GRAZING_COS, FLAG_GRAZING_VIEW, 0)
    rho_s = specular_energy(Smu, shadow, lights, n, v, eta) if not single else np.zeros(n_f)
    # fallbacks for functions without enough data: finite, flagged
    bad = black | few
    n = np.where(bad[:, None], np.where(black[:, None], v, nm), n)
    n1 = np.where(black[:, None], v, n1)
    rho_d = np.where(bad[:, None], 0.0, rho_d)
    rho_s = np.where(bad, 0.0, rho_s)
    return {"n": n, "nm": nm, "n1": n1, "mm": mm, "m1": m1, "d0": d0, "a0": a0, "a1": a1,
            "rd": rho_d, "rs": rho_s, "D": D, "flags": flags, "cast": cast}
