"""The detector geometry derived in amigo (niriss.nominal_geometry_matrix) against the
JWST SIAF as pysiaf computes it: an independent implementation of the same chain
(V2/V3 -> ideal -> science pixels, with the full distortion polynomial)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from amigo import niriss


@pytest.fixture(scope="module")
def aperture():
    pysiaf = pytest.importorskip("pysiaf", reason="pysiaf (test extra) is not installed")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # it cannot check its PRD version offline
        return pysiaf.Siaf("NIRISS")["NIS_AMI1"]


def test_siaf_numbers_are_those_pysiaf_ships(aperture):
    a = aperture
    assert a.XSciSize == a.YSciSize == niriss.SUBARRAY_SIZE
    assert a.V3IdlYAngle == pytest.approx(niriss.V3_IDL_Y_ANGLE_DEG, abs=1e-9)
    assert a.VIdlParity == niriss.VIDL_PARITY
    linear = np.array([[a.Sci2IdlX10, a.Sci2IdlX11], [a.Sci2IdlY10, a.Sci2IdlY11]])
    np.testing.assert_allclose(niriss.SIAF_SCI_TO_IDEAL_ARCSEC_PER_PIX, linear, rtol=1e-12)


def test_geometry_chain_matches_pysiaf_at_the_reference_pixel(aperture):
    """Science-pixel steps of +-1 pixel about the aperture's reference pixel through
    pysiaf's sci_to_tel (science -> ideal -> V2/V3 with the full distortion polynomial and
    the spherical V2/V3 rotation), taken to amigo's optical frame (``x = -V2``,
    ``y = +V3``): the inverse of the central-difference Jacobian equals amigo's G to 2e-6.
    pysiaf's separately fitted inverse polynomial (tel_to_sci, V2/V3 steps of +-0.5
    arcsec) agrees to 1e-4 (its fit's accuracy: 1e-4 of 8 pixels is 0.05 mas)."""
    a = aperture
    to_optical = np.linalg.inv(niriss.pupil_to_v2v3_matrix())
    columns = []
    for step in np.eye(2):
        ends = []
        for sign in (1.0, -1.0):
            v2, v3 = a.sci_to_tel(a.XSciRef + sign * step[0], a.YSciRef + sign * step[1])
            ends.append(to_optical @ np.array([v2 - a.V2Ref, v3 - a.V3Ref]))
        columns.append((ends[0] - ends[1]) / 2.0)
    arcsec_per_pixel = np.array(columns).T
    g_siaf = np.linalg.inv(arcsec_per_pixel) * niriss.PIXEL_SCALE_ARCSEC
    g = niriss.nominal_geometry_matrix()
    # The same chain through pysiaf's inverse polynomial, V2/V3 -> science.
    h = 0.5
    columns = []
    for step in np.eye(2) * h:
        ends = []
        for sign in (1.0, -1.0):
            v2v3 = niriss.pupil_to_v2v3_matrix() @ (sign * step)
            ends.append(np.array(a.tel_to_sci(a.V2Ref + v2v3[0], a.V3Ref + v2v3[1])))
        columns.append((ends[0] - ends[1]) / (2 * h))
    g_inverse_polynomial = np.array(columns).T * niriss.PIXEL_SCALE_ARCSEC
    print(
        f"\namigo G:\n{g}\nmax |G - pysiaf sci_to_tel| {np.abs(g_siaf - g).max():.1e}, "
        f"max |G - pysiaf tel_to_sci| {np.abs(g_inverse_polynomial - g).max():.1e}"
    )
    np.testing.assert_allclose(g, g_siaf, atol=2e-6)
    np.testing.assert_allclose(g, g_inverse_polynomial, atol=1e-4)


def test_nominal_geometry_turns_clockwise_with_a_skew():
    """The numbers docs/geometry.md quotes; the rotation is negative (clockwise), the sense
    the SIAF and real data share (the research code's +0.561 deg turned it the other way)."""
    g = niriss.nominal_geometry()
    assert g.rotation_deg == pytest.approx(-0.4437, abs=1e-4)
    assert g.skew_deg == pytest.approx(-0.2591, abs=1e-4)
    assert g.anisotropy == pytest.approx(1.00601, abs=1e-5)
    assert g.scale == pytest.approx(1.0, abs=2e-5)
    # V3IdlYAngle alone turns the optical frame by -0.561 deg in the ideal frame.
    ideal = niriss.v2v3_to_ideal_matrix() @ niriss.pupil_to_v2v3_matrix()
    turn = np.rad2deg(np.arctan2(ideal[1, 0], ideal[0, 0]))
    assert turn == pytest.approx(-niriss.V3_IDL_Y_ANGLE_DEG, abs=1e-9)
