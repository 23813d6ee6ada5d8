"""Spectral skin in five steps: spectra, albedo, a parameter map, its inverse fit, an edit.

Run:  python examples/spectral_skin.py [output_dir]

1. Reflectance spectra of four skin types (Donner & Jensen 2006 with the multipole/dipole
   two-layer diffusion model) and their linear-sRGB albedo.
2. A small 48 × 64 "face" of physiological parameter maps from the regional generator.
3. The inverse fit of its albedo, with the fraction of texels where C_m and C_h are
   identifiable, and the parameter maps saved as 16-bit PNG.
4. An edit — 50 % more blood — giving a new albedo map for relighting.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from facegeo.appearance import spectral


def main(out_dir: Path) -> None:
    # 1. Spectra and albedo of four skin types.
    wl = np.arange(400.0, 701.0, 50.0)
    print("skin type   C_m    beta_m  C_h     R(400..700 nm, every 50 nm)          linear sRGB")
    for name, p in spectral.SKIN_TYPES.items():
        spec = spectral.skin_spectrum(p["C_m"], p["beta_m"], p["C_h"], wl)
        rgb = spectral.skin_rgb(p["C_m"], p["beta_m"], p["C_h"])
        print(
            f"{name:10s}  {p['C_m']:.3f}  {p['beta_m']:.2f}    {p['C_h']:.4f}  "
            f"{np.array2string(spec, precision=3, separator=' ')}  "
            f"{np.array2string(rgb, precision=3, separator=' ')}"
        )

    # 2. Parameter maps over a small patch of face: u spans the front of the head.
    h, w = 48, 64
    y, x = np.meshgrid(np.linspace(0.8, -0.9, h), np.linspace(-0.8, 0.8, w), indexing="ij")
    z = np.sqrt(np.clip(1.0 - 0.5 * x**2 - 0.3 * y**2, 0.0, None))  # a rough front surface
    u = np.stack([x, y, z], axis=-1)
    albedo_fn = spectral.spectral_albedo_fn("light", seed=7, exact=True)
    truth = albedo_fn.parameter_maps(u)
    albedo = albedo_fn(u)  # (48, 64, 3) float32, linear sRGB
    print(f"\nalbedo map {albedo.shape}, mean linear sRGB {albedo.reshape(-1, 3).mean(0).round(3)}")

    # 3. Inverse fit of the albedo map.
    fit = spectral.fit_albedo(albedo)
    err_m = np.abs(fit.C_m / truth.C_m - 1.0)
    err_h = np.abs(fit.C_h / truth.C_h - 1.0)
    ok_m, ok_h = fit.identifiable[..., 0], fit.identifiable[..., 2]
    print(
        f"fit: in gamut {fit.in_gamut.mean():.0%}; C_m identifiable {ok_m.mean():.0%} "
        f"(max error there {err_m[ok_m].max(initial=0):.2%}), C_h identifiable {ok_h.mean():.0%} "
        f"(max error there {err_h[ok_h].max(initial=0):.2%}); median residual "
        f"{np.median(fit.residual):.2e} (linear RGB)"
    )
    known = spectral.fit_albedo(albedo, beta_m=float(np.median(truth.beta_m)))
    print(
        f"with beta_m fixed at its median: C_h identifiable {known.identifiable[..., 2].mean():.0%}"
    )
    meta = spectral.save_parameter_maps(fit, out_dir / "parameter_maps")
    print(f"parameter maps written: {sorted(p.name for p in meta.parent.iterdir())}")

    # 4. An edit: 50 % more blood (a flush), as a new albedo map for relighting.
    flushed = spectral.edit(fit, C_h=lambda c: 1.5 * c)
    ratio = (flushed / albedo).reshape(-1, 3).mean(0)
    print(f"flush (C_h x 1.5): mean albedo ratio R, G, B = {ratio.round(3)}")


if __name__ == "__main__":
    if len(sys.argv) > 1:
        main(Path(sys.argv[1]))
    else:
        with tempfile.TemporaryDirectory() as tmp:
            main(Path(tmp))
