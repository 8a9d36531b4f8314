"""Time layout of tokenized windows (see the package docstring of :mod:`r1sim_sumo.tokens`).

The one definition of these facts: the 10 Hz step itself is :data:`r1sim_sumo.scenario.DT_S` (0.1 s), the
SUMO step length every run uses (:mod:`r1sim_sumo.sumo_launch`).
"""

from r1sim_sumo.scenario import CURRENT_INDEX, DT_S, N_WINDOW_10HZ

STEPS_PER_TOKEN = 5  # [10 Hz steps per token] (0.5 s)
TOKEN_DT_S = STEPS_PER_TOKEN * DT_S  # [s] one token = one policy decision (0.5 s)
FRAMES_PER_TOKEN = STEPS_PER_TOKEN + 1  # frames of one token trajectory, both ends included
N_WINDOW = N_WINDOW_10HZ  # [10 Hz states] 91 = 11 history + 80 future
N_POSE = N_WINDOW // STEPS_PER_TOKEN + 1  # 19 boundary poses in a 91-state window (states 0, 5, ..., 90)
N_TOK = N_POSE - 1  # 18 tokens in a window
CURRENT_POSE = CURRENT_INDEX // STEPS_PER_TOKEN  # 2: boundary pose index of the current state (state 10)
N_HIST_TOK = CURRENT_POSE  # 2 history tokens (states 0..10)
N_MAP_PTS = 11  # points per map token (5 m at 0.5 m spacing)
