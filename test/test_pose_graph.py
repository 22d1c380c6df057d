"""GTSAM pose graphs: loop closure with robust loop edges, per-edge sigmas, the two levels of LoopGraphs."""
import math

import numpy as np
import pytest
import torch

from gausem_core.geometry import make_pose, se3_exp, so3_exp

pytest.importorskip("gtsam")
from gausem_core.slam.pose_graph import PoseGraph  # noqa: E402


def _pose(rho, omega):
    return se3_exp(torch.tensor([*rho, *omega], dtype=torch.float64)).numpy()


def _circle(n=40, radius=3.0):
    """Ground-truth cam_to_world poses on a horizontal circle, camera looking along the direction of travel."""
    poses = []
    for i in range(n):
        a = 2 * math.pi * i / n
        rot = so3_exp(torch.tensor([0.0, -a, 0.0], dtype=torch.float64))
        poses.append(make_pose(rot, torch.tensor([radius * math.sin(a), 0.0, radius * math.cos(a)],
                                                 dtype=torch.float64)).numpy())
    return poses


def _drifted(truth, rng):
    """Integrate the true relative motions corrupted by a constant yaw bias and noise (odometry drift)."""
    bias = _pose([0.01, 0.0, 0.0], [0.0, 0.012, 0.004])
    est = [truth[0]]
    for a, b in zip(truth[:-1], truth[1:]):
        noise = _pose(rng.normal(0, 0.003, 3), rng.normal(0, 0.002, 3))
        est.append(est[-1] @ np.linalg.inv(a) @ b @ bias @ noise)
    return est


def _ate(est: dict, truth):
    return float(np.sqrt(np.mean([np.sum((est[i][:3, 3] - t[:3, 3]) ** 2) for i, t in enumerate(truth)])))


def _graph(truth, initial, robust, outlier):
    graph = PoseGraph(robust_kernel=robust)
    for i, pose in enumerate(initial):
        graph.add_node(i, pose)
    for i in range(1, len(initial)):
        graph.add_odometry(i - 1, i)
    n = len(truth)
    for a, b in ((0, n - 1), (0, n - 2), (1, n - 1), (n // 2, n // 2 + 3)):  # true loop closures
        graph.add_loop(a, b, np.linalg.inv(truth[a]) @ truth[b])
    if outlier:
        graph.add_loop(5, n // 2, _pose([2.0, 0.5, -1.0], [0.0, 1.5, 0.0]))  # a gross false loop
    return graph.optimize()


def test_pose_graph_closes_a_drifting_loop_and_huber_rejects_an_outlier():
    rng = np.random.default_rng(0)
    truth = _circle()
    initial = _drifted(truth, rng)
    ate_before = _ate(dict(enumerate(initial)), truth)
    assert ate_before > 0.3
    clean = _graph(truth, initial, "huber", outlier=False)
    assert clean.error_after < clean.error_before
    ate_clean = _ate(clean.poses, truth)
    assert ate_clean < 0.5 * ate_before
    np.testing.assert_allclose(clean.poses[0], truth[0], atol=1e-6)  # the prior holds the first node
    huber = _graph(truth, initial, "huber", outlier=True)
    plain = _graph(truth, initial, "none", outlier=True)
    assert _ate(huber.poses, truth) < min(0.5 * ate_before, 1.5 * ate_clean)
    assert _ate(plain.poses, truth) > 2 * _ate(huber.poses, truth)  # without the kernel the outlier does harm


@pytest.mark.parametrize("robust", ["none", "huber", "cauchy"])
def test_between_convention_is_a_inverse_b(robust):
    """A loop edge (a, b) measures a^-1 b with world-from-node poses: with a fixed, b goes to a @ measurement."""
    a = _pose([1.0, 2.0, 0.5], [0.1, 0.4, -0.2])
    measured = _pose([0.5, 0.0, 1.0], [0.0, 0.3, 0.0])
    graph = PoseGraph(robust_kernel=robust)
    graph.add_node(3, a)
    graph.add_node(9, np.eye(4))
    graph.add_loop(3, 9, measured)
    result = graph.optimize()
    np.testing.assert_allclose(result.poses[9], a @ measured, atol=1e-6)
    assert result.error_after < 1e-8 < result.error_before
    assert graph.keys == [3, 9]


def test_pose_graph_rejects_bad_input():
    with pytest.raises(ValueError, match="robust_kernel"):
        PoseGraph(robust_kernel="tukey")
    with pytest.raises(ValueError, match="odometry_sigmas"):
        PoseGraph(odometry_sigmas=(0.0, 0.1))
    graph = PoseGraph()
    graph.add_node(0, np.eye(4))
    with pytest.raises(ValueError, match="already exists"):
        graph.add_node(0, np.eye(4))
    with pytest.raises(ValueError, match="unknown node 1"):
        graph.add_odometry(0, 1)
    with pytest.raises(ValueError, match="rigid"):
        graph.add_node(1, 2 * np.eye(4))


def test_per_edge_sigmas_weight_loop_against_odometry():
    """Two nodes, odometry says b = a, a loop says b is 10 cm along x: the share each edge gets follows its sigma."""
    loop = _pose([0.1, 0.0, 0.0], [0.0, 0.0, 0.0])

    def solve(odometry, loop_sigmas):
        graph = PoseGraph(robust_kernel="none")
        graph.add_node(0, np.eye(4))
        graph.add_node(1, np.eye(4))
        graph.add_odometry(0, 1, odometry)
        graph.add_loop(0, 1, loop, loop_sigmas)
        return graph.optimize().poses[1][0, 3]

    assert solve((0.01, 0.01), (0.01, 0.01)) == pytest.approx(0.05, abs=1e-6)  # equal weights: half way
    assert solve((0.01, 0.03), (0.01, 0.01)) == pytest.approx(0.09, abs=1e-6)  # variance ratio 9 : 1
    graph = PoseGraph()
    graph.add_node(0, np.eye(4))
    graph.add_node(1, np.eye(4))
    with pytest.raises(ValueError, match="sigmas must be two positive"):
        graph.add_loop(0, 1, loop, (0.0, 0.1))
    with pytest.raises(ValueError, match="sigmas must be two positive"):
        graph.add_odometry(0, 1, (0.1,))


def test_loop_graphs_optimise_the_level_of_each_loop_and_keep_nothing_from_a_bad_one():
    from gausem_core.config import LoopConfig
    from gausem_core.slam.loop_closure import LoopConstraint
    from gausem_core.slam.loop_graphs import LoopGraphs
    graphs = LoopGraphs(LoopConfig())
    for k in range(4):  # keyframes of submap 0 on a line, 0.1 m apart (odometry)
        graphs.set_keyframe(5 * k, 0, _pose([0.1 * k, 0, 0], [0, 0, 0]))
    for s in range(3):
        graphs.set_anchor(s, _pose([s, 0, 0], [0, 0, 0]))
    sigmas = (0.005, 0.01)
    unknown = LoopConstraint(0, 99, 0, 0, torch.eye(4, dtype=torch.float64), sigmas, 1.0, True)
    with pytest.raises(ValueError, match="keyframe 99"):
        graphs.add(unknown)
    assert graphs.missing(unknown) == ["keyframe 99"] and graphs.constraints == []
    intra = LoopConstraint(0, 15, 0, 0, torch.from_numpy(_pose([0.2, 0, 0], [0, 0, 0])), sigmas, 1.0, True)
    update = graphs.add(intra)
    assert sorted(update.keyframes) == [0, 5, 10, 15] and not update.anchors
    x = [update.keyframes[k][0, 3] for k in (0, 5, 10, 15)]
    assert x[0] == pytest.approx(0.0, abs=1e-9) and 0.2 < x[3] < 0.3 and x[1] < x[2] < x[3]  # pulled, order kept
    assert graphs.keyframes[15][1][0, 3] == x[3]  # kept for the next loop
    inter = LoopConstraint(0, 15, 0, 2, torch.from_numpy(_pose([1.8, 0, 0], [0, 0, 0])), sigmas, 1.0, False)
    update = graphs.add(inter)
    assert sorted(update.anchors) == [0, 1, 2] and not update.keyframes
    assert 1.8 < update.anchors[2][0, 3] < 2.0 and graphs.constraints == [intra, inter]


def test_a_segment_stays_where_it_is_until_a_loop_merges_it_onto_the_first():
    """Anchors 0-2 and, after a break, 3-5 (a second tracking segment started at a wrong guess, 2 m and 90 degrees
    off): optimised without a loop between them, each segment keeps its poses (the second is held, not left free);
    a loop 1 -> 4 moves the whole second segment rigidly onto the first (its odometry kept), and the graph knows
    them as one segment from then on."""
    from gausem_core.config import LoopConfig
    from gausem_core.slam.loop_closure import LoopConstraint
    from gausem_core.slam.loop_graphs import LoopGraphs
    from gausem_core.slam.pose_graph import optimise_chain

    truth = {s: _pose([s, 0, 0], [0, 0.1 * s, 0]) for s in range(6)}
    wrong = _pose([2.0, 0.5, 0.0], [0.0, math.pi / 2, 0.0])
    start = {s: truth[s] if s < 3 else wrong @ truth[s] for s in range(6)}
    sigmas = lambda _: (0.01, 0.02)  # noqa: E731
    alone = optimise_chain(start, [], sigmas, breaks=[3])
    for s in range(6):
        np.testing.assert_allclose(alone.poses[s], start[s], atol=1e-6)
    loop = (1, 4, np.linalg.inv(truth[1]) @ truth[4], (0.005, 0.01))
    merged = optimise_chain(start, [loop], sigmas, breaks=[3])
    for s in range(6):
        np.testing.assert_allclose(merged.poses[s], truth[s], atol=1e-6)
    bound = optimise_chain(start, [loop], sigmas)  # no break: odometry 2 -> 3 holds the wrong guess against the loop
    assert np.abs(bound.poses[5] - truth[5]).max() > 0.1

    graphs = LoopGraphs(LoopConfig())
    for s in range(6):
        graphs.set_anchor(s, start[s], starts_segment=s == 3)
    assert graphs.segments() == [{0, 1, 2}, {3, 4, 5}] and not graphs.connected(1, 4)
    update = graphs.add(LoopConstraint(10, 40, 1, 4, torch.from_numpy(loop[2]), loop[3], 1.0, False))
    assert graphs.segments() == [set(range(6))] and graphs.connected(1, 4)
    np.testing.assert_allclose(update.anchors[5], truth[5], atol=1e-6)
