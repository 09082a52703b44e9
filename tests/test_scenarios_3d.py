"""Tests of the 3-D manoeuvre scenarios in kftrack.scenarios (chapter 6)."""
import numpy as np
import pytest

from kftrack import frenet as fr
from kftrack import scenarios as sc

ALL = {
    "drone I": lambda rng: sc.drone_scenario(rng, "I"),
    "drone II": lambda rng: sc.drone_scenario(rng, "II"),
    "drone III": lambda rng: sc.drone_scenario(rng, "III"),
    "zigzag": lambda rng: sc.tilted_zigzag(rng),
    "helix": lambda rng: sc.climbing_helix(rng),
    "manoeuvre": lambda rng: sc.torsion_manoeuvre(rng),
}


@pytest.mark.parametrize("name", list(ALL))
def test_deterministic_under_seed_and_labelled(name):
    a = ALL[name](np.random.default_rng(7))
    b = ALL[name](np.random.default_rng(7))
    c = ALL[name](np.random.default_rng(8))
    for x, y in zip(a[:4], b[:4]):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.truth, c.truth)
    assert not np.array_equal(a.z, c.z)
    T = len(a.t)
    assert a.truth.shape == (T, 6) and a.z.shape == (T, 3) and a.label.shape == (T,)
    np.testing.assert_array_equal(a.truth[:, [0, 2, 4]], a.track.r)
    np.testing.assert_array_equal(a.truth[:, [1, 3, 5]], a.track.v)
    # labels: straight samples have no normal acceleration, turning ones have v^2 |kappa|
    speed = np.linalg.norm(a.track.v, axis=1)
    a_n = np.linalg.norm(np.cross(a.track.v, a.track.a), axis=1) / speed
    np.testing.assert_allclose(a_n[a.label == 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(a_n[a.label == 1], speed[a.label == 1] ** 2 * np.abs(a.track.kappa[a.label == 1]),
                               rtol=1e-9)
    assert set(np.unique(a.label)) <= {0, 1}
    # measurement noise has the stated size (chi-square bound, 3 T dof at 99.9 %)
    from scipy import stats
    sigma = {"drone I": 0.5, "drone II": 2.0, "drone III": 5.0, "zigzag": 75.0, "helix": 10.0, "manoeuvre": 10.0}[name]
    ss = np.sum(((a.z - a.track.r) / sigma) ** 2)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], 3 * T)
    assert lo < ss < hi


def test_drone_scenarios_as_printed():
    dts = [round(s.dt, 4) for s in sc.MARTINS2018_SCENARIOS.values()]
    assert dts == [0.3904, 0.4472, 2.6833]
    rng = np.random.default_rng(1)
    one = sc.drone_scenario(rng, "I")
    assert len(one.t) == 201 and one.label.sum() == 0
    np.testing.assert_allclose(one.truth[0], [1, 1, 1, 0.8, 0, 0])
    np.testing.assert_allclose(np.linalg.norm(one.truth[-1, [0, 2]] - one.truth[0, [0, 2]]), 100.0, rtol=1e-12)
    two = sc.drone_scenario(rng, "II")
    assert np.argmax(two.label) == 50
    three = sc.drone_scenario(rng, "III")
    assert np.argmax(three.label) == 60
    np.testing.assert_allclose(three.truth[:, 4], 10.0, atol=1e-9)
    np.testing.assert_allclose(three.truth[0, [0, 2]], [0, 0.7])
    assert sc.drone_scenario(rng, "I", sigma=0.0).z.tolist() == one.track.r.tolist()


def test_tilted_zigzag_is_planar_in_a_30_degree_plane():
    z = sc.tilted_zigzag(np.random.default_rng(0))
    assert np.all(np.diff(z.t) == 4.0)
    np.testing.assert_allclose(np.linalg.norm(z.track.v, axis=1), 250.0, rtol=1e-12)
    b = z.track.frame[:, 2]
    np.testing.assert_allclose(b, np.broadcast_to(b[0], b.shape), atol=1e-12)  # zero torsion
    assert np.rad2deg(np.arccos(b[0, 2])) == pytest.approx(30.0)
    np.testing.assert_allclose((z.track.r - z.track.r[0]) @ b[0], 0.0, atol=1e-7)
    np.testing.assert_allclose(z.truth[0], [-30000, 196.16, -30000, 154.98, 600, 0], atol=0.01)
    # seven segments, three turns: +45, -90, +45 degrees at 0.05 rad/s
    assert len(np.unique(z.track.segment)) == 7
    turns = np.flatnonzero(np.diff(np.r_[0, z.label, 0]))
    assert len(turns) == 6
    assert z.truth[:, 4].min() >= 600 - 1e-6
    heading = np.arctan2(z.truth[-1, 3], z.truth[-1, 1])
    assert heading == pytest.approx(np.arctan2(154.98, 196.16), abs=1e-9)


def test_helix_curvature_torsion_and_climb():
    h = sc.climbing_helix(np.random.default_rng(0), speed=100.0, rate=0.05, climb_deg=10.0)
    turn = h.label == 1
    k, tau = fr.curvature_torsion(h.track.v[turn], h.track.a[turn], h.track.jerk[turn])
    g = np.deg2rad(10.0)
    R = 100.0 * np.cos(g) / 0.05
    np.testing.assert_allclose(k, np.cos(g) ** 2 / R, rtol=1e-12)
    np.testing.assert_allclose(tau, np.sin(g) * np.cos(g) / R, rtol=1e-10)
    np.testing.assert_allclose(h.truth[:, 5], 100.0 * np.sin(g), rtol=1e-12)  # constant climb rate
    w_vertical = np.diff(np.unwrap(np.arctan2(h.truth[turn, 3], h.truth[turn, 1])))
    np.testing.assert_allclose(w_vertical, 0.05, rtol=1e-9)
    # a negative rate: the mirror image, clockwise from above, a left-handed helix (tau < 0)
    m = sc.climbing_helix(np.random.default_rng(0), rate=-0.05)
    k_m, tau_m = fr.curvature_torsion(m.track.v[turn], m.track.a[turn], m.track.jerk[turn])
    np.testing.assert_allclose(k_m, k, rtol=1e-12)
    np.testing.assert_allclose(tau_m, -tau, rtol=1e-10)
    np.testing.assert_allclose(m.truth[:, [0, 1, 4, 5]], h.truth[:, [0, 1, 4, 5]], atol=1e-6)
    np.testing.assert_allclose(m.truth[:, [2, 3]], -h.truth[:, [2, 3]], atol=1e-6)


def test_manoeuvre_speed_profile():
    m = sc.torsion_manoeuvre(np.random.default_rng(0))
    speed = np.linalg.norm(m.track.v, axis=1)
    np.testing.assert_allclose(speed**2, 3600 + 2 * np.where(m.track.s > 600, np.minimum(m.track.s, 1400) - 600, 0)
                               - 2 * np.clip(m.track.s - 1400, 0, 400), rtol=1e-12)
    assert (m.track.tau != 0).any() and m.label.sum() > 0


def test_bad_inputs():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="name"):
        sc.drone_scenario(rng, "IV")
    with pytest.raises(TypeError, match="rng"):
        sc.tilted_zigzag(np.random.RandomState(0))
    with pytest.raises(ValueError, match="sigma"):
        sc.climbing_helix(rng, sigma=-1.0)
    for kw in ("speed", "dt", "omega", "turn_deg", "leg"):
        with pytest.raises(ValueError, match=f"^{kw} must be > 0"):
            sc.tilted_zigzag(rng, **{kw: 0.0})
    with pytest.raises(ValueError, match="^rate must be non-zero"):
        sc.climbing_helix(rng, rate=0.0)
    with pytest.raises(ValueError, match="climb_deg"):
        sc.climbing_helix(rng, climb_deg=90.0)
    with pytest.raises(ValueError, match="^speed must be > 0"):
        sc.climbing_helix(rng, speed=-100.0)
