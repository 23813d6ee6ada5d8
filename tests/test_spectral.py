"""Tests of facegeo.appearance.spectral: the Donner & Jensen 2006 spectral skin model, forward and inverse.

Every comparison states its metric; tolerances are named below with their units.
"""

from __future__ import annotations

import json
import logging
import warnings

import numpy as np
import pytest

from facegeo.appearance import spectral
from facegeo.errors import InputError, ScanFormatError, ShapeError
from facegeo.appearance.spectral import (
    FLAG_C_H_UNIDENTIFIABLE,
    FLAG_DARK,
    FLAG_OUT_OF_GAMUT,
    SkinParameters,
)
from conftest import shared_file

# --------------------------------------------------------------------------- tolerances

#: Published dipole R_d are printed to 2 decimals: |ours − published| (reflectance, absolute).
PUBLISHED_RD_TOL = 0.01
#: Numerical plane integral of a radial profile against its closed-form total (absolute).
PROFILE_INTEGRAL_TOL = 1e-4
#: Thick multipole against the dipole (absolute reflectance).
THICK_SLAB_TOL = 1e-9
#: Adding relation with identical layers against the half-space dipole, skin-like slab
#: (d = 0.25 mm ≥ 1 mfp): the error of the layer combination (absolute reflectance).
LAYER_CONSISTENCY_TOL = 0.01
#: Non-absorbing slab, R + T against 1 (energy conservation, absolute).
ENERGY_TOL = 1e-3
#: White reflector → (1, 1, 1) (linear sRGB, absolute per channel).
WHITE_TOL = 1e-12
#: Trilinear table against the exact model (relative per channel, worst case).
LUT_REL_TOL = 2e-3
#: Goal for the fit of measured spectra (median RMSE over 400–700 nm, reflectance).
XIAO_MEDIAN_RMSE_GOAL = 0.03
#: Round trip: fitted C_m, C_h against the truth where flagged identifiable (relative, max).
ROUND_TRIP_REL_TOL = 0.10
#: 16-bit PNG maps: half a code step of each map's scale (absolute, in the map's unit).
PNG_HALF_STEP = 0.5 / 65535.0

XIAO = "skin/xiao2016_skin_reflectance_spectra.csv"
PRAHL = "skin/ext_and_molarext_oxy_and_deo_Prahl.txt"

# Jensen et al. 2001, Table 2 (mm⁻¹; η = 1.3): σ_s′, σ_a and the diffuse reflectance R_d per
# R, G, B channel.
JENSEN_2001 = {
    "skin1": ((0.74, 0.88, 1.01), (0.032, 0.17, 0.48), (0.44, 0.22, 0.13)),
    "skin2": ((1.09, 1.59, 1.79), (0.013, 0.070, 0.145), (0.63, 0.44, 0.34)),
}


def _plane_integral(profile, r_max=400.0, n=200_001):
    """∫ profile(r) 2πr dr on a log-spaced grid (trapezoid), r in mm."""
    r = np.concatenate([[0.0], np.geomspace(1e-7, r_max, n)])
    return np.trapezoid(profile(r) * 2.0 * np.pi * r, r)


def _lab(reflectance, wl):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour
    xyz = spectral.spectrum_to_xyz(reflectance, wl)
    white = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    lab = colour.XYZ_to_Lab(xyz, white)
    return lab, colour.Lab_to_LCHab(lab)


# --------------------------------------------------------------------------- absorption


def test_absorption_equations_at_500nm():
    """Eqs. 3–8 at 500 nm against values computed by hand from the printed formulas."""
    wl = 500.0
    assert spectral.eumelanin_absorption(wl) == pytest.approx(6.6e10 * 500.0**-3.33, rel=1e-12)
    assert spectral.eumelanin_absorption(wl, convention="Donner Jensen 2006 printed") == (
        pytest.approx(6.6e11 * 500.0**-3.33, rel=1e-12)
    )
    assert spectral.pheomelanin_absorption(wl) == pytest.approx(2.9e14 * 500.0**-4.75, rel=1e-12)
    base = 0.0244 + 8.53 * np.exp(-(500.0 - 154.0) / 66.2)
    assert spectral.baseline_absorption(wl) == pytest.approx(base, rel=1e-12)
    ss = 14.74 * 500.0**-0.22 + 2.2e11 * 500.0**-4
    assert spectral.epidermis_scattering(wl) == pytest.approx(ss, rel=1e-12)
    assert spectral.dermis_scattering(wl) == pytest.approx(0.5 * ss, rel=1e-12)
    # Eq. 6 limits: C_m = 0 is the baseline; C_m = 1 is pure eumelanin (β=1) or pheomelanin (β=0).
    w = np.array([500.0])
    assert spectral.epidermis_absorption(w, 0.0, 0.3)[0] == pytest.approx(base)
    assert spectral.epidermis_absorption(w, 1.0, 1.0)[0] == pytest.approx(spectral.eumelanin_absorption(500.0))
    assert spectral.epidermis_absorption(w, 1.0, 0.0)[0] == pytest.approx(spectral.pheomelanin_absorption(500.0))
    # Eq. 7 with γ = 0.75: C_h = 1 is whole blood.
    oxy, deoxy = spectral.haemoglobin_absorption(w)
    assert spectral.dermis_absorption(w, 1.0)[0] == pytest.approx(0.75 * oxy[0] + 0.25 * deoxy[0])
    with pytest.raises(InputError, match="convention"):
        spectral.eumelanin_absorption(wl, convention="nobody 1999")


@pytest.mark.shared_data
def test_haemoglobin_table_is_prahl(shared_data):
    """The package's 4 nm table equals Prahl's file; μa = ln10 · ε · 150/64500 / 10 mm⁻¹."""
    data = np.loadtxt(shared_file(shared_data, PRAHL), skiprows=1)
    from facegeo.appearance.spectral._hemoglobin import HB_EPSILON_DEOXY, HB_EPSILON_OXY, HB_WAVELENGTHS_NM

    rows = data[np.isin(data[:, 0], HB_WAVELENGTHS_NM)]
    assert rows.shape[0] == HB_WAVELENGTHS_NM.size == 101
    np.testing.assert_array_equal(rows[:, 1], HB_EPSILON_OXY)
    np.testing.assert_array_equal(rows[:, 2], HB_EPSILON_DEOXY)
    oxy, deoxy = spectral.haemoglobin_absorption([540.0, 576.0])
    c = 150.0 / 64500.0
    assert oxy[0] == pytest.approx(np.log(10) * 53236 * c / 10, rel=1e-12)  # 28.5 mm⁻¹
    assert oxy[1] == pytest.approx(np.log(10) * 55540 * c / 10, rel=1e-12)
    assert deoxy[0] == pytest.approx(np.log(10) * 46592 * c / 10, rel=1e-12)


@pytest.mark.shared_data
def test_melanin_unit_choice_matches_sarna(shared_data):
    """The deviation from the printed Eq. 3: with 6.6e10 mm⁻¹ the eumelanin/pheomelanin ratio
    matches Sarna & Swartz's measured extinction ratio (within a factor 1.5 over 410–700 nm);
    the printed 6.6e11 is off by ≥ 5×."""
    eu = np.loadtxt(shared_file(shared_data, "skin/ext_and_molarext_eum_Sarna.txt"), skiprows=1)
    ph = np.loadtxt(shared_file(shared_data, "skin/ext_and_molarext_phe_Sarna.txt"), skiprows=1)
    wl = np.arange(410.0, 701.0, 10.0)
    measured = np.interp(wl, eu[:, 0], eu[:, 1]) / np.interp(wl, ph[:, 0], ph[:, 1])
    ours = spectral.eumelanin_absorption(wl) / spectral.pheomelanin_absorption(wl)
    printed = spectral.eumelanin_absorption(wl, convention="Donner Jensen 2006 printed") / (
        spectral.pheomelanin_absorption(wl)
    )
    assert np.max(np.abs(np.log(ours / measured))) < np.log(1.5)
    assert np.min(printed / measured) > 5.0


def test_wavelengths_outside_the_table_are_rejected():
    with pytest.raises(InputError, match="380"):
        spectral.haemoglobin_absorption([370.0, 500.0])
    with pytest.raises(InputError, match="wavelengths"):
        spectral.skin_spectrum(0.02, 0.5, 0.01, [400.0, 800.0])
    with pytest.raises(ShapeError):
        spectral.skin_spectrum(0.02, 0.5, 0.01, [[400.0, 500.0]])


# --------------------------------------------------------------------------- diffusion


@pytest.mark.parametrize("name", sorted(JENSEN_2001))
def test_dipole_reproduces_jensen_2001(name):
    """Closed-form R_d and the numerically integrated dipole profile against Table 2."""
    ss, sa, published = (np.array(v) for v in JENSEN_2001[name])
    closed = spectral.dipole_total_reflectance(sa, ss, 1.3)
    s = np.sqrt(3 * (1 - ss / (ss + sa)))
    A = spectral.boundary_coefficient(1.3)
    alpha = ss / (ss + sa)
    formula = alpha / 2 * (1 + np.exp(-4 / 3 * A * s)) * np.exp(-s)  # Jensen 2001 §2.5
    np.testing.assert_allclose(closed, formula, rtol=1e-12)
    for c in range(3):
        integral = _plane_integral(lambda r: spectral.dipole_profile(r, sa[c], ss[c], 1.3))
        assert abs(integral - closed[c]) < PROFILE_INTEGRAL_TOL, (c, integral, closed[c])
    assert np.max(np.abs(closed - published)) < PUBLISHED_RD_TOL, (closed, published)


def test_multipole_reduces_to_dipole_for_a_thick_slab():
    sa = np.array([0.013, 0.07, 0.5])
    ss = np.array([1.09, 1.59, 7.0])
    R, T = spectral.multipole_totals(sa, ss, 200.0, 1.3, 1.0)
    np.testing.assert_allclose(R, spectral.dipole_total_reflectance(sa, ss, 1.3), atol=THICK_SLAB_TOL)
    assert np.all(np.abs(T) < THICK_SLAB_TOL)
    r = np.array([0.05, 0.5, 2.0])
    Rp, _ = spectral.multipole_profiles(r, 0.07, 1.59, 200.0, 1.3, 1.0, n_pairs=3)
    np.testing.assert_allclose(Rp, spectral.dipole_profile(r, 0.07, 1.59, 1.3), rtol=1e-9)


@pytest.mark.parametrize(
    "sa, ss, d, eta_top, eta_bottom",
    [(0.5, 7.0, 0.25, 1.4, 1.0), (0.05, 4.4, 0.25, 1.0, 1.4), (2.0, 20.0, 0.1, 1.4, 1.4)],
)
def test_multipole_totals_are_the_integrated_profiles(sa, ss, d, eta_top, eta_bottom):
    """The closed-form (geometric-series) totals against the plane integral of R(r), T(r)."""
    R, T = spectral.multipole_totals(sa, ss, d, eta_top, eta_bottom)
    Ri = _plane_integral(lambda r: spectral.multipole_profiles(r, sa, ss, d, eta_top, eta_bottom)[0])
    Ti = _plane_integral(lambda r: spectral.multipole_profiles(r, sa, ss, d, eta_top, eta_bottom)[1])
    assert abs(R - Ri) < PROFILE_INTEGRAL_TOL and abs(T - Ti) < PROFILE_INTEGRAL_TOL


def test_multipole_conserves_energy_without_absorption_and_stays_bounded():
    ss = np.array([4.0, 5.0, 10.0, 50.0])
    R, T = spectral.multipole_totals(1e-4, ss, 0.25, 1.4, 1.0)
    assert np.max(np.abs(R + T - 1.0)) < ENERGY_TOL
    sa = np.geomspace(1e-3, 100.0, 50)[:, None]
    ss = np.geomspace(3.0, 60.0, 20)[None, :]
    for eta_top, eta_bottom in ((1.4, 1.0), (1.0, 1.4)):
        R, T = spectral.multipole_totals(sa, ss, 0.25, eta_top, eta_bottom)
        assert np.all(R >= 0) and np.all(T >= 0) and np.all(R + T <= 1.0 + 1e-12)


def test_two_layer_with_identical_layers_is_the_half_space():
    """Epidermis-like coefficients, d = 0.25 mm: the layer combination is consistent."""
    wl = np.array([450.0, 550.0, 650.0])
    ss = spectral.epidermis_scattering(wl)
    for sa in (spectral.epidermis_absorption(wl, 0.02, 0.5), np.full(3, 0.05)):
        R = spectral.two_layer_total_reflectance(sa, ss, 0.25, sa, ss, 1.4)
        D = spectral.dipole_total_reflectance(sa, ss, 1.4)
        assert np.max(np.abs(R - D)) < LAYER_CONSISTENCY_TOL, (R, D)


def test_diffusion_rejects_non_physical_coefficients():
    with pytest.raises(InputError, match="sigma_a > 0"):
        spectral.dipole_total_reflectance(0.0, 1.0, 1.3)
    with pytest.raises(InputError, match="non-finite"):
        spectral.multipole_totals(np.nan, 1.0, 0.25, 1.4, 1.0)
    with pytest.raises(InputError, match="thickness"):
        spectral.multipole_totals(0.1, 1.0, -0.25, 1.4, 1.0)


# --------------------------------------------------------------------------- colour, surface


@pytest.mark.parametrize("grid", [np.arange(380.0, 781.0, 4.0), np.arange(400.0, 701.0, 10.0)])
def test_white_reflector_is_rgb_one(grid):
    """White → (1, 1, 1) holds by construction (rows of the weights are normalised); what can
    fail here is the XYZ scale: Y of the white reflector is 1 and its x, z are D65's."""
    rgb = spectral.spectrum_to_rgb(np.ones(grid.size), grid)
    assert np.max(np.abs(rgb - 1.0)) < WHITE_TOL
    xyz = spectral.spectrum_to_xyz(np.ones(grid.size), grid)
    assert xyz[1] == pytest.approx(1.0, abs=1e-12)
    assert xyz[0] == pytest.approx(0.9505, abs=2e-3) and xyz[2] == pytest.approx(1.089, abs=2e-3)


#: max |facegeo − colour-science| over XYZ and linear-sRGB channels, absolute (measured ≤ 3.5e-4:
#: piecewise-linear spectra on the 1 nm CIE grid vs colour-science's own interpolation)
COLOUR_SCIENCE_ABS_TOL = 1e-3


@pytest.mark.parametrize("patch", ["dark skin", "light skin", "blue", "red", "yellow"])
def test_colour_matches_colour_science_on_colorchecker(patch):
    """Non-flat spectra (ColorChecker N Ohta, 380–780 nm at 5 nm) against colour-science's
    ``sd_to_XYZ`` (integration, D65, CIE 1931 2°) and ``XYZ_to_RGB`` (sRGB, linear): an
    independent reference that a swapped channel, a wrong matrix or a wrong normalisation
    fails (the white-reflector test cannot see those)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour
        sd = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"][patch]
        sd = sd.copy().trim(colour.SpectralShape(380, 780, 5))
        wl, R = np.asarray(sd.wavelengths, float), np.asarray(sd.values, float)
        cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
        xyz_ref = colour.sd_to_XYZ(sd, cmfs, colour.SDS_ILLUMINANTS["D65"],
                                   method="Integration") / 100.0
        rgb_ref = colour.XYZ_to_RGB(xyz_ref, colour.RGB_COLOURSPACES["sRGB"],
                                    apply_cctf_encoding=False)
    err_xyz = np.abs(spectral.spectrum_to_xyz(R, wl) - xyz_ref).max()
    err_rgb = np.abs(spectral.spectrum_to_rgb(R, wl) - rgb_ref).max()
    assert err_xyz < COLOUR_SCIENCE_ABS_TOL, f"{patch}: max |XYZ − colour-science| {err_xyz:.2g}"
    assert err_rgb < COLOUR_SCIENCE_ABS_TOL, f"{patch}: max |RGB − colour-science| {err_rgb:.2g}"


def test_rho_dr_and_surface_term():
    """ρ_dr(1.4) by quadrature against the Egan–Hilgeman fit through the étendue relation
    1 − ρ_dr,ext = (1 − F_dr,int)/η² (the fit is good to ~1 %)."""
    rho = spectral.rho_dr(1.4)
    via_fit = 1.0 - 1.4**2 * (1.0 - spectral.fresnel_diffuse_reflectance(1.4))
    assert rho == pytest.approx(0.0768, abs=5e-4)
    assert rho == pytest.approx(via_fit, abs=2e-3)
    assert spectral.subsurface_transmission() == pytest.approx(1.0 - rho)
    from facegeo.appearance.brdf import specular_brdf

    n = np.array([0.0, 0.0, 1.0])
    l = np.array([0.3, 0.1, 0.9486832980505138])
    v = np.array([-0.2, 0.05, 0.9784172926535934])
    l, v = l / np.linalg.norm(l), v / np.linalg.norm(v)
    f = spectral.surface_brdf(n, l, v, 0.4)
    assert f == pytest.approx(specular_brdf(n, l, v, 0.4, 0.35, 1.4))
    assert f > 0


# --------------------------------------------------------------------------- forward model


def test_forward_model_shapes_and_vectorisation():
    wl = np.arange(400.0, 701.0, 20.0)
    C_m = np.array([[0.01], [0.1]])  # (2, 1)
    C_h = np.array([0.005, 0.02, 0.1])  # (3,)
    s = spectral.skin_spectrum(C_m, 0.5, C_h, wl)
    assert s.shape == (2, 3, wl.size)
    one = spectral.skin_spectrum(0.1, 0.5, 0.02, wl)
    np.testing.assert_allclose(s[1, 1], one, rtol=1e-12)
    assert np.all((s > 0) & (s < 1))
    rgb = spectral.skin_rgb(C_m, 0.5, C_h)
    assert rgb.shape == (2, 3, 3) and rgb.dtype == np.float64
    # The table and the exact model agree through the same factorised path.
    from facegeo.appearance.spectral._lut import layered_spectra_grid

    g = layered_spectra_grid([0.01, 0.1], [0.5], [0.005, 0.02, 0.1], wl)
    np.testing.assert_allclose(g[:, 0], s, rtol=1e-12)
    extreme = spectral.skin_spectrum([0.0, 1.0], [0.0, 1.0], [0.0, 1.0])
    assert np.all(np.isfinite(extreme)) and np.all(extreme > 0)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(C_m=-0.1, beta_m=0.5, C_h=0.01), "C_m"),
        (dict(C_m=0.1, beta_m=1.5, C_h=0.01), "beta_m"),
        (dict(C_m=0.1, beta_m=0.5, C_h=np.nan), "C_h"),
        (dict(C_m=[0.1, 0.2], beta_m=0.5, C_h=[0.01, 0.02, 0.03]), "broadcast"),
        (dict(C_m="lots", beta_m=0.5, C_h=0.01), "C_m"),
    ],
)
def test_forward_model_rejects_bad_parameters(kwargs, match):
    with pytest.raises(InputError, match=match):
        spectral.skin_spectrum(**kwargs)


def test_more_melanin_darkens_and_flattens():
    """D&J 2006 Fig. 3 trend: mean reflectance and spectral range fall as C_m rises."""
    wl = np.arange(400.0, 701.0, 2.0)
    C_m = np.array([0.01, 0.03, 0.1, 0.3, 0.5])
    s = spectral.skin_spectrum(C_m, 0.5, 0.02, wl)
    mean = s.mean(axis=1)
    spread = s.max(axis=1) - s.min(axis=1)
    assert np.all(np.diff(mean) < 0) and np.all(np.diff(spread) < 0)
    assert spread[-1] < 0.2 * spread[0]
    print(f"\nC_m {C_m.tolist()}: mean R {np.round(mean, 3).tolist()}, range {np.round(spread, 3).tolist()}")


def test_more_haemoglobin_deepens_the_w():
    """D&J 2006 Fig. 4 trend: the oxy-haemoglobin 'W' (minima at 542 and 577 nm) appears and
    the band deepens against the red shoulder as C_h rises (C_m = 0.02, β_m = 0.5).

    The depth below the red shoulder rises up to C_h = 0.05 and then falls slightly (at 0.1
    the blood's deoxy-haemoglobin absorbs the red shoulder too and the band saturates); the
    reflectance inside the band keeps falling over the whole range."""
    wl = np.arange(500.0, 661.0, 2.0)
    C_h = np.array([0.001, 0.005, 0.01, 0.02, 0.05, 0.1])
    s = spectral.skin_spectrum(0.02, 0.5, C_h, wl)

    def at(k):
        return np.log(s[:, wl == k][:, 0])

    band = at(650) - 0.5 * (at(542) + at(576))  # depth of the W below the red shoulder
    assert np.all(np.diff(band[:5]) > 0)  # C_h 0.001 → 0.05
    assert np.all(np.diff(s[:, wl == 542][:, 0]) < 0) and np.all(np.diff(s[:, wl == 576][:, 0]) < 0)
    hump = at(560) - 0.5 * (at(542) + at(576))  # the middle of the W stands above its dips
    assert hump[2] > hump[0] > 0
    for i in range(2, 6):  # C_h in [0.01, 0.1]: two local minima within 6 nm of 542 and 577 nm
        inner = (wl >= 530) & (wl <= 590)
        y, w = s[i, inner], wl[inner]
        minima = w[1:-1][(y[1:-1] < y[:-2]) & (y[1:-1] < y[2:])]
        assert len(minima) == 2 and abs(minima[0] - 542) <= 6 and abs(minima[1] - 577) <= 6, minima
    print(f"\nC_h {C_h.tolist()}: W band depth {np.round(band, 3).tolist()}, hump {np.round(hump, 4).tolist()}")


def test_melanin_blend_shifts_brown_to_yellow():
    """D&J 2006 Fig. 5 trend: lowering β_m (more pheomelanin) makes skin yellower (b* up) and
    lighter; at C_m = 0.02 the CIELAB hue angle rises (toward yellow) by several degrees."""
    wl = np.arange(400.0, 701.0, 2.0)
    beta = np.linspace(1.0, 0.0, 5)  # eumelanin (brown) → pheomelanin (yellow)
    for C_m in (0.02, 0.1):
        lab, lch = _lab(spectral.skin_spectrum(C_m, beta, 0.02, wl), wl)
        assert np.all(np.diff(lab[:, 2]) > 0), lab  # b* rises
        assert np.all(np.diff(lab[:, 0]) > 0), lab  # L* rises
    lab, lch = _lab(spectral.skin_spectrum(0.02, beta, 0.02, wl), wl)
    assert np.all(np.diff(lch[:, 2]) > 0) and lch[-1, 2] - lch[0, 2] > 3.0
    print(f"\nC_m 0.02, beta_m {beta.tolist()}: hue angle {np.round(lch[:, 2], 1).tolist()} deg")


# --------------------------------------------------------------------------- lookup table


def test_lut_interpolates_the_exact_model():
    lut = spectral.skin_lut()
    assert spectral.skin_lut() is lut  # built once per process
    rng = np.random.default_rng(7)
    n = 300
    C_m = rng.uniform(np.cbrt(0.001), np.cbrt(0.5), n) ** 3
    beta = rng.uniform(0, 1, n)
    C_h = rng.uniform(np.cbrt(0.001), np.cbrt(0.32), n) ** 3
    rel = np.abs(lut.interpolate(C_m, beta, C_h) / spectral.skin_rgb(C_m, beta, C_h) - 1.0)
    assert rel.max() < LUT_REL_TOL, rel.max()
    i = (5, 3, 40)
    g = lut.grid_parameters
    np.testing.assert_allclose(
        lut.rgb[i], spectral.skin_rgb(g[0][i], g[1][i], g[2][i]), rtol=1e-12
    )
    with pytest.raises(InputError, match="C_h"):
        lut.interpolate(0.1, 0.5, 0.5)  # outside the table's C_h range


def test_lut_disk_cache_round_trip(tmp_path):
    small = (6, 3, 5)
    a = spectral.skin_lut(small, disk_cache=tmp_path)
    files = list(tmp_path.glob("skinlut-*.npz"))
    assert len(files) == 1
    b = spectral.skin_lut(small, disk_cache=tmp_path)  # read back from disk
    np.testing.assert_array_equal(a.rgb, b.rgb)
    assert b.shape == small and b.ranges == a.ranges
    files[0].write_bytes(b"not a table")  # a corrupt cache is rebuilt, not trusted
    c = spectral.skin_lut(small, disk_cache=tmp_path)
    np.testing.assert_array_equal(a.rgb, c.rgb)


# --------------------------------------------------------------------------- measured skin


@pytest.mark.shared_data
def test_fit_of_measured_skin_spectra(shared_data):
    """200 seeded spectra of Xiao et al. 2016, fitted over 400–700 nm."""
    path = shared_file(shared_data, XIAO)
    data = np.genfromtxt(path, delimiter=",", skip_header=1)
    wl_all = np.arange(360.0, 741.0, 10.0)
    assert data.shape[1] == 1 + wl_all.size
    sel = (wl_all >= 400) & (wl_all <= 700)
    rows = np.random.default_rng(2016).choice(data.shape[0], 200, replace=False)
    y = data[rows][:, 1:][:, sel]
    fit = spectral.fit_spectra(y, wl_all[sel])
    median = float(np.median(fit.rmse))
    print(
        f"\nXiao 2016, 200 spectra, 400-700 nm: median RMSE {median:.4f}, "
        f"90th percentile {np.percentile(fit.rmse, 90):.4f}; median C_m {np.median(fit.C_m):.3f}, "
        f"beta_m {np.median(fit.beta_m):.2f}, C_h {np.median(fit.C_h):.4f}"
    )
    assert np.all(np.isfinite(fit.rmse))
    np.testing.assert_allclose(fit.rmse, np.sqrt(np.mean((fit.model - y) ** 2, axis=1)))
    assert median <= XIAO_MEDIAN_RMSE_GOAL


def test_fit_spectra_recovers_model_spectra_and_rejects_bad_shapes():
    wl = np.arange(400.0, 701.0, 10.0)
    truth = (np.array([0.01, 0.05, 0.2]), np.array([0.2, 0.7, 0.9]), np.array([0.004, 0.03, 0.1]))
    fit = spectral.fit_spectra(spectral.skin_spectrum(*truth, wl), wl)
    assert np.max(fit.rmse) < 1e-4
    np.testing.assert_allclose(fit.C_m, truth[0], rtol=0.05)
    with pytest.raises(ShapeError, match="reflectance"):
        spectral.fit_spectra(np.ones((2, 5)), wl)


# --------------------------------------------------------------------------- inverse


def _realistic_parameters(n, seed):
    rng = np.random.default_rng(seed)
    C_m = rng.uniform(np.cbrt(0.002), np.cbrt(0.4), n) ** 3
    beta = rng.uniform(0.0, 1.0, n)
    C_h = rng.uniform(np.cbrt(0.002), np.cbrt(0.3), n) ** 3
    return C_m, beta, C_h


def test_round_trip_parameters_rgb_parameters():
    """params → exact RGB → fit: C_m and C_h within 10 % wherever they are flagged identifiable."""
    C_m, beta, C_h = _realistic_parameters(2000, 11)
    rgb = spectral.skin_rgb(C_m, beta, C_h)
    fit = spectral.fit_albedo(rgb)
    assert fit.C_m.shape == (2000,) and fit.flags.dtype == np.uint8
    assert np.all(fit.in_gamut), "every model colour is in the model's gamut"
    err_m = np.abs(fit.C_m / C_m - 1.0)
    err_h = np.abs(fit.C_h / C_h - 1.0)
    ok_m, ok_h = fit.identifiable[:, 0], fit.identifiable[:, 2]
    assert err_m[ok_m].max() <= ROUND_TRIP_REL_TOL
    assert err_h[ok_h].max() <= ROUND_TRIP_REL_TOL
    assert ok_m.mean() > 0.6 and ok_h.mean() > 0.1
    # Where the flags say "not identifiable", the errors are real: they can exceed 10 %.
    assert err_h[~ok_h].max() > ROUND_TRIP_REL_TOL
    assert np.all((fit.flags & FLAG_C_H_UNIDENTIFIABLE).astype(bool) == ~ok_h)
    # With β_m known, C_m and C_h are identifiable far more often.
    fixed = spectral.fit_albedo(spectral.skin_rgb(C_m, 0.5, C_h), beta_m=0.5)
    e_m = np.abs(fixed.C_m / C_m - 1.0)
    e_h = np.abs(fixed.C_h / C_h - 1.0)
    assert e_m[fixed.identifiable[:, 0]].max() <= ROUND_TRIP_REL_TOL
    assert e_h[fixed.identifiable[:, 2]].max() <= ROUND_TRIP_REL_TOL
    assert fixed.identifiable[:, 2].mean() > ok_h.mean()
    print(
        f"\nround trip (2000 texels): identifiable C_m {ok_m.mean():.1%}, C_h {ok_h.mean():.1%}; "
        f"max error there {err_m[ok_m].max():.3f}, {err_h[ok_h].max():.3f}; "
        f"median error overall {np.median(err_m):.4f}, {np.median(err_h):.4f}. "
        f"beta_m known: identifiable C_m {fixed.identifiable[:, 0].mean():.1%}, "
        f"C_h {fixed.identifiable[:, 2].mean():.1%}"
    )


def test_exact_refinement_and_lookup_stage():
    C_m, beta, C_h = _realistic_parameters(40, 3)
    rgb = spectral.skin_rgb(C_m, beta, C_h)
    exact = spectral.fit_albedo(rgb, refine="exact")
    assert np.max(exact.residual_log) < 1e-5  # the exact model reaches the exact colour
    lookup = spectral.fit_albedo(rgb, refine="none")
    lut = spectral.skin_lut()
    idx = lut.nearest(rgb)
    np.testing.assert_array_equal(lookup.x_lut, lut.x_of_index(idx))
    np.testing.assert_allclose(lookup.rgb_model, lut.rgb_flat[idx])
    assert np.median(lookup.residual_log) > np.median(exact.residual_log)


def test_two_solutions_for_one_colour_are_flagged():
    """Pheomelanin and blood both redden: (C_m, β_m, C_h) = (0.0719, 0.682, 0.0675) and
    (0.067, 0.946, 0.0016) give the same albedo within 0.05 %, so C_h is not identifiable."""
    a = spectral.skin_rgb(0.0719, 0.6822, 0.0675)
    b = spectral.skin_rgb(0.067, 0.946, 0.0016)
    assert np.max(np.abs(a / b - 1)) < 5e-4
    fit = spectral.fit_albedo(np.stack([a, b]))
    assert np.all(fit.flags & FLAG_C_H_UNIDENTIFIABLE)
    assert np.all(fit.in_gamut)


def test_out_of_gamut_and_black_albedo_are_flagged_not_raised():
    rgb = np.array([[0.1, 0.5, 0.1], [0.1, 0.1, 0.6], [0.7, 0.7, 0.7], [0.0, 0.0, 0.0]])
    fit = spectral.fit_albedo(rgb)
    assert np.all(fit.flags[:3] & FLAG_OUT_OF_GAMUT)
    assert fit.flags[3] & FLAG_DARK and fit.flags[3] & FLAG_OUT_OF_GAMUT
    assert np.all(np.isfinite(fit.C_m)) and np.all(np.isfinite(fit.residual))
    assert np.all(fit.residual[:3] > 0.05)


@pytest.mark.parametrize(
    "rgb, kwargs, err, match",
    [
        (np.ones((4, 2)), {}, ShapeError, r"\(\.\.\., 3\)"),
        (np.array([[0.2, np.nan, 0.1]]), {}, InputError, "non-finite"),
        (np.array([[0.2, 0.1, 0.1]]), {"refine": "magic"}, InputError, "refine"),
        (np.array([[0.2, 0.1, 0.1]]), {"beta_m": 2.0}, InputError, "beta_m"),
        (np.array([[0.2, 0.1, 0.1]]), {"noise": -1.0}, InputError, "noise"),
    ],
)
def test_fit_albedo_rejects_bad_input(rgb, kwargs, err, match):
    with pytest.raises(err, match=match):
        spectral.fit_albedo(rgb, **kwargs)


def test_fit_albedo_keeps_map_shape():
    albedo = spectral.spectral_albedo_fn("medium", seed=2)(
        np.random.default_rng(0).uniform(-1, 1, (6, 7, 3))
    )
    fit = spectral.fit_albedo(albedo, beta_profile=0)
    assert fit.C_m.shape == (6, 7) and fit.rgb_model.shape == (6, 7, 3) and fit.sigma.shape == (6, 7, 3)
    empty = spectral.fit_albedo(np.zeros((0, 3)))
    assert empty.C_m.shape == (0,)


# --------------------------------------------------------------------------- maps and edits


def test_parameter_maps_png_and_npy_round_trip(tmp_path):
    C_m, beta, C_h = (a.reshape(5, 8) for a in _realistic_parameters(40, 5))
    fit = spectral.fit_albedo(spectral.skin_rgb(C_m, beta, C_h), beta_profile=0)
    meta_path = spectral.save_parameter_maps(fit, tmp_path / "png")
    meta = json.loads(meta_path.read_text())
    assert meta["files"]["C_m"]["scale"] == 0.5 and meta["files"]["C_h"]["scale"] == 0.32
    import cv2

    assert cv2.imread(str(tmp_path / "png" / "C_h.png"), -1).dtype == np.uint16
    flags = cv2.imread(str(tmp_path / "png" / "flags.png"), -1)
    np.testing.assert_array_equal(flags, fit.flags)
    back = spectral.load_parameter_maps(tmp_path / "png")
    for name in ("C_m", "beta_m", "C_h"):
        scale = spectral.PNG_SCALES[name]
        assert np.max(np.abs(getattr(back, name) - getattr(fit, name))) <= PNG_HALF_STEP * scale * 1.0001
    spectral.save_parameter_maps(fit.parameters, tmp_path / "npy", fmt="npy")
    exact = spectral.load_parameter_maps(tmp_path / "npy")
    np.testing.assert_array_equal(exact.C_h, fit.C_h)
    with pytest.raises(InputError, match="2-D"):
        spectral.save_parameter_maps(SkinParameters(C_m.ravel(), beta.ravel(), C_h.ravel()), tmp_path / "x")
    with pytest.raises(ScanFormatError, match="parameter_maps.json"):
        spectral.load_parameter_maps(tmp_path / "nothing")
    assert not list((tmp_path / "png").glob(".*"))  # no temporary files left behind


def test_edit_more_blood_reddens_and_noop_is_exact(caplog):
    u = np.random.default_rng(1).uniform(-1, 1, (200, 3))
    albedo = spectral.spectral_albedo_fn("light", seed=4)(u)
    fit = spectral.fit_albedo(albedo, beta_profile=0)
    same = spectral.edit(fit)
    np.testing.assert_array_equal(same, albedo)  # no edit, no change: detail is preserved
    flushed = spectral.edit(fit, C_h=lambda c: 1.5 * c)
    assert flushed.dtype == np.float32 and flushed.shape == albedo.shape
    ratio = flushed / albedo
    assert np.all(ratio[:, 1] < 1.0) and np.mean(ratio[:, 1]) < np.mean(ratio[:, 0])  # G falls most
    params = spectral.regional_parameter_maps(u, "light", seed=4)
    direct = spectral.edit(params, C_m=0.2)
    assert np.all(direct.mean(axis=1) < albedo.mean(axis=1))  # more melanin: darker
    with caplog.at_level(logging.WARNING, logger="facegeo.appearance.spectral._inverse"):
        spectral.edit(params, C_h=lambda c: 100 * c)
    assert "clipped" in caplog.text
    with pytest.raises(InputError, match="non-finite"):
        spectral.edit(params, C_h=lambda c: c * np.nan)


# --------------------------------------------------------------------------- generator


def test_regional_parameter_maps_are_pure_smooth_and_regional():
    rng = np.random.default_rng(0)
    u = rng.uniform(-1, 1, (500, 3))
    a = spectral.regional_parameter_maps(u, "medium", seed=3)
    b = spectral.regional_parameter_maps(u, "medium", seed=3)
    c = spectral.regional_parameter_maps(u, "medium", seed=4)
    np.testing.assert_array_equal(a.C_h, b.C_h)
    assert not np.allclose(a.C_h, c.C_h)
    for name, (lo, hi) in spectral.PARAMETER_RANGES.items():
        v = getattr(a, name)
        assert v.shape == (500,) and v.min() >= lo and v.max() <= hi
    # Smooth: a 1e-4 step in u moves every parameter by O(1e-4) (relative for C_m, C_h).
    d = spectral.regional_parameter_maps(u + 1e-4, "medium", seed=3)
    assert np.max(np.abs(np.log(d.C_h / a.C_h))) < 0.01 and np.max(np.abs(d.rho_s - a.rho_s)) < 0.01
    centres = {k: np.array(v[0]) for k, v in spectral.PARAMETER_REGIONS.items()}
    p = spectral.regional_parameter_maps(
        np.stack([centres["lips"], centres["cheeks"], centres["forehead"], centres["nose"]]),
        "medium", seed=3, variation=1.0,
    )
    lips, cheek, forehead, nose = range(4)
    assert p.C_h[lips] > p.C_h[cheek] > p.C_h[forehead]
    assert p.rho_s[forehead] > p.rho_s[cheek] and p.rho_s[nose] > p.rho_s[cheek]
    flat = spectral.regional_parameter_maps(u, {"C_m": 0.1}, variation=0.0)
    np.testing.assert_allclose(flat.C_m, 0.1, rtol=1e-12)
    np.testing.assert_allclose(flat.C_h, spectral.SKIN_TYPES["medium"]["C_h"], rtol=1e-12)


def test_spectral_albedo_fn_matches_exact_model_and_plugs_into_skin_field():
    u = np.random.default_rng(5).uniform(-1, 1, (4, 5, 3))
    fn = spectral.spectral_albedo_fn("olive", seed=9)
    a = fn(u)
    assert a.shape == (4, 5, 3) and a.dtype == np.float32
    p = fn.parameter_maps(u)
    exact = spectral.skin_rgb(p.C_m, p.beta_m, p.C_h)
    assert np.max(np.abs(a / exact - 1)) < LUT_REL_TOL
    np.testing.assert_array_equal(fn(u), a)
    skin = pytest.importorskip("facegeo.synth.skin")
    field = skin.SkinField(center=(0.0, 0.0, 0.0), half_extent=(0.1, 0.12, 0.1), seed=9, albedo_fn=fn)
    sample = field.evaluate(u * np.array([0.1, 0.12, 0.1]))
    np.testing.assert_allclose(sample.alpha_0, a, rtol=1e-6)
    # As a named, serialisable model (the noise seed is the field's seed).
    named = skin.SkinField(
        center=(0.0, 0.0, 0.0), half_extent=(0.1, 0.12, 0.1), seed=9,
        albedo_model="spectral", albedo_params={"params": "olive"},
    )
    np.testing.assert_allclose(named.evaluate(u * np.array([0.1, 0.12, 0.1])).alpha_0, a, rtol=1e-6)


@pytest.mark.parametrize(
    "u, params, err, match",
    [
        (np.zeros((3, 2)), "medium", ShapeError, "u"),
        (np.full((1, 3), np.nan), "medium", InputError, "non-finite"),
        (np.zeros((1, 3)), "martian", InputError, "martian"),
        (np.zeros((1, 3)), {"C_m": 0.9}, InputError, "C_m"),
        (np.zeros((1, 3)), {"melanin": 0.1}, InputError, "unknown"),
    ],
)
def test_generator_rejects_bad_input(u, params, err, match):
    with pytest.raises(err, match=match):
        spectral.regional_parameter_maps(u, params)


# --------------------------------------------------------------------------- LM bad steps


def test_lm_counts_skipped_steps_instead_of_dropping_them(caplog):
    """Levenberg–Marquardt on a toy problem r = x − t: rows with no finite step (an inf in the
    Jacobian) or a NaN residual count every skipped step and are logged; healthy rows count
    none and converge."""
    from facegeo.appearance.spectral._inverse import _lm

    t = np.array([[0.2, 0.3, 0.4], [0.5, 0.1, 0.7], [0.3, 0.3, 0.3], [0.6, 0.6, 0.6]])

    def residual(x):
        r = x - t[: len(x)]
        J = np.broadcast_to(np.eye(3), (len(x), 3, 3)).copy()
        J[2, 0, 0] = np.inf  # row 2: a non-finite Jacobian, so no finite step exists
        r[3] = np.nan  # row 3: the residual is not finite anywhere
        return r, J

    x0 = np.full((4, 3), 0.5)
    with caplog.at_level(logging.DEBUG, logger="facegeo.appearance.spectral._inverse"):
        x, skipped = _lm(x0, residual, np.zeros(3), np.ones(3), 6, np.array([True, True, True]))
    assert skipped.tolist()[:2] == [0, 0], "healthy rows skip nothing"
    assert skipped[2] == 6, "a non-finite step is skipped every iteration"
    assert skipped[3] == 6, "a NaN residual skips every iteration"
    assert np.abs(x[:2] - t[:2]).max() < 1e-6, "healthy rows converge (max abs, parameters)"
    assert np.array_equal(x[3], x0[3]), "the NaN row keeps its start"
    assert "skipped" in caplog.text, "skipped steps are logged"


def test_fit_albedo_flags_skipped_steps():
    """A NaN in the LUT residual (here: a target forced to NaN after validation would be
    refused, so the residual function is broken instead) surfaces as FLAG_SKIPPED_STEPS."""
    from facegeo.appearance.spectral import _inverse

    rgb = spectral.skin_rgb(np.array([0.03, 0.1]), 0.5, np.array([0.01, 0.02]))
    good = spectral.fit_albedo(rgb, beta_profile=0)
    assert np.all(good.skipped_steps == 0), "a clean fit skips no step"
    assert not np.any(good.flags & _inverse.FLAG_SKIPPED_STEPS)
    real = _inverse._lm

    def nan_first_row(x, fn, *a):
        def broken(xx):
            r, J = fn(xx)
            r = r.copy()
            r[0] = np.nan
            return r, J
        return real(x, broken, *a)

    try:
        _inverse._lm = nan_first_row
        bad = spectral.fit_albedo(rgb, beta_profile=0)
    finally:
        _inverse._lm = real
    assert bad.skipped_steps[0] > 0 and bad.skipped_steps[1] == 0, bad.skipped_steps
    assert bad.flags[0] & _inverse.FLAG_SKIPPED_STEPS, "flagged"
    assert not bad.flags[1] & _inverse.FLAG_SKIPPED_STEPS, "only the broken texel"


def test_first_spectral_call_leaves_numpy_print_options_alone():
    """colour-science's import sets ``np.set_printoptions(legacy="1.13")`` process-wide; the
    first spectral call (which imports it) must not change how the user's arrays print. In a
    fresh interpreter: this process may have imported colour already."""
    import subprocess
    import sys

    code = ("import numpy as np; before = np.get_printoptions(); "
            "from facegeo.appearance import spectral; spectral.skin_rgb(0.03, 0.05, 0.008); "
            "assert np.get_printoptions() == before, np.get_printoptions(); print('ok')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr[-2000:]
