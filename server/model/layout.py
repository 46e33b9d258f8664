"""Array layouts shared by the numba kernels, the numpy reference and the thin model class.

Everything the haptic step touches lives in a handful of preallocated arrays whose columns are
named here, so kernels index by constant and no Python object is touched per step.

Frames: "world" is the environment's frame (the engine's). "body" is the proxy's own frame (its
centre of mass, rotated with it); the paper's proxy-frame contact point p~ is stored in body
coordinates. Units are SI throughout (m, kg, s, N, N m, N s).
"""
from __future__ import annotations

# --- tool kinds -------------------------------------------------------------------------------
TOOL_1DOF = 0
TOOL_PLANAR = 1
TOOL_SPATIAL = 2
TOOL_LINKAGE = 3        # a kinematic tree held by one link; planar or spatial: see LM_PLANAR
TOOL_KIND_NAMES = {"1dof": TOOL_1DOF, "planar": TOOL_PLANAR, "spatial": TOOL_SPATIAL, "linkage": TOOL_LINKAGE}
#: (configuration-space dimension d, hand-wrench dimension h, number of position coordinates nq)
#: of the rigid kinds; a linkage's follow from its links (``linkage_dims``).
TOOL_DIMS = {TOOL_1DOF: (1, 1, 1), TOOL_PLANAR: (3, 3, 3), TOOL_SPATIAL: (6, 6, 7)}
#: Largest configuration space the generic kernels size their workspace for: a planar linkage
#: has d = 3 + joints (<= 9 joints), a spatial one d = 6 + joints (<= 6 joints).
MAX_DOF = 12

# --- update policies --------------------------------------------------------------------------
POLICY_RIGID = 0        # eq. 1 at every update: no deformation (the paper's Fig. 6a / IR baseline)
POLICY_DEFORM = 1       # eqs. 4/5/6 rule table of the notes (LM0 when the engine sends epsilon = 0)
#: The three selectable policies: "rigid" (eq. 1, no deformation), "lm0" (deformation with active
#: geometry only: the engine is granted epsilon = 0) and "lm" (deformation with epsilon-active
#: geometry, any epsilon >= 0). One rule set serves both "lm0" and "lm": the engine folds epsilon
#: into the separation it reports (d = s_eps + epsilon). "deformation" is an alias of "lm".
POLICY_NAMES = {"rigid": POLICY_RIGID, "lm0": POLICY_DEFORM, "lm": POLICY_DEFORM, "deformation": POLICY_DEFORM}
#: The paper's eq. 6 read literally, for reproducing its Fig. 14 numbers only (not in
#: POLICY_NAMES: never a server setting; ``LocalModel.read_eq6_literally``): the rendered
#: separation is ``(s - epsilon)`` with ``s`` the reported real-tool separation, i.e. the
#: epsilon-inflated tool is rendered, and new contacts too are placed by eq. 6 (a late one keeps
#: its penetration: no eq. 4); existing contacts follow the same case table on ``s - epsilon``.
POLICY_PAPER_LITERAL = 2

# --- local contact states (section IV-A) ------------------------------------------------------
CST_IMPENDING = 0
CST_COLLIDING = 1
CST_PENETRATING = 2
CST_SEPARATING = 3
CONTACT_STATE_NAMES = ("impending", "colliding", "penetrating", "separating")

# --- proxy states -----------------------------------------------------------------------------
PS_FREE = 0
PS_COLLIDING = 1
PS_RESTING = 2
PROXY_STATE_NAMES = ("free", "colliding", "resting")

# --- contact store, float64 columns (capacity rows; the first `m` rows are live) -------------
C_CP = 0            # 0..2 constraint position c_p at the update, world, m
C_N = 3             # 3..5 constraint normal n, unit, world, environment -> tool
C_D = 6             # real-tool separation d reported by the engine, m (positive apart)
C_VC = 7            # constraint normal velocity v_constr = n . v(c_p), m/s (eq. 2)
C_TU = 8            # model time of the update that set this constraint, s
C_P = 9             # 9..11 local contact point p~, body frame of its link, m (rigid: the COM
                    # frame; linkage: the link's own frame, origin at its joint)
C_S = 12            # separation s_t at this step (eq. 3), m
C_SPREV = 13        # separation s_{t-1}; +inf for a contact that has just arisen
C_VN = 14           # proxy normal velocity relative to the (moving) constraint, m/s
C_FN = 15           # penalty normal force this step, N (>= 0: never pulling)
C_Z = 16            # 16..18 friction bristle (stick spring elongation), world, m
C_FT = 19           # 19..21 friction force on the proxy, world, N
C_IMP = 22          # collision impulse at this contact this step, N s (eq. 11)
C_DEF = 23          # deformation still to recover, m (>= 0): how far the update rules (eqs. 4/5)
                    # put the local contact point out along n from the true feature, and how far
                    # the passivity layer held the constraint's advance back (``_hold``)
C_REC = 24          # deformation recovered since the update, less the advance held back, m: the
                    # proxy's separation at this contact is eq. 3 minus C_REC (the constraint moved
                    # towards the tool by it; negative while the layer holds the constraint back)
NCOLS_F = 25

# --- contact store, int64 columns -------------------------------------------------------------
CI_KEY = 0          # 0..2 stable key: (tool link, environment body, feature)
CI_STATE = 3        # CS_* of this step
CI_SLIP = 4         # 1 while the friction bristle slips (kinetic), 0 while it sticks
CI_AGE = 5          # number of model updates this contact has survived
CI_FLIPS = 6        # consecutive updates whose reversed normal for this contact was refused (FLIP_*)
NCOLS_I = 7

# --- parameters (float64) ---------------------------------------------------------------------
P_DT = 0            # haptic step, s
P_K = 1             # local contact stiffness k_lc, N/m
P_B = 2             # local contact damping b_lc, N s/m
P_E = 3             # restitution e in [0, 1]
P_MUS = 4           # static friction coefficient
P_MUK = 5           # kinetic friction coefficient
P_KT = 6            # tangential (bristle) stiffness, N/m
P_BT = 7            # tangential damping while sticking, N s/m
P_MASS = 8          # tool mass, kg
P_INERTIA = 9       # 9..17 body-frame inertia about the COM, row-major 3x3, kg m^2
P_GRAV = 18         # 18..20 gravity, world, m/s^2
P_AXIS = 21         # 21..23 1-DOF translation axis, unit, world
P_ORIGIN = 24       # 24..26 1-DOF COM position at q = 0, world, m
P_HAND = 27         # 27..29 hand (grasp) point, body frame, m
P_POLICY = 30       # POLICY_* (stored as float)
P_EPS = 31          # epsilon granted to the engine, m (metadata: the engine applies it)
P_REC_V = 32        # deformation recovery: largest speed at which a contact's constraint moves back
                    # towards the true geometry, m/s (0: no recovery, the paper's eq. 5 for ever)
P_REC_FRATE = 33    # deformation recovery: largest rate of change of the summed penalty force it
                    # causes, N/s (the speed per contact is capped at P_REC_FRATE / (k * recovering))
P_REC_TAU = 34      # deformation recovery: the last part is recovered exponentially with this time
                    # constant, s (speed <= remaining / tau: the proxy lands on the surface gently)
P_REC_AGE = 35      # deformation recovery: only contacts that survived at least this many model
                    # updates are recovered (stored as float)
P_REC_VN = 36       # deformation recovery: only while the proxy's normal speed at the contact is at
                    # most this, m/s (a resting contact, not an impact or a shaken one; 0: no gate)
P_CPL_KT = 37       # the controller's coupling spring between the device and the proxy's hand point,
                    # translational, N/m (the controller writes it every step it drives the proxy;
                    # 0: no coupling, as with direct coupling or a bare model)
P_CPL_BT = 38       # ... its translational damper, N s/m
P_CPL_KR = 39       # ... its rotational spring, N m/rad
P_CPL_BR = 40       # ... its rotational damper, N m s/rad
P_INTEG = 41        # INTEG_*: how the step treats the stiff and damped terms (stored as float)
P_REC_CUT = 42      # the share the passivity layer takes away, 0..1, of the model's two active
                    # elements: the deformation recovery's P_REC_V, and the advance into the tool
                    # (v_constr > 0) of a constraint the proxy touches (set-position modulation: the
                    # held part becomes deformation, recovered later). The controller writes its
                    # last limiting factor every step it drives the proxy: both slow as the layer's
                    # tank runs short and stop when it is empty; 0: a bare model, or the layer off
NPAR = 43

# --- integrators (P_INTEG) --------------------------------------------------------------------
#: Semi-implicit Euler with every force explicit (the paper's step): M dv = dt F(q, qd). Stable
#: only while k dt^2 / m and b dt / m stay small for every spring-damper on every coordinate.
INTEG_EXPLICIT = 0
#: The spring-dampers (the device coupling at the hand point, penalty contacts along their
#: normals, sticking friction) linearised implicitly: (M + dt B + dt^2 K) dv = dt F(q, qd).
INTEG_IMPLICIT = 1
INTEGRATOR_NAMES = {"explicit": INTEG_EXPLICIT, "implicit": INTEG_IMPLICIT}

# --- state (float64) --------------------------------------------------------------------------
S_T = 0             # model time, s
S_Q = 1             # 1..7 configuration q (1dof: x; planar: x, y, theta; spatial: x, y, z, qw, qx, qy, qz)
S_QD = 8            # 8..19 configuration velocity qd (spatial: v world, omega world), up to MAX_DOF
S_FH = 20           # 20..25 hand wrench applied to the proxy, world, at the hand point (input)
S_FENV = 26         # 26..31 environment wrench rendered to the hand, eq. 8 + eq. 12 (output)
S_FIMP = 32         # 32..37 impulsive part of S_FENV (eq. 12)
S_FPEN = 38         # 38..43 penalty + friction part of S_FENV (eq. 8)
S_KE = 44           # proxy kinetic energy after the step, J
S_KE_PRE = 45       # kinetic energy before this step's collision impulse, J
S_KE_POST = 46      # kinetic energy right after it, J
S_GIMP = 47         # 47..58 generalized impulse Jc^T p of this step, config space
S_LQ = 59           # 59..71 linkage configuration: the root link frame's pose (planar: x, y,
                    # theta; spatial: x, y, z, qw, qx, qy, qz; world) then one q per joint in link
                    # order (rad or m). Rigid tools keep q at S_Q; qd is at S_QD for both (root:
                    # velocity of the root frame's origin and angular velocity, world; then joints)
S_EREC = 72         # energy the deformation recovery gave the proxy since reset, J (sum of the
                    # normal force times the recovered distance: the moving constraint's work)
S_RECF = 73         # penalty force the recovery added at this step at a fixed pose, k x sum of the
                    # distances recovered, N (what the recovery's force-rate bound limits)
S_FCPL = 74         # 74..79 the implicit step's change of the coupling wrench over the step, hand space
                    # (as S_FH): -(B + dt K) J_h dv, so the coupling wrench the proxy felt is S_FH's
                    # coupling part plus this; the controller renders the same to the device (0 with
                    # the explicit step)
S_QDP = 80          # 80..91 the velocity qd at the start of the previous step (the divergence watch
                    # compares the starts of consecutive steps: with direct coupling the device sets it)
NSTATE = 92

# --- counters (int64) -------------------------------------------------------------------------
K_M = 0             # live contacts
K_PROXY = 1         # PS_* of the last step
K_STEPS = 2
K_UPDATES = 3
K_DROPPED = 4       # contacts dropped over capacity (smallest separations kept), cumulative
K_COLLISIONS = 5    # steps in which an impulse was applied
K_NONFINITE = 6     # steps whose result was not finite: state kept, zero wrench rendered
K_NEW = 7           # contacts that entered the model, cumulative
K_DEFORMED = 8      # update rule applications that deformed the proxy (eq. 4 or 5), cumulative
K_LEFT = 9          # contacts that left the model at an update, cumulative
K_N_IMPENDING = 10  # counts of this step, by state
K_N_COLLIDING = 11
K_N_PENETRATING = 12
K_N_SEPARATING = 13
K_RANK = 14         # rank of the collision constraint set at the last impulse
K_SLIPPING = 15     # contacts slipping this step
K_FLIPS = 16        # reported normals refused because they reversed an existing contact's (cumulative)
K_REKEYED = 17      # new keys that took over a contact that left at the same feature (cumulative)
K_RECOVERING = 18   # contacts whose deformation was being recovered this step
K_FLIPS_TAKEN = 19  # reversed normals taken, not refused: the held one had the tool behind its surface, or the
                    # reversal outlasted the refusals (cumulative; the held contact left, the reported one is new)
K_OSC_RUN = 20      # consecutive steps at whose start a coordinate of the proxy's velocity had reversed
                    # since the previous step's start without decaying, above DIVERGE_SPEED (a
                    # numerical instability's signature)
K_DIVERGED = 21     # times K_OSC_RUN reached DIVERGE_STEPS (cumulative): the proxy's integration diverged
K_HELD = 22        # contacts whose constraint's advance into the tool the passivity layer held back
                    # this step (set-position modulation: ``P_REC_CUT`` of v_constr, while touching)
NCOUNT = 23

# --- linkages ---------------------------------------------------------------------------------
JT_ROOT = 0         # joint types, the protocol's JointType values
JT_REVOLUTE = 1
JT_PRISMATIC = 2
# meta (int64[NLM])
LM_NLINKS = 0       # number of links L (link 0 is the root: the floating base)
LM_PLANAR = 1       # 1: planar (x-y plane, rotation about +z), 0: spatial
LM_HELD = 2         # the link the hand holds (at its frame origin)
LM_D = 3            # configuration-space dimension d = LM_R + L - 1
LM_H = 4            # hand-space dimension h (3 planar, 6 spatial)
LM_R = 5            # root velocity coordinates (3 planar, 6 spatial)
LM_NQR = 6          # root position coordinates (3 planar, 7 spatial)
LM_COR = 7          # 1: velocity-product (Coriolis, centripetal, gyroscopic) terms included;
                    # 0: neglected, as the paper's eq. 7 writes it
NLM = 8
# per-link constants (float64[L, NLK]), link frame unless noted
LK_MASS = 0         # kg
LK_COM = 1          # 1..3 centre of mass, link frame, m
LK_I = 4            # 4..12 inertia about the COM, link frame, row-major 3x3, kg m^2
LK_AXIS = 13        # 13..15 unit joint axis, link frame
LK_OP = 16          # 16..18 joint origin: this link's frame origin in the parent's frame at q = 0, m
LK_OR = 19          # 19..27 joint origin rotation (this link's frame in the parent's), row-major
NLK = 28
# per-link integers (int64[L, NLI])
LI_PARENT = 0       # parent link (-1 for the root)
LI_TYPE = 1         # JT_*
LI_NCHAIN = 2       # number of configuration columns that move this link (root + ancestor joints)
LI_CHAIN = 3        # 3..3+MAX_DOF-1 those columns, ascending
NLI = 3 + MAX_DOF
# per-link work rows (float64[L, NLW]); the first 12 columns are also the layout of the link-pose
# rows the update rule table reads (rigid tools pass one such row)
LW_R = 0            # 0..8 link frame rotation, link -> world, row-major
LW_P = 9            # 9..11 link frame origin, world, m
LW_A = 12           # 12..14 joint axis, world
LW_C = 15           # 15..17 centre of mass, world, m
LW_IW = 18          # 18..26 inertia about the COM, world, row-major
LW_JV = 27          # 27.. velocity of the COM per chain column (3 x MAX_DOF, column-major by chain slot)
LW_JW = LW_JV + 3 * MAX_DOF     # angular velocity per chain column (3 x MAX_DOF)
LW_W = LW_JW + 3 * MAX_DOF      # angular velocity of the link, world, rad/s
LW_V = LW_W + 3     # velocity of the link frame origin, world, m/s
LW_AL = LW_V + 3    # velocity-product part of the link's angular acceleration (qdd = 0), rad/s^2
LW_AC = LW_AL + 3   # velocity-product part of the frame origin's acceleration (qdd = 0), m/s^2
NLW = LW_AC + 3

# --- step / update return codes (0 = ok); the class turns them into ValueError ----------------
E_OK = 0
E_HAND_NONFINITE = 1
E_CONTACT_NONFINITE = 2
E_NORMAL_NOT_UNIT = 3
E_NORMAL_OUT_OF_PLANE = 4
E_LINK_OUT_OF_RANGE = 5
E_TOO_MANY = 6
E_DUPLICATE_KEY = 7

ERROR_FIELDS = {
    E_HAND_NONFINITE: ("hand_wrench", "must be finite"),
    E_CONTACT_NONFINITE: ("contacts", "position_m, normal, separation_m and v_constr_m_per_s must be finite"),
    E_NORMAL_NOT_UNIT: ("normal", "must be unit length within 1e-6"),
    E_NORMAL_OUT_OF_PLANE: ("normal", "must lie in the x-y plane (|n_z| <= 1e-6) for a planar tool"),
    E_LINK_OUT_OF_RANGE: ("keys", "tool link (column 0) out of range for this tool"),
    E_TOO_MANY: ("contacts", "more contacts than the update buffer holds"),
    E_DUPLICATE_KEY: ("keys", "duplicate contact key in one update"),
}

#: Unit-length tolerance on normals (the issue's 1e-6).
UNIT_TOL = 1e-6
#: A local contact counts as touching when its separation is at most this (m). The update rules
#: put deformed contacts at exactly s = 0, which rounding turns into +-1e-19; without a margin
#: the contact state there would flip on the last bit.
TOUCH_TOL_M = 1e-12
#: An existing key whose reported normal turned by more than 90 deg (n_new . n_old below this)
#: reversed: an edge-edge normal without a fixed sign, or a feature seen from the wrong side. The
#: update keeps that contact as it was (its previous geometry and state) instead of pushing the
#: proxy the other way; counted in K_FLIPS. Which of the two is wrong is told by the tool: a normal
#: points from the environment towards the tool, so the contact's link (its frame origin, a
#: rigid tool's centre of mass) lies in front of the true constraint plane. A reversal that puts
#: the link in front of its plane while the held normal has it behind (by more than
#: 2 REKEY_DISTANCE_M between the two) corrects the held one: taken at once (K_FLIPS_TAKEN; the
#: contact born with a reversed normal would otherwise refuse the true one for ever). One that
#: puts the link behind is refused, up to FLIP_REFUSE_MAX updates in a row (5-10 s at 30-60 Hz: a
#: backstop for a tool the test misjudges, a hook whose link origin lies behind the true plane);
#: one the link cannot tell (it lies on the plane) once. A reversal reported after that is taken:
#: nothing is refused for ever.
FLIP_DOT = 0.0
FLIP_REFUSE_MAX = 300
#: A new key is the same contact under a new number (engines re-number feature ids) when a
#: contact that left in the same update has a normal within 5 deg of it, and the proxy's point
#: of that contact lies within REKEY_DISTANCE_M of the new feature both along the surface and
#: across it (the two constraint planes coincide): it inherits that contact's state (its
#: penetration, friction, age), so the force neither drops nor overshoots; counted in K_REKEYED.
#: Reported in reverse (n_new . n_old below -REKEY_COS) at the same point, it is a flip: the old
#: contact is kept as it was.
REKEY_COS = 0.9961946980917455   # cos(5 deg)
#: A coordinate of the proxy's velocity that reverses from one step to the next without decaying
#: (by less than DIVERGE_DECAY: |qd_new| >= (1 - DIVERGE_DECAY) |qd_old|), faster than
#: DIVERGE_SPEED (m/s or rad/s), oscillates at the haptic rate's Nyquist frequency: no motion
#: of a physical tool does that, an unstable step does (an explicit damper with b dt / m > 2
#: flips the sign each step and grows; one-sided contacts can hold such a flip at a constant
#: size, give or take rounding). DIVERGE_STEPS such steps in a row: the proxy's integration
#: diverged (K_OSC_RUN; K_DIVERGED counts the times, and stays non-zero for the model's life).
DIVERGE_SPEED = 1e-3
DIVERGE_DECAY = 0.01
DIVERGE_STEPS = 8
REKEY_DISTANCE_M = 0.002
#: A kept key continues its contact only at that contact: the two constraint planes within
#: REKEY_DISTANCE_M of each other, and the reported feature along the surface within
#: REKEY_DISTANCE_M + KEY_SLIDE_FACTOR x how far the proxy's point of the contact now lies from
#: the old constraint point along the surface, on the tool's side (the proxy's point) or on the
#: environment's (the constraint point): a vertex sliding on a face keeps the first, a face
#: sliding over a vertex the second, a crossing edge moves both. A key that comes back elsewhere
#: (an engine numbering contacts by their order in its list, a reused feature id) is another
#: contact: the old one leaves (or continues under its own new key), the reported one is new. So
#: a contact that arrived deep is never taken for one that rested elsewhere, with its
#: penetration, its age (a recovery would start at once) and its friction.
KEY_SLIDE_FACTOR = 2.0
