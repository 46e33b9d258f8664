"""The update's matching (same keys, reversed normals, re-numbered keys: ``layout.FLIP_DOT``,
``REKEY_COS``, ``REKEY_DISTANCE_M``) as the kernel does it gives bit for bit the contact table of
a straightforward reference: the rule table as first written (a linear scan over the existing
contacts for each incoming key, the full feature test against every contact left), run as plain
Python on copies of the same arrays, over random chains of updates with kept, re-numbered,
reversed and new keys, on one or several links, in both frames (``use_qe``) and every policy."""
import numpy as np
import pytest

from hapticproxy.server.model import kernels as _k
from hapticproxy.server.model.layout import (
    C_CP, C_D, C_DEF, C_FN, C_FT, C_IMP, C_N, C_P, C_REC, C_S, C_SPREV, C_TU, C_VC, C_VN, C_Z,
    CI_AGE, CI_KEY, CI_SLIP, CI_STATE, CS_IMPENDING, FLIP_DOT, K_DEFORMED, K_DROPPED, K_FLIPS,
    K_LEFT, K_M, K_NEW, K_REKEYED, K_UPDATES, MAX_DOF, NCOLS_F, NCOLS_I, NCOUNT, NLW, NPAR, NSTATE,
    P_EPS, P_POLICY, POLICY_DEFORM, POLICY_PAPER_LITERAL, POLICY_RIGID, REKEY_COS,
    REKEY_DISTANCE_M, S_T,
)

# the reference's own scratch columns (the kernel's layout of W is its own business)
_W_SP = 0
_W_TAKEN = 1
_W_FOUND = 2
_W_FLIP = 3
_W_XP = 4


# ---- the reference: the update as first written, O(n m) matching, plain Python -------------

def _ref_feature_point(j, k, cp, nrm, dsep, P, Pe, use_qe, out):
    """The reported tool feature as the proxy carries it (world, into ``out``); returns its
    separation s_w from the reported constraint along n (the engine frame: the feature taken in
    the engine tool's frame and put on the proxy; the paper's eq. 1: c_p + d n, s_w = d)."""
    if use_qe:
        fx = cp[j, 0] + dsep[j] * nrm[j, 0] - Pe[k, 9]
        fy = cp[j, 1] + dsep[j] * nrm[j, 1] - Pe[k, 10]
        fz = cp[j, 2] + dsep[j] * nrm[j, 2] - Pe[k, 11]
        bx = Pe[k, 0] * fx + Pe[k, 3] * fy + Pe[k, 6] * fz
        by = Pe[k, 1] * fx + Pe[k, 4] * fy + Pe[k, 7] * fz
        bz = Pe[k, 2] * fx + Pe[k, 5] * fy + Pe[k, 8] * fz
        out[0] = P[k, 9] + P[k, 0] * bx + P[k, 1] * by + P[k, 2] * bz
        out[1] = P[k, 10] + P[k, 3] * bx + P[k, 4] * by + P[k, 5] * bz
        out[2] = P[k, 11] + P[k, 6] * bx + P[k, 7] * by + P[k, 8] * bz
        return nrm[j, 0] * (out[0] - cp[j, 0]) + nrm[j, 1] * (out[1] - cp[j, 1]) + nrm[j, 2] * (out[2] - cp[j, 2])
    for q_ in range(3):
        out[q_] = cp[j, q_] + dsep[j] * nrm[j, q_]
    return dsep[j]


def _ref_same_feature(C, CI, X, t, i, k, xp, cp, nrm, j):
    """n_old . n_new if the existing contact ``i`` (on link ``k``) sits where the reported feature
    ``xp`` / constraint ``j`` is (REKEY_DISTANCE_M along the surface and across it), else 0."""
    if CI[i, CI_KEY] != k:
        return 0.0
    dot = C[i, C_N] * nrm[j, 0] + C[i, C_N + 1] * nrm[j, 1] + C[i, C_N + 2] * nrm[j, 2]
    if abs(dot) < REKEY_COS:
        return 0.0
    # the two constraint planes (the old one moved on with v_constr since its update)
    ds = C[i, C_VC] * (t - C[i, C_TU]) + C[i, C_REC]
    across = 0.0
    for a in range(3):
        across += nrm[j, a] * (cp[j, a] - C[i, C_CP + a] - ds * C[i, C_N + a])
    if abs(across) > REKEY_DISTANCE_M:
        return 0.0
    # the proxy's point of the old contact against the new feature, along the surface (the
    # deformation only moved it along n)
    e0 = X[i, 0] - xp[0]
    e1 = X[i, 1] - xp[1]
    e2 = X[i, 2] - xp[2]
    en = e0 * nrm[j, 0] + e1 * nrm[j, 1] + e2 * nrm[j, 2]
    e0 -= en * nrm[j, 0]
    e1 -= en * nrm[j, 1]
    e2 -= en * nrm[j, 2]
    if e0 * e0 + e1 * e1 + e2 * e2 > REKEY_DISTANCE_M * REKEY_DISTANCE_M:
        return 0.0
    return dot


def reference_apply_update(planar, par, st, C, CI, cnt, X, W, keys, cp, nrm, dsep, vc, n_in, nk, sel,
                 newF, newI, P, Pe, use_qe):
    """The rule table of the notes on a validated update (``sel[:nk]`` kept). ``P[k]``: pose row
    of tool link k (rotation link -> world row-major, then the link frame's origin, world) at the
    proxy's configuration, ``Pe[k]`` the same at the engine's (read only when ``use_qe``). A
    contact's local point is stored in the frame of its link (key column 0). ``X`` (m x 3) and
    ``W`` (cap x >= 4): scratch.

    Two events real engines produce are caught before the rules (``layout.FLIP_DOT``,
    ``REKEY_COS``, ``REKEY_DISTANCE_M``): a reported normal that reverses an existing contact's
    is refused for this update (the contact keeps its previous geometry and state, so the force
    is not turned round into a pull towards the surface), and a new key at the feature of a
    contact that left in the same update continues that contact (its penetration is kept, as
    eq. 5 keeps any existing contact's, instead of restarting at zero through eq. 4)."""
    m = cnt[K_M]
    t = st[S_T]
    policy = int(par[P_POLICY])
    # current world points and proxy separations s_p of the existing contacts
    for i in range(m):
        k = CI[i, CI_KEY]
        for a in range(3):
            s = P[k, 9 + a]
            for b2 in range(3):
                s += P[k, 3 * a + b2] * C[i, C_P + b2]
            X[i, a] = s
        s = -C[i, C_VC] * (t - C[i, C_TU]) - C[i, C_REC]
        for a in range(3):
            s += C[i, C_N + a] * (X[i, a] - C[i, C_CP + a])
        W[i, _W_SP] = s
        W[i, _W_TAKEN] = 0.0
    # pass 1: the same keys
    for a in range(nk):
        j = sel[a]
        found = -1
        for i in range(m):
            if CI[i, CI_KEY] == keys[j, 0] and CI[i, CI_KEY + 1] == keys[j, 1] \
                    and CI[i, CI_KEY + 2] == keys[j, 2]:
                found = i
                break
        W[a, _W_FOUND] = found
        W[a, _W_FLIP] = 0.0
        if found >= 0:
            W[found, _W_TAKEN] = 1.0
            dot = C[found, C_N] * nrm[j, 0] + C[found, C_N + 1] * nrm[j, 1] + C[found, C_N + 2] * nrm[j, 2]
            if dot < FLIP_DOT:
                W[a, _W_FLIP] = 1.0
    # pass 2: new keys at the feature of a contact that left (re-numbered, or reversed)
    n_rekey = 0
    for a in range(nk):
        if W[a, _W_FOUND] >= 0.0:
            continue
        j = sel[a]
        k = keys[j, 0]
        xp = W[a, _W_XP:_W_XP + 3]
        _ref_feature_point(j, k, cp, nrm, dsep, P, Pe, use_qe, xp)
        best = -1
        best_dot = 0.0
        for i in range(m):
            if W[i, _W_TAKEN] != 0.0:
                continue
            dot = _ref_same_feature(C, CI, X, t, i, k, xp, cp, nrm, j)
            if dot != 0.0 and (best < 0 or abs(dot) > abs(best_dot)):
                best = i
                best_dot = dot
        if best >= 0:
            W[a, _W_FOUND] = best
            W[best, _W_TAKEN] = 1.0
            if best_dot < 0.0:
                W[a, _W_FLIP] = 1.0
            else:
                n_rekey += 1
    # pass 3: the rule table
    matched = 0
    n_new = 0
    n_def = 0
    n_flip = 0
    for a in range(nk):
        j = sel[a]
        k = keys[j, 0]
        found = int(W[a, _W_FOUND])
        if found >= 0:
            matched += 1
        if found >= 0 and W[a, _W_FLIP] != 0.0:
            # refused for this update: the contact stays exactly as it was (key included)
            for q_ in range(NCOLS_F):
                newF[a, q_] = C[found, q_]
            for q_ in range(NCOLS_I):
                newI[a, q_] = CI[found, q_]
            newI[a, CI_AGE] = CI[found, CI_AGE] + 1
            n_flip += 1
            continue
        # the tool feature as the proxy carries it (xp) and its separation dj along n
        xp = W[a, _W_XP:_W_XP + 3]
        dj = _ref_feature_point(j, k, cp, nrm, dsep, P, Pe, use_qe, xp)
        # the separation the rules render: the real tool's, or (the paper read literally, for the
        # reproductions only) the epsilon-inflated tool's, new contacts included (eq. 6, no eq. 4)
        literal = policy == POLICY_PAPER_LITERAL
        dr = dj - par[P_EPS] if literal else dj
        # offset along n of the target world point from c_p (eq. 1/6: d, eq. 5: s_p, eq. 4: 0)
        if found >= 0:
            s_p = W[found, _W_SP]
            if policy == POLICY_RIGID or dr > 0.0 or s_p < dr:
                off = dr
            elif s_p <= 0.0:
                off = s_p
                n_def += 1
            else:
                off = 0.0
                n_def += 1
            newF[a, C_S] = C[found, C_S]
            newF[a, C_SPREV] = C[found, C_SPREV]
            for q_ in range(3):
                newF[a, C_Z + q_] = C[found, C_Z + q_]
            newI[a, CI_SLIP] = CI[found, CI_SLIP]
            newI[a, CI_STATE] = CI[found, CI_STATE]
            newI[a, CI_AGE] = CI[found, CI_AGE] + 1
        else:
            n_new += 1
            if policy == POLICY_RIGID or literal or dr > 0.0:
                off = dr
            else:
                off = 0.0
                n_def += 1
            newF[a, C_S] = np.inf             # has just arisen: next step may be a collision
            newF[a, C_SPREV] = np.inf
            for q_ in range(3):
                newF[a, C_Z + q_] = 0.0
            newI[a, CI_SLIP] = 0
            newI[a, CI_STATE] = CS_IMPENDING
            newI[a, CI_AGE] = 0
        for q_ in range(3):
            newI[a, CI_KEY + q_] = keys[j, q_]
            newF[a, C_CP + q_] = cp[j, q_]
            newF[a, C_N + q_] = nrm[j, q_]
        if planar:
            newF[a, C_CP + 2] = 0.0
            newF[a, C_N + 2] = 0.0
        newF[a, C_D] = dsep[j]
        newF[a, C_VC] = vc[j]
        newF[a, C_TU] = t
        newF[a, C_VN] = 0.0
        newF[a, C_FN] = 0.0
        newF[a, C_IMP] = 0.0
        for q_ in range(3):
            newF[a, C_FT + q_] = 0.0
        # what the rules put the proxy off the true geometry by (eqs. 4/5): to be recovered. Only
        # known in the engine frame: with the paper's eq. 1 the reported separation is the engine
        # tool's, not the proxy's, and "recovering" towards it only creeps after the engine's tool
        newF[a, C_DEF] = off - dr if (off > dr and use_qe) else 0.0
        newF[a, C_REC] = 0.0
        # local contact point in the link frame: p = R^T (Xp + (off - s_w) n - c); with the
        # engine at the proxy's pose Xp = c_p + d n, s_w = d: p = R^T (c_p + off n - c)  (eqs. 1, 4, 5, 6)
        w0 = xp[0] + (off - dj) * newF[a, C_N] - P[k, 9]
        w1 = xp[1] + (off - dj) * newF[a, C_N + 1] - P[k, 10]
        w2 = xp[2] + (off - dj) * newF[a, C_N + 2] - P[k, 11]
        for q_ in range(3):
            newF[a, C_P + q_] = P[k, q_] * w0 + P[k, 3 + q_] * w1 + P[k, 6 + q_] * w2
        if planar:
            newF[a, C_P + 2] = 0.0
    for a in range(nk):
        for q_ in range(NCOLS_F):
            C[a, q_] = newF[a, q_]
        for q_ in range(NCOLS_I):
            CI[a, q_] = newI[a, q_]
    cnt[K_M] = nk
    cnt[K_UPDATES] += 1
    cnt[K_DROPPED] += n_in - nk
    cnt[K_NEW] += n_new
    cnt[K_DEFORMED] += n_def
    cnt[K_LEFT] += m - matched
    cnt[K_FLIPS] += n_flip
    cnt[K_REKEYED] += n_rekey



# ---- random chains of updates ----------------------------------------------------------------

CAP = 64


def _rotation(rng, planar, scale=None):
    """A random rotation (``scale``: a small one, of about that many radians)."""
    if planar:
        th = rng.uniform(-np.pi, np.pi) if scale is None else rng.normal() * scale
        c, s = np.cos(th), np.sin(th)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    if scale is None:
        w, x, y, z = rng.normal(size=4)
    else:
        w, (x, y, z) = 1.0, rng.normal(size=3) * scale / 2
    r = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / r, x / r, y / r, z / r
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _poses(rng, links, planar):
    P = np.zeros((links, NLW))
    for k in range(links):
        P[k, :9] = _rotation(rng, planar).ravel()
        P[k, 9:12] = rng.normal(size=3) * 0.03
        if planar:
            P[k, 11] = 0.0
    return P


def _moved(rng, P, planar, scale):
    """The pose rows moved a little (the proxy since the last update, or the engine's tool)."""
    Q = P.copy()
    for k in range(P.shape[0]):
        Q[k, :9] = (_rotation(rng, planar, scale) @ P[k, :9].reshape(3, 3)).ravel()
        Q[k, 9:12] += rng.normal(size=3) * scale * 0.01
        if planar:
            Q[k, 11] = 0.0
    return Q


def _unit(v, planar):
    v = np.array(v, dtype=float)
    if planar:
        v[2] = 0.0
    return v / np.linalg.norm(v)


class _Engine:
    """Reports contacts the way real engines do: most keys kept, some re-numbered at the same
    feature, some normals reversed, some contacts gone, some new ones, clusters of nearby
    features with similar normals (so a new key can have several candidates)."""

    def __init__(self, rng, links, planar):
        self.rng, self.links, self.planar = rng, links, planar
        self.next_feature = 1000

    def _key(self, link):
        self.next_feature += 1
        return [link, int(self.rng.integers(0, 3)), self.next_feature]

    def _near(self, cp, n, offset_m, tilt):
        rng = self.rng
        n = _unit(n + rng.normal(size=3) * tilt, self.planar)
        cp = cp + rng.normal(size=3) * offset_m
        if self.planar:
            cp[2] = 0.0
        return cp, n

    def fresh(self, count):
        rows = []
        while len(rows) < count:
            link = int(self.rng.integers(0, self.links))
            cp = self.rng.normal(size=3) * 0.02
            if self.planar:
                cp[2] = 0.0
            n = _unit(self.rng.normal(size=3), self.planar)
            for _ in range(int(self.rng.integers(1, 4))):       # a cluster of 1-3 features
                if len(rows) < count:
                    rows.append((self._key(link), *self._near(cp, n, 1e-3, 0.02)))
        return rows

    def report(self, C, CI, m):
        rng = self.rng
        rows = []
        offsets = (0.0, 3e-4, 1e-3, 2.5e-3, 6e-3)       # straddle REKEY_DISTANCE_M
        tilts = (0.0, 0.02, 0.06, 0.15)                 # straddle 5 degrees
        for i in range(m):
            key = [int(v) for v in CI[i, CI_KEY:CI_KEY + 3]]
            cp0, n0 = C[i, C_CP:C_CP + 3].copy(), C[i, C_N:C_N + 3].copy()
            what = rng.choice(["kept", "kept", "reversed", "renumbered", "renumbered", "renumbered-reversed",
                               "other-link", "twice", "gone"])
            cp, n = self._near(cp0, n0, rng.choice(offsets), rng.choice(tilts))
            if what == "kept":
                rows.append((key, cp, n))
            elif what == "reversed":
                rows.append((key, cp, -n))
            elif what == "renumbered":
                rows.append((self._key(key[0]), cp, n))
            elif what == "renumbered-reversed":
                rows.append((self._key(key[0]), cp, -n))
            elif what == "other-link":
                rows.append((self._key((key[0] + 1) % self.links), cp, n))
            elif what == "twice":                       # two new keys compete for one feature
                rows.append((self._key(key[0]), cp, n))
                rows.append((self._key(key[0]), *self._near(cp0, n0, 5e-4, 0.03)))
        rows += self.fresh(int(rng.integers(0, 12)))
        if rng.random() < 0.5:
            rng.shuffle(rows)
        n_in = len(rows)
        keys = np.array([r[0] for r in rows], dtype=np.int64).reshape(n_in, 3)
        cp = np.array([r[1] for r in rows], dtype=float).reshape(n_in, 3)
        nrm = np.array([r[2] for r in rows], dtype=float).reshape(n_in, 3)
        dsep = rng.uniform(-2e-3, 2e-3, n_in)
        vc = rng.normal(size=n_in) * 0.05
        return keys, cp, nrm, dsep, vc


def _update(planar, arrays, keys, cp, nrm, dsep, vc, sel, nk, P, Pe, use_qe, fn):
    par, st, C, CI, cnt, X, W, newF, newI = arrays
    fn(planar, par, st, C, CI, cnt, X, W, keys, cp, nrm, dsep, vc, len(keys), nk, sel, newF, newI, P, Pe,
       use_qe)


def _bits(a):
    return a.view(np.int64) if a.dtype == np.float64 else a


@pytest.mark.parametrize("planar", [False, True], ids=["spatial", "planar"])
@pytest.mark.parametrize("use_qe", [0, 1], ids=["eq1", "engine-frame"])
def test_the_matching_gives_the_reference_contact_table(planar, use_qe):
    rng = np.random.default_rng(1400 + 2 * planar + use_qe)
    seen = dict(rekeyed=0, flips=0, flips_of_new_keys=0, kept=0, new=0, small_m=0, large_m=0, left=0)
    for chain in range(24):
        links = int(rng.integers(1, 4))
        engine = _Engine(rng, links, planar)
        par = np.zeros(NPAR)
        par[P_POLICY] = rng.choice([POLICY_RIGID, POLICY_DEFORM, POLICY_PAPER_LITERAL])
        par[P_EPS] = rng.uniform(0.0, 2e-3)
        st = np.zeros(NSTATE)
        st[S_T] = rng.uniform(0.0, 10.0)
        ours = (par, st, np.zeros((CAP, NCOLS_F)), np.zeros((CAP, NCOLS_I), dtype=np.int64),
                np.zeros(NCOUNT, dtype=np.int64), np.zeros((CAP, 3)), rng.normal(size=(CAP, MAX_DOF)),
                np.zeros((CAP, NCOLS_F)), np.zeros((CAP, NCOLS_I), dtype=np.int64))
        P = _poses(rng, links, planar)
        for u in range(5):
            C, CI, cnt = ours[2], ours[3], ours[4]
            m = int(cnt[K_M])
            seen["small_m" if m <= 8 else "large_m"] += 1
            if u == 0:
                rows = engine.fresh(int(rng.integers(1, 70)))
                keys = np.array([r[0] for r in rows], dtype=np.int64)
                cp = np.array([r[1] for r in rows])
                nrm = np.array([r[2] for r in rows])
                dsep, vc = rng.uniform(-2e-3, 2e-3, len(rows)), rng.normal(size=len(rows)) * 0.05
            else:
                keys, cp, nrm, dsep, vc = engine.report(C, CI, m)
                # what the steps since did to the live contacts (inherited by a continued one)
                C[:m, C_S] = rng.uniform(-2e-3, 2e-3, m)
                C[:m, C_SPREV] = rng.uniform(-2e-3, 2e-3, m)
                C[:m, C_Z:C_Z + 3] = rng.normal(size=(m, 3)) * 1e-4
                C[:m, C_REC] = np.where(rng.random(m) < 0.3, rng.uniform(0.0, 1e-3, m), 0.0)
                CI[:m, CI_SLIP] = rng.integers(0, 2, m)
                CI[:m, CI_STATE] = rng.integers(0, 4, m)
                st[S_T] += rng.choice([0.0, 1e-3, 0.016])
                if rng.random() < 0.5:
                    P = _moved(rng, P, planar, 0.01)
            if rng.random() < 0.15:           # normals not quite unit: the kernel's fallbacks
                nrm = nrm * (1.0 + rng.uniform(-2e-5, 2e-5, (len(nrm), 1)))
            n_in = len(keys)
            Pe = _moved(rng, P, planar, 0.02) if use_qe else np.zeros_like(P)
            nk = min(n_in, CAP) if rng.random() < 0.7 else int(rng.integers(0, min(n_in, CAP) + 1))
            sel = (np.arange(n_in, dtype=np.int64) if nk == n_in and rng.random() < 0.5
                   else rng.permutation(n_in).astype(np.int64))
            theirs = tuple(a.copy() for a in ours)
            before = cnt.copy()
            _update(planar, ours, keys, cp, nrm, dsep, vc, sel, nk, P, Pe, use_qe, _k.apply_update)
            _update(planar, theirs, keys, cp, nrm, dsep, vc, sel, nk, P, Pe, use_qe, reference_apply_update)
            for name, a, b in zip(("par", "st", "C", "CI", "cnt"), ours[:5], theirs[:5]):
                assert np.array_equal(_bits(a), _bits(b)), f"chain {chain} update {u}: {name} differs"
            d = cnt - before
            seen["rekeyed"] += d[K_REKEYED]
            seen["flips"] += d[K_FLIPS]
            seen["new"] += d[K_NEW]
            seen["left"] += d[K_LEFT]
            seen["kept"] += nk - d[K_NEW]
            incoming = {tuple(keys[j]) for j in sel[:nk]}
            seen["flips_of_new_keys"] += sum(tuple(CI[a, :3]) not in incoming for a in range(nk))
    # every case the matching distinguishes occurred
    assert all(v > 0 for v in seen.values()), seen
