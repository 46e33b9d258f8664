"""Linkage tools: D(q), G(q), J_i(q), J_h(q) of the kernels against the numpy reference and
finite differences; a one-link linkage is the rigid tool; the numba step agrees with the numpy
reference step; a chain pressed onto a wall settles with the contact forces balancing the hand; a
self-contact keeps two links from passing through each other; bad input is refused by name."""
from __future__ import annotations

import math

import numpy as np
import pytest
from linkage_helpers import (
    bar_chain, bar_corners, chain_contacts, closest_on_bar, random_linkage, random_normals, random_q,
)

from hapticproxy.server.model import ContactParams, LinkSpec, LocalModel, ToolSpec
from hapticproxy.server.model import linkage as LK
from hapticproxy.server.model.layout import (
    C_P, CI_KEY, CI_SLIP, K_N_COLLIDING, MAX_DOF, NCOLS_F, NCOLS_I, S_LQ, S_Q,
)
from hapticproxy.server.model.reference import LinkageReference


def _model(tool, **kw):
    kw.setdefault("period_s", 1e-3)
    return LocalModel(tool, ContactParams(kw.pop("k", 4000.0), kw.pop("b", 30.0), 0.0, kw.pop("mus", 0.0),
                                          kw.pop("muk", 0.0)), **kw)


def _kernel_kin(model, q, links, points, gravity=(0.0, 0.0, 0.0)):
    """D, taug, X, J (m x 3 x d), Jh (h x d) from the linkage kernel at configuration q."""
    par, st, _, _, _ = model.arrays()
    par = par.copy()
    par[18:21] = gravity
    st = st.copy()
    st[S_LQ:S_LQ + model.nq] = q
    m = len(points)
    C = np.zeros((m, NCOLS_F))
    C[:, C_P:C_P + 3] = points
    CI = np.zeros((m, NCOLS_I), dtype=np.int64)
    CI[:, CI_KEY] = links
    lmeta, lk, lki, lw = model.linkage_args()
    lw = lw.copy()
    D = np.zeros((MAX_DOF, MAX_DOF)); taug = np.zeros(MAX_DOF)
    J = np.zeros((m, 3, MAX_DOF)); X = np.zeros((m, 3)); Jh = np.zeros((6, MAX_DOF))
    LK._kin_linkage(lmeta, lk, lki, par, st, C, CI, m, lw, D, taug, J, X, Jh)
    d, h = model.dof, model.hand_dim
    return D[:d, :d], taug[:d], X, J[:, :, :d], Jh[:h, :d]


CASES = [(3, True, False), (4, True, True), (7, True, True), (10, True, True),
         (2, False, False), (4, False, True), (7, False, True)]


@pytest.mark.parametrize("n_links,planar,branching", CASES)
def test_inertia_matrix_is_symmetric_positive_definite_and_matches_the_reference(n_links, planar, branching):
    rng = np.random.default_rng(100 * n_links + planar)
    for _ in range(10):
        tool = random_linkage(rng, n_links, planar, branching=branching)
        model = _model(tool, warm=False)
        ref = LinkageReference.of(tool)
        for _ in range(10):
            q = random_q(rng, tool)
            grav = rng.normal(size=3) * 9.81
            if planar:
                grav[2] = 0.0
            links = rng.integers(0, n_links, size=5)
            pts = rng.normal(size=(5, 3)) * 0.05
            if planar:
                pts[:, 2] = 0.0
            D, taug, X, J, Jh = _kernel_kin(model, q, links, pts, grav)
            np.testing.assert_array_equal(D, D.T)
            assert np.linalg.eigvalsh(D).min() > 0.0
            Dr, taugr, Xr, Jr, Jhr = ref.kinematics(q, grav, links, pts)
            np.testing.assert_allclose(D, Dr, rtol=1e-10, atol=1e-13)
            np.testing.assert_allclose(taug, taugr, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(X, Xr, atol=1e-14)
            np.testing.assert_allclose(J, Jr, atol=1e-13)
            np.testing.assert_allclose(Jh, Jhr, atol=1e-13)


@pytest.mark.parametrize("n_links,planar,branching", CASES)
def test_jacobians_and_gravity_match_finite_differences(n_links, planar, branching):
    rng = np.random.default_rng(7 + 100 * n_links + planar)
    for _ in range(10):
        tool = random_linkage(rng, n_links, planar, branching=branching)
        model = _model(tool, warm=False)
        ref = LinkageReference.of(tool)  # only its integrator: q (+) dt qd on the manifold
        q = random_q(rng, tool)
        qd = rng.normal(size=model.dof)
        links = rng.integers(0, n_links, size=6)
        pts = rng.normal(size=(6, 3)) * 0.05
        if planar:
            pts[:, 2] = 0.0
        grav = rng.normal(size=3) * 9.81
        if planar:
            grav[2] = 0.0
        D, taug, X, J, Jh = _kernel_kin(model, q, links, pts, grav)
        eps = 1e-6
        qp, qm = ref.integrate(q, qd, eps), ref.integrate(q, qd, -eps)
        Rp, pp = model.link_poses(qp)
        Rm, pm = model.link_poses(qm)
        # contact points: world velocity J_i qd
        Xp = np.array([pp[k] + Rp[k] @ x for k, x in zip(links, pts)])
        Xm = np.array([pm[k] + Rm[k] @ x for k, x in zip(links, pts)])
        np.testing.assert_allclose(np.einsum("ijk,k->ij", J, qd), (Xp - Xm) / (2 * eps), atol=1e-7)
        # hand: the held link's frame origin and its angular velocity
        hk = tool.held_link
        v_fd = (pp[hk] - pm[hk]) / (2 * eps)
        Wx = (Rp[hk] - Rm[hk]) / (2 * eps) @ model.link_poses(q)[0][hk].T  # [w]x
        w_fd = np.array([Wx[2, 1], Wx[0, 2], Wx[1, 0]])
        v_hand = Jh @ qd
        if planar:
            np.testing.assert_allclose(v_hand, [v_fd[0], v_fd[1], w_fd[2]], atol=1e-7)
        else:
            np.testing.assert_allclose(v_hand, np.r_[v_fd, w_fd], atol=1e-7)
        # gravity: taug . qd = d/dt of sum m g . c (minus the potential's rate)
        def work(qq):
            Rs, ps = model.link_poses(qq)
            return sum(ln.mass_kg * grav @ (ps[k] + Rs[k] @ np.asarray(ln.com_m)) for k, ln in enumerate(tool.links))
        np.testing.assert_allclose(taug @ qd, (work(qp) - work(qm)) / (2 * eps), rtol=1e-6, atol=1e-8)
        # kinetic energy: 1/2 qd^T D qd = sum of the links' 1/2 m v_c^2 + 1/2 w^T I w (finite differences)
        ke = 0.0
        for k, ln in enumerate(tool.links):
            vc = ((pp[k] + Rp[k] @ np.asarray(ln.com_m)) - (pm[k] + Rm[k] @ np.asarray(ln.com_m))) / (2 * eps)
            Wk = (Rp[k] - Rm[k]) / (2 * eps) @ model.link_poses(q)[0][k].T
            wk = np.array([Wk[2, 1], Wk[0, 2], Wk[1, 0]])
            Rk = model.link_poses(q)[0][k]
            Iw = Rk @ ln.inertia_matrix() @ Rk.T
            ke += 0.5 * ln.mass_kg * vc @ vc + 0.5 * (wk[2] ** 2 * Iw[2, 2] if planar else wk @ Iw @ wk)
        assert 0.5 * qd @ D @ qd == pytest.approx(ke, rel=1e-6)


@pytest.mark.parametrize("planar", [True, False])
def test_a_one_link_linkage_is_the_rigid_tool(planar):
    """Root frame at the COM: the same D, the same contacts, the same steps as ToolSpec.planar /
    spatial (hand at the COM). Each step starts from the same state (the linkage's copied from
    the rigid model's), so a contact state decided by rounding cannot make them part ways."""
    rng = np.random.default_rng(3)
    if planar:
        rigid = ToolSpec.planar(0.3, 2e-4)
        link = LinkSpec(0.3, inertia_kg_m2=(1e-4, 1e-4, 2e-4))
    else:
        rigid = ToolSpec.spatial(0.3, (1e-4, 2e-4, 3e-4))
        link = LinkSpec(0.3, inertia_kg_m2=(1e-4, 2e-4, 3e-4))
    a = _model(rigid, mus=0.5, muk=0.3)
    # the rigid spatial tool has no gyroscopic term: compare with the paper's eq. 7
    b = _model(ToolSpec.linkage([link], 0, planar), mus=0.5, muk=0.3, linkage_dynamics="paper")
    q0 = np.r_[0.01, -0.02, 0.3] if planar else np.r_[0.01, -0.02, 0.03, 0.9, 0.1, -0.2, 0.3]
    if not planar:
        q0[3:] /= np.linalg.norm(q0[3:])
    a.reset(q0, rng.normal(size=a.dof) * 0.1)
    for it in range(300):
        if it % 16 == 0:
            n = 6
            nrm = random_normals(rng, n, "planar" if planar else "spatial")
            keys = np.c_[np.zeros(n, int), np.arange(n) + it, np.zeros(n, int)]
            cp = a.pose_matrix()[1] + rng.normal(size=(n, 3)) * 0.01
            if planar:
                cp[:, 2] = 0.0
            a.update(keys, cp, nrm, rng.uniform(-1e-3, 1e-3, n))
        for src, dst in zip(a.arrays()[1:], b.arrays()[1:]):
            dst[...] = src
        b.arrays()[1][S_LQ:S_LQ + a.nq] = a.q
        hand = rng.normal(size=a.hand_dim)
        fa = a.step(hand).copy()
        fb = b.step(hand).copy()
        np.testing.assert_allclose(fb, fa, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(b.q, a.q, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(b.qd, a.qd, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(b.arrays()[2], a.arrays()[2], rtol=1e-9, atol=1e-12)
        # contact keys, states and ages (the stick/slip flag sits on a rounding-sized boundary)
        np.testing.assert_array_equal(np.delete(b.arrays()[3], CI_SLIP, 1), np.delete(a.arrays()[3], CI_SLIP, 1))
    assert a.counters()["collisions"] > 10


@pytest.mark.parametrize("n_links,planar", [(3, True), (10, True), (3, False), (7, False)])
def test_numba_and_numpy_agree_on_random_linkage_scenes(n_links, planar, against_reference):
    from test_reference_oracle import random_coupling

    rng = np.random.default_rng(21 + n_links + planar)
    collisions = 0
    for i in range(16):
        tool = random_linkage(rng, n_links, planar)
        mus = rng.uniform(0, 1)
        m = LocalModel(tool, ContactParams(rng.uniform(1e3, 1e4), rng.uniform(0, 50), rng.uniform(0, 1), mus,
                                           rng.uniform(0, mus)),
                       capacity=64, gravity_m_per_s2=rng.normal(size=3) * (np.r_[1, 1, 0] if planar else 1),
                       policy=str(rng.choice(["rigid", "deformation"])), warm=False,
                       integrator=("explicit", "implicit")[i % 2])
        random_coupling(rng, m)
        m.reset(random_q(rng, tool), rng.normal(size=m.dof) * 0.1)
        n = int(rng.integers(0, 40))
        nrm = random_normals(rng, n, "planar" if planar else "spatial")
        keys = np.c_[rng.integers(0, n_links, n), np.arange(n), np.zeros(n, int)]
        m.update(keys, rng.normal(size=(n, 3)) * 0.02, nrm, rng.uniform(-0.002, 0.002, n), rng.normal(size=n) * 0.01)
        ref = LinkageReference.of(tool)
        for _ in range(4):
            cnt, _ = against_reference(m, rng.normal(size=m.hand_dim), rtol=1e-8, linkage=ref)
            collisions += int(cnt[K_N_COLLIDING] > 0)
    assert collisions > 0


def _settle_on_wall(tool, q0, push, *, seconds=3.0, mus=0.5):
    """The chain dropped onto the floor y = 0 by a constant hand wrench on the held link; the
    'engine' reports the bar corners at ~60 Hz from the proxy's own pose."""
    m = _model(tool, k=4000.0, b=30.0, mus=mus, muk=0.8 * mus, policy="deformation")
    m.reset(q0)
    push = np.asarray(push, dtype=float)
    for i in range(int(seconds * 1000)):
        if i % 16 == 0:
            m.update(*chain_contacts(m, wall_y=0.0))
        m.step(push)
    return m


def test_a_planar_chain_pressed_onto_a_wall_settles_with_the_contacts_balancing_the_hand():
    tool = bar_chain(3)  # held by its last link; starts 3 mm above the floor, slightly bent
    m = _settle_on_wall(tool, np.r_[-0.09, 0.0105, 0.0, 0.05, -0.05], (0.0, -0.5, 0.0))
    f_env = m.env_wrench.copy()
    # the environment's wrench at the hand cancels the push (eq. 8 at rest: F_env = -F_h)
    np.testing.assert_allclose(f_env, [0.0, 0.5, 0.0], atol=2e-3)
    snap = m.contacts()
    assert snap.normal_force_n.sum() == pytest.approx(0.5, abs=2e-3)       # sum of f_n n_y = the push
    # the hand point is at rest; the unheld links (no gravity, free joints) are in neutral
    # equilibrium and may still drift slowly
    assert np.linalg.norm(m.hand_state()[7:9]) < 1e-3
    assert m.proxy_separations().min() > -0.5 / 4000.0 - 1e-4              # penetration ~ F / k at most


def test_a_spatial_chain_pressed_onto_a_wall_settles_with_the_contacts_balancing_the_hand():
    tool = bar_chain(3, planar=False)
    q0 = np.r_[-0.09, 0.0105, 0.0, 1.0, 0.0, 0.0, 0.0, 0.05, -0.05]
    m = _settle_on_wall(tool, q0, (0.0, -0.5, 0.0, 0.0, 0.0, 0.0), seconds=3.0)
    np.testing.assert_allclose(m.env_wrench, [0.0, 0.5, 0.0, 0.0, 0.0, 0.0], atol=3e-3)
    assert np.linalg.norm(m.hand_state()[7:10]) < 1e-3


def _free_flight(dynamics, seconds, push):
    """A free 3-bar chain (no contacts) pushed at the held link's origin: (kinetic energy, work
    done by the hand, linear momentum) after ``seconds``."""
    tool = bar_chain(3)
    m = _model(tool, linkage_dynamics=dynamics)
    m.reset(np.r_[0.0, 0.0, 0.0, 0.05, -0.05])
    push = np.asarray(push, dtype=float)
    work = 0.0
    for _ in range(int(seconds * 1000)):
        x0 = m.hand_state()[:2]
        m.step(push)
        work += push[:2] @ (m.hand_state()[:2] - x0)
    Rs, ps = m.link_poses()
    ref = LinkageReference.of(tool)
    p = sum(ln.mass_kg * ref.jacobian(m.q, k, ps[k] + Rs[k] @ np.asarray(ln.com_m))[0] @ m.qd
            for k, ln in enumerate(tool.links))
    return m.kinetic_energy_j, work, p


def test_full_dynamics_keep_the_energy_balance_the_paper_s_eq_7_does_not():
    """With the velocity-product terms the kinetic energy is the hand's work (up to the
    integrator's O(dt)) and the momentum the hand's impulse; neglecting them (the paper's eq. 7)
    a chain whose free links swing fast gains energy."""
    ke, work, p = _free_flight("full", 0.15, (0.0, -0.5, 0.0))
    assert ke == pytest.approx(work, rel=0.02)
    # (semi-implicit Euler with the free links at ~20 rad/s: a 2 % error at 1 kHz)
    np.testing.assert_allclose(p, [0.0, -0.5 * 0.15, 0.0], atol=0.02 * 0.075)
    ke, work, _ = _free_flight("paper", 0.15, (0.0, -0.5, 0.0))
    assert ke > 2.0 * work


def _fold(self_contacts: bool) -> tuple[float, float]:
    """Link 2 of a free 3-bar chain swung at 1 rad/s towards link 0 (joint 1 at 120 deg: the
    triangle closes at joint 2 = 120 deg); returns (the deepest overlap of a bar corner of link 2
    in link 0 or back, m; the largest joint 2 angle, deg)."""
    tool = bar_chain(3, held_link=1)
    m = _model(tool, k=4000.0, b=30.0)
    m.reset(np.r_[0.0, 0.0, 0.0, math.radians(120), math.radians(90)], np.r_[0.0, 0.0, 0.0, 0.0, 1.0])
    deepest = 0.0
    q2_max = 0.0
    for i in range(1500):
        if i % 16 == 0:
            m.update(*chain_contacts(m, self_pairs=((0, 2),) if self_contacts else ()))
        m.step(np.zeros(3))
        q2_max = max(q2_max, math.degrees(m.q[4]))
        if i % 4 == 0:
            Rs, ps = m.link_poses()
            for owner, other in ((2, 0), (0, 2)):
                for c in bar_corners(Rs[owner], ps[owner]):
                    deepest = min(deepest, closest_on_bar(Rs[other], ps[other], c)[2])
    return deepest, q2_max


def test_a_self_contact_stops_two_links_passing_through_each_other():
    deepest, q2_max = _fold(False)
    # without self-contacts link 2 sweeps through link 0 (a corner reaches the 15 mm bar's middle)
    assert q2_max > 150.0 and deepest < -0.007
    deepest, q2_max = _fold(True)                 # with them (two contacts, one on each link) ...
    assert q2_max < 110.0 and deepest > -0.001    # ... it stops on link 0


def test_bad_linkages_and_contacts_are_refused_by_name():
    root = LinkSpec(0.1, inertia_kg_m2=(1e-4, 1e-4, 1e-4))
    bar = LinkSpec(0.1, (0.03, 0, 0), (1e-4, 1e-4, 1e-4), 0, "revolute", (0, 0, 1), (0.06, 0, 0))
    with pytest.raises(ValueError, match=r"tool.links\[1\].axis"):
        _model(ToolSpec.linkage([root, LinkSpec(0.1, (0, 0, 0), (1e-4,) * 3, 0, "revolute", (1, 0, 0))], 0, True))
    with pytest.raises(ValueError, match=r"tool.links\[1\].parent"):
        _model(ToolSpec.linkage([root, LinkSpec(0.1, (0, 0, 0), (1e-4,) * 3, 1, "revolute")], 0, True))
    with pytest.raises(ValueError, match=r"tool.links\[0\]"):
        _model(ToolSpec.linkage([bar], 0, True))
    with pytest.raises(ValueError, match="tool.held_link"):
        _model(ToolSpec.linkage([root, bar], 2, True))
    with pytest.raises(ValueError, match="at most 7 links"):
        _model(ToolSpec.linkage([root] + [bar] * 7, 0, False))
    with pytest.raises(ValueError, match=r"tool.links\[1\].inertia_kg_m2"):
        _model(ToolSpec.linkage([root, LinkSpec(0.1, (0, 0, 0), (1e-4, 0.0, 1e-4), 0, "revolute")], 0, False))
    m = _model(ToolSpec.linkage([root, bar], 1, True))
    before = m.arrays()[1].copy()
    with pytest.raises(ValueError, match="keys"):
        m.update([[2, 1, 0]], [[0, 0, 0]], [[0, 1, 0]], [0.0])
    with pytest.raises(ValueError, match="tool_q"):
        m.update([[1, 1, 0]], [[0, 0, 0]], [[0, 1, 0]], [0.0], tool_q=[0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="hand_wrench"):
        m.step([1.0, 2.0])
    np.testing.assert_array_equal(m.arrays()[1], before)
    assert m.arrays()[1][S_Q] == 0.0


def test_engine_frame_locates_features_on_the_engine_links():
    """A contact computed with the engine's chain elsewhere (tool_q) lands on the proxy's link
    at the same place on the link: the proxy's separation there is the reported one."""
    tool = bar_chain(3)
    m = _model(tool, policy="rigid")  # eq. 1/6 only: no deformation moves the points
    q_proxy = np.r_[0.0, 0.02, 0.1, 0.3, -0.2]
    q_engine = np.r_[0.004, 0.015, 0.12, 0.25, -0.15]
    m.reset(q_proxy)
    eng = _model(tool, warm=False)
    eng.reset(q_engine)
    k, cp, n, d, vc = chain_contacts(eng, wall_y=0.0, epsilon=0.05)
    assert len(k) >= 4
    m.update(k, cp, n, d, vc, tool_q=q_engine)
    # the local points are the engine's body points: proxy separation = n . (proxy point - c_p)
    Rs_e, ps_e = eng.link_poses()
    snap = m.contacts()
    for i, key in enumerate(snap.keys):
        link = int(key[0])
        body = Rs_e[link].T @ (cp[i] + d[i] * n[i] - ps_e[link])
        np.testing.assert_allclose(snap.local_point_body_m[i], body, atol=1e-12)


@pytest.mark.parametrize("planar", [True, False])
def test_joint_state_splits_the_hand_wrench_by_coordinates(planar):
    """ProxyState content: the root frame's pose and twist; J_h^T F_h split into the wrench on
    the root frame's origin and one effort per joint."""
    rng = np.random.default_rng(5 + planar)
    for _ in range(10):
        tool = random_linkage(rng, 4, planar)
        m = _model(tool, warm=False)
        m.reset(random_q(rng, tool), rng.normal(size=m.dof))
        F = rng.normal(size=6)
        if planar:
            F[2:5] = 0.0
        pose, twist, wrench, effort, jq, jqd = m.joint_state(F)
        ref = LinkageReference.of(tool)
        _, _, _, _, Jh = ref.kinematics(m.q, np.zeros(3), np.zeros(0, int), np.zeros((0, 3)))
        gen = Jh.T @ (F[[0, 1, 5]] if planar else F)
        r = 3 if planar else 6
        np.testing.assert_allclose(effort, gen[r:], atol=1e-12)
        np.testing.assert_allclose(wrench[[0, 1, 5]] if planar else wrench, gen[:r], atol=1e-12)
        Rs, ps = m.link_poses()
        np.testing.assert_allclose(pose[:3], ps[0], atol=1e-15)
        w, x, y, z = pose[3:]
        np.testing.assert_allclose(Rs[0], [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                                           [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                                           [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], atol=1e-12)
        np.testing.assert_allclose(twist[[0, 1, 5]] if planar else twist, m.qd[:r], atol=1e-15)
        np.testing.assert_array_equal(jq, m.q[(3 if planar else 7):])
        np.testing.assert_array_equal(jqd, m.qd[r:])


def test_rigid_tools_never_run_linkage_code():
    """Scenes without a linkage pay nothing for it: a rigid model steps through the class's
    ``step`` -> ``kernels.step_rigid`` and the loop's rigid kernel calls no linkage function."""
    from hapticproxy.server import control
    from hapticproxy.server.model import kernels

    rigid = _model(ToolSpec.planar(0.3, 2e-4), warm=False)
    assert rigid.step.__func__ is LocalModel.step and not rigid.is_linkage
    linkage_names = {"step_linkage", "hand_state_linkage", "update_linkage", "_kin_linkage"}
    for fn in (kernels.step_rigid, kernels.update_rigid, control.haptic_step):
        assert not linkage_names & set(fn.py_func.__code__.co_names)
    chain = _model(bar_chain(3), warm=False)
    assert chain.step.__func__ is LocalModel._step_linkage
