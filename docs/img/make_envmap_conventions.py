"""Make ``docs/img/envmap_conventions.png``: the axis-lobe test map (+X red, +Y green, +Z blue,
−X cyan, −Y magenta, −Z yellow; ``facegeo.lighting.envmap.axis_lobe_map``) in every projection
and lat-long convention facegeo reads, with the world axes labelled where
``directions_to_pixels`` puts them. Run from the repository root:

    .venv/bin/python docs/img/make_envmap_conventions.py

Not a test and not imported by the package (docs/lighting.md links the picture).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from facegeo.capture import imageio
from facegeo.lighting import envmap as E
from facegeo.lighting._cubemap import cube_geometry

#: Rows of each panel's map and the display scale (pixels per map pixel).
ROWS = 60
SCALE = 2
#: Lobe exponent: narrow enough that the six lobes do not merge.
EXPONENT = 24.0
AXES = {"+X": (1, 0, 0), "-X": (-1, 0, 0), "+Y": (0, 1, 0), "-Y": (0, -1, 0),
        "+Z": (0, 0, 1), "-Z": (0, 0, -1)}
PANELS = [
    ("latlong facegeo (OpenEXR, Mitsuba)", "latlong", "facegeo", "cross", ROWS),
    ("latlong u0_at_plus_z (grid azimuth)", "latlong", "u0_at_plus_z", "cross", ROWS),
    ("latlong blender (Blender, three.js)", "latlong", "blender", "cross", ROWS),
    ("mirror-ball", "mirror-ball", "facegeo", "cross", ROWS),
    ("angular", "angular", "facegeo", "cross", ROWS),
    ("cube, horizontal cross (4:3)", "cube", "facegeo", "cross", ROWS),
    ("cube, horizontal strip (6:1)", "cube", "facegeo", "strip", ROWS // 3),
]
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _panel(title, projection, convention, layout, rows):
    env = E.axis_lobe_map(rows, projection=projection, exponent=EXPONENT,
                          convention=convention, layout=layout)
    img = np.clip(env.image, 0, 1) ** (1 / 2.2)  # display only
    h, w = img.shape[:2]
    big = cv2.resize((img * 255).astype(np.uint8), (w * SCALE, h * SCALE),
                     interpolation=cv2.INTER_NEAREST)
    if projection == "cube":  # face outlines
        a = cube_geometry(h, w)[0] * SCALE
        for x in range(0, w * SCALE + 1, a):
            cv2.line(big, (min(x, w * SCALE - 1), 0), (min(x, w * SCALE - 1), h * SCALE - 1),
                     (90, 90, 90), 1)
        for y in range(0, h * SCALE + 1, a):
            cv2.line(big, (0, min(y, h * SCALE - 1)), (w * SCALE - 1, min(y, h * SCALE - 1)),
                     (90, 90, 90), 1)
    for name, axis in AXES.items():
        if projection in ("mirror-ball", "angular") and name == "-Z":
            continue  # the disc's rim
        q = E.directions_to_pixels(projection, np.asarray(axis, float), h, w,
                                   convention=convention)
        x = int(round((q[0] % w + 0.5) * SCALE))
        y = int(round((q[1] + 0.5) * SCALE))
        y = min(max(y, 12), h * SCALE - 4)
        x = min(max(x, 2), w * SCALE - 24)
        cv2.putText(big, name, (x - 10, y + 4), FONT, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    head = np.full((18, big.shape[1], 3), 30, np.uint8)
    cv2.putText(head, title, (2, 13), FONT, 0.36, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([head, big], 0)


def main(out: Path | None = None) -> Path:
    out = out or Path(__file__).resolve().parent / "envmap_conventions.png"
    panels = [_panel(*p) for p in PANELS]
    width = max(p.shape[1] for p in panels)
    rows, row, row_w = [], [], 0
    for p in panels:  # pack left to right, wrap at the widest panel's width
        if row and row_w + p.shape[1] + 6 > 2 * width:
            rows.append(row)
            row, row_w = [], 0
        row.append(p)
        row_w += p.shape[1] + 6
    rows.append(row)
    canvas_w = max(sum(p.shape[1] + 6 for p in r) for r in rows)
    lines = []
    for r in rows:
        hmax = max(p.shape[0] for p in r)
        line = np.full((hmax + 6, canvas_w, 3), 30, np.uint8)
        x = 0
        for p in r:
            line[:p.shape[0], x:x + p.shape[1]] = p
            x += p.shape[1] + 6
        lines.append(line)
    return Path(imageio.write_image(out, np.concatenate(lines, 0)))


if __name__ == "__main__":
    print(main())
