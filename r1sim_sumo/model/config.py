"""Typed configuration of the traffic policy (:class:`PolicyConfig`) and its size presets.

Presets (parameter counts with the default vocabulary 2048 / 512 / 512):
``nano`` (~1.1M, the shipped default) and ``tiny`` (~6M, SMART-tiny-like). YAML overrides live in
``configs/model_<preset>.yaml``; an unknown key is an error that names it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from r1sim_sumo.config import ConfigError
from r1sim_sumo.config import from_dict as _from_dict


@dataclass
class PolicyConfig:
    """Sizes, neighbourhoods and regularisation of :class:`r1sim_sumo.model.TrafficPolicy`."""

    hidden_dim: int = 64
    """Width D of every token feature."""
    num_heads: int = 4
    """Attention heads (hidden_dim must be divisible by it)."""
    ffn_mult: int = 4
    """Feed-forward width = ffn_mult * hidden_dim."""
    map_layers: int = 2
    """Map-to-map self-attention layers (run once per scene)."""
    agent_layers: int = 4
    """Agent layers, each = temporal -> map-to-agent -> agent-to-agent attention."""
    vocab_sizes: tuple[int, int, int] = (2048, 512, 512)
    """Motion-token vocabulary sizes per agent type (vehicle, cyclist, pedestrian)."""
    map_radius_m: float = 10.0
    """Map-to-map neighbour radius [m]."""
    map_k: int = 16
    """At most this many nearest map tokens per map token."""
    map_agent_radius_m: float = 30.0
    """Map-to-agent neighbour radius [m] (agent pose to map-segment centre)."""
    map_agent_k: int = 16
    """At most this many nearest map tokens per agent and step."""
    agent_radius_m: float = 60.0
    """Agent-to-agent neighbour radius [m] at the same step."""
    agent_k: int = 16
    """At most this many nearest other agents per agent and step."""
    temporal_span: int = 6
    """Temporal attention window in token steps, the query step included (6 = the last 3 s)."""
    fourier_bands: int = 8
    """Learned frequencies per continuous input of a Fourier embedding."""
    dropout: float = 0.1
    """Dropout on attention outputs and feed-forward blocks (training only)."""
    num_agent_types: int = 3
    """Agent types (vehicle, cyclist, pedestrian)."""
    num_map_kinds: int = 2
    """Map token kinds the model tells apart: 2 = lane centre, road edge; 3 adds the lanes that end beside a lane
    that goes on (``tokens.map_tokens.ENDING_LANE``; with 2 they read as lane centres)."""
    num_tl_states: int = 4
    """Traffic-light states (none, green, yellow, red)."""
    desired_speed_input: bool = False
    """Each agent's desired (free-road) speed [m/s] is an input, embedded with its type and size
    (``SceneBatch.agent_desired_speed``; NaN = unknown). Older checkpoints have it off."""
    speed_gap_input: bool = False
    """Every node also gets its desired speed minus the mean speed of its previous token [m/s] (needs
    ``desired_speed_input``; no contribution where either is unknown): how far below its desired speed the agent
    drives, the quantity a car-following model accelerates on. Older checkpoints have it off."""
    speed_trend_input: bool = False
    """Every node also gets its previous token's mean speed minus the mean speed of the token before it [m/s] (the
    speed gained over the last 0.5 s; no contribution where either token is unknown): the trend of the speed, which
    the previous token alone (a 0.5 s segment at its mean speed) does not carry. Older checkpoints have it off."""

    def __post_init__(self) -> None:
        self.vocab_sizes = tuple(int(v) for v in self.vocab_sizes)
        problems = []
        if self.hidden_dim % self.num_heads:
            problems.append(f"hidden_dim={self.hidden_dim} is not divisible by num_heads={self.num_heads}")
        if len(self.vocab_sizes) != self.num_agent_types:
            problems.append(f"vocab_sizes has {len(self.vocab_sizes)} entries, expected num_agent_types={self.num_agent_types}")
        if any(v < 1 for v in self.vocab_sizes):
            problems.append(f"vocab_sizes must be >= 1, got {self.vocab_sizes}")
        for name in ("map_k", "map_agent_k", "agent_k", "temporal_span", "fourier_bands", "agent_layers"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.speed_gap_input and not self.desired_speed_input:
            problems.append("speed_gap_input needs desired_speed_input")
        if not 0.0 <= self.dropout < 1.0:
            problems.append(f"dropout must be in [0, 1), got {self.dropout}")
        if problems:
            raise ConfigError("PolicyConfig: " + "; ".join(problems))

    @property
    def head_dim(self) -> int:
        return self.hidden_dim // self.num_heads

    @property
    def vocab_max(self) -> int:
        """Width of the shared token head; ids >= the agent type's vocabulary size are masked."""
        return max(self.vocab_sizes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["vocab_sizes"] = list(self.vocab_sizes)
        return d

    @classmethod
    def from_dict(cls, data: dict, source: str = "PolicyConfig") -> PolicyConfig:
        """Build from a mapping; unknown keys raise :class:`ConfigError` naming them and the valid keys."""
        return _from_dict(cls, dict(data), source)

    @classmethod
    def preset(cls, name: str, **overrides) -> PolicyConfig:
        """``PolicyConfig.preset("nano", vocab_sizes=(1024, 256, 256))``."""
        if name not in PRESETS:
            raise ConfigError(f"unknown model preset {name!r}; available: {sorted(PRESETS)}")
        return cls.from_dict({**PRESETS[name], **overrides}, f"preset '{name}'")


PRESETS: dict[str, dict] = {
    "nano": dict(hidden_dim=64, num_heads=4, map_layers=2, agent_layers=4),
    "tiny": dict(hidden_dim=128, num_heads=8, map_layers=3, agent_layers=6),
}
