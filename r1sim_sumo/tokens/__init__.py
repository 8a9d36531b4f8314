"""Tokenizer: motion vocabulary (k-disk), rolling matching, map tokens, tokenized scene batches.

Time layout of a 91-state window at 10 Hz (state index 10 = current): token boundaries are the states
0, 5, 10, ..., 90, i.e. ``N_POSE = 19`` boundary poses and ``N_TOK = 18`` tokens. Token ``k`` moves an
agent from boundary pose ``k`` to pose ``k+1`` (0.5 s = 5 steps = 6 frames including both ends). Tokens
0 and 1 are history (states 0..10); tokens 2..17 (8 s) are the future; pose ``CURRENT_POSE = 2`` is "now".

See ``/work/notes/TOKENS_MODEL_SPEC.md`` (the interface with the policy model).
"""

STEPS_PER_TOKEN = 5  # [10 Hz steps per token] (0.5 s)
FRAMES_PER_TOKEN = STEPS_PER_TOKEN + 1  # frames of one token trajectory, both ends included
N_POSE = 19  # boundary poses in a 91-state window (states 0, 5, ..., 90)
N_TOK = 18  # tokens in a window
N_HIST_TOK = 2  # history tokens (states 0..10)
CURRENT_POSE = 2  # boundary pose index of the current state (state 10)
N_MAP_PTS = 11  # points per map token (5 m at 0.5 m spacing)

from r1sim_sumo.tokens.motion_vocab import (  # noqa: E402
    BOX_SIZE_M,
    MotionVocab,
    VocabBuildConfig,
    build_vocab,
    build_vocab_from_dataset,
    extract_segments,
    kdisk_cluster,
    reconstruction_report,
    synthetic_segments,
)
from r1sim_sumo.tokens.matching import (  # noqa: E402
    TokenizedAgents,
    advance_pose,
    match_agents,
    reconstruct_states,
)
from r1sim_sumo.tokens.map_tokens import MapTokens, tokenize_map  # noqa: E402
from r1sim_sumo.tokens.batch import (  # noqa: E402
    SceneBatch,
    TokenizedDataset,
    TokenizedScene,
    collate,
    crop_map,
    tokenize_scenario,
)

__all__ = [
    "STEPS_PER_TOKEN", "FRAMES_PER_TOKEN", "N_POSE", "N_TOK", "N_HIST_TOK", "CURRENT_POSE", "N_MAP_PTS",
    "BOX_SIZE_M", "MotionVocab", "VocabBuildConfig", "build_vocab", "build_vocab_from_dataset",
    "extract_segments", "kdisk_cluster", "reconstruction_report", "synthetic_segments",
    "TokenizedAgents", "advance_pose", "match_agents", "reconstruct_states",
    "MapTokens", "tokenize_map",
    "SceneBatch", "TokenizedDataset", "TokenizedScene", "collate", "crop_map", "tokenize_scenario",
]
