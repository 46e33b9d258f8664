"""Array layouts shared by the simulated-device kernels (``dynamics``) and the hand kernels
(``hands``): index constants only, so both kernel modules compile against the same numbers.

Every array is float64 unless said otherwise and is owned by a thin Python class
(:class:`~hapticproxy.server.devices.sim.SimDevice`); the kernels never allocate.

numba freezes these numbers into the cached machine code of the kernels that use them, and its
cache only notices changes to the kernel's own source file: after changing a number here, delete
``server/devices/__pycache__`` (or touch ``dynamics.py`` and ``hands.py``).
"""
from __future__ import annotations

from .base import DEV_NSTATE, DS_BUTTONS, DS_GRIPPER, DS_HAND, DS_POSE, DS_TIME, DS_TWIST

KIND_1DOF = 0
KIND_PLANAR = 1
KIND_SPATIAL = 2
KIND_IDS = {"1dof": KIND_1DOF, "planar": KIND_PLANAR, "spatial": KIND_SPATIAL}

# -- device parameters (float64[NPAR]) ---------------------------------------------------------
DP_KIND = 0        # KIND_*
DP_DT = 1          # haptic period [s]
DP_MASS = 2        # device mass at the handle [kg] (without the hand)
DP_B = 3           # translational viscous damping [N s/m]
DP_BR = 4          # rotational viscous damping [N m s/rad]
DP_IZZ = 5         # planar: I_zz [kg m^2]
DP_IB = 6          # 6..14 spatial: inertia about the handle, body frame, row-major [kg m^2]
DP_AXIS = 15       # 15..17 1dof: unit axis, world
DP_ORIGIN = 18     # 18..20 1dof: handle position at s = 0, world [m]
DP_LO = 21         # 21..23 workspace minimum, world [m]
DP_HI = 24         # 24..26 workspace maximum, world [m]
DP_SLO = 27        # 1dof: travel along the axis, minimum [m]
DP_SHI = 28        # 1dof: travel along the axis, maximum [m]
DP_ROTLIM = 29     # rotation limit [rad] (0: none); planar |theta|, spatial |rotation vector|
DP_KS = 30         # end-stop stiffness [N/m]
DP_BS = 31         # end-stop damping [N s/m]
DP_KSR = 32        # rotational end-stop stiffness [N m/rad]
DP_BSR = 33        # rotational end-stop damping [N m s/rad]
DP_FMAX = 34       # force cap per axis [N]
DP_TMAX = 35       # torque cap per axis [N m]
DP_VMAX = 36       # speed the hardware is rated for [m/s] (over-speed steps are counted)
DP_WMAX = 37       # angular speed the hardware is rated for [rad/s]
NPAR = 40

# -- device state (float64[NST]); the first DEV_NSTATE columns are the state row of base.py ----
DST_POSE = DS_POSE     # 0..6
DST_TWIST = DS_TWIST   # 7..12
DST_HAND = DS_HAND     # 13..18 hand wrench over the last step (ideal force sensor)
DST_TIME = DS_TIME     # 19 device clock [s]
DST_BUTTONS = DS_BUTTONS  # 20 the hand's button script (NaN: no buttons)
DST_GRIP = DS_GRIPPER  # 21..22 the hand's gripper script: angle [rad], rate [rad/s] (NaN: no gripper)
DST_S = 23             # 1dof: position along the axis [m]
DST_SD = 24            # 1dof: velocity along the axis [m/s]
DST_TH = 25            # planar: theta [rad], not wrapped
DST_CMD = 26           # 26..31 wrench rendered in the last step (masked, capped), world
DST_STOP = 32          # 32..37 end-stop wrench of the last step, world
NST = 39
assert DST_S >= DEV_NSTATE

# -- control words (int64[NCTL]) ----------------------------------------------------------------
DC_ENABLED = 0     # 1: output armed
DC_FAULT = 1       # latched DEV_FAULT_* code
DC_LAST_NS = 2     # clock of the last write (or of enable) [ns]
DC_WD_NS = 3       # watchdog [ns] (0: none)
NCTL = 4

# -- counters (int64[NCNT]) ---------------------------------------------------------------------
DK_STEPS = 0           # dynamics steps (one per write)
DK_SAT_WRITES = 1      # writes with at least one capped component
DK_SAT_COMPONENTS = 2  # capped components, summed over writes
DK_NONFINITE = 3       # refused non-finite commands
DK_WATCHDOG = 4        # watchdog trips
DK_ZEROED = 5          # writes rendered as zero (disabled or faulted)
DK_ENDSTOP = 6         # steps with an end-stop engaged
DK_OVERSPEED = 7       # steps faster than max_speed / max_angular_speed
NCNT = 8
COUNTER_NAMES = ("steps", "saturated_writes", "saturated_components", "nonfinite_refused",
                 "watchdog_trips", "zeroed_writes", "endstop_steps", "overspeed_steps")

# -- hand output (float64[NHO]): what the hand wants this step, filled by hands.hand_eval ------
HO_W = 0      # 0..5 explicit wrench (scripted hands), world, at the handle
HO_XT = 6     # 6..11 impedance target: x y z [m], rotation vector rx ry rz [rad] (planar: rz = theta)
HO_VT = 12    # 12..17 impedance target twist [m/s, rad/s]
HO_K = 18     # grip stiffness [N/m]
HO_B = 19     # grip damping [N s/m]
HO_KR = 20    # rotational grip stiffness [N m/rad]
HO_BR = 21    # rotational grip damping [N m s/rad]
HO_M = 22     # hand mass moving with the handle [kg]
HO_I = 23     # hand rotational inertia moving with the handle (isotropic) [kg m^2]
NHO = 24
