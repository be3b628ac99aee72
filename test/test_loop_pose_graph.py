"""Loop-closure pose graph (vings_core.loop.pose_graph): GTSAM conventions, exact recovery of known
drift (SIM3 and SE3), increments in the exchange convention, Huber against a false loop, bad input."""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from vings_core.errors import InputError
from vings_core.geometry import (np_pose_inverse, np_so3_exp, sim3, sim3_apply_to_pose, sim3_compose,
                                 sim3_inverse, sim3_scale)
from vings_core.loop.pose_graph import (GraphMode, LoopEdge, PoseGraphResult, optimize_pose_graph, sim3_from_gtsam,
                                        sim3_to_gtsam)

T0 = 1_000_000_000          # first keyframe stamp (ns)
DT = 50_000_000             # keyframe spacing (ns)


def true_chain(n: int, half: float = 4.0) -> dict[int, np.ndarray]:
    """``n`` rigid ``T_wc`` on a closed, rounded square (side ~``2 half`` m), camera looking along
    the path with a little pitch and height wiggle; the last keyframe is one step before the first."""
    th = 2 * np.pi * np.arange(n) / n
    c, s = np.cos(th), np.sin(th)
    yaw = np_so3_exp(np.stack([0 * th, 0 * th, th + np.pi / 2], 1))
    pitch = np_so3_exp(np.stack([0.05 * np.sin(3 * th), 0 * th, 0 * th], 1))
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = yaw @ pitch
    T[:, :3, 3] = np.stack([half * np.sign(c) * np.sqrt(abs(c)), half * np.sign(s) * np.sqrt(abs(s)),
                            0.2 * np.sin(2 * th)], 1)
    return {T0 + DT * k: T[k] for k in range(n)}


def drift_step(scale: float = 1.06) -> np.ndarray:
    """A world-frame similarity drift step: yaw, a little roll, translation and scale."""
    return sim3(np_so3_exp(np.array([0.01, -0.005, 0.06])), [0.25, -0.15, 0.04], scale)


def compounding(stamps: list[int], d: np.ndarray) -> dict[int, np.ndarray]:
    """Drift ``D_k = d^k`` of the ``k``-th keyframe (plain products of similarity matrices)."""
    D, acc = {}, np.eye(4)
    for s in stamps:
        D[s], acc = acc, d @ acc
    return D


def apply_drift(true: dict[int, np.ndarray], D: dict[int, np.ndarray]) -> tuple[dict, dict]:
    """Current poses ``T_k = sim3_apply_to_pose(D_k, T_true_k)`` (centre mapped by ``D_k`` as a
    point, rotation turned by its ``R``; computed batched here, the same formula) and the corrected
    similarities the graph should find, ``S*_k = D_k^-1 T_k`` (rotation and centre of the truth,
    scale ``1/s(D_k)``: keyframe ``k``'s content is ``s(D_k)`` times too large)."""
    stamps = sorted(true)
    Dm = np.stack([D[s] for s in stamps])
    Tt = np.stack([true[s] for s in stamps])
    sc = np.cbrt(np.linalg.det(Dm[:, :3, :3]))[:, None, None]
    cur = np.tile(np.eye(4), (len(stamps), 1, 1))
    cur[:, :3, :3] = Dm[:, :3, :3] / sc @ Tt[:, :3, :3]
    cur[:, :3, 3] = (Dm[:, :3, :3] @ Tt[:, :3, 3:4])[..., 0] + Dm[:, :3, 3]
    want = np.linalg.inv(Dm) @ cur
    return {s: cur[k] for k, s in enumerate(stamps)}, {s: want[k] for k, s in enumerate(stamps)}


#: per-keyframe drift (world frame): 0.003 rad yaw, 0.001 rad roll, ~1 cm, 0.3 % scale; over 40
#: keyframes 0.12 rad, ~0.5 m and 13 % scale, about what the default odometry sigmas allow
PER_STEP_DRIFT = sim3(np_so3_exp(np.array([0.001, 0.0, 0.003])), [0.01, -0.008, 0.002], 1.003)


def rel_err(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.abs(A - B).max() / max(1.0, np.abs(B).max()))


def centre_err(res: PoseGraphResult, true: dict[int, np.ndarray]) -> float:
    return max(float(np.linalg.norm(res.poses[s][:3, 3] - T[:3, 3])) for s, T in true.items())


# --------------------------------------------------------------------------- GTSAM conventions


def test_similarity3_convention_and_round_trip():
    """gtsam 4.3: Similarity3(R, t, s) maps p -> s (R p + t), matrix() = [[R, t], [0, 1/s]]; ours
    [[s R, t], [0, 1]] maps p -> s R p + t. The helpers convert exactly, compose like the matrices,
    and the tangent order is [omega, u, log s]."""
    R = np_so3_exp(np.array([0.3, -0.2, 1.1]))
    g = gtsam.Similarity3(gtsam.Rot3(R), np.array([1.0, 2.0, 3.0]), 2.0)
    p = np.array([0.5, -1.0, 2.0])
    np.testing.assert_allclose(g.transformFrom(p), 2.0 * (R @ p + [1, 2, 3]), atol=1e-12)
    np.testing.assert_allclose(g.matrix()[3, 3], 0.5)

    S = sim3(R, [0.4, -2.0, 7.0], 1.7)
    gS = sim3_to_gtsam(S)
    np.testing.assert_allclose(gS.transformFrom(p), S[:3, :3] @ p + S[:3, 3], atol=1e-12)
    np.testing.assert_allclose(sim3_from_gtsam(gS), S, atol=1e-12)
    np.testing.assert_allclose(sim3_from_gtsam(g), sim3(R, [2.0, 4.0, 6.0], 2.0), atol=1e-12)
    B = sim3(np_so3_exp(np.array([-0.5, 0.1, 0.2])), [3.0, 0.0, -1.0], 0.6)
    np.testing.assert_allclose(sim3_from_gtsam(gS.compose(sim3_to_gtsam(B))), S @ B, atol=1e-12)
    np.testing.assert_allclose(sim3_from_gtsam(gS.inverse()), sim3_inverse(S), atol=1e-12)
    # tangent order [omega (3), u (3), lambda = log s]
    E = sim3_from_gtsam(gtsam.Similarity3.Expmap(np.array([0, 0, 0.2, 0.1, 0, 0, 0.3])))
    assert sim3_scale(E) == pytest.approx(np.exp(0.3))
    np.testing.assert_allclose(E[:3, :3] / sim3_scale(E), np_so3_exp(np.array([0, 0, 0.2])), atol=1e-12)


# --------------------------------------------------------------------------- exact recovery


def segmented_case(mode: GraphMode, n: int = 32, segments: int = 4):
    """Drift that grows along the chain, built so that the optimum is exactly the truth.

    The chain is cut into ``segments`` runs; run ``g`` carries the drift ``D_g = d^g`` (``d``: yaw,
    roll, translation and, in SIM3, scale), so the drift compounds from run to run. Within a run all
    keyframes share one similarity, so the odometry measured from the current poses,
    ``T_i^-1 T_j``, equals ``S*_i^-1 S*_j`` for the corrected similarities ``S*_k = D_g^-1 T_k``
    exactly (the ``D_g`` cancels; in SIM3 ``S*_k`` carries the scale ``1/s(D_g)``, and the
    rotation-block rescaling of :func:`sim3_apply_to_pose` cancels too). Only the junction edges
    between runs (where tracking broke and re-initialised) are wrong: ``odometry_info`` gives them
    a negligible information (1e-12), and each drifted run gets a loop edge, from its last keyframe
    to the first keyframe, measured from the truth: ``T_on = S*_first^-1 S*_k``. Every measurement
    that carries weight is then satisfied exactly by ``S*``, each run is pinned by its loop edge
    (run 0 by the fixed first keyframe), so ``S*`` is the unique optimum (up to ~1e-16 from the
    junctions' weak terms) and the solver must reach it to round-off."""
    true = true_chain(n)
    stamps = sorted(true)
    d = drift_step(1.06 if mode is GraphMode.SIM3 else 1.0)
    run = [k * segments // n for k in range(n)]
    Dg = [np.eye(4)]
    for _ in range(segments - 1):
        Dg.append(sim3_compose(d, Dg[-1]))
    D = {s: Dg[run[k]] for k, s in enumerate(stamps)}
    cur, want = apply_drift(true, D)
    dim = 7 if mode is GraphMode.SIM3 else 6
    weak = {(stamps[k - 1], stamps[k]): 1e-12 * np.eye(dim) for k in range(1, n) if run[k] != run[k - 1]}
    lasts = [k for k in range(n) if k == n - 1 or run[k + 1] != run[k]][1:]
    loops = [LoopEdge(stamps[0], stamps[k], sim3_inverse(want[stamps[0]]) @ want[stamps[k]], 0.01, 0.05)
             for k in lasts]
    return true, cur, want, D, loops, weak


@pytest.mark.parametrize("mode", [GraphMode.SIM3, GraphMode.SE3])
def test_known_drift_recovered_exactly(mode):
    true, cur, want, D, loops, weak = segmented_case(mode)
    stamps = sorted(true)
    before = max(rel_err(cur[s], want[s]) for s in stamps)
    assert before > 0.3                                          # the drift is not small
    res = optimize_pose_graph(cur, loops, mode, odometry_info=weak)
    assert res.error_before > 10 and res.error_after < 1e-12
    for s in stamps:
        assert rel_err(res.poses[s], want[s]) < 1e-6, s
        np.testing.assert_allclose(res.poses[s][:3, 3], true[s][:3, 3], atol=1e-6)     # centre: the truth
        R = res.poses[s][:3, :3] / sim3_scale(res.poses[s])
        np.testing.assert_allclose(R, true[s][:3, :3], atol=1e-7)                        # rotation: the truth
        assert rel_err(res.increments[s], sim3_inverse(D[s])) < 1e-6                   # C_k = D_k^-1
    if mode is GraphMode.SE3:
        assert all(abs(sim3_scale(S) - 1) < 1e-12 for S in res.poses.values())
    else:
        assert sim3_scale(res.poses[stamps[-1]]) == pytest.approx(1.06 ** -3, rel=1e-6)
    for r in res.loop_residuals:
        assert r["weight"] == 1.0 and r["rot_deg"] < 1e-6 and r["pos"] < 1e-6 and abs(r["scale"]) < 1e-6


def test_single_loop_with_per_step_drift_closes():
    """Realistic case: drift compounds at every step (no exact optimum exists: the odometry itself
    is drifted), one loop edge last -> first from the truth. The loop closes and every keyframe
    moves towards the truth."""
    n = 40
    true = true_chain(n)
    stamps = sorted(true)
    d = PER_STEP_DRIFT
    D = compounding(stamps, d)
    cur, want = apply_drift(true, D)
    loop = LoopEdge(stamps[0], stamps[-1], sim3_inverse(want[stamps[0]]) @ want[stamps[-1]], 0.01, 0.05)
    res = optimize_pose_graph(cur, [loop], GraphMode.SIM3)
    assert res.error_after < 0.2 * res.error_before
    r = res.loop_residuals[0]
    assert r["weight"] == 1.0 and r["rot_deg"] < 0.5 and r["pos"] < 0.1 and abs(r["scale"]) < 0.05
    before = max(float(np.linalg.norm(cur[s][:3, 3] - true[s][:3, 3])) for s in stamps)
    assert centre_err(res, true) < 0.3 * before


# --------------------------------------------------------------------------- increments, gauge


@pytest.mark.parametrize("mode", [GraphMode.SIM3, GraphMode.SE3])
def test_increments_follow_the_exchange_convention(mode):
    true, cur, want, D, loops, weak = segmented_case(mode)
    stamps = sorted(true)
    res = optimize_pose_graph(cur, loops, mode, odometry_info=weak)
    assert np.array_equal(res.increments[stamps[0]], np.eye(4))
    assert np.array_equal(res.poses[stamps[0]], cur[stamps[0]])
    for s in stamps:
        C, S = res.increments[s], res.poses[s]
        moved = sim3_apply_to_pose(C, cur[s])                   # what the exchange does with C
        np.testing.assert_allclose(moved[:3, 3], S[:3, 3], atol=1e-9)
        np.testing.assert_allclose(moved[:3, :3], S[:3, :3] / sim3_scale(S), atol=1e-9)
        assert sim3_scale(C) == pytest.approx(sim3_scale(S), rel=1e-12)
        np.testing.assert_allclose(C @ cur[s], S, atol=1e-9)    # C = S_new S_old^-1

    # another fixed keyframe: it stays put, and the solution differs by a global similarity only
    mid = stamps[len(stamps) // 2]
    res2 = optimize_pose_graph(cur, loops, mode, odometry_info=weak, fixed=mid)
    assert np.array_equal(res2.increments[mid], np.eye(4))
    np.testing.assert_allclose(res2.poses[mid], cur[mid], atol=1e-12)
    G = res2.poses[mid] @ sim3_inverse(res.poses[mid])
    for s in stamps:
        assert rel_err(res2.poses[s], G @ res.poses[s]) < 1e-6


def test_odometry_info_order_matches_the_sigma_model():
    """A 7x7 (SIM3) / 6x6 (SE3) information diag(1/sigma^2) in GTSAM order [rot, pos, (log-scale)]
    for every odometry edge reproduces the built-in sigma model: the documented order is right."""
    n = 20
    true = true_chain(n)
    stamps = sorted(true)
    d = sim3(np_so3_exp(np.array([0.0, 0.01, 0.02])), [0.05, 0.0, 0.01], 1.02)
    D = compounding(stamps, d)
    cur, want = apply_drift(true, D)
    for mode in (GraphMode.SIM3, GraphMode.SE3):
        Z = want[stamps[-1]] if mode is GraphMode.SIM3 else true[stamps[-1]]
        loop = LoopEdge(stamps[0], stamps[-1], sim3_inverse(want[stamps[0]]) @ Z, 0.02, 0.1)
        ref = optimize_pose_graph(cur, [loop], mode, odo_sigma_rot=0.003, odo_sigma_pos_rel=0.05,
                                  odo_sigma_pos_min=0.01, odo_sigma_scale=0.02)
        info = {}
        for a, b in zip(stamps[:-1], stamps[1:]):
            pos = max(0.05 * np.linalg.norm((np_pose_inverse(cur[a]) @ cur[b])[:3, 3]), 0.01)
            sig = [0.003] * 3 + [pos] * 3 + ([0.02] if mode is GraphMode.SIM3 else [])
            info[(a, b)] = np.diag(1.0 / np.square(sig))
        alt = optimize_pose_graph(cur, [loop], mode, odometry_info=info)
        assert alt.error_after == pytest.approx(ref.error_after, rel=1e-6)
        for s in stamps:
            assert rel_err(alt.poses[s], ref.poses[s]) < 1e-7


# --------------------------------------------------------------------------- robustness


def test_huber_downweights_a_false_loop():
    """One correct loop (last -> first) and one false one (keyframes 10 -> 25, 25 deg and 2 m off).
    The Huber kernel leaves the false edge with weight << 1 and the correct one an inlier; the
    trajectory stays much closer to the truth than with plain least squares."""
    n = 40
    true = true_chain(n)
    stamps = sorted(true)
    d = PER_STEP_DRIFT
    D = compounding(stamps, d)
    cur, want = apply_drift(true, D)
    good = LoopEdge(stamps[0], stamps[-1], sim3_inverse(want[stamps[0]]) @ want[stamps[-1]], 0.01, 0.05)
    a, b = stamps[10], stamps[25]
    wrong = sim3_inverse(want[a]) @ want[b] @ sim3(np_so3_exp(np.array([0.0, 0.1, np.radians(25)])), [2.0, -1.0, 0.3])
    bad = LoopEdge(a, b, wrong, 0.01, 0.05)
    clean = optimize_pose_graph(cur, [good], GraphMode.SIM3)
    robust = optimize_pose_graph(cur, [good, bad], GraphMode.SIM3)
    plain = optimize_pose_graph(cur, [good, bad], GraphMode.SIM3, robust_k=None)
    w_good, w_bad = (r["weight"] for r in robust.loop_residuals)
    assert w_bad < 0.05 and w_good == 1.0
    assert all(r["weight"] == 1.0 for r in plain.loop_residuals)
    # measured: centre error vs truth 0.31 m without the false loop, 0.55 m with it (Huber), 1.3 m (L2)
    e_clean, e_robust, e_plain = centre_err(clean, true), centre_err(robust, true), centre_err(plain, true)
    assert e_robust < 0.5 * e_plain, (e_clean, e_robust, e_plain)
    dev_robust = max(float(np.linalg.norm(robust.poses[s][:3, 3] - clean.poses[s][:3, 3])) for s in stamps)
    dev_plain = max(float(np.linalg.norm(plain.poses[s][:3, 3] - clean.poses[s][:3, 3])) for s in stamps)
    assert dev_robust < 0.4 * dev_plain, (dev_robust, dev_plain)
    assert robust.loop_residuals[1]["rot_deg"] > 15        # the false loop is left open, not enforced
    assert plain.loop_residuals[1]["rot_deg"] < robust.loop_residuals[1]["rot_deg"]


def test_large_drift_long_chain_converges_fast():
    """1000 keyframes, 1 rad of yaw and 1.5x scale drift: Huber-LM started from the current poses
    would stall (the true loop looks like a 100-sigma outlier there); the kernel-free first solve
    reaches the optimum, where the loop is an inlier. Also a (generous) speed bound."""
    n = 1000
    true = true_chain(n, half=20.0)
    stamps = sorted(true)
    d = sim3(np_so3_exp(np.array([0.0, 0.0, 1.0 / n])), np.array([3.0, 2.0, 0.0]) / n, 1.5 ** (1.0 / n))
    D = compounding(stamps, d)
    cur, want = apply_drift(true, D)
    loop = LoopEdge(stamps[0], stamps[-1], sim3_inverse(want[stamps[0]]) @ want[stamps[-1]], 0.01, 0.05)
    res = optimize_pose_graph(cur, [loop], GraphMode.SIM3)
    r = res.loop_residuals[0]
    assert r["weight"] == 1.0 and r["rot_deg"] < 0.1
    assert res.error_after < 0.02 * res.error_before
    assert res.seconds < 5.0


# --------------------------------------------------------------------------- input checks


def test_bad_input_raises_input_error():
    true = true_chain(6)
    stamps = sorted(true)
    good = LoopEdge(stamps[0], stamps[-1], np_pose_inverse(true[stamps[0]]) @ true[stamps[-1]], 0.01, 0.05)

    def run(poses=true, loops=(good,), mode=GraphMode.SIM3, **kw):
        return optimize_pose_graph(poses, list(loops), mode, **kw)

    run()                                                         # the baseline is fine
    with pytest.raises(InputError, match="at least 2"):
        run(poses={stamps[0]: true[stamps[0]]}, loops=())
    with pytest.raises(InputError, match="not among the poses"):
        run(loops=[LoopEdge(stamps[0], 123, np.eye(4), 0.01, 0.05)])
    nan = dict(true)
    nan[stamps[2]] = np.full((4, 4), np.nan)
    with pytest.raises(InputError, match=f"keyframe {stamps[2]}"):
        run(poses=nan)
    sheared = dict(true)
    sheared[stamps[3]] = true[stamps[3]] @ np.diag([1.0, 1.1, 1.0, 1.0])
    with pytest.raises(InputError, match="rigid"):
        run(poses=sheared)
    T = good.T_on.copy()
    T[0, 3] = np.inf
    with pytest.raises(InputError, match="T_on"):
        run(loops=[LoopEdge(stamps[0], stamps[-1], T, 0.01, 0.05)])
    with pytest.raises(InputError, match="rigid loop"):
        run(loops=[LoopEdge(stamps[0], stamps[-1], 2.0 * np.eye(4) + np.diag([0, 0, 0, -1.0]), 0.01, 0.05)],
            mode=GraphMode.SE3)
    with pytest.raises(InputError, match="sigma_pos"):
        run(loops=[LoopEdge(stamps[0], stamps[-1], good.T_on, 0.01, 0.0)])
    with pytest.raises(InputError, match="itself"):
        run(loops=[LoopEdge(stamps[1], stamps[1], np.eye(4), 0.01, 0.05)])
    with pytest.raises(InputError, match="fixed"):
        run(fixed=42)
    with pytest.raises(InputError, match="consecutive"):
        run(odometry_info={(stamps[0], stamps[2]): np.eye(7)})
    with pytest.raises(InputError, match="positive definite"):
        run(odometry_info={(stamps[0], stamps[1]): -np.eye(7)})
    with pytest.raises(InputError, match="7x7"):
        run(odometry_info={(stamps[0], stamps[1]): np.eye(6)})
    with pytest.raises(InputError, match="mode"):
        run(mode="sim2")
    with pytest.raises(InputError, match="robust_k"):
        run(robust_k=-1.0)
