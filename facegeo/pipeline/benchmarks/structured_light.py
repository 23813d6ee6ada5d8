"""Benchmark of Gray-code decoding: vectorised numpy against OpenCV's ``getProjPixel``."""

from __future__ import annotations

import numpy as np

from facegeo.pipeline.bench import BenchRow, best_of, register


@register("structured_light.decode_gray")
def bench_decode_gray(quick: bool) -> list[BenchRow]:
    import cv2

    from facegeo.geometry.structured_light import PatternSpec, decode_gray, pattern_names, pattern_value_at

    w, h = (640, 512) if quick else (1280, 1024)
    spec = PatternSpec(width=1024, height=768, white_black=False)
    rng = np.random.default_rng(0)
    # a smooth camera → projector warp, so every projector code appears
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    qx = 20 + xx * (980 / w) + 6 * np.sin(yy / 90)
    qy = 15 + yy * (740 / h) + 5 * np.sin(xx / 70)
    q = np.stack([qx, qy], -1)
    albedo = 0.3 + 0.6 * rng.random((h, w))
    names = [n for n in pattern_names(spec) if n.startswith("gray")]
    frames = {n: (albedo * pattern_value_at(spec, n, q)).astype(np.float32) for n in names}
    t, dec = best_of(lambda: decode_gray(frames, spec), 3)
    truth_x = np.floor(qx + 0.5)
    truth_y = np.floor(qy + 0.5)
    wrong = float(np.mean((dec.proj_x != truth_x) | (dec.proj_y != truth_y) | ~dec.valid))
    mpx = w * h / t / 1e6
    rows = [BenchRow("structured_light.decode_gray", f"facegeo, {w}x{h}, {len(names)} frames", mpx,
                     "Mpx/s", error=wrong, error_unit="fraction of pixels not decoded exactly",
                     extra={"ms": round(1e3 * t, 2)})]
    # OpenCV's per-pixel decoder on a sample of pixels (it takes ~10 µs a pixel)
    gc = cv2.structured_light.GrayCodePattern.create(spec.width, spec.height)
    imgs = [np.clip(frames[n] * 255, 0, 255).astype(np.uint8) for n in names]
    pix = rng.integers(0, [w, h], size=(400 if quick else 2000, 2))
    def run_cv():
        out = []
        for x, y in pix:
            err, p = gc.getProjPixel(imgs, int(x), int(y))
            out.append(p if not err else (-1, -1))
        return np.array(out)
    t_cv, cv_pts = best_of(run_cv, 1)
    cv_mpx = len(pix) / t_cv / 1e6
    agree = float(np.mean((cv_pts[:, 0] == dec.proj_x[pix[:, 1], pix[:, 0]])
                          & (cv_pts[:, 1] == dec.proj_y[pix[:, 1], pix[:, 0]])))
    rows[0].ratios["vs cv2 getProjPixel"] = mpx / cv_mpx
    rows.append(BenchRow("structured_light.decode_gray", f"cv2 getProjPixel, {len(pix)} pixels",
                         cv_mpx, "Mpx/s", error=1 - agree,
                         error_unit="fraction disagreeing with facegeo"))
    return rows
