"""Tests of kftrack.trackeval: GOSPA over time and track-level metrics, on hand-made cases whose
answers are worked out in the comments."""
import numpy as np
import pytest

from kftrack import association as asc, trackeval as te

C = 10.0


def test_gospa_over_time_by_hand():
    # c = 10, p = 2, so a missed or false target costs c^2/2 = 50 (in d^p)
    # t=0: truth A (0,0), estimate (3,4): d = 5 -> loc 25; estimate at (1000,0): false -> 25 + 50 = 75
    # t=1: truth A (1,0), B (50,0); estimate (1,1) on A: loc 1; B missed -> 1 + 50 = 51
    # t=2: nothing at all -> 0
    # t=3: truth A (3,0), estimate (3,12): d = 12 > c, no pair -> missed 1, false 1 -> 100
    truth = [(["A"], [[0.0, 0.0]]), (["A", "B"], [[1.0, 0.0], [50.0, 0.0]]), ([], []), (["A"], [[3.0, 0.0]])]
    est = [([1, 2], [[3.0, 4.0], [1000.0, 0.0]]), ([1], [[1.0, 1.0]]), ([], []), ([1], [[3.0, 12.0]])]
    g = te.gospa_over_time([0.0, 1.0, 2.0, 3.0], truth, est, c=C)
    np.testing.assert_allclose(g.distance**2, [75.0, 51.0, 0.0, 100.0], rtol=1e-14)
    np.testing.assert_allclose(g.localisation, [25.0, 1.0, 0.0, 0.0], rtol=1e-14)
    np.testing.assert_array_equal(g.missed, [0, 1, 0, 1])
    np.testing.assert_array_equal(g.false, [1, 0, 0, 1])
    # each time agrees with association.gospa
    for k in range(4):
        ref = asc.gospa(truth[k][1], est[k][1], c=C)
        assert (g.distance[k], g.localisation[k], g.missed[k], g.false[k]) == tuple(ref)


def test_gospa_assignment_pairs():
    # truths (0,0), (10,0), (20,0); estimates (10.5,0) -> truth 1, (19,0) -> truth 2; truth 0 missed
    g, pairs = asc.gospa_assignment([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]], [[10.5, 0.0], [19.0, 0.0]], c=5.0)
    assert pairs.tolist() == [[1, 0], [2, 1]]
    assert (g.missed, g.false, g.localisation) == (1, 0, 0.25 + 1.0)
    assert asc.gospa_assignment([], [[0.0, 0.0]], c=1.0)[1].shape == (0, 2)


def test_identity_switches_by_hand():
    # truths A at x=0 and B at x=100 for 4 scans; tracks 1 on A and 2 on B at t=0,1, then swapped
    # at t=2,3. Assigned tracks: A: 1,1,2,2 and B: 2,2,1,1. At t=2 A changes 1 -> 2 while track 1 is
    # still reported: a switch; the same for B: switches = 2, breaks = 0. Every track and truth is
    # assigned at all its times: no false track, no missed target; time to confirm 0 for both.
    truth = [(["A", "B"], [[0.0, 0.0], [100.0, 0.0]])] * 4
    on, off = [[1.0, 0.0], [101.0, 0.0]], [[101.0, 0.0], [1.0, 0.0]]
    est = [([1, 2], on), ([1, 2], on), ([1, 2], off), ([1, 2], off)]
    m = te.track_metrics(np.arange(4.0), truth, est, c=C)
    assert (m.switches, m.breaks, m.false_tracks, m.missed_targets) == (2, 0, 0, 0)
    assert m.truth_ids == ["A", "B"] and m.track_ids == [1, 2]
    np.testing.assert_array_equal(m.time_to_confirm, [0.0, 0.0])
    np.testing.assert_array_equal(m.coverage, [1.0, 1.0])


def test_breaks_false_tracks_missed_targets_and_time_to_confirm_by_hand():
    # times 0..5 (s). Truths (x positions; y = 0):
    #   A at x=0 during t=0..5; B at x=500 during t=2..5; C at x=-300 during t=1..5.
    # Tracks:
    #   1 on A at t=0,1; none on A at t=2,3; 3 on A at t=4,5           -> A: 1,1,-,-,3,3
    #   2 at x=1000 (no truth near) at t=0..3                         -> never assigned
    #   4 on C at t=3..5                                               -> C: -,-,4,4,4 (from t=3)
    #   5 on C at t=5 too, but 4 is nearer: 5 is unassigned at its only time
    # A: change 1 -> 3 at t=4 while track 1 is no longer reported: one break, no switch.
    # False tracks: 2 (0 of 4 times) and 5 (0 of 1) -> 2; tracks 1, 3, 4 assigned at all times.
    # Missed targets: B (0 of 4 times) -> 1; A is assigned 4/6 >= 1/2, C 3/5 >= 1/2.
    # Time to confirm: A 0 - 0 = 0; B never: NaN; C 3 - 1 = 2 s.
    truth, est = [], []
    for t in range(6):
        ids, xy = ["A"], [[0.0, 0.0]]
        if t >= 2:
            ids, xy = ids + ["B"], xy + [[500.0, 0.0]]
        if t >= 1:
            ids, xy = ids + ["C"], xy + [[-300.0, 0.0]]
        truth.append((ids, xy))
        eids, exy = [], []
        if t <= 1:
            eids, exy = eids + [1], exy + [[2.0, 0.0]]
        if t >= 4:
            eids, exy = eids + [3], exy + [[-2.0, 1.0]]
        if t <= 3:
            eids, exy = eids + [2], exy + [[1000.0, 0.0]]
        if t >= 3:
            eids, exy = eids + [4], exy + [[-301.0, 0.0]]
        if t == 5:
            eids, exy = eids + [5], exy + [[-305.0, 0.0]]
        est.append((eids, exy))
    m = te.track_metrics(np.arange(6.0), truth, est, c=C)
    assert (m.breaks, m.switches, m.false_tracks, m.missed_targets) == (1, 0, 2, 1)
    assert m.truth_ids == ["A", "C", "B"]  # order of first appearance
    np.testing.assert_array_equal(m.time_to_confirm, [0.0, 2.0, np.nan])
    np.testing.assert_allclose(m.coverage, [4 / 6, 3 / 5, 0.0], rtol=1e-15)
    assert m.track_ids == [1, 2, 4, 3, 5]
    np.testing.assert_array_equal(m.track_coverage, [1.0, 0.0, 1.0, 1.0, 0.0])
    # a stricter min_fraction: A (4/6) and C (3/5) now count as missed too
    assert te.track_metrics(np.arange(6.0), truth, est, c=C, min_fraction=0.7).missed_targets == 3


def test_the_same_track_after_a_gap_is_neither_break_nor_switch():
    # truth A at 0..3; track 1 on it at t=0 and t=3, unassigned (far off, x=50) at t=1, absent at t=2
    truth = [(["A"], [[0.0, 0.0]])] * 4
    est = [([1], [[0.0, 0.0]]), ([1], [[50.0, 0.0]]), ([], []), ([1], [[0.0, 0.0]])]
    m = te.track_metrics(np.arange(4.0), truth, est, c=C)
    assert (m.breaks, m.switches) == (0, 0)
    # track 1 is assigned at 2 of its 3 reported times: not false
    assert m.false_tracks == 0 and m.track_coverage.tolist() == [2 / 3]


def test_bad_input():
    truth = [(["A"], [[0.0, 0.0]])] * 2
    est = [([1], [[0.0, 0.0]])] * 2
    with pytest.raises(ValueError, match="strictly increasing"):
        te.track_metrics([1.0, 1.0], truth, est, c=C)
    with pytest.raises(ValueError, match=r"one \(ids, xy\) pair per time \(2 from times\), got 1 and 2"):
        te.gospa_over_time([0.0, 1.0], truth[:1], est, c=C)
    with pytest.raises(ValueError, match=r"truth\[0\] must be a pair"):
        te.gospa_over_time([0.0], [np.zeros((1, 2))], est[:1], c=C)
    with pytest.raises(ValueError, match="ids must be distinct"):
        te.track_metrics([0.0], truth[:1], [([1, 1], [[0.0, 0.0], [1.0, 0.0]])], c=C)
    with pytest.raises(ValueError, match="ids and xy must have the same length"):
        te.track_metrics([0.0], [(["A", "B"], [[0.0, 0.0]])], est[:1], c=C)
    with pytest.raises(ValueError, match="c .cut-off distance."):
        te.gospa_over_time([0.0], truth[:1], est[:1], c=-1.0)
    with pytest.raises(ValueError, match="min_fraction"):
        te.track_metrics([0.0], truth[:1], est[:1], c=C, min_fraction=0.0)
    with pytest.raises(ValueError, match=r"times must have shape \(K,\)"):
        te.track_metrics([[0.0]], truth[:1], est[:1], c=C)
