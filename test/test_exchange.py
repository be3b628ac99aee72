"""The pose exchange (vings_core.exchange): keeper, followers, policies, increments crossing in flight."""
from __future__ import annotations

import random

import numpy as np
import pytest

from vings_core.errors import InputError
from vings_core.exchange import ExchangeConfig, IncrementBatch, PoseFollower, PoseKeeper, WritebackPolicy
from vings_core.geometry import np_pose, np_so3_exp, sim3, sim3_apply_to_pose


class DictOwner:
    """A stage whose keyframe poses are a dict: the exchange's view of the front end or the mapper."""

    def __init__(self, poses: dict[int, np.ndarray]) -> None:
        self.poses = {s: T.copy() for s, T in poses.items()}
        self.kf_pose_version = 0
        self._written: dict[int, int] = {}
        self.pose_system = None
        self.applied: list[dict] = []

    def pose(self, s: int) -> np.ndarray:
        return self.poses[s].copy()

    def keyframes_moved_since(self, version: int) -> list[int]:
        return [s for s, v in self._written.items() if v > version]

    def move(self, s: int, C: np.ndarray) -> None:
        self.poses[s] = sim3_apply_to_pose(C, self.poses[s])
        self.kf_pose_version += 1
        self._written[s] = self.kf_pose_version

    def apply_increments(self, incs: dict[int, np.ndarray]) -> None:
        self.applied.append(incs)
        for s, C in incs.items():
            self.move(s, C)


def _random_pose(rng) -> np.ndarray:
    return np_pose(np_so3_exp(rng.normal(size=3) * 0.3), rng.normal(size=3))


def _shift(rng, scale: float) -> np.ndarray:
    """A pure translation: translations commute, so the final poses are known exactly."""
    return np_pose(np.eye(3), rng.normal(size=3) * scale)


def _graph(n: int = 5, seed: int = 0, policies: dict | None = None):
    rng = np.random.default_rng(seed)
    poses = {s: _random_pose(rng) for s in range(1, n + 1)}
    cfg = ExchangeConfig(**(policies or {"mapper": WritebackPolicy.ALL}), extra_writers=["fixer"])
    fe, mp, fx = DictOwner(poses), DictOwner(poses), DictOwner(poses)
    keeper = PoseKeeper(fe, cfg)
    followers = {"mapper": PoseFollower("mapper", mp), "fixer": PoseFollower("fixer", fx)}
    for s, T in poses.items():
        keeper.keyframe_sent(s, T)
        for f in followers.values():
            f.keyframe_added(s, T)
    return rng, keeper, followers, (fe, mp, fx)


def _flush(keeper, followers, to_keeper: list, to_followers: dict) -> None:
    for _ in range(4):
        b = keeper.outgoing()
        if b is not None:
            for q in to_followers.values():
                q.append(b)
        for name, q in to_followers.items():
            while q:
                followers[name].receive(q.pop(0))
        while to_keeper:
            keeper.receive(to_keeper.pop(0))


def _assert_agree(owners, tol=1e-9) -> None:
    fe = owners[0]
    for o in owners[1:]:
        for s in fe.poses:
            np.testing.assert_allclose(o.poses[s], fe.poses[s], atol=tol)


def test_third_writer_correction_reaches_keeper_and_mapper():
    """A fake stage applies one known rigid correction to every keyframe: the keeper (front end) and
    the mapper both end at the corrected poses."""
    rng, keeper, followers, owners = _graph()
    before = {s: T.copy() for s, T in owners[0].poses.items()}
    G = np_pose(np_so3_exp(np.array([0.0, 0.0, 0.3])), np.array([1.0, -2.0, 0.5]))
    fx = owners[2]
    fx.apply_increments({s: G for s in fx.poses})
    to_keeper = [followers["fixer"].send({s: G for s in fx.poses})]
    _flush(keeper, followers, to_keeper, {"mapper": [], "fixer": []})
    for o in owners:
        for s, T in before.items():
            np.testing.assert_allclose(o.poses[s], G @ T, atol=1e-12)
    assert keeper.stats["applied"] == len(before)
    assert followers["mapper"].stats["moved"] == len(before)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_crossing_increments_neither_lost_nor_applied_twice(seed):
    """Keeper moves, mapper refinements and a third writer's correction cross in flight in a random
    order: all three end at the same poses, equal to the start plus every increment once
    (translations commute, so that sum is exact)."""
    rng, keeper, followers, owners = _graph(seed=seed)
    fe, mp, fx = owners
    expect = {s: T.copy() for s, T in fe.poses.items()}
    to_keeper: list = []
    to_followers: dict = {"mapper": [], "fixer": []}
    pyrng = random.Random(seed)
    for step in range(60):
        act = pyrng.choice(["ba", "refine", "fix", "deliver_k", "deliver_f", "publish"])
        if act == "ba":
            s = pyrng.choice(list(fe.poses))
            C = _shift(rng, 0.01)
            fe.move(s, C)
            expect[s][:3, 3] += C[:3, 3]
        elif act in ("refine", "fix"):
            name, owner = ("mapper", mp) if act == "refine" else ("fixer", fx)
            ss = pyrng.sample(list(owner.poses), 2 if act == "refine" else len(owner.poses))
            incs = {s: _shift(rng, 0.05 if act == "fix" else 0.01) for s in ss}
            owner.apply_increments(incs)
            to_keeper.append(followers[name].send(incs))
            for s, C in incs.items():
                expect[s][:3, 3] += C[:3, 3]
        elif act == "deliver_k" and to_keeper:
            keeper.receive(to_keeper.pop(0))
        elif act == "deliver_f":
            for name, q in to_followers.items():
                if q and pyrng.random() < 0.7:
                    followers[name].receive(q.pop(0))
        elif act == "publish":
            b = keeper.outgoing()
            if b is not None:
                for q in to_followers.values():
                    q.append(b)
    _flush(keeper, followers, to_keeper, to_followers)
    _assert_agree(owners)
    for s, T in expect.items():
        np.testing.assert_allclose(fe.poses[s], T, atol=1e-9)


def test_crossing_rotations_end_in_agreement():
    """With rotations the order matters; every stage still ends at the keeper's poses."""
    rng, keeper, followers, owners = _graph(seed=7)
    fe, mp, fx = owners
    small = lambda: np_pose(np_so3_exp(rng.normal(size=3) * 0.02), rng.normal(size=3) * 0.02)  # noqa: E731
    fe.move(1, small())
    C = {1: small(), 2: small()}
    mp.apply_increments(C)
    b_m = followers["mapper"].send(C)
    b_k = keeper.outgoing()             # crosses the mapper's batch in flight
    followers["mapper"].receive(b_k)
    keeper.receive(b_m)
    G = sim3(np_so3_exp(np.array([0.1, 0.0, 0.0])), np.array([0.0, 1.0, 0.0]))
    fx.apply_increments({s: G for s in fx.poses})
    b_f = followers["fixer"].send({s: G for s in fx.poses})
    followers["fixer"].receive(b_k)
    keeper.receive(b_f)
    _flush(keeper, followers, [], {"mapper": [], "fixer": []})
    _assert_agree(owners)
    # both writers' increments were taken, none refused (the graph's policies accept them)
    assert keeper.stats["applied"] == len(C) + len(fx.poses) and keeper.stats["rejected"] == 0


def test_refused_increment_is_undone_by_its_writer():
    rng, keeper, followers, owners = _graph(policies={"mapper": WritebackPolicy.NONE})
    fe, mp, _ = owners
    start = {s: T.copy() for s, T in fe.poses.items()}
    C = {2: _shift(rng, 0.1)}
    mp.apply_increments(C)
    keeper.receive(followers["mapper"].send(C))
    assert keeper.stats["rejected"] == 1 and keeper.stats["applied"] == 0
    b = keeper.outgoing()
    assert b is not None and not b.increments and b.acks["mapper"] == 1   # an ack alone
    followers["mapper"].receive(b)
    for s, T in start.items():
        np.testing.assert_allclose(mp.poses[s], T, atol=1e-12)
        np.testing.assert_allclose(fe.poses[s], T, atol=0)


def test_duplicate_batches_are_ignored():
    rng, keeper, followers, owners = _graph()
    fe, mp, _ = owners
    C = {3: _shift(rng, 0.1)}
    mp.apply_increments(C)
    b = followers["mapper"].send(C)
    keeper.receive(b)
    keeper.receive(b)
    assert keeper.stats["duplicates"] == 1 and keeper.stats["applied"] == 1
    fe.move(1, _shift(rng, 0.1))
    out = keeper.outgoing()
    followers["mapper"].receive(out)
    followers["mapper"].receive(out)
    assert followers["mapper"].stats["duplicates"] == 1
    _assert_agree(owners[:2])


def test_similarity_increment_carries_scale_to_followers():
    """A loop closer's Sim(3) correction passes the keeper (policy all) and reaches the mapper with
    its scale."""
    rng, keeper, followers, owners = _graph()
    fe, mp, fx = owners
    S = sim3(np_so3_exp(np.array([0.0, 0.2, 0.0])), np.array([0.5, 0.0, 0.0]), 1.25)
    fx.apply_increments({s: S for s in fx.poses})
    keeper.receive(followers["fixer"].send({s: S for s in fx.poses}))
    fe.move(1, _shift(rng, 0.01))         # an own move on top of the accepted similarity
    b = keeper.outgoing()
    scales = [np.cbrt(np.linalg.det(C[:3, :3])) for C in b.increments.values()]
    np.testing.assert_allclose(scales, 1.25, rtol=1e-12)
    followers["mapper"].receive(b)
    followers["fixer"].receive(b)
    _assert_agree(owners)
    mp_scales = [np.cbrt(np.linalg.det(C[:3, :3])) for inc in mp.applied for C in inc.values()]
    np.testing.assert_allclose(mp_scales, 1.25, rtol=1e-12)


def test_keeper_moves_before_a_keyframe_arrives_are_applied_on_arrival():
    rng = np.random.default_rng(3)
    T = _random_pose(rng)
    fe, mp = DictOwner({9: T}), DictOwner({})
    keeper, fol = PoseKeeper(fe), PoseFollower("mapper", mp)
    keeper.keyframe_sent(9, T)
    fe.move(9, _shift(rng, 0.2))
    fol.receive(keeper.outgoing())       # the keyframe itself is still in the mapper's queue
    mp.poses[9] = T.copy()
    fol.keyframe_added(9, T)
    np.testing.assert_allclose(mp.poses[9], fe.poses[9], atol=1e-12)


def test_consistent_policy_refuses_moves_outside_the_window():
    rng, keeper, followers, owners = _graph(policies={"mapper": WritebackPolicy.CONSISTENT})
    C = {2: _shift(rng, 0.1)}
    owners[1].apply_increments(C)
    keeper.receive(followers["mapper"].send(C))   # no pose system: nothing to check against
    assert keeper.stats["rejected"] == 1


def test_exchange_config_policies_and_validation():
    cfg = ExchangeConfig()
    assert cfg.policy("mapper") is WritebackPolicy.CONSISTENT
    assert cfg.policy("loop_closer") is WritebackPolicy.ALL
    assert cfg.policy("anything") is WritebackPolicy.ALL
    with pytest.raises(ValueError):
        ExchangeConfig(confidence=1.5).validate()
    with pytest.raises(ValueError):
        ExchangeConfig(extra_writers=["frontend"]).validate()


def test_batch_check_refuses_malformed_increments():
    good = IncrementBatch("mapper", 1, {1: np.eye(4)})
    assert good.check("t") is good
    with pytest.raises(InputError, match="sequence"):
        IncrementBatch("mapper", 0, {}).check("t")
    bad = np.eye(4)
    bad[0, 1] = 0.5
    with pytest.raises(InputError, match="similarity"):
        IncrementBatch("mapper", 1, {1: bad}).check("t")
    with pytest.raises(InputError, match="finite"):
        IncrementBatch("mapper", 1, {1: np.full((4, 4), np.nan)}).check("t")


def _one_window_system(fe: DictOwner, stamp: int, sigma: float):
    """A BA window of one keyframe whose pose information is ``1 / sigma^2`` per tangent axis."""
    import torch

    from vings_core.frontend.ba import PoseSystem
    return PoseSystem([stamp], torch.from_numpy(np.linalg.inv(fe.pose(stamp)))[None],
                      torch.eye(6, dtype=torch.float64) / sigma ** 2, torch.zeros(6, dtype=torch.float64))


def _se3(rho, phi):
    from vings_core.geometry import np_se3_exp
    return np_se3_exp(np.asarray(list(rho) + list(phi), np.float64))


def test_consistency_gate_uses_the_keepers_information():
    """Increments within the keeper's pose uncertainty pass the chi-square test, large ones and
    those of keyframes outside its BA window do not."""
    from vings_core.exchange import correction_consistency
    rng, keeper, followers, (fe, mp, _) = _graph(policies={"mapper": WritebackPolicy.CONSISTENT})
    sigma = 0.01                                  # 1 cm / 10 mrad per axis
    fe.pose_system = _one_window_system(fe, 2, sigma)
    small = _se3([0.5 * sigma, 0, 0], [0, 0.5 * sigma, 0])
    big = _se3([5 * sigma, 0, 0], [0, 0, 0])
    ok, q, lim = correction_consistency(fe.pose_system, fe.pose, {2: small}, 0.99)
    assert set(ok) == {2} and q < lim
    ok, q, lim = correction_consistency(fe.pose_system, fe.pose, {2: big}, 0.99)
    assert ok == {} and q > lim
    ok, q, lim = correction_consistency(fe.pose_system, fe.pose, {1: small}, 0.99)   # not in the window
    assert ok == {} and q is None
    T2 = fe.pose(2)
    mp.apply_increments({2: small})
    assert set(keeper.receive(followers["mapper"].send({2: small}))) == {2}
    np.testing.assert_allclose(fe.pose(2), small @ T2, atol=1e-12)


def test_consistency_gate_counts_increments_accepted_since_the_ba():
    """Many small increments, each within the keeper's noise, must not add up unchecked: the gate
    measures the deviation from the BA's linearisation point, not each increment alone."""
    rng, keeper, followers, (fe, mp, _) = _graph(policies={"mapper": WritebackPolicy.CONSISTENT})
    sigma = 0.01
    fe.pose_system = _one_window_system(fe, 2, sigma)
    step = _se3([2.5 * sigma, 0, 0], [0, 0, 0])   # q = 6.25 < chi2(0.99, 6) = 16.8 alone
    accepted = 0
    for _ in range(6):
        mp.apply_increments({2: step})
        accepted += len(keeper.receive(followers["mapper"].send({2: step})))
    assert accepted == 1                           # 2 steps: q = 25 > 16.8
    followers["mapper"].receive(keeper.outgoing())   # the five refused ones are undone
    np.testing.assert_allclose(mp.poses[2], fe.poses[2], atol=1e-9)


def test_pose_written_before_the_keyframe_is_sent_reaches_the_follower():
    """outgoing() runs before keyframe_sent() for a keyframe whose pose was written after its packet
    was made: the write is not lost (the keeper compares every newly sent keyframe once)."""
    T3 = _se3([2.0, 0, 0], [0, 0.2, 0])
    fe, mp = DictOwner({3: T3}), DictOwner({3: T3})
    keeper, fol = PoseKeeper(fe), PoseFollower("mapper", mp)
    fe.move(3, _se3([0.1, 0, 0], [0, 0, 0]))       # moved after the packet (made at T3) was made
    fe._written.clear()                            # ... and before the keeper compares writes
    assert keeper.outgoing() is None               # not sent yet: nothing to compare
    keeper.keyframe_sent(3, T3)
    fol.keyframe_added(3, T3)
    b = keeper.outgoing()
    assert list(b.increments) == [3]
    fol.receive(b)
    np.testing.assert_allclose(mp.poses[3], fe.poses[3], atol=1e-12)


def test_abandon_undoes_increments_the_stopped_keeper_never_answered():
    rng, keeper, followers, (fe, mp, _) = _graph(policies={"mapper": WritebackPolicy.ALL})
    C1, C2 = _shift(rng, 0.1), _shift(rng, 0.05)
    mp.apply_increments({2: C1})
    keeper.receive(followers["mapper"].send({2: C1}))       # answered below: stays
    followers["mapper"].receive(keeper.outgoing())
    mp.apply_increments({2: C2, 3: C2})
    followers["mapper"].send({2: C2, 3: C2})                 # the keeper stops before it answers
    assert followers["mapper"].abandon() == 2
    for s in fe.poses:
        np.testing.assert_allclose(mp.poses[s], fe.poses[s], atol=1e-12)
    assert not followers["mapper"].in_flight


def test_keeper_carries_its_owners_own_similarity_to_the_followers():
    """The front end's visual-inertial alignment moves and scales its keyframes itself: the keeper's
    next batch carries that similarity (with its scale), so the mapper scales its Gaussians too."""
    from vings_core.exchange import PoseKeeper
    from vings_core.geometry import sim3_apply_to_pose

    class Owner:
        kf_pose_version = 0
        pose_system = None

        def __init__(self):
            self.poses = {}

        def pose(self, s):
            return self.poses[s]

        def keyframes_moved_since(self, version):
            return list(self.poses)

        def apply_increments(self, incs):
            raise AssertionError("not called here")

    owner = Owner()
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 0.5]
    owner.poses[7] = T.copy()
    keeper = PoseKeeper(owner)
    keeper.keyframe_sent(7, T)
    assert keeper.outgoing() is None or 7 not in keeper.outgoing().increments
    C = np.eye(4)
    C[:3, :3] = 2.5 * np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    owner.poses[7] = sim3_apply_to_pose(C, T)
    keeper.own_similarity({7: C, 99: C})            # 99 was never sent: ignored
    batch = keeper.outgoing()
    assert set(batch.increments) == {7}
    assert np.allclose(batch.increments[7], C)      # the scale travels, not a rigid stand-in
    assert keeper.outgoing() is None                # sent once


def test_keeper_counts_and_ignores_corrections_for_stamps_it_never_sent():
    rng, keeper, _, (fe, _, _) = _graph(n=3)
    before = {s: fe.pose(s) for s in fe.poses}
    C = _shift(rng, 0.1)
    got = keeper.receive(IncrementBatch("mapper", 1, {10 ** 12: C, 10 ** 12 + 1: C, 2: C}, {}))
    assert set(got) == {2} and keeper.stats["unknown_stamps"] == 2
    assert np.allclose(fe.pose(2), sim3_apply_to_pose(C, before[2]))
    assert all(np.array_equal(fe.pose(s), before[s]) for s in (1, 3))
