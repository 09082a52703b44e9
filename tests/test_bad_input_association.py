"""Bad input to kftrack.association and kftrack.metrics (issue 25, the newcomer's list): each case
raises a ValueError or TypeError whose message names the argument; the legitimate neighbours of
each case still work."""
import numpy as np
import pytest

from kftrack import association as A, metrics, models

nan, inf = np.nan, np.inf
cv = models.ConstantVelocity(ndim=2, q=1.0)
x, P, H, R = np.zeros(4), 10 * np.eye(4), cv.H, 4 * np.eye(2)
Z = np.array([[1.0, 1.0], [3.0, -2.0], [50.0, 50.0]])
E3 = np.array([[0.5, 0.0], [30.0, 30.0]])
T3 = np.array([[0.0, 0.0], [10.0, 10.0]])


@pytest.mark.parametrize("kw,name", [(dict(P_D=np.array([0.9, 0.8])), "P_D"), (dict(P_G=np.array([0.99, 0.9])), "P_G")])
def test_pdaf_probabilities_must_be_scalars(kw, name):
    args = dict(P_D=0.9, P_G=0.99, clutter_density=1e-3) | kw
    with pytest.raises(ValueError, match=rf"{name} \(.*probability\) must be a scalar.*shape \(2,\)"):
        A.pdaf_update(x, P, Z, H, R, **args)
    with pytest.raises(ValueError, match=name):
        A.jpda_update(np.stack([x, x]), np.stack([P, P]), Z, H, R, **args)
    # a 0-d array is a scalar and works
    A.pdaf_update(x, P, Z, H, R, **(args | {name: np.array(0.9)}))


@pytest.mark.parametrize("fn", [A.gospa, A.ospa])
def test_gospa_refuses_nan_and_inf(fn):
    with pytest.raises(ValueError, match="truth must be finite, but it contains NaN"):
        fn(np.array([[nan, 0.0], [10.0, 10.0]]), E3, c=10.0)
    with pytest.raises(ValueError, match="estimate must be finite, but it contains inf"):
        fn(T3, np.array([[inf, 0.0], [30.0, 30.0]]), c=10.0)
    d = fn(T3, E3, c=10.0)  # finite sets still work
    assert np.isfinite(d.distance if fn is A.gospa else d)


def test_nees_names_the_shapes():
    with pytest.raises(ValueError, match=r"truth \(5,\), estimate \(3,\)"):
        metrics.nees(np.ones((5, 4)), np.zeros((3, 4)), P)
    with pytest.raises(ValueError, match=r"y \(5,\), S \(3,\)"):
        metrics.nis(np.ones((5, 2)), np.broadcast_to(np.eye(2), (3, 2, 2)))
    assert metrics.nees(np.ones((5, 4)), np.zeros((1, 4)), P).shape == (5,)  # broadcasting still works


def test_anees_names_the_axis():
    v = np.random.default_rng(0).chisquare(2, (50, 20))
    with pytest.raises(ValueError, match=r"axis 5 is out of range for nees_values of shape \(50, 20\)"):
        metrics.anees(v, 2, axis=5)
    with pytest.raises(TypeError, match="axis"):
        metrics.anees(v, 2, axis=1.0)
    np.testing.assert_allclose(metrics.anees(v, 2, axis=-1), v.mean(-1) / 2, rtol=1e-15)


def test_rmse_refuses_nan_and_empty():
    with pytest.raises(ValueError, match="estimate must be finite, but it contains NaN"):
        metrics.rmse(np.ones((10, 2)), np.full((10, 2), nan))
    with pytest.raises(ValueError, match="truth must be finite, but it contains inf"):
        metrics.rmse(np.full((10, 2), inf), np.ones((10, 2)))
    with pytest.raises(ValueError, match=r"truth and estimate must hold at least one value, got shapes \(0,\) and \(0,\)"):
        metrics.rmse([], [])
    with pytest.raises(ValueError, match="axis 2 is out of range"):
        metrics.rmse(np.ones((10, 2)), np.zeros((10, 2)), axis=2, vector=True)
    assert metrics.rmse(np.ones((10, 2)), np.zeros((10, 2)), vector=True) == pytest.approx(np.sqrt(2), rel=1e-15)


def test_gnn_assignment_bad_input():
    cost, gate = np.array([[5.0, 0.0], [0.0, 10.0]]), np.array([[True, False], [True, True]])
    with pytest.raises(ValueError, match=r"miss_cost must be a scalar or have shape \(2,\)"):
        A.gnn_assignment(cost, gate, miss_cost=np.ones(3))
    with pytest.raises(ValueError, match="miss_cost must be finite"):
        A.gnn_assignment(cost, gate, miss_cost=inf)
    with pytest.raises(ValueError, match="cost must be finite where gate_mask is true"):
        A.gnn_assignment(np.where(gate, nan, 0.0), gate)
    with pytest.raises(TypeError, match="gate_mask must be a boolean array"):
        A.gnn_assignment(cost, gate.astype(int))
    with pytest.raises(ValueError, match=r"cost and gate_mask must both have shape \(T, M\)"):
        A.gnn_assignment(cost, gate[:1])


def test_jpda_21_by_21_raises_with_the_size_and_the_alternatives():
    # 12 x 12 is exact now (subset programme, issue 28); beyond 16 measurements in one cluster it raises
    with pytest.raises(ValueError) as err:
        A.jpda_update(np.zeros((21, 4)), np.broadcast_to(P, (21, 4, 4)), np.zeros((21, 2)), H, R, P_D=0.9, P_G=0.99,
                      clutter_density=1e-3)
    msg = str(err.value)
    for word in ("joint events", "21 targets and 21 measurements", "max_events = 100000", "at most 16", "P_G",
                 "pdaf_update", "gnn_assignment"):
        assert word in msg, (word, msg)
