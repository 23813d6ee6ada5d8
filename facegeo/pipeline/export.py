"""``facegeo export``: the fitted model as a binary glTF 2.0 file other tools open.

``run_export(scan_dir, out_dir=None)`` reads the atlas (``out/atlas/atlas.npz``,
``texels.npz``) and the fit's Fig. 14-style maps (``out/fit/normal.exr``, ``albedo.exr`` /
``albedo.png``, ``specular.exr``, ``fitted.png``; :mod:`facegeo.pipeline.fit`) and writes
``out/export/``:

    model.glb              mesh (metres) + PBR material: baseColorTexture = albedo.png,
                           normalTexture = normal.png, metallic 0, roughness sqrt(m),
                           KHR_materials_specular (strength ρ_s, specular_weight.png) and
                           KHR_materials_ior (the fit's η)
    albedo.png, albedo.exr fitted diffuse albedo ρ_d: sRGB 8-bit (the fit's PNG, byte for byte)
                           and linear float
    normal.png             tangent-space normal map (glTF convention, the .glb's TANGENT frame)
    normal_tangent.exr     the same normals as floats in [−1, 1]
    normal_world.exr       the fit's world-frame normals (0 where nothing was fitted)
    specular.exr           the fit's specular energy ρ_s (linear float)
    specular_weight.png    RGBA, alpha = ρ_s clipped to [0, 1], 8-bit linear (the
                           extension's specularTexture)
    export.json            what was written, the conventions and the counts

Texels without a fit (``fitted.png`` 0) get the mesh's own normal, (0, 0, 1) in tangent space,
and the albedo the fit wrote there (0). The roughness is not fitted per texel (the paper's
model takes the specular lobe's shape from the data, docs/skin.md): the material carries one
``roughness = sqrt(m)`` of a Beckmann slope m (:func:`facegeo.render.gltf.roughness_from_beckmann`,
default :data:`BECKMANN_M`). docs/export.md.

Not a cached stage of ``reconstruct``: a command run on a scan whose ``fit`` is done.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from facegeo.checks import fmt_value
from facegeo.errors import InputError
from facegeo.fsutil import atomic_write_bytes, atomic_write_text

log = logging.getLogger(__name__)

__all__ = ["run_export", "EXPORT_FORMATS", "BECKMANN_M"]

#: Formats ``facegeo export --format`` writes.
EXPORT_FORMATS = ("glb",)
#: Beckmann RMS slope m of the exported specular lobe when none is given: a typical skin
#: value, inside the range the synthetic generator draws (0.25–0.5, docs/synth.md) — a
#: stated default, not a fit.
BECKMANN_M = 0.35

#: The fit's default index of refraction (``run_fit(eta=1.4)``), used when its stage.json
#: does not say.
FIT_ETA = 1.4

_ATLAS_FILES = ("atlas.npz", "texels.npz")
_FIT_FILES = ("normal.exr", "albedo.exr", "albedo.png", "specular.exr", "fitted.png")


def _check_products(scan_dir: Path, out: Path) -> None:
    """InputError naming the stage to run when an atlas or fit product is missing."""
    for stage, names in (("atlas", _ATLAS_FILES), ("fit", _FIT_FILES)):
        missing = [n for n in names if not (out / stage / n).is_file()]
        if missing:
            raise InputError(
                f"export: no {stage} products in {out / stage} (missing "
                f"{', '.join(missing)}): run 'facegeo fit {scan_dir}' first (it runs the atlas "
                "and projection stages it needs)")


def _tangent_normal_image(atlas, texels, n_world_img: np.ndarray,
                          fitted_img: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The tangent-space normal image ``(H, W, 3)`` float64, the vertex tangents ``(V, 4)`` it
    is encoded in (written to the file as ``TANGENT``) and the count of fitted texels."""
    from facegeo.render.gltf import tangent_space_normals, vertex_tangents

    tangents = vertex_tangents(atlas.vertices, atlas.faces, atlas.uv, atlas.normals)
    h, w = texels.shape
    img = np.zeros((h, w, 3))
    img[..., 2] = 1.0  # the mesh's own normal wherever nothing was fitted
    n = n_world_img[texels.row, texels.col].astype(np.float64)
    sel = (fitted_img[texels.row, texels.col] > 0) & (np.linalg.norm(n, axis=1) > 0.5)
    if sel.any():
        img[texels.row[sel], texels.col[sel]] = tangent_space_normals(
            n[sel], texels.face[sel], texels.bary[sel], atlas.faces, atlas.normals, tangents)
    return img, tangents, int(sel.sum())


def _write_textures(dest: Path, fit: Path, n_tan: np.ndarray, rho_s: np.ndarray) -> list[str]:
    """The texture files beside the model (atomically); their names, ``model.glb`` and
    ``export.json`` included."""
    from facegeo.capture import imageio
    from facegeo.render.gltf import encode_normal_map

    imageio.write_image(dest / "normal.png", encode_normal_map(n_tan))
    imageio.write_image(dest / "normal_tangent.exr", n_tan.astype(np.float32))
    weight = np.full(rho_s.shape + (4,), 255, np.uint8)  # KHR_materials_specular reads alpha
    weight[..., 3] = np.rint(np.clip(np.nan_to_num(rho_s), 0.0, 1.0) * 255)
    imageio.write_image(dest / "specular_weight.png", weight)
    for src, name in (("normal.exr", "normal_world.exr"), ("albedo.exr", "albedo.exr"),
                      ("albedo.png", "albedo.png"), ("specular.exr", "specular.exr")):
        atomic_write_bytes(dest / name, (fit / src).read_bytes())
    return ["model.glb", "albedo.png", "albedo.exr", "normal.png", "normal_tangent.exr",
            "normal_world.exr", "specular.exr", "specular_weight.png", "export.json"]


def _conventions(roughness: float, beckmann_m: float, eta: float, n_fitted: int, n_texels: int,
                 clipped: int) -> dict:
    """What the files hold, for ``export.json`` and the ``.glb``'s ``extras.facegeo``."""
    return {"units": "metres", "frame": "facegeo world frame: +Y up, subject looks along +Z",
            "uv": "glTF TEXCOORD_0 (origin top-left, v down) = (u, 1 - v) of the atlas uv",
            "normal_texture": "tangent space of the TANGENT attribute (B = w N x T along +v)",
            "roughness": {"value": roughness, "beckmann_m": float(beckmann_m),
                          "mapping": "roughness = sqrt(m) (GGX alpha = roughness^2 = m)"},
            "metallic": 0.0, "fitted_texels": n_fitted, "texels": n_texels,
            "specular": {"KHR_materials_specular": "strength = rho_s (Fig. 14 d), clipped "
                                                   "to [0, 1], alpha of specular_weight.png",
                         "KHR_materials_ior": eta, "clipped_texels": clipped},
            "textures": {"baseColor": "albedo.png", "normal": "normal.png",
                         "specular": "specular_weight.png",
                         "linear": ["albedo.exr", "normal_tangent.exr", "normal_world.exr",
                                    "specular.exr"]}}


def _fit_eta(fit_dir: Path) -> float:
    """The index of refraction η the fit used (its ``stage.json`` settings; default 1.4)."""
    try:
        eta = json.loads((fit_dir / "stage.json").read_text())["settings"]["eta"]
    except (OSError, ValueError, KeyError, TypeError):
        return FIT_ETA
    if isinstance(eta, bool) or not isinstance(eta, (int, float)) or not eta >= 1.0:
        raise InputError(f"export: {fit_dir / 'stage.json'} settings.eta is {fmt_value(eta)}; "
                         "expected a number >= 1")
    return float(eta)


def run_export(scan_dir, out_dir=None, *, format: str = "glb",
               beckmann_m: float = BECKMANN_M) -> dict:
    """Write the fitted model as ``out_dir/export/model.glb`` with its textures beside it.

    Parameters
    ----------
    scan_dir : path-like
        Scan directory.
    out_dir : path-like, optional
        Products folder holding ``atlas/`` and ``fit/`` (default ``scan_dir/out``); the export
        goes to ``out_dir/export/``.
    format : str
        ``"glb"`` (:data:`EXPORT_FORMATS`).
    beckmann_m : float
        Beckmann RMS slope m of the material's specular lobe (> 0; roughness = sqrt(m)).

    Returns
    -------
    dict
        ``files`` (names in ``export/``), ``vertices``, ``faces``, ``atlas_size``,
        ``texels``, ``fitted_texels``, ``roughness``, ``ior``, ``specular_clipped_texels``
        (texels with ρ_s > 1), ``glb_bytes``, ``seconds``.
    """
    from facegeo.capture import imageio
    from facegeo.render.gltf import roughness_from_beckmann, write_glb
    from facegeo.surface.atlas import Atlas, Texels

    t0 = time.perf_counter()
    if format not in EXPORT_FORMATS:
        raise InputError(f"format: expected one of {', '.join(EXPORT_FORMATS)}, got "
                         f"{fmt_value(format)}")
    scan_dir = Path(scan_dir)
    if not scan_dir.is_dir():
        raise InputError(f"export: no scan directory at {scan_dir}")
    out = Path(out_dir) if out_dir is not None else scan_dir / "out"
    _check_products(scan_dir, out)
    roughness = float(roughness_from_beckmann(beckmann_m))
    atlas = Atlas.load(out / "atlas" / "atlas.npz")
    texels = Texels.load(out / "atlas" / "texels.npz")
    fit = out / "fit"
    n_world = imageio.read_image(fit / "normal.exr")
    fitted = imageio.read_image(fit / "fitted.png")
    rho_s = imageio.read_image(fit / "specular.exr").astype(np.float64)
    rho_s = rho_s if rho_s.ndim == 2 else rho_s[..., 0]
    eta = _fit_eta(fit)
    for name, img in (("normal.exr", n_world), ("fitted.png", fitted),
                      ("specular.exr", rho_s)):
        if img.shape[:2] != texels.shape:
            raise InputError(
                f"export: {fit / name} is {img.shape[1]}×{img.shape[0]} but the atlas in "
                f"{out / 'atlas'} is {texels.shape[1]}×{texels.shape[0]}: the fit is of "
                f"another atlas; rerun 'facegeo fit {scan_dir}'")

    dest = out / "export"
    n_tan, tangents, n_fitted = _tangent_normal_image(atlas, texels, n_world, fitted)
    files = _write_textures(dest, fit, n_tan, rho_s)
    clipped = int((rho_s[texels.row, texels.col] > 1.0).sum())
    info = _conventions(roughness, beckmann_m, eta, n_fitted, len(texels), clipped)
    glb = write_glb(dest / "model.glb", atlas.vertices, atlas.faces, atlas.uv, atlas.normals,
                    base_color_png=dest / "albedo.png", normal_png=dest / "normal.png",
                    tangents=tangents, roughness_factor=roughness, metallic_factor=0.0,
                    specular_png=dest / "specular_weight.png", ior=eta, name="facegeo_model",
                    extras={"facegeo": info})
    metrics = {"files": files, "vertices": int(atlas.vertices.shape[0]),
               "faces": int(atlas.faces.shape[0]), "atlas_size": [atlas.width, atlas.height],
               "texels": len(texels), "fitted_texels": n_fitted, "roughness": roughness,
               "ior": eta, "specular_clipped_texels": clipped,
               "glb_bytes": glb.stat().st_size, "seconds": time.perf_counter() - t0}
    atomic_write_text(dest / "export.json", json.dumps({**metrics, "conventions": info},
                                                       indent=2) + "\n")
    if n_fitted == 0:
        log.warning("export: no fitted texels in %s: the normal map is the mesh's own and the "
                    "albedo is 0", fit)
    return metrics
