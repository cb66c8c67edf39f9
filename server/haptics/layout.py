"""Layout of the haptic stage's state and parameter vectors (float64, numba-friendly).

The stage's state is one float64 vector per session so that each tick is one numba call with
no Python objects inside; these names index it. Grid frame, mm, s, N.
"""

from __future__ import annotations

import numpy as np

# State (``new_state``).
S_PROXY = 0  # [0:3] proxy position, mm
S_PROXY_V = 3  # [3:6] proxy velocity, mm/s
S_FORCE = 6  # [6:9] the force sent last tick (what the device renders now), N
S_ENERGY = 9  # passivity observer: energy taken in from the device, N·mm (mJ)
S_PERIOD = 10  # smoothed packet interval (client clock), s; 0 = none seen yet
S_READY = 11  # 1 once the proxy has been placed
S_K = 12  # coupling stiffness in use, N/mm
S_B = 13  # coupling damping in use, N·s/mm
S_A = 14  # the implicit step's diagonal m/dt + k·dt + b, N·s/mm
S_DT = 15  # this tick's interval, s
S_FREE = 16  # [16:19] the proxy's velocity without bone forces (the model's feed), mm/s
S_DEVICE = 19  # [19:22] device position this tick, mm
S_DEVICE_V = 22  # [22:25] device velocity this tick, mm/s
S_DEVICE_PREV = 25  # [25:28] device position when the last force was sent, mm
S_HAVE_PREV = 28  # 1 if S_DEVICE_PREV is valid (the observer can integrate)
S_TRIAL = 29  # [29:32] the feed the bone engine evaluates: the predicted proxy velocity, mm/s
S_CUT = 32  # 1 if the bone cut the proxy last tick (the next trial is then its velocity)
N_STATE = 33

# Parameters (``params_vector``).
P_MAX_FORCE = 0  # N
P_MAX_STIFFNESS = 1  # N/mm
P_MAX_DAMPING = 2  # N·s/mm
P_MAX_SLEW = 3  # N/s
P_RATED_PERIOD = 4  # s
P_PROXY_MASS = 5  # N·s²/mm (kg / 1000)
P_SKIN = 6  # contact depth left unresolved, mm
P_DEPTH_FLOOR = 7  # smallest depth the cut's depth term divides by, mm
P_MAX_SPEED = 8  # a proxy faster than this is re-placed at the device, mm/s
P_PUSH_OUT = 9  # fraction of a penetration resolved per tick (0, 1]
P_PERIOD_GAIN = 10  # smoothing gain of the packet interval
P_TRIAL_RELAX = 11  # how far the evaluated feed moves toward each tick's guess, (0, 1]
P_SHAFT_RADIUS = 12  # the shaft's radius, mm (0: unknown; set by the session from its engine)
N_PARAMS = 13

# Result of a coupled tick (``HapticOutput.finish``).
R_FORCE = 0  # [0:3] force for the hand (device), N
R_CUT_SCALE = 3  # λ = |cutting force met| / |trial cutting force|
R_PC_DAMPING = 4  # passivity controller's damping this tick, N·s/mm
R_K = 5  # coupling stiffness, N/mm
R_B = 6  # coupling damping, N·s/mm
R_PROXY = 7  # [7:10] proxy position after the tick, mm
R_PROXY_V = 10  # [10:13] proxy velocity, mm/s
R_ENERGY = 13  # observer energy, mJ
R_CUT = 14  # [14:17] the cutting force the proxy met, N
R_COMPONENTS = 17  # [17:20] its feed, lateral, normal components (model.md), N
N_RESULT = 20


def new_state() -> np.ndarray:
    """A fresh state vector, float64 (N_STATE,)."""
    return np.zeros(N_STATE, dtype=np.float64)
