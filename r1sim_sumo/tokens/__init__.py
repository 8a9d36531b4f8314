"""Tokenizer: motion vocabulary (k-disk), rolling matching, map tokens, tokenized scene batches.

Time layout of a 91-state window at 10 Hz (state index 10 = current): token boundaries are the states
0, 5, 10, ..., 90, i.e. ``N_POSE = 19`` boundary poses and ``N_TOK = 18`` tokens. Token ``k`` moves an
agent from boundary pose ``k`` to pose ``k+1`` (0.5 s = 5 steps = 6 frames including both ends). Tokens
0 and 1 are history (states 0..10); tokens 2..17 (8 s) are the future; pose ``CURRENT_POSE = 2`` is "now".

See ``/work/notes/TOKENS_MODEL_SPEC.md`` (the interface with the policy model).
"""

from r1sim_sumo.tokens.batch import (
    SceneBatch,
    TokenizedDataset,
    TokenizedScene,
    collate,
    crop_map,
    tokenize_scenario,
)
from r1sim_sumo.tokens.constants import (
    CURRENT_POSE,
    FRAMES_PER_TOKEN,
    N_HIST_TOK,
    N_MAP_PTS,
    N_POSE,
    N_TOK,
    N_WINDOW,
    STEPS_PER_TOKEN,
)
from r1sim_sumo.tokens.map_tokens import MapTokens, tokenize_map
from r1sim_sumo.tokens.matching import TokenizedAgents, advance_pose, match_agents, reconstruct_states
from r1sim_sumo.tokens.motion_vocab import (
    BOX_SIZE_M,
    MotionVocab,
    VocabBuildConfig,
    build_vocab,
    extract_segments,
    kdisk_cluster,
    synthetic_segments,
)
from r1sim_sumo.tokens.vocab_build import build_vocab_from_dataset, reconstruction_report

__all__ = [
    "STEPS_PER_TOKEN", "FRAMES_PER_TOKEN", "N_POSE", "N_TOK", "N_HIST_TOK", "CURRENT_POSE", "N_MAP_PTS", "N_WINDOW",
    "BOX_SIZE_M", "MotionVocab", "VocabBuildConfig", "build_vocab", "build_vocab_from_dataset",
    "extract_segments", "kdisk_cluster", "reconstruction_report", "synthetic_segments",
    "TokenizedAgents", "advance_pose", "match_agents", "reconstruct_states",
    "MapTokens", "tokenize_map",
    "SceneBatch", "TokenizedDataset", "TokenizedScene", "collate", "crop_map", "tokenize_scenario",
]
