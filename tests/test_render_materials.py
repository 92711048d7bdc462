"""Thin-film reflectance (transfer-matrix) against closed forms and published constants.

No Mitsuba needed: these run in every install.
"""

import numpy as np
import pytest

from mehs.errors import InputError
from mehs.render.materials import (FilmStack, parse_material, reflectance_TMM, refractive_index,
                                   rgb_table, spectral_table)

LAM = np.arange(400.0, 701.0, 5.0)


def airy_single_film(n0, n1, n2, d, lam, cos0, pol):
    """Born & Wolf's one-film formula at oblique incidence, written out independently."""
    sin0 = np.sqrt(1 - cos0 ** 2)
    c1 = np.sqrt(1 - (n0 * sin0 / n1) ** 2 + 0j)
    c2 = np.sqrt(1 - (n0 * sin0 / n2) ** 2 + 0j)
    # forward branch: Im(n cos) >= 0
    c1 = np.where((n1 * c1).imag < 0, -c1, c1)
    c2 = np.where((n2 * c2).imag < 0, -c2, c2)
    if pol == "s":
        r01 = (n0 * cos0 - n1 * c1) / (n0 * cos0 + n1 * c1)
        r12 = (n1 * c1 - n2 * c2) / (n1 * c1 + n2 * c2)
    else:
        r01 = (n1 * cos0 - n0 * c1) / (n1 * cos0 + n0 * c1)
        r12 = (n2 * c1 - n1 * c2) / (n2 * c1 + n1 * c2)
    e = np.exp(2j * 2 * np.pi * n1 * c1 * d / lam)
    return np.abs((r01 + r12 * e) / (1 + r01 * r12 * e)) ** 2


def test_sio2_on_si_normal_incidence_matches_airy_closed_form():
    n1, n2 = refractive_index("SiO2", LAM), refractive_index("Si", LAM)
    r01, r12 = (1 - n1) / (1 + n1), (n1 - n2) / (n1 + n2)
    e = np.exp(4j * np.pi * n1 * 300.0 / LAM)
    closed = np.abs((r01 + r12 * e) / (1 + r01 * r12 * e)) ** 2
    tmm = FilmStack((("SiO2", 300.0),), "Si").reflectance(LAM, np.array([1.0]))[:, 0]
    assert np.max(np.abs(tmm - closed)) <= 1e-6
    # interference: a 300 nm film gives reflectance minima/maxima inside the visible range
    assert tmm.max() - tmm.min() > 0.3


@pytest.mark.parametrize("cos0", [0.9, 0.5, 0.1])
def test_oblique_incidence_matches_airy_per_polarisation(cos0):
    n1, n2 = refractive_index("SiO2", LAM), refractive_index("Si", LAM)
    stack = [np.ones_like(n1), n1, n2]
    for pol in ("s", "p"):
        from mehs.render.materials import amplitude_TMM

        tmm = np.abs(amplitude_TMM(stack, [300.0], LAM, np.array(cos0), pol)) ** 2
        ref = airy_single_film(1.0, n1, n2, 300.0, LAM, cos0, pol)
        assert np.max(np.abs(tmm - ref)) <= 1e-6


def test_two_films_match_nested_airy():
    """Al 5 nm on SiO2 400 nm on Si: the stack equals Airy applied twice (inner film first)."""
    n_al, n_ox, n_si = (refractive_index(m, LAM) for m in ("Al", "SiO2", "Si"))
    r = lambda a, b: (a - b) / (a + b)  # noqa: E731
    e_ox = np.exp(2j * 2 * np.pi * n_ox * 400.0 / LAM)
    r_inner = (r(n_al, n_ox) + r(n_ox, n_si) * e_ox) / (1 + r(n_al, n_ox) * r(n_ox, n_si) * e_ox)
    e_al = np.exp(2j * 2 * np.pi * n_al * 5.0 / LAM)
    r_all = (r(1.0, n_al) + r_inner * e_al) / (1 + r(1.0, n_al) * r_inner * e_al)
    tmm = FilmStack((("Al", 5.0), ("SiO2", 400.0)), "Si").reflectance(LAM, np.array([1.0]))[:, 0]
    assert np.max(np.abs(tmm - np.abs(r_all) ** 2)) <= 1e-6


def test_lossless_stack_conserves_energy_and_grazing_is_a_mirror():
    lam = LAM[:, None]
    n = refractive_index("SiO2", LAM)[:, None]
    cos = np.linspace(0.0, 1.0, 11)[None, :]
    # SiO2 film on a glass-like lossless substrate: R in [0, 1], grazing R = 1
    R = reflectance_TMM([np.ones_like(n), n, np.full_like(n, 1.9)], [250.0], lam, cos)
    assert np.all((R >= 0) & (R <= 1 + 1e-12))
    assert np.allclose(R[:, 0], 1.0)
    # a zero-thickness film is no film
    bare = reflectance_TMM([np.ones_like(n), np.full_like(n, 1.9)], [], lam, cos)
    assert np.allclose(reflectance_TMM([np.ones_like(n), n, np.full_like(n, 1.9)], [0.0], lam, cos),
                       bare, atol=1e-12)


def test_published_optical_constants():
    # Malitson 1965: fused silica n_D (589.3 nm) = 1.4584; Green 2008: Si at 600 nm
    assert refractive_index("SiO2", np.array([589.3]))[0].real == pytest.approx(1.4584, abs=2e-4)
    si = refractive_index("Si", np.array([600.0]))[0]
    assert si.real == pytest.approx(3.940) and si.imag == pytest.approx(0.019934)
    al = refractive_index("Al", np.array([500.0]))[0]
    assert al.real == pytest.approx(0.6257, abs=1e-3) and al.imag == pytest.approx(5.3205, abs=1e-3)
    with pytest.raises(InputError, match="cover"):
        refractive_index("Si", np.array([300.0]))


def test_parse_material_and_tables():
    kind, stack = parse_material("thin-film:Al:5nm,SiO2:400nm")
    assert kind == "thin-film" and stack.layers == (("Al", 5.0), ("SiO2", 400.0))
    assert stack.substrate == "Si"
    assert parse_material("thin-film:SiO2:300nm@Al")[1].substrate == "Al"
    assert parse_material("diffuse:0.5") == ("diffuse", 0.5)
    for bad in ("thin-film:SiO2:300", "thin-film:Gold:5nm", "plastic", "diffuse:2"):
        with pytest.raises(InputError, match="--material"):
            parse_material(bad)
    t = spectral_table(parse_material("thin-film:SiO2:300nm")[1])
    assert np.all((t >= 0) & (t <= 1)) and np.allclose(t[:, 0], 1.0)
    rgb = rgb_table(FilmStack((), "Al"))
    # bare aluminium is a bright, nearly neutral mirror at normal incidence
    assert np.all(rgb[:, -1] > 0.85) and np.ptp(rgb[:, -1]) < 0.05
