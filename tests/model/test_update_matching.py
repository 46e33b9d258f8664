"""The update's matching (same keys at the same contact, reversed normals refused or taken,
re-numbered keys: ``layout.FLIP_DOT``, ``FLIP_REFUSE_MAX``, ``KEY_SLIDE_FACTOR``, ``REKEY_COS``,
``REKEY_DISTANCE_M``) as the kernel does it gives bit for bit the contact table of a
straightforward reference: the rule table as first written (a linear scan over the existing
contacts for each incoming key, the full feature test against every contact left), run as plain
Python on copies of the same arrays, over random chains of updates with kept, re-numbered,
reversed, handed-round and new keys, on one or several links, in both frames (``use_qe``) and
every policy."""
import numpy as np
import pytest

from hapticproxy.server.model import kernels as _k
from hapticproxy.server.model.layout import (
    C_CP, C_D, C_DEF, C_FN, C_FT, C_IMP, C_N, C_P, C_REC, C_S, C_SPREV, C_TU, C_VC, C_VN, C_Z,
    CI_AGE, CI_FLIPS, CI_KEY, CI_SLIP, CI_STATE, CST_IMPENDING, FLIP_DOT, FLIP_REFUSE_MAX, K_DEFORMED,
    K_DROPPED, K_FLIPS, K_FLIPS_TAKEN, K_LEFT, K_M, K_NEW, K_REKEYED, K_UPDATES, KEY_SLIDE_FACTOR, MAX_DOF,
    NCOLS_F, NCOLS_I, NCOUNT, NLW, NPAR, NSTATE, P_EPS, P_POLICY, P_REC_VN, POLICY_DEFORM, POLICY_PAPER_LITERAL,
    POLICY_RIGID, REKEY_COS, REKEY_DISTANCE_M, S_T,
)

# the reference's own scratch columns (the kernel's layout of W is its own business)
_W_SP = 0
_W_TAKEN = 1
_W_FOUND = 2
_W_FLIP = 3
_W_XP = 4


# ---- the reference: the update as first written, O(n m) matching, plain Python -------------

def _sum3(v):
    """v[0] + v[1] + v[2], left to right (the kernels' order of summation)."""
    return v[0] + v[1] + v[2]


def _to_world(P, k, v):
    """Pose row ``P[k]`` (rotation row-major, then the origin) applied to the point ``v``: the
    origin plus the rotation's columns times the components, added in that order."""
    return P[k, 9:12] + P[k, 0:9:3] * v[0] + P[k, 1:9:3] * v[1] + P[k, 2:9:3] * v[2]


def _ref_feature_point(j, k, cp, nrm, dsep, P, Pe, use_qe, out):
    """The reported tool feature as the proxy carries it (world, into ``out``); returns its
    separation s_w from the reported constraint along n (the engine frame: the feature taken in
    the engine tool's frame and put on the proxy; the paper's eq. 1: c_p + d n, s_w = d)."""
    feature = cp[j] + dsep[j] * nrm[j]
    if not use_qe:
        out[:] = feature
        return dsep[j]
    f = feature - Pe[k, 9:12]
    local = Pe[k, 0:3] * f[0] + Pe[k, 3:6] * f[1] + Pe[k, 6:9] * f[2]  # R_e^T f
    out[:] = _to_world(P, k, local)
    return _sum3(nrm[j] * (out - cp[j]))


def _ref_same_feature(C, CI, X, t, i, k, xp, cp, nrm, j):
    """n_old . n_new if the existing contact ``i`` (on link ``k``) sits where the reported feature
    ``xp`` / constraint ``j`` is (REKEY_DISTANCE_M along the surface and across it), else 0."""
    if CI[i, CI_KEY] != k:
        return 0.0
    n_old = C[i, C_N:C_N + 3]
    dot = _sum3(n_old * nrm[j])
    if abs(dot) < REKEY_COS:
        return 0.0
    # the two constraint planes (the old one moved on with v_constr since its update)
    ds = C[i, C_VC] * (t - C[i, C_TU]) + C[i, C_REC]
    if abs(_sum3(nrm[j] * (cp[j] - C[i, C_CP:C_CP + 3] - ds * n_old))) > REKEY_DISTANCE_M:
        return 0.0
    # the proxy's point of the old contact against the new feature, along the surface (the
    # deformation only moved it along n)
    e = X[i, :3] - xp
    e = e - _sum3(e * nrm[j]) * nrm[j]
    if _sum3(e * e) > REKEY_DISTANCE_M * REKEY_DISTANCE_M:
        return 0.0
    return dot


def _tangential(v, n):
    """v without its component along n (the kernels' order of operations)."""
    return v - _sum3(v * n) * n


def _ref_same_contact(C, X, t, i, k, cp, nrm, dsep, P, Pe, use_qe, xp, j):
    """A kept key names existing contact ``i`` only where ``i`` is (``layout.KEY_SLIDE_FACTOR``):
    the planes within REKEY_DISTANCE_M, and along the surface the reported constraint point or
    the reported feature within REKEY_DISTANCE_M + KEY_SLIDE_FACTOR x the distance of the proxy's
    point of ``i`` from its old constraint point (both constraint points where they are now)."""
    moved = (C[i, C_VC] * (t - C[i, C_TU]) + C[i, C_REC]) * C[i, C_N:C_N + 3]
    e = cp[j] - C[i, C_CP:C_CP + 3] - moved
    if abs(_sum3(e * nrm[j])) > REKEY_DISTANCE_M:
        return False
    away = X[i, :3] - C[i, C_CP:C_CP + 3] - moved
    tol = REKEY_DISTANCE_M + KEY_SLIDE_FACTOR * np.sqrt(_sum3(_tangential(away, nrm[j]) ** 2))
    if _sum3(_tangential(e, nrm[j]) ** 2) <= tol * tol:
        return True
    _ref_feature_point(j, k, cp, nrm, dsep, P, Pe, use_qe, xp)
    return _sum3(_tangential(X[i, :3] - xp, nrm[j]) ** 2) <= tol * tol


def _ref_refuse_reversal(C, CI, t, i, k, cp, nrm, P, j):
    """Refuse a reversed normal for contact ``i`` (kept as it was), or take it? By which of the
    two normals has the link's frame origin in front of its plane (``layout.FLIP_DOT``)."""
    origin = P[k, 9:12]
    held = -(C[i, C_VC] * (t - C[i, C_TU]) + C[i, C_REC])   # the plane moved on since its update
    for term in C[i, C_N:C_N + 3] * (origin - C[i, C_CP:C_CP + 3]):
        held += term
    reported = _sum3(nrm[j] * (origin - cp[j]))
    if reported > held + 2 * REKEY_DISTANCE_M:
        return False
    return CI[i, CI_FLIPS] < (FLIP_REFUSE_MAX if held > reported + 2 * REKEY_DISTANCE_M else 1)


#: eq. 4 placements the reference made, by how they start (for the test's coverage count)
REF_TOUCHES = {"resting": 0, "colliding": 0}


def reference_apply_update(planar, par, st, C, CI, cnt, X, W, keys, cp, nrm, dsep, vc, n_in, nk, sel,
                           newF, newI, P, Pe, use_qe, Vk):
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
        X[i, :3] = _to_world(P, k, C[i, C_P:C_P + 3])
        s_p = -C[i, C_VC] * (t - C[i, C_TU]) - C[i, C_REC]
        for term in C[i, C_N:C_N + 3] * (X[i, :3] - C[i, C_CP:C_CP + 3]):
            s_p += term
        W[i, [_W_SP, _W_TAKEN]] = (s_p, 0.0)
    # pass 1: the same keys, at the same contact (-1: a new contact; -2: a reversal taken)
    for a in range(nk):
        j = sel[a]
        found = -1
        for i in range(m):
            if CI[i, CI_KEY] == keys[j, 0] and CI[i, CI_KEY + 1] == keys[j, 1] \
                    and CI[i, CI_KEY + 2] == keys[j, 2]:
                found = i
                break
        W[a, _W_FLIP] = 0.0
        if found >= 0 and not _ref_same_contact(C, X, t, found, keys[j, 0], cp, nrm, dsep, P, Pe, use_qe,
                                                W[a, _W_XP:_W_XP + 3], j):
            found = -1
        W[a, _W_FOUND] = found
        if found >= 0:
            W[found, _W_TAKEN] = 1.0
            dot = C[found, C_N] * nrm[j, 0] + C[found, C_N + 1] * nrm[j, 1] + C[found, C_N + 2] * nrm[j, 2]
            if dot < FLIP_DOT:
                if _ref_refuse_reversal(C, CI, t, found, keys[j, 0], cp, nrm, P, j):
                    W[a, _W_FLIP] = 1.0
                else:
                    W[a, _W_FOUND] = -2
    # pass 2: new keys at the feature of a contact that left (re-numbered, or reversed)
    n_rekey = 0
    for a in range(nk):
        if W[a, _W_FOUND] != -1.0:
            continue
        j = sel[a]
        k = keys[j, 0]
        xp = W[a, _W_XP:_W_XP + 3]
        _ref_feature_point(j, k, cp, nrm, dsep, P, Pe, use_qe, xp)
        # every contact not yet continued that sits at this feature; the largest |cos| wins, the
        # lowest index on a tie
        dots = [(i, _ref_same_feature(C, CI, X, t, i, k, xp, cp, nrm, j)) for i in range(m) if W[i, _W_TAKEN] == 0.0]
        dots = [(i, d) for i, d in dots if d != 0.0]
        if not dots:
            continue
        best, best_dot = max(dots, key=lambda c: (abs(c[1]), -c[0]))
        W[[a, best], [_W_FOUND, _W_TAKEN]] = (best, 1.0)
        if best_dot >= 0.0:
            n_rekey += 1
        elif _ref_refuse_reversal(C, CI, t, best, k, cp, nrm, P, j):
            W[a, _W_FLIP] = 1.0
        else:
            W[a, _W_FOUND] = -2
    # pass 3: the rule table, row by row (written as slices, not as the kernel's column loops:
    # the reference states the rules once more in its own form, with the same arithmetic)
    literal = policy == POLICY_PAPER_LITERAL
    matched = n_new = n_def = n_flip = n_flip_taken = 0
    for a in range(nk):
        j = sel[a]
        k = keys[j, 0]
        found = int(W[a, _W_FOUND])
        matched += found >= 0
        n_flip_taken += found == -2
        if found >= 0 and W[a, _W_FLIP] != 0.0:
            # refused for this update: the contact stays exactly as it was (key included)
            newF[a, :NCOLS_F] = C[found, :NCOLS_F]
            newI[a, :NCOLS_I] = CI[found, :NCOLS_I]
            newI[a, [CI_AGE, CI_FLIPS]] = CI[found, [CI_AGE, CI_FLIPS]] + 1
            n_flip += 1
            continue
        xp = W[a, _W_XP:_W_XP + 3]
        dj = _ref_feature_point(j, k, cp, nrm, dsep, P, Pe, use_qe, xp)
        # rendered separation: the real tool's, or the epsilon-inflated tool's read literally
        dr = dj - par[P_EPS] if literal else dj
        if found >= 0:
            # eq. 1/6 while apart or receding (d), eq. 5 (s_p, at most 0) while penetrating
            s_p = W[found, _W_SP]
            rigid = policy == POLICY_RIGID or dr > 0.0 or s_p < dr
            off = dr if rigid else min(s_p, 0.0)
            touch = not rigid and s_p > 0.0   # eq. 4: the proxy was apart, put touching
            newF[a, [C_S, C_SPREV]] = C[found, [C_S, C_SPREV]]
            newF[a, C_Z:C_Z + 3] = C[found, C_Z:C_Z + 3]
            newI[a, [CI_SLIP, CI_STATE, CI_AGE]] = CI[found, [CI_SLIP, CI_STATE, CI_AGE]] + np.array([0, 0, 1])
        else:
            # eq. 1/6 (d) for a new contact apart; eq. 4 (0) for one that arises penetrating
            n_new += 1
            rigid = policy == POLICY_RIGID or literal or dr > 0.0
            off = dr if rigid else 0.0
            touch = not rigid
            newF[a, [C_S, C_SPREV]] = np.inf  # has just arisen: the next step may be a collision
            newF[a, C_Z:C_Z + 3] = 0.0
            newI[a, [CI_SLIP, CI_STATE, CI_AGE]] = (0, CST_IMPENDING, 0)
        n_def += not rigid
        newI[a, CI_FLIPS] = 0
        newI[a, CI_KEY:CI_KEY + 3] = keys[j]
        newF[a, C_CP:C_CP + 3] = cp[j]
        newF[a, C_N:C_N + 3] = nrm[j]
        if planar:
            newF[a, [C_CP + 2, C_N + 2]] = 0.0
        newF[a, [C_D, C_VC, C_TU]] = (dsep[j], vc[j], t)
        newF[a, [C_FN, C_IMP, C_REC]] = 0.0
        newF[a, C_FT:C_FT + 3] = 0.0
        # the deformation to recover: known only in the engine frame
        newF[a, C_DEF] = off - dr if (off > dr and use_qe) else 0.0
        # the local point in the link frame: R^T (Xp + (off - s_w) n - c)
        w = xp + (off - dj) * newF[a, C_N:C_N + 3] - P[k, 9:12]
        newF[a, C_P:C_P + 3] = P[k, 0:3] * w[0] + P[k, 3:6] * w[1] + P[k, 6:9] * w[2]
        if planar:
            newF[a, C_P + 2] = 0.0
        # the proxy's normal speed at the point (link origin's velocity + w x r), less the constraint's
        omega, v = Vk[k, 0:3], Vk[k, 3:6]
        point_v = v + np.array([omega[1] * w[2], omega[2] * w[0], omega[0] * w[1]]) \
            - np.array([omega[2] * w[1], omega[0] * w[2], omega[1] * w[0]])
        vn = _sum3(newF[a, C_N:C_N + 3] * point_v) - vc[j]
        newF[a, C_VN] = vn
        if touch:
            # resting unless the proxy moves into it faster than the resting speed: then a collision
            newF[a, C_S] = np.inf if vn <= -par[P_REC_VN] else 0.0
            REF_TOUCHES["colliding" if vn <= -par[P_REC_VN] else "resting"] += 1
    C[:nk, :NCOLS_F] = newF[:nk, :NCOLS_F]
    CI[:nk, :NCOLS_I] = newI[:nk, :NCOLS_I]
    cnt[K_M] = nk
    for col, added in ((K_UPDATES, 1), (K_DROPPED, n_in - nk), (K_NEW, n_new), (K_DEFORMED, n_def),
                       (K_LEFT, m - matched), (K_FLIPS, n_flip), (K_FLIPS_TAKEN, n_flip_taken),
                       (K_REKEYED, n_rekey)):
        cnt[col] += added



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
        kept = []
        for i in range(m):
            key = [int(v) for v in CI[i, CI_KEY:CI_KEY + 3]]
            cp0, n0 = C[i, C_CP:C_CP + 3].copy(), C[i, C_N:C_N + 3].copy()
            what = rng.choice(["kept", "kept", "reversed", "renumbered", "renumbered", "renumbered-reversed",
                               "other-link", "twice", "gone"])
            cp, n = self._near(cp0, n0, rng.choice(offsets), rng.choice(tilts))
            if what == "kept":
                kept.append(len(rows))
                rows.append((key, cp, n))
            elif what == "reversed":
                kept.append(len(rows))
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
        if len(kept) > 1 and rng.random() < 0.4:
            # the keys of some kept contacts handed round (an engine numbering its contacts by
            # their order in its list): each key comes back at another contact's place
            turn = [kept[q] for q in rng.permutation(len(kept))[:int(rng.integers(2, len(kept) + 1))]]
            moved = [rows[q][0] for q in turn]
            for q, key in zip(turn, moved[1:] + moved[:1]):
                rows[q] = (key, rows[q][1], rows[q][2])
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


def _update(planar, arrays, keys, cp, nrm, dsep, vc, sel, nk, P, Pe, use_qe, Vk, fn):
    par, st, C, CI, cnt, X, W, newF, newI = arrays
    fn(planar, par, st, C, CI, cnt, X, W, keys, cp, nrm, dsep, vc, len(keys), nk, sel, newF, newI, P, Pe,
       use_qe, Vk)


def _bits(a):
    return a.view(np.int64) if a.dtype == np.float64 else a


@pytest.mark.parametrize("planar", [False, True], ids=["spatial", "planar"])
@pytest.mark.parametrize("use_qe", [0, 1], ids=["eq1", "engine-frame"])
def test_the_matching_gives_the_reference_contact_table(planar, use_qe):
    rng = np.random.default_rng(1400 + 2 * planar + use_qe)
    touches0 = dict(REF_TOUCHES)
    seen = dict(rekeyed=0, flips=0, flips_of_new_keys=0, kept=0, new=0, small_m=0, large_m=0, left=0,
                flips_taken=0, flips_refused_again=0, kept_key_elsewhere=0, touch_resting=0, touch_colliding=0)
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
                C[:m, C_VN] = rng.normal(size=m) * 0.05
                C[:m, C_SPREV] = rng.uniform(-2e-3, 2e-3, m)
                C[:m, C_Z:C_Z + 3] = rng.normal(size=(m, 3)) * 1e-4
                C[:m, C_REC] = np.where(rng.random(m) < 0.3, rng.uniform(0.0, 1e-3, m), 0.0)
                CI[:m, CI_SLIP] = rng.integers(0, 2, m)
                CI[:m, CI_STATE] = rng.integers(0, 4, m)
                CI[:m, CI_FLIPS] = np.where(rng.random(m) < 0.5, 0, rng.integers(0, FLIP_REFUSE_MAX + 2, m))
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
            # the links' angular and origin velocities (world); the resting speed, now and then 0
            Vk = rng.normal(size=(links, 6)) * rng.choice([0.0, 0.03, 0.3])
            par[P_REC_VN] = rng.choice([0.0, 0.03, 0.1])
            theirs = tuple(a.copy() for a in ours)
            before = cnt.copy()
            keys_before = {tuple(CI[i, :3]) for i in range(int(cnt[K_M]))}
            _update(planar, ours, keys, cp, nrm, dsep, vc, sel, nk, P, Pe, use_qe, Vk, _k.apply_update)
            _update(planar, theirs, keys, cp, nrm, dsep, vc, sel, nk, P, Pe, use_qe, Vk, reference_apply_update)
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
            seen["flips_taken"] += d[K_FLIPS_TAKEN]
            # contacts put touching by eq. 4: resting, or (approached fast) colliding
            seen["touch_resting"] = REF_TOUCHES["resting"] - touches0["resting"]
            seen["touch_colliding"] = REF_TOUCHES["colliding"] - touches0["colliding"]
            seen["flips_refused_again"] += int(np.sum(CI[:nk, CI_FLIPS] > 1))
            # a key kept from before that came back as a new contact (elsewhere, or a reversal taken)
            seen["kept_key_elsewhere"] += sum(tuple(CI[a, :3]) in keys_before and CI[a, CI_AGE] == 0
                                              for a in range(nk)) - d[K_FLIPS_TAKEN]
    # every case the matching distinguishes occurred
    assert all(v > 0 for v in seen.values()), " ".join(f"{k}={int(v)}" for k, v in seen.items())
