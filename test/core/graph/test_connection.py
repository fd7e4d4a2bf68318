"""Connection of distribution maxima (Sec. V): assignment, leftovers, closing rules, bridging.

The synthetic roads run east (heading 0), so a maximum's lateral position is its world y.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from hdmap_core.errors import HdmapError
from hdmap_core.graph.connection import connect_segment as _connect_segment
from hdmap_core.graph.connection_config import ConnectionConfig
from hdmap_core.graph.segment_graph import feature_chains, stable_uid
from hdmap_core.model import FeatureType
from hdmap_core.steps import Segment, StepResult

from former_configs import former, former_paper, former_replace


def connect_segment(segment, *, config: ConnectionConfig | None = None, **kw):
    """``connection.connect_segment`` with the connection's first implementation (``former``)
    unless a config is given: the rules these tests were drawn for."""
    return _connect_segment(segment, config=former(ConnectionConfig) if config is None else config, **kw)


B, S, D = int(FeatureType.ROAD_BORDER), int(FeatureType.SOLID), int(FeatureType.DASHED)


def make_step(
    index: int,
    lateral: list[float],
    types: list[int],
    *,
    pivot: str = "p",
    step_m: float = 2.0,
    x0: float = 0.0,
    y0: float = 0.0,
    counts: list[int] | None = None,
    std: list[float] | None = None,
    valid: bool = True,
    processed_before: bool = False,
    heading: float = 0.0,
    midpoint: np.ndarray | None = None,
    width_m: float = 12.0,
) -> StepResult:
    """A step of a pivot driving straight along ``heading`` from (x0, y0), or at ``midpoint``."""
    k = len(lateral)
    s = index * step_m
    mid = np.array([x0 + s * math.cos(heading), y0 + s * math.sin(heading)]) if midpoint is None else midpoint
    return StepResult(
        pivot_id=pivot,
        index=index,
        s_m=s,
        midpoint=mid,
        heading=heading,
        width_m=width_m,
        valid=valid,
        processed_before=processed_before,
        lateral_m=np.asarray(lateral, dtype=float),
        types=np.asarray(types, dtype=np.int64),
        counts=np.asarray(counts if counts is not None else [5] * k, dtype=np.int64),
        std_m=np.asarray(std if std is not None else [0.1] * k, dtype=float),
        drive_ids=("a", "b"),
    )


def straight(n: int, lateral: list[float], types: list[int], **kw) -> list[StepResult]:
    return [make_step(i, lateral, types, **kw) for i in range(n)]


def chains_xy(g):
    return [g.node_xy[c] for c in g.polylines()]


def succ_count(g, chain_of_node, chain):
    """Number of distinct polylines following the last node of ``chain``."""
    last = chain[-1]
    return len({chain_of_node[v] for u, v in g.edges if u == last and chain_of_node[v] != chain_of_node[last]})


def pred_count(g, chain_of_node, chain):
    first = chain[0]
    return len({chain_of_node[u] for u, v in g.edges if v == first and chain_of_node[u] != chain_of_node[first]})


def chain_index(g):
    out = np.full(g.n_nodes, -1)
    for k, c in enumerate(g.polylines()):
        out[c] = k
    return out


@pytest.fixture
def three_lines():
    """y= 3.5  B ------------------------
         y= 0.0  D - - - - - - - - - - - -
         y=-3.5  B ------------------------   (20 steps, 2 m apart)
    with per-step counts/std varying along x."""
    steps = [
        make_step(i, [-3.5, 0.0, 3.5], [B, D, B], counts=[i + 1, 10, 3], std=[0.2, 0.05 + 0.01 * i, 0.3])
        for i in range(20)
    ]
    return Segment("p", tuple(steps))


def test_straight_road_gives_one_polyline_per_line(three_lines):
    g = connect_segment(three_lines)
    chains = g.polylines()
    assert len(chains) == 3
    assert sorted(len(c) for c in chains) == [20, 20, 20]
    for c in chains:
        xy = g.node_xy[c]
        assert np.all(np.diff(xy[:, 0]) > 0)  # ordered in driving direction
        np.testing.assert_allclose(np.diff(xy[:, 0]), 2.0, atol=1e-9)
        assert np.ptp(xy[:, 1]) < 1e-9
    dashed = next(c for c in chains if g.node_type[c[0]] == D)
    np.testing.assert_allclose(g.node_std[dashed], 0.05 + 0.01 * np.arange(20), atol=1e-12)
    right = next(c for c in chains if g.node_xy[c[0], 1] < 0)
    np.testing.assert_array_equal(g.node_count[right], np.arange(1, 21))
    assert g.stats.used == 20 and len(g.edges) == 57
    assert g.n_topo == 20 and len(g.topo_edges) == 19
    np.testing.assert_array_equal(g.node_topo[:6], [0, 0, 0, 1, 1, 1])  # cross references


def test_unsorted_lateral_and_curved_road():
    """Maxima listed in any order along a 90-degree curve still pair by position."""
    r = 100.0
    steps = []
    for i in range(40):
        th = i * 2.0 / r
        mid = np.array([r * math.sin(th), r - r * math.cos(th)])
        lat = [3.5, -3.5, 0.0] if i % 2 else [0.0, 3.5, -3.5]
        typ = [B, B, D] if i % 2 else [D, B, B]
        st = make_step(i, lat, typ, heading=th)
        steps.append(StepResult(**{**st.__dict__, "midpoint": mid}))
    g = connect_segment(Segment("p", tuple(steps)))
    chains = g.polylines()
    assert len(chains) == 3
    for c in chains:
        radius = np.linalg.norm(g.node_xy[c] - [0.0, r], axis=1)
        assert np.ptp(radius) < 1e-6  # every chain stays on one concentric line


def _split_segment():
    r"""Two lines become three at a gore (the right line splits), 2 m steps:

    y=3.5   B ----------------------------------------
    y=0     S ----------------------------------------
    y=-3.5  D --------------------*  gore at step 10
                                   \----- D (y: -3.5 - 0.6*k)
    """
    steps = []
    for i in range(25):
        if i <= 10:
            steps.append(make_step(i, [3.5, 0.0, -3.5], [B, S, D]))
        else:
            k = i - 10
            steps.append(make_step(i, [3.5, 0.0, -3.5 + 0.1, -3.5 - 0.6 * k], [B, S, D, D]))
    return Segment("p", tuple(steps))


def test_split_gives_feature_with_two_successors():
    g = connect_segment(_split_segment(), config=former(ConnectionConfig))
    ci = chain_index(g)
    chains = g.polylines()
    splitting = [c for c in chains if succ_count(g, ci, c) == 2]
    assert len(splitting) == 1
    assert g.node_type[splitting[0][0]] == D
    # at step 11 the branches are 0.7 m apart (< min_separation_m: one line seen twice), from
    # step 12 on (1.3 m) they are two lines: the split is at step 11
    np.testing.assert_allclose(g.node_xy[splitting[0][-1]], [22.0, -3.4])
    assert g.stats.splits == 1 and g.stats.merges == 0 and g.stats.suppressed == 1
    gp = connect_segment(_split_segment(), config=former(ConnectionConfig, min_separation_m=0.0))
    split_p = [c for c in gp.polylines() if succ_count(gp, chain_index(gp), c) == 2]
    np.testing.assert_allclose(gp.node_xy[split_p[0][-1]], [20.0, -3.5])
    assert len(chains) == 5  # B, S, dashed before the gore, its two branches


def test_merge_gives_feature_with_two_predecessors():
    """The split road driven backwards: two dashed lines converge into one."""
    steps = []
    for i in range(25):
        if i < 14:
            k = 14 - i
            steps.append(make_step(i, [3.5, 0.0, -3.5 + 0.1, -3.5 - 0.6 * k], [B, S, D, D]))
        else:
            steps.append(make_step(i, [3.5, 0.0, -3.5], [B, S, D]))
    g = connect_segment(Segment("p", tuple(steps)))
    ci = chain_index(g)
    merging = [c for c in g.polylines() if pred_count(g, ci, c) == 2]
    assert len(merging) == 1
    assert g.node_type[merging[0][0]] == D
    assert g.stats.merges == 1 and g.stats.splits == 0


def test_road_border_never_connects_to_marking():
    """A border that vanishes beside a marking 0.5 m away is not joined to it (nor leftover-joined)."""
    steps = [make_step(i, [0.0, -4.0, -4.5], [D, S, B]) for i in range(8)]
    steps += [make_step(i, [0.0, -4.0], [D, S]) for i in range(8, 12)]
    steps += [make_step(i, [0.0, -4.0, -4.5], [D, S, B]) for i in range(12, 16)]
    for cfg in (former(ConnectionConfig), former_paper(ConnectionConfig)):
        g = connect_segment(Segment("p", tuple(steps)), config=cfg)
        t = g.node_type
        assert not np.any((t[g.edges[:, 0]] == B) != (t[g.edges[:, 1]] == B))
    # the border is missing for 4 steps (8 m < max_gap_m): bridged into one polyline
    g = connect_segment(Segment("p", tuple(steps)))
    borders = [c for c in g.polylines() if g.node_type[c[0]] == B]
    assert len(borders) == 1 and len(borders[0]) == 12


def test_type_change_closes_polyline_rule1():
    """dashed for 10 steps, then solid: two polylines, linked end to start."""
    steps = [make_step(i, [0.0], [D if i < 10 else S]) for i in range(20)]
    g = connect_segment(Segment("p", tuple(steps)))
    chains = g.polylines()
    assert len(chains) == 2
    types = {int(g.node_type[c[0]]): len(c) for c in chains}
    assert types == {D: 10, S: 10}
    assert len(g.edges) == 19  # still connected: the dashed line's successor is the solid line


@pytest.mark.parametrize("n_invalid, pieces", [(3, 1), (15, 2)])
def test_gap_bridged_when_short_and_closes_when_long_rule3(n_invalid, pieces):
    """Steps 10.. 10+n_invalid-1 failed (EM rejected): 8 m gap bridged, 32 m gap (> 20 m) closed."""
    steps = []
    for i in range(40):
        bad = 10 <= i < 10 + n_invalid
        steps.append(make_step(i, [] if bad else [-1.75, 1.75], [] if bad else [S, D], valid=not bad))
    g = connect_segment(Segment("p", tuple(steps)))
    assert len(g.polylines()) == 2 * pieces
    assert len(g.components()) == pieces
    if pieces == 1:
        assert g.stats.gaps_bridged == 1 and g.stats.gaps_closed == 0
    else:
        assert g.stats.gaps_closed == 1


def test_processed_before_closes_polylines_rule4():
    steps = [make_step(i, [-1.75, 1.75], [S, D], processed_before=10 <= i < 12) for i in range(30)]
    g = connect_segment(Segment("p", tuple(steps)))
    assert g.stats.processed_before == 2
    assert len(g.polylines()) == 4
    assert len(g.components()) == 2
    assert g.n_topo == 28


def test_implausible_angle_step_rejected():
    """One step's maxima all jump 3 m sideways (a failed optimisation): rejected and bridged."""
    steps = [
        make_step(i, [-1.75 + (3.0 if i == 7 else 0.0), 1.75 + (3.0 if i == 7 else 0.0)], [S, D]) for i in range(15)
    ]
    g = connect_segment(Segment("p", tuple(steps)))
    assert g.stats.rejected_angle == 1
    assert 7 not in g.topo_step.tolist()
    chains = g.polylines()
    assert len(chains) == 2 and all(len(c) == 14 for c in chains)
    assert np.all(np.abs(np.abs(g.node_xy[:, 1]) - 1.75) < 1e-9)


def test_leftover_far_away_does_not_make_false_merge():
    """A marking missing for a few steps 3.5 m from its neighbour: no merge by default, a merge in
    the paper's variant (every leftover joins its nearest neighbour)."""
    steps = [
        make_step(i, [-3.5, 0.0, 3.5] if not 5 <= i < 8 else [-3.5, 3.5], [B, D, B] if not 5 <= i < 8 else [B, B])
        for i in range(15)
    ]
    g = connect_segment(Segment("p", tuple(steps)))
    assert g.stats.merges == 0 and len(g.polylines()) == 3
    gp = connect_segment(Segment("p", tuple(steps)), config=former_paper(ConnectionConfig))
    assert len(gp.polylines()) > 3  # the paper's variant fragments here


def test_ids_stable_and_distinct():
    seg = _split_segment()
    g1, g2 = connect_segment(seg), connect_segment(seg)
    np.testing.assert_array_equal(g1.node_uid, g2.node_uid)
    np.testing.assert_array_equal(g1.topo_uid, g2.topo_uid)
    assert len(set(g1.node_uid.tolist())) == g1.n_nodes
    assert int(g1.node_uid.max()) < 2**63 and int(g1.node_uid.min()) > 0
    other = connect_segment(Segment("q", tuple(make_step(i, [0.0], [S], pivot="q") for i in range(3))))
    assert not set(other.node_uid.tolist()) & set(g1.node_uid.tolist())
    # the same pivot/step/slot always gives the same id, whatever else is in the segment
    np.testing.assert_array_equal(stable_uid("feature:p", [3], [1]), g1.node_uid[3 * 3 + 1 : 3 * 3 + 2])


def test_input_not_mutated_and_bad_input_rejected(three_lines):
    before = [st.lateral_m.copy() for st in three_lines.steps]
    connect_segment(three_lines)
    for a, st in zip(before, three_lines.steps):
        np.testing.assert_array_equal(a, st.lateral_m)
    # a malformed step is skipped and reported, the rest goes on
    bad = make_step(5, [0.0, 1.0], [S])
    nan_mid = StepResult(**{**make_step(6, [0.0], [S]).__dict__, "midpoint": np.array([np.nan, 0.0])})
    ok = [make_step(i, [0.0], [S]) for i in range(12) if i not in (5, 6)]
    g = connect_segment(Segment("p", tuple(ok + [bad, nan_mid])))
    assert g.stats.malformed == 2 and any("types" in p for p in g.stats.problems)
    assert g.stats.used == 10 and len(g.polylines()) == 1  # bridged over the two skipped steps
    nan_lat = make_step(3, [0.0, np.nan], [S, D])
    g = connect_segment(Segment("p", tuple([make_step(i, [0.0], [S]) for i in range(3)] + [nan_lat])))
    assert g.n_nodes == 4 and np.isfinite(g.node_xy).all()
    with pytest.raises(HdmapError, match="pivot"):
        connect_segment(Segment("q", (make_step(0, [0.0], [S]),)))


def test_empty_segment():
    g = connect_segment(Segment("p", ()))
    assert g.n_nodes == 0 and g.polylines() == [] and g.components() == []


def test_feature_chains_opens_a_ring_deterministically():
    edges = np.array([[0, 1], [1, 2], [2, 0]])
    uid = np.array([30, 10, 20], dtype=np.uint64)
    chains = feature_chains(3, edges, np.zeros(3, bool), np.zeros(3, int), uid)
    assert len(chains) == 1 and chains[0].tolist() == [1, 2, 0]


def test_feature_leaving_while_another_enters_keeps_the_step():
    """The left border leaves the cut while a new line enters on the right in the same step: the
    step is kept (median angle) and the two lines that persist stay single polylines."""
    steps = [make_step(i, [-3.5, 0.0, 3.5], [S, D, S]) for i in range(6)]
    steps += [make_step(i, [-7.0, -3.5, 0.0], [S, S, D]) for i in range(6, 12)]
    g = connect_segment(Segment("p", tuple(steps)))
    assert g.stats.rejected_angle == 0
    lengths = sorted(len(c) for c in g.polylines())
    assert lengths == [6, 6, 12, 12]


def test_close_duplicate_markings_suppressed():
    """A misclassified copy of the dashed line 0.2 m beside it (fewer drives) is dropped; a border
    0.5 m from a marking is kept (borders and markings are never merged); the paper's variant keeps all."""
    steps = [
        make_step(i, [0.0, 0.2, -3.5, -4.0], [D, S, S, B], counts=[6, 2, 5, 4])
        if 3 <= i < 6
        else make_step(i, [0.0, -3.5, -4.0], [D, S, B], counts=[6, 5, 4])
        for i in range(10)
    ]
    g = connect_segment(Segment("p", tuple(steps)))
    assert g.stats.suppressed == 3 and g.stats.splits == 0 and g.stats.merges == 0
    assert sorted(len(c) for c in g.polylines()) == [10, 10, 10]
    # slots stay those of the step's own arrays (stable ids): at step 3 the kept ones are 0, 2, 3
    at3 = g.features_of(3)
    assert set(g.node_uid[at3].tolist()) == set(stable_uid("feature:p", 3, np.array([0, 2, 3])).tolist())
    gp = connect_segment(Segment("p", tuple(steps)), config=former_paper(ConnectionConfig))
    assert gp.stats.suppressed == 0 and len(gp.polylines()) > 3


def test_fast_path_equals_assignment(monkeypatch):
    """The vectorised identity pairing of unchanged steps gives exactly the assignment's graph."""
    import hdmap_core.graph.connection as conn_mod

    rng = np.random.default_rng(3)
    steps = []
    for i in range(200):
        lat = [-3.5, 0.0, 3.5] + ([-7.0] if 50 <= i < 120 else [])
        typ = [B, D, B] + ([S] if 50 <= i < 120 else [])
        valid = not (140 <= i < 143)
        steps.append(make_step(i, list(np.asarray(lat) + rng.normal(0, 0.05, len(lat))), typ, valid=valid))
    seg = Segment("p", tuple(steps))
    fast = connect_segment(seg)
    monkeypatch.setattr(conn_mod, "_fast_pairs", lambda valid, *a, **k: np.zeros(len(valid), dtype=bool))
    slow = connect_segment(seg)
    np.testing.assert_array_equal(fast.edges, slow.edges)
    np.testing.assert_array_equal(fast.edge_leftover, slow.edge_leftover)
    np.testing.assert_array_equal(fast.node_uid, slow.node_uid)
    assert fast.stats == slow.stats


def test_low_support_maxima_dropped():
    """A maximum seen by 1 of 10 drives flickering beside the dashed line is noise when
    min_support_share=0.25 (1 < 2.5): no split/merge, three clean polylines."""

    def st(i):
        s = make_step(
            i,
            [-3.5, 0.0, 1.6, 3.5] if i % 3 == 0 else [-3.5, 0.0, 3.5],
            [B, D, D, B] if i % 3 == 0 else [B, D, B],
            counts=[8, 9, 1, 7] if i % 3 == 0 else [8, 9, 7],
        )
        return StepResult(**{**s.__dict__, "drive_ids": tuple(f"d{k}" for k in range(10))})

    seg = Segment("p", tuple(st(i) for i in range(30)))
    g = connect_segment(seg, config=former(ConnectionConfig, min_support_share=0.25))
    assert sorted(len(c) for c in g.polylines()) == [30, 30, 30]
    assert g.stats.splits == 0 and g.stats.merges == 0
    g0 = connect_segment(seg, config=former(ConnectionConfig, min_support_share=0.0))
    assert len(g0.polylines()) > 3


def test_support_window_keeps_far_lines_of_a_wide_cut():
    """A wide cut (a ramp beside the carriageway): the far lines are seen by 5-6 of 30 drives,
    below a 0.25 share of the step's drives but not of the best line within 4 m (18); a
    flickering weak copy beside a line 20 drives see is still dropped."""

    def st(i):
        lat = [-12.0, -9.0, -6.5, -3.5, 0.0, 3.5]
        typ = [B, S, B, D, D, B]
        cnt = [5, 6, 18, 19, 20, 18]
        if i % 3 == 0:  # the weak copy, 1.6 m beside the dashed line at 0
            lat, typ, cnt = lat + [1.6], typ + [D], cnt + [2]
        s = make_step(i, lat, typ, counts=cnt)
        return StepResult(**{**s.__dict__, "drive_ids": tuple(f"d{k}" for k in range(30))})

    seg = Segment("p", tuple(st(i) for i in range(30)))
    g_all = connect_segment(seg, config=former(ConnectionConfig, min_support_share=0.25))
    g_win = connect_segment(seg, config=former(ConnectionConfig, min_support_share=0.25, support_window_m=4.0))
    lat_all = sorted(round(float(np.median(g_all.node_xy[c][:, 1])), 1) for c in g_all.polylines())
    lat_win = sorted(round(float(np.median(g_win.node_xy[c][:, 1])), 1) for c in g_win.polylines())
    assert lat_all == [-6.5, -3.5, 0.0, 3.5]  # the far border and line are lost
    assert lat_win == [-12.0, -9.0, -6.5, -3.5, 0.0, 3.5]  # kept, and no weak copy
    assert all(len(c) == 30 for c in g_win.polylines())
    assert g_win.stats.splits == 0 and g_win.stats.merges == 0


def test_lone_line_of_one_drive_kept_copies_and_lane_noise_dropped():
    """One drive in the lane next to the right border sees the edge line at -3.5 that the
    others (8 of 30, in the other lanes) do not: 1 < 0.25 x 8 within 4 m, so the support rules
    drop it. It lies 3.5 m from the border and from the next line: with lone_line_gap_m 3 it is
    kept. One drive's copy 1.2 m beside the dashed line at 3.5 and one drive's false positive
    in the middle of a lane (1.75 m from the lines) are still dropped."""

    def st(i):
        lat = [-7.0, -3.5, 0.0, 1.75 + 3.5, 3.5, 4.7, 7.0]
        typ = [B, S, D, S, D, D, B]
        cnt = [8, 1, 8, 1, 8, 1, 8]
        s = make_step(i, lat, typ, counts=cnt)
        return StepResult(**{**s.__dict__, "drive_ids": tuple(f"d{k}" for k in range(30))})

    seg = Segment("p", tuple(st(i) for i in range(30)))
    base = former(ConnectionConfig, min_support_share=0.25, support_window_m=4.0)

    def lines(cfg):
        g = connect_segment(seg, config=cfg)
        return sorted(round(float(np.median(g.node_xy[c][:, 1])), 2) for c in g.polylines())

    assert lines(base) == [-7.0, 0.0, 3.5, 7.0]
    assert lines(former_replace(base, lone_line_gap_m=3.0)) == [-7.0, -3.5, 0.0, 3.5, 7.0]
    # window_min_count still applies to the lone line
    assert lines(former_replace(base, lone_line_gap_m=3.0, window_min_count=2)) == [-7.0, 0.0, 3.5, 7.0]


def test_lone_edge_line_beside_the_border():
    """The edge line 1.0 m inside the right border (8 drives), seen by one drive, 3.5 m from the
    next line inward: with lone_line_border_gap_m 0.5 a border neighbour need only be 0.5 m
    away, so it is kept; with the lane gap alone (3 m) it is not. A one-drive marking 0.3 m
    from the border stays dropped; one 0.6 m from it is kept with 0.5 m, dropped with the
    default preset's 0.8 m (esmini_soderleden: one drive's solid along the border)."""

    def st(i, edge):
        s = make_step(i, [-7.0 + edge, -7.0, -3.5 + edge, 0.0, 3.5, 7.0], [S, B, D, D, D, B], counts=[1, 8, 8, 8, 8, 8])
        return StepResult(**{**s.__dict__, "drive_ids": tuple(f"d{k}" for k in range(30))})

    base = former(ConnectionConfig, min_support_share=0.25, support_window_m=4.0, lone_line_gap_m=3.0)

    def lines(edge, cfg):
        g = connect_segment(Segment("p", tuple(st(i, edge) for i in range(30))), config=cfg)
        return sorted(round(float(np.median(g.node_xy[c][:, 1])), 2) for c in g.polylines())

    # the marking at -7 + edge, the lane line moved with it so the inward gap stays 3.5 m
    assert lines(1.0, base) == [-7.0, -2.5, 0.0, 3.5, 7.0]
    near = former_replace(base, lone_line_border_gap_m=0.5)
    assert lines(1.0, near) == [-7.0, -6.0, -2.5, 0.0, 3.5, 7.0]
    assert lines(0.3, near) == [-7.0, -3.2, 0.0, 3.5, 7.0]
    assert lines(0.6, near) == [-7.0, -6.4, -2.9, 0.0, 3.5, 7.0]
    from hdmap_core.pipeline import presets  # noqa: PLC0415

    preset = presets.preset("default").connection.lone_line_border_gap_m
    assert preset == 0.8
    tight = former_replace(base, lone_line_border_gap_m=preset)
    assert lines(0.6, tight) == [-7.0, -2.9, 0.0, 3.5, 7.0]
    assert lines(1.0, tight) == [-7.0, -6.0, -2.5, 0.0, 3.5, 7.0]


def test_lone_edge_line_needs_its_border_on_the_outer_side():
    """esmini_soderleden_100_s4: 97 drives; the lane line at 0 (84 drives) has a two-drive copy
    typed as border at -0.1, and one drive reports a dashed line at -2.35, 1.15 m inside the
    right border. Taking the copy as a border neighbour (2.25 m >= 0.8) made that line a lone
    edge line; with lone_line_border_outer the border counts only outward (below -2.35 here), and
    the copy inward is an ordinary neighbour, 2.25 m < 3 m: the false line is dropped. The true
    edge line of test_lone_edge_line_beside_the_border, its border outward, is kept either way."""

    def st(i, lat, typ, cnt, n=97):
        s = make_step(i, lat, typ, counts=cnt)
        return StepResult(**{**s.__dict__, "drive_ids": tuple(f"d{k}" for k in range(n))})

    def lines(steps, cfg):
        g = connect_segment(Segment("p", tuple(steps)), config=cfg)
        return sorted(round(float(np.median(g.node_xy[c][:, 1])), 2) for c in g.polylines())

    loose = former(
        ConnectionConfig, min_support_share=0.25, support_window_m=4.0, lone_line_gap_m=3.0, lone_line_border_gap_m=0.8
    )
    outer = former_replace(loose, lone_line_border_outer=True)
    copy = [st(i, [-3.5, -2.35, -0.1, 0.0, 3.5], [B, D, B, D, B], [68, 1, 2, 84, 57]) for i in range(30)]
    assert lines(copy, loose) == [-3.5, -2.35, 0.0, 3.5]
    assert lines(copy, outer) == [-3.5, 0.0, 3.5]
    # mirrored (the false line left of the midpoint, its border above it): the same
    mirror = [st(i, [-3.5, 0.0, 0.1, 2.35, 3.5], [B, D, B, D, B], [57, 84, 2, 1, 68]) for i in range(30)]
    assert lines(mirror, loose) == [-3.5, 0.0, 2.35, 3.5]
    assert lines(mirror, outer) == [-3.5, 0.0, 3.5]
    edge = [st(i, [-6.0, -7.0, -2.5, 0.0, 3.5, 7.0], [S, B, D, D, D, B], [1, 8, 8, 8, 8, 8], n=30) for i in range(30)]
    assert lines(edge, outer) == [-7.0, -6.0, -2.5, 0.0, 3.5, 7.0]
    from hdmap_core.pipeline import presets  # noqa: PLC0415

    assert presets.preset("default").connection.lone_line_border_outer
    assert not presets.preset("paper").connection.lone_line_gap_m  # the rule it belongs to is off


def test_topology_node_holds_the_pivots_lane():
    """carla_town04_30_s3's T-junction: a step sees only the border on its right, its 4.5 m cut
    (midpoint y 1.65, from -0.6 to 3.9) lies beside the pivot at y -1.15. With
    topo_pivot_lane_m=1.75 the topology node's cross-section reaches 1.75 m beyond the pivot
    (-2.9 .. 3.9: midpoint 0.5, width 6.8); the features stay where they are. A step whose pivot
    is on its cut (at the midpoint, or 0.25 m inside its end), or that has no pose, keeps its cut."""

    def st(i, pose_y):
        s = make_step(i, [1.85], [B], midpoint=np.array([2.0 * i, 1.65]), width_m=4.5)
        return StepResult(**{**s.__dict__, "pose": None if pose_y is None else np.array([2.0 * i, pose_y])})

    seg = Segment("p", (st(0, 1.65), st(1, -1.15), st(2, None), st(3, -0.35)))
    plain = connect_segment(seg, config=former(ConnectionConfig))
    lane = connect_segment(seg, config=former(ConnectionConfig, topo_pivot_lane_m=1.75))
    np.testing.assert_allclose(plain.topo_xy[:, 1], [1.65] * 4)
    np.testing.assert_allclose(plain.topo_width, [4.5] * 4)
    np.testing.assert_allclose(lane.topo_xy[:, 1], [1.65, 0.5, 1.65, 1.65])
    np.testing.assert_allclose(lane.topo_width, [4.5, 6.8, 4.5, 4.5])
    np.testing.assert_allclose(lane.node_xy, plain.node_xy)
    from hdmap_core.pipeline import presets  # noqa: PLC0415

    assert presets.preset("default").connection.topo_pivot_lane_m == 0.5
    assert presets.preset("paper").connection.topo_pivot_lane_m == 0.0


def test_window_min_count_drops_one_drive_maxima_of_the_window_rule():
    """A far line seen by one drive beside a border seen by three (of 30): the window rule alone
    keeps it (1 >= 0.25 x 3); with window_min_count=2 only maxima of two or more drives are
    rescued, the border stays."""

    def st(i):
        s = make_step(i, [-12.0, -9.5, -3.5, 0.0, 3.5], [B, S, D, D, B], counts=[3, 1, 19, 20, 18])
        return StepResult(**{**s.__dict__, "drive_ids": tuple(f"d{k}" for k in range(30))})

    seg = Segment("p", tuple(st(i) for i in range(30)))
    cfg = former(ConnectionConfig, min_support_share=0.25, support_window_m=4.0)
    lat1 = sorted(
        round(float(np.median(g.node_xy[c][:, 1])), 1)
        for g in [connect_segment(seg, config=cfg)]
        for c in g.polylines()
    )
    g2 = connect_segment(
        seg, config=former(ConnectionConfig, min_support_share=0.25, support_window_m=4.0, window_min_count=2)
    )
    lat2 = sorted(round(float(np.median(g2.node_xy[c][:, 1])), 1) for c in g2.polylines())
    assert lat1 == [-12.0, -9.5, -3.5, 0.0, 3.5]
    assert lat2 == [-12.0, -3.5, 0.0, 3.5]


# --- branches of the other marking type (leftover_other_type_m) ----------------------------------


def _exit_segment(gap: float) -> Segment:
    """A solid edge line at y=0 bending right by 3 cm/m from x=20; an exit's dashed line appears at
    x=30 (when the two are resolved) ``gap`` m left of the solid line and runs straight on (the
    solid line's first value there)."""
    steps = []
    for i in range(40):
        x = 2.0 * i
        y_solid = -0.03 * max(x - 20.0, 0.0)
        if x < 30:
            steps.append(make_step(i, [y_solid], [S]))
        else:
            steps.append(make_step(i, [y_solid, -0.3 + gap], [S, D]))
    return Segment("p", tuple(steps))


def test_dashed_branch_starting_beside_a_solid_line_is_a_split():
    """The dashed line's first node (0.3 m beside the solid line) is the solid tip's leftover
    partner: a split edge across marking types. Farther than leftover_other_type_m (or with it 0)
    the dashed line starts unconnected, as a line of the other type ending beside one does."""
    g = connect_segment(_exit_segment(0.0), config=former(ConnectionConfig, min_separation_m=0.0))
    assert g.stats.splits == 1
    (k,) = np.flatnonzero(g.edge_leftover)
    u, v = g.edges[k]
    assert g.node_type[u] == S and g.node_type[v] == D
    assert g.node_xy[v, 0] == pytest.approx(30.0) and g.node_xy[u, 0] == pytest.approx(28.0)
    off = connect_segment(
        _exit_segment(0.0), config=former(ConnectionConfig, min_separation_m=0.0, leftover_other_type_m=0.0)
    )
    assert off.stats.splits == 0 and not off.edge_leftover.any()
    far = connect_segment(_exit_segment(1.5), config=former(ConnectionConfig, min_separation_m=0.0))
    assert far.stats.splits == 0


def test_solid_line_ending_beside_a_dashed_line_is_a_merge():
    """An entry: the ramp's solid line converges on the dashed line and ends 0.5 m from it (the two
    are not resolved closer): the solid line's last node joins the dashed line (a merge)."""
    steps = []
    for i in range(30):
        x = 2.0 * i
        if x < 30:
            steps.append(make_step(i, [0.0, -2.0 + x * 0.05], [D, S]))
        else:
            steps.append(make_step(i, [0.0], [D]))
    g = connect_segment(Segment("p", tuple(steps)), config=former(ConnectionConfig, min_separation_m=0.0))
    assert g.stats.merges == 1
    (k,) = np.flatnonzero(g.edge_leftover)
    u, v = g.edges[k]
    assert g.node_type[u] == S and g.node_type[v] == D and g.node_xy[v, 0] == pytest.approx(30.0)


def test_chain_links_through_keeps_the_regular_continuation():
    """Node 1 splits into 2 (regular, same type) and 3 (leftover); node 4 merges into 2 by an
    edge of another type. Through: 0-1-2 stays one chain, 3 and 4 are branches. Without: every
    junction closes the chains."""
    from hdmap_core.graph.segment_graph import chain_links

    edges = np.array([[0, 1], [1, 2], [1, 3], [4, 2]])
    leftover = np.array([False, False, True, False])
    types = np.array([S, S, S, S, D])
    assert chain_links(5, edges, leftover, types, through=True).tolist() == [True, True, False, False]
    assert chain_links(5, edges, leftover, types).tolist() == [True, False, False, False]
    uid = np.arange(1, 6, dtype=np.uint64)
    chains = feature_chains(5, edges, leftover, types, uid, through=True)
    assert [c.tolist() for c in chains] == [[0, 1, 2], [3], [4]]


def test_chain_links_through_takes_a_lone_leftover_of_its_type():
    """An entry: the solid tip 0 merged into solid node 1 by a leftover edge while the dashed tip 2
    took node 1 by the regular assignment (dashed -> solid). The solid line continues through
    the leftover edge (its only edge of its type); two leftover edges of one type do not."""
    from hdmap_core.graph.segment_graph import chain_links

    edges = np.array([[0, 1], [2, 1], [1, 3]])
    types = np.array([S, S, D, S])
    assert chain_links(4, edges, np.array([True, False, False]), types, through=True).tolist() == [True, False, True]
    assert chain_links(4, edges, np.array([True, False, False]), types).tolist() == [False, False, True]
    both = np.array([[0, 1], [2, 1], [1, 3]])
    assert chain_links(4, both, np.array([True, True, False]), np.array([S, S, S, S]), through=True).tolist() == [
        False,
        False,
        True,
    ]


def test_bridged_tip_does_not_take_the_next_line_when_a_line_appears():
    """A solid line at y=0 is missing for 4 steps (bridged tip, 10 m back); when it is still
    missing, a new solid line appears 1.2 m beside the one at -10.5. The assignment must pair
    one tip with a node beyond the edge limits (dropped afterwards); pricing that pair by its full
    distance made the shifted pairing cheaper (bridged solid tip -> dashed line 3.4 m across,
    dashed tip -> solid line 7 m across, dropped). Now the dashed line continues, the bridged
    tip's far pair is the dropped one and the new line is a split of its neighbour."""
    steps = []
    for i in range(10):
        if i < 5:
            steps.append(make_step(i, [-10.5, -3.6, 0.0], [S, D, S]))
        elif i < 9:
            steps.append(make_step(i, [-10.5, -3.6], [S, D]))
        else:
            steps.append(make_step(i, [-11.7, -10.5, -3.4], [S, S, D]))
    g = connect_segment(Segment("p", tuple(steps)))
    last = np.flatnonzero(np.isclose(g.node_xy[:, 0], 18.0))
    into = {int(v): [int(u) for u in g.edges[g.edges[:, 1] == v, 0]] for v in last}
    dashed = [v for v in last if g.node_type[v] == D][0]
    (u,) = into[dashed]
    assert g.node_type[u] == D and g.node_xy[u, 1] == pytest.approx(-3.6)
    for v in last:  # nothing reaches step 9 from the solid line at y=0
        assert all(abs(g.node_xy[w, 1]) > 1.0 for w in into[v])


def _turning_pivot_segment() -> Segment:
    """Four straight dashed lines along x (y = 0, 3.5, 7, 10.5) and the pivot's right line at
    y = -3.5. The pivot drives at y = -1.75 for 10 steps, then turns 12 deg right onto an exit
    whose lines (+-1.75 m beside it) follow it; 4 steps at the turn failed. After the gap its
    cuts cross the straight lines obliquely."""
    lines = [0.0, 3.5, 7.0, 10.5]
    h1 = math.radians(-12.0)
    steps = []
    for i in range(25):
        if i < 10:
            mid, h, own = np.array([2.0 * i, -1.75]), 0.0, [-1.75]
        else:
            mid, h, own = (
                np.array([18.0, -1.75]) + 2.0 * (i - 9) * np.array([math.cos(h1), math.sin(h1)]),
                h1,
                [-1.75, 1.75],
            )
        valid = not 10 <= i < 14
        lat = sorted([(c - mid[1]) / math.cos(h) for c in lines] + own) if valid else []
        steps.append(make_step(i, lat, [D] * len(lat), midpoint=mid, heading=h, width_m=30.0, valid=valid))
    return Segment("p", tuple(steps))


def _straight_line_jumps(g) -> list[float]:
    """Across the gap: how far across each edge leaving a straight line (y >= 0) moves."""
    a, b = g.node_xy[g.edges[:, 0]], g.node_xy[g.edges[:, 1]]
    sel = (a[:, 0] < 19.0) & (b[:, 0] > 19.0) & (a[:, 1] > -0.5)
    return np.abs(b[sel, 1] - a[sel, 1]).tolist()


def test_lines_keep_their_place_when_the_pivot_turns_off():
    """Where the pivot leaves the lines (an exit ramp), its heading is no frame for them: across
    its rotated cut the pairing shifted by one lane looked straighter, so every line joined the
    next one 3.5 m over (Town04's cloverleaf). Each tip is now paired in its own line's
    direction: each straight line continues on itself."""
    jumps = _straight_line_jumps(connect_segment(_turning_pivot_segment()))
    assert len(jumps) == 4 and max(jumps) < 0.05


def test_tip_frame_off_keeps_the_pivot_frame():
    assert former_paper(ConnectionConfig).tip_frame_deg == 0.0
    jumps = _straight_line_jumps(
        connect_segment(_turning_pivot_segment(), config=former(ConnectionConfig, tip_frame_deg=0.0))
    )
    assert max(jumps) > 3.0  # the shifted pairing of the pivot's frame


def test_bridged_gap_does_not_join_a_line_to_its_neighbour_steeply():
    """An inner (gore) border at y = 0 ends in a 10 m gap of failed steps; after it only the
    outer border at y = -6 goes on (an entry ramp's gore closing). Across the gap the border tip
    could pair with it at 27 deg (within max_edge_angle_deg): the outer border's piece then
    continued the inner one and the outer border's own upstream piece stayed apart. A bridged
    edge steeper than bridge_edge_angle_deg is not made: the outer border starts anew."""
    steps = []
    for i in range(25):
        bad = 10 <= i < 15
        lat, typ = ([0.0, 3.5], [B, D]) if i < 10 else ([-6.0, 3.5], [B, D])
        steps.append(make_step(i, [] if bad else lat, [] if bad else typ, valid=not bad))
    g = connect_segment(Segment("p", tuple(steps)))
    dy = np.abs(g.node_xy[g.edges[:, 1], 1] - g.node_xy[g.edges[:, 0], 1])
    assert dy.max() < 0.05
    assert len(g.polylines()) == 3  # the dashed line bridged, two border pieces
    g0 = connect_segment(Segment("p", tuple(steps)), config=former(ConnectionConfig, bridge_edge_angle_deg=90.0))
    assert np.abs(g0.node_xy[g0.edges[:, 1], 1] - g0.node_xy[g0.edges[:, 0], 1]).max() > 5.0


def _crossing_pivot_segment(angle_deg: float, *, turn_at: int | None = None, n: int = 30) -> Segment:
    """Straight dashed lines along x at y = 0, 3.5, 7, 10.5 and a pivot crossing them at
    ``angle_deg`` (2 m steps; its cut sees what lies within 12 m). Without ``turn_at`` the
    pivot comes in from y = -14 (an entry ramp, its own solid lines +-1.75 m beside it up to
    y = -4); with it the pivot drives along x at y = -1.75 and turns off at step ``turn_at``
    (an exit). Steps whose cut sees nothing are invalid."""
    lines = [0.0, 3.5, 7.0, 10.5]
    h = math.radians(angle_deg)
    u = np.array([math.cos(h), math.sin(h)])
    steps = []
    for i in range(n):
        if turn_at is None:
            mid, hd = np.array([0.0, -14.0]) + 2.0 * i * u, h
        elif i < turn_at:
            mid, hd = np.array([2.0 * i, -1.75]), 0.0
        else:
            mid, hd = np.array([2.0 * (turn_at - 1), -1.75]) + 2.0 * (i - turn_at + 1) * u, h
        lat = [(c - mid[1]) / math.cos(hd) for c in lines]
        lat = [v for v in lat if abs(v) <= 12.0]
        typ = [D] * len(lat)
        if turn_at is None and mid[1] + 1.75 < -4.0:
            lat, typ = lat + [-1.75, 1.75], typ + [S, S]
        order = np.argsort(lat)
        steps.append(
            make_step(
                i,
                np.asarray(lat, dtype=float)[order],
                np.asarray(typ, dtype=np.int64)[order],
                midpoint=mid,
                heading=hd,
                width_m=24.0,
                valid=bool(lat),
            )
        )
    return Segment("p", tuple(steps))


def _line_hops(g) -> list[float]:
    """How far across (in y) each edge between two nodes of the straight lines moves."""
    a, b = g.node_xy[g.edges[:, 0]], g.node_xy[g.edges[:, 1]]
    sel = (a[:, 1] > -0.5) & (b[:, 1] > -0.5) & (g.node_type[g.edges[:, 0]] == D)
    return np.abs(b[sel, 1] - a[sel, 1]).tolist()


def test_lines_crossed_by_an_entering_pivot_do_not_hop():
    """A pivot entering at 20 deg: in its frame a line's true continuation moves 0.73 m across
    per 2 m step (20 deg: the step is rejected by the angle check), and over a bridged 6 m
    the next lane's line lay 1.5 m across (14 deg): every line joined the next one (Town04,
    3.2 m over 6 m). Lines with a direction of their own that leaves the pivot's heading by more
    than line_frame_deg are paired in it: each line continues on itself, across every step."""
    seg = _crossing_pivot_segment(20.0)
    cfg = former(ConnectionConfig, line_frame_deg=12.0)
    g = connect_segment(seg, config=cfg)
    hops = _line_hops(g)
    assert len(hops) > 20 and max(hops) < 0.05
    assert g.stats.rejected_angle == 0
    # each straight line is one polyline of several steps (not pieces joined one lane over)
    ys = [np.unique(np.round(g.node_xy[c, 1], 1)) for c in g.polylines() if len(c) > 3 and g.node_type[c[0]] == D]
    assert len(ys) == 4 and all(len(y) == 1 for y in ys)
    g0 = connect_segment(seg, config=former(ConnectionConfig, line_frame_deg=0.0))
    assert max(_line_hops(g0)) > 3.0  # the pivot's frame: lines joined one lane over


def test_lines_left_by_a_pivot_turning_off_steeply_end():
    """A pivot turning off at 50 deg (beyond line_frame_max_deg) keeps its own frame, where the
    lines it leaves looked continued one or two lanes over; an edge implausible against the
    line's own direction is not made (line_frame_check): no line joins its neighbour. (At 40 deg
    one line still does: its tip's only predecessor edge is a leftover one, so it has no
    direction to check against.)"""
    seg = _crossing_pivot_segment(-50.0, turn_at=10)
    g = connect_segment(seg, config=former(ConnectionConfig, line_frame_deg=12.0))
    assert max(_line_hops(g)) < 0.05
    g1 = connect_segment(seg, config=former(ConnectionConfig, line_frame_deg=12.0, line_frame_check=False))
    assert max(_line_hops(g1)) > 3.0


def _right_angle_turn_segment(turn_deg: float = -95.0, *, fresh_line: bool = False) -> Segment:
    """A pivot drives east along y = -1.75 (dashed lines at y = 0 and 3.5, a solid line at
    y = -3.5), its steps fail for 4 steps while it turns ``turn_deg`` (an intersection, a side
    road leaving the motorway), then it drives on with dashed lines 2 m right and 1.5 m left of
    it. Its first cut after the turn holds the right line 6 m straight ahead of the y = 0 line's
    end, in the pivot's new frame. ``fresh_line``: the y = 0 line is reached by the last cut
    before the turn only (one node, no direction of its own: a crossing road's line)."""
    h = math.radians(turn_deg)
    u, n = np.array([math.cos(h), math.sin(h)]), np.array([-math.sin(h), math.cos(h)])
    start = np.array([18.0, -6.0]) + 2.0 * n
    steps = []
    for i in range(24):
        if i < 10:
            lat, typ = ([-1.75, 5.25], [S, D]) if fresh_line and i < 9 else ([-1.75, 1.75, 5.25], [S, D, D])
            steps.append(make_step(i, lat, typ, midpoint=np.array([2.0 * i, -1.75])))
        elif i < 14:
            steps.append(make_step(i, [], [], valid=False))
        else:
            steps.append(make_step(i, [-2.0, 1.5], [D, D], midpoint=start + 2.0 * (i - 14) * u, heading=h))
    return Segment("p", tuple(steps))


def _corner_edges(g) -> int:
    """Edges from a node of the east-going lines (x <= 18, y >= -4) to one after the turn."""
    a, b = g.node_xy[g.edges[:, 0]], g.node_xy[g.edges[:, 1]]
    return int(np.count_nonzero((a[:, 0] <= 18.0) & (a[:, 1] >= -4.0) & (b[:, 1] < -4.0)))


def test_lines_do_not_turn_a_right_angle_with_the_pivot():
    """Across a bridged gap where the pivot turned 95 deg, in its new frame the y = 0 line's end
    lay straight behind the new road's right line, and the two were joined: a line turning a
    corner no line has (Town04 50 s1: the median line continued 28 m across the carriageway
    into the side road). Checked against its own direction (line_check_max_deg 180), the old
    line ends; the new road's lines start anew."""
    seg = _right_angle_turn_segment()
    g = connect_segment(seg, config=former(ConnectionConfig, line_frame_deg=12.0))
    assert _corner_edges(g) == 0
    assert len(g.polylines()) == 5  # three lines before the turn, two after it
    g90 = connect_segment(seg, config=former(ConnectionConfig, line_frame_deg=12.0, line_check_max_deg=90.0))
    assert _corner_edges(g90) >= 1  # the old bound: the lines left behind joined around the corner
    from hdmap_core.pipeline import presets

    assert presets.preset("default").connection.line_check_max_deg == 180.0


def test_a_line_just_reached_does_not_turn_with_the_pivot():
    """The y = 0 line is one node, reached by the last cut before the pivot turns 95 deg across a
    bridged gap: no direction of its own, so neither its own frame nor the line check applied,
    and in the pivot's new frame it was joined to the new road's line straight ahead of it (a
    crossing line carried across an intersection). Checked against the pivot's heading at its
    step (line_check_undirected), it ends there."""
    seg = _right_angle_turn_segment(fresh_line=True)
    g = connect_segment(seg, config=former(ConnectionConfig, line_frame_deg=12.0))
    assert _corner_edges(g) == 0
    g0 = connect_segment(seg, config=former(ConnectionConfig, line_frame_deg=12.0, line_check_undirected=False))
    assert _corner_edges(g0) >= 1
    # a pivot that does not turn: the fresh line continues as before
    straight = Segment(
        "p",
        tuple(
            make_step(
                i,
                [-1.75, 5.25] if i < 9 else [-1.75, 1.75, 5.25],
                [S, D] if i < 9 else [S, D, D],
                valid=not 10 <= i < 14,
            )
            if not 10 <= i < 14
            else make_step(i, [], [], valid=False)
            for i in range(24)
        ),
    )
    a = connect_segment(straight, config=former(ConnectionConfig, line_frame_deg=12.0))
    b = connect_segment(straight, config=former(ConnectionConfig, line_frame_deg=12.0, line_check_undirected=False))
    assert sorted(map(tuple, a.edges.tolist())) == sorted(map(tuple, b.edges.tolist()))
    assert former_paper(ConnectionConfig).line_frame_deg == 0.0  # the paper: the rule is off with the line frames


def test_line_frame_is_off_in_the_paper_and_on_by_default():
    from hdmap_core.pipeline import presets

    assert former_paper(ConnectionConfig).line_frame_deg == 0.0
    assert former(ConnectionConfig).line_frame_deg == 0.0
    assert presets.preset("default").connection.line_frame_deg > 0.0
    assert presets.preset("default").connection.line_frame_bend_deg > 0.0
    assert former_paper(ConnectionConfig).line_frame_bend_deg == 0.0


def _curve_segment(radius: float = 14.0, n: int = 30) -> Segment:
    """A pivot driving a left-hand curve of ``radius`` (2 m steps; Town06's corners) with
    dashed lines concentric to its path 1.75 and 5.25 m either side."""
    offs = [-5.25, -1.75, 1.75, 5.25]
    steps = []
    for i in range(n):
        a = 2.0 * i / radius
        mid = np.array([radius * math.sin(a), radius * (1.0 - math.cos(a))])
        steps.append(make_step(i, offs, [D] * len(offs), midpoint=mid, heading=a, width_m=24.0))
    return Segment("p", tuple(steps))


def test_lines_curving_with_the_pivot_keep_its_frame():
    """On a tight curve a line's direction from 4 m back lags the pivot's heading by more than
    line_frame_deg; paired in that lagging frame its true continuation looks steep (steps
    rejected by the angle check). line_frame_bend_deg: a line whose history bends keeps the
    pivot's frame, the graph is the one without the rule; straight lines (the entering pivot)
    still get their own frame."""
    seg = _curve_segment(8.0)
    g0 = connect_segment(seg, config=former(ConnectionConfig, line_frame_deg=0.0))
    g1 = connect_segment(seg, config=former(ConnectionConfig, line_frame_deg=12.0))
    g2 = connect_segment(seg, config=former(ConnectionConfig, line_frame_deg=12.0, line_frame_bend_deg=5.0))
    assert g0.stats.rejected_angle == 0 and len(g0.polylines()) == 4
    assert g1.stats.rejected_angle > 0 or len(g1.polylines()) > 4
    assert g2.stats.rejected_angle == 0
    assert sorted(map(tuple, g2.edges.tolist())) == sorted(map(tuple, g0.edges.tolist()))
    g3 = connect_segment(
        _crossing_pivot_segment(20.0), config=former(ConnectionConfig, line_frame_deg=12.0, line_frame_bend_deg=5.0)
    )
    assert max(_line_hops(g3)) < 0.05 and g3.stats.rejected_angle == 0


def _gore_under_a_stale_tip() -> Segment:
    """paper_like_536's gore at (729, -832) (docs/pipeline.md "Fresh tips first"): the through line
    (solid, y 0) and the exit line diverging from it were one maximum up to step 8; a one-drive
    dashed maximum at y +1.5 in step 6 left a tip open across steps 7-8. From step 9 the exit line
    (y -1.6 and on to the right) and the through line (y +0.1) are two maxima."""
    steps = []
    for i in range(16):
        lat, typ = [-5.0, 0.0, 5.0], [B, S, B]
        if i == 6:
            lat, typ = [-5.0, 0.0, 1.5, 5.0], [B, S, D, B]
        if i >= 9:
            lat, typ = [-5.0, -1.6 - 0.2 * (i - 9), 0.1, 5.0], [B, S, S, B]
        steps.append(make_step(i, lat, typ))
    return Segment("p", tuple(steps))


def _pred_lateral(g, step: int, y: float) -> list[tuple[int, float, bool]]:
    """(step, y, leftover) of each edge into the node at ``y`` of ``step``."""
    owner = np.repeat(np.arange(len(g.topo_step)), np.diff(g.topo_start))
    (k,) = [k for k in range(len(g.node_xy)) if g.topo_step[owner[k]] == step and abs(g.node_xy[k][1] - y) < 1e-6]
    return [
        (int(g.topo_step[owner[a]]), round(float(g.node_xy[a][1]), 2), bool(lo))
        for (a, b), lo in zip(g.edges, g.edge_leftover)
        if b == k
    ]


@pytest.mark.parametrize("fresh_first", [False, True])
def test_tips_of_the_last_step_are_assigned_before_bridged_ones(fresh_first: bool):
    """In one joint assignment the stale dashed tip (y +1.5, step 6) takes the through line
    (1.4 m) and the solid tip (y 0, step 8) the exit line (1.6 m): 3.0 m against 3.2 m for the
    right pairs, and the split is lost. With ``fresh_first`` the step-8 tips are assigned first:
    the through line continues the solid line and the exit line joins it as a leftover (a
    split); the stale tip is left unpaired (6 m along, 3.1 m across: too steep)."""
    g = connect_segment(_gore_under_a_stale_tip(), config=former(ConnectionConfig, fresh_first=fresh_first))
    through, exit_ = _pred_lateral(g, 9, 0.1), _pred_lateral(g, 9, -1.6)
    if fresh_first:
        assert through == [(8, 0.0, False)] and exit_ == [(8, 0.0, True)]
    else:
        assert through == [(6, 1.5, False)] and exit_ == [(8, 0.0, False)]


def test_fresh_first_only_in_the_default_preset():
    from hdmap_core.pipeline import presets

    assert presets.preset("default").connection.fresh_first
    assert not former(ConnectionConfig).fresh_first and not former_paper(ConnectionConfig).fresh_first
    assert not presets.preset("naive").connection.fresh_first


def test_step_angles_on_a_tight_loop_are_judged_less_the_maxima_noise():
    """A pivot around a loop of 13 m radius (carla_town06_30_s6's at y 148), six lines from the
    inner border 6.5 m to the outer 6.5 m left and right, the maxima jittering 0.2 m across from
    step to step. The inner lines' maxima of consecutive steps lie only ~1 m apart along the
    road, so the jitter alone is ~20 deg there: judged on the raw angles most steps are rejected
    as implausible; with ``mean_angle_slack`` (default preset) the noise (``edge_slack_m``) is
    taken off first and the six lines run around the loop unbroken."""
    radius, lat0 = 13.0, [-6.5, -5.25, -1.75, 1.75, 5.25, 6.5]
    steps = []
    for i in range(40):
        phi = 2.0 * i / radius  # the pivot turns left about (0, radius)
        mid = np.array([radius * math.sin(phi), radius - radius * math.cos(phi)])
        jitter = 0.2 if i % 2 else -0.2
        steps.append(make_step(i, [v + jitter for v in lat0], [B, S, D, D, S, B], heading=phi, midpoint=mid))
    raw = connect_segment(Segment("p", tuple(steps)), config=former(ConnectionConfig))
    assert raw.stats.rejected_angle > 10
    slack = connect_segment(Segment("p", tuple(steps)), config=former(ConnectionConfig, mean_angle_slack=True))
    assert slack.stats.rejected_angle == 0 and slack.n_topo == 40
    assert len(slack.polylines()) == 6 and all(len(c) == 40 for c in slack.polylines())
    from hdmap_core.pipeline import presets  # noqa: PLC0415

    assert presets.preset("default").connection.mean_angle_slack
    assert not former_paper(ConnectionConfig).mean_angle_slack
    # a real jump is still one: all maxima 3 m sideways at one step (as above)
    jump = [
        make_step(i, [-1.75 + (3.0 if i == 7 else 0.0), 1.75 + (3.0 if i == 7 else 0.0)], [S, D]) for i in range(15)
    ]
    assert (
        connect_segment(
            Segment("p", tuple(jump)), config=former(ConnectionConfig, mean_angle_slack=True)
        ).stats.rejected_angle
        == 1
    )
