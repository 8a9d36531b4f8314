"""Matplotlib pictures of a :class:`~r1sim_sumo.scenario.Scenario` (internal frame: metres, y north).

``plot_scenario`` draws the map (lane centres thin grey with a direction arrow each, road edges black),
each agent's track (history solid, future dashed, valid steps only), its box at the current step with a
heading tick, coloured by type, and the traffic-light states at the current step as coloured dots at the
end of the controlled lanes. Optional sampled rollouts are overlaid as thin lines. The Agg backend is used,
so no display is needed.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from r1sim_sumo.geometry import box_corners
from r1sim_sumo.scenario import AGENT_TYPES, LANE_CENTRE, ROAD_EDGE, TL_GREEN, TL_RED, TL_YELLOW, Scenario

TYPE_COLOURS = ("tab:blue", "tab:orange", "tab:green")  # vehicle, cyclist, pedestrian
TL_COLOURS = {TL_GREEN: "limegreen", TL_YELLOW: "gold", TL_RED: "red"}
ZOOM_MARGIN_M = 15.0  # [m] around the agents when zooming


def _pyplot():
    import matplotlib

    if matplotlib.get_backend().lower() != "agg":
        matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _draw_map(ax, sc: Scenario) -> None:
    from matplotlib.collections import LineCollection

    m = sc.map
    lanes = [m.polyline(i) for i in range(m.num_polylines) if m.kind[i] == LANE_CENTRE]
    edges = [m.polyline(i) for i in range(m.num_polylines) if m.kind[i] == ROAD_EDGE]
    ax.add_collection(LineCollection(lanes, colors="0.6", linewidths=0.7, zorder=1))
    ax.add_collection(LineCollection(edges, colors="black", linewidths=1.2, zorder=1))
    # one direction arrow per lane centre, at its arc-length middle
    mids, dirs = [], []
    for p in lanes:
        seg = np.diff(p, axis=0)
        n = np.linalg.norm(seg, axis=1)
        if len(seg) == 0 or n.sum() <= 0:
            continue
        k = int(np.searchsorted(np.cumsum(n), 0.5 * n.sum()))
        k = min(k, len(seg) - 1)
        mids.append(p[k] + 0.5 * seg[k])
        dirs.append(seg[k] / max(n[k], 1e-9))
    if mids:
        mids, dirs = np.asarray(mids), np.asarray(dirs)
        ax.quiver(mids[:, 0], mids[:, 1], dirs[:, 0], dirs[:, 1], color="0.45", angles="xy", scale_units="width",
                  scale=40, width=0.003, headwidth=4, zorder=2)
    # traffic lights at the current step: a dot at the end (stop line) of each controlled lane
    if m.tl_state.shape[1] > sc.current_index:
        st = m.tl_state[:, sc.current_index]
        for state, colour in TL_COLOURS.items():
            idx = np.flatnonzero(st == state)
            if len(idx):
                pts = np.array([m.polyline(i)[-1] for i in idx])
                ax.scatter(pts[:, 0], pts[:, 1], s=28, c=colour, edgecolors="black", linewidths=0.5, zorder=5)


def _draw_agents(ax, sc: Scenario) -> None:
    from matplotlib.patches import Polygon

    a, c = sc.agents, sc.current_index
    for i in range(a.num_agents):
        colour = TYPE_COLOURS[int(a.agent_type[i])]
        for sl, style in ((slice(0, c + 1), "-"), (slice(c, None), "--")):
            v = a.valid[i, sl]
            x = np.where(v, a.x_m[i, sl], np.nan)  # NaN breaks the line at invalid steps
            y = np.where(v, a.y_m[i, sl], np.nan)
            ax.plot(x, y, style, color=colour, linewidth=1.0, alpha=0.8, zorder=3)
        if not a.valid[i, c]:
            continue
        x, y, yaw = float(a.x_m[i, c]), float(a.y_m[i, c]), float(a.yaw_rad[i, c])
        corners = box_corners(np.float64(x), np.float64(y), np.float64(yaw), float(a.length_m[i]), float(a.width_m[i]))
        ax.add_patch(Polygon(corners, closed=True, facecolor=colour, edgecolor="black", linewidth=0.6, alpha=0.85, zorder=4))
        hl = 0.5 * float(a.length_m[i])
        ax.plot([x, x + hl * np.cos(yaw)], [y, y + hl * np.sin(yaw)], color="black", linewidth=0.8, zorder=5)


def _draw_rollouts(ax, sc: Scenario, rollouts) -> None:
    r = np.asarray(rollouts, dtype=np.float64)
    if r.ndim == 3:
        r = r[None]
    if r.ndim != 4 or r.shape[-1] < 2 or r.shape[1] != sc.agents.num_agents:
        raise ValueError(f"rollouts: expected [R, A={sc.agents.num_agents}, T, >=2] x/y positions, got {r.shape}")
    for i in range(r.shape[1]):
        colour = TYPE_COLOURS[int(sc.agents.agent_type[i])]
        for k in range(r.shape[0]):
            ax.plot(r[k, i, :, 0], r[k, i, :, 1], "-", color=colour, linewidth=0.5, alpha=0.35, zorder=2)


def _title(sc: Scenario) -> str:
    md = sc.metadata
    parts = [str(md.get("source", "?")), str(md.get("network", ""))]
    for key in ("scene_id", "recording_id", "start_time_s"):
        if key in md:
            parts.append(f"{key}={md[key]}")
    return " | ".join(p for p in parts if p) + f"\n{sc.agents.num_agents} agents, {sc.num_steps} steps, t={sc.current_index * sc.dt_s:.1f}s"


def plot_scenario(scenario: Scenario, ax=None, rollouts=None):
    """Draw a scenario on ``ax`` (a new figure if None) and return the axes.

    :param rollouts: optional x/y positions ``[R, A, T, >=2]`` (or ``[A, T, >=2]``) in the internal frame, one
        row per agent of ``scenario.agents`` (same order), drawn as thin lines in the agent's colour.
    """
    plt = _pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(9, 7))
    _draw_map(ax, scenario)
    if rollouts is not None:
        _draw_rollouts(ax, scenario, rollouts)
    _draw_agents(ax, scenario)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(_title(scenario), fontsize=9)
    from matplotlib.lines import Line2D

    present = sorted(set(np.asarray(scenario.agents.agent_type).tolist()))
    handles = [Line2D([], [], color=TYPE_COLOURS[t], lw=2, label=AGENT_TYPES[t]) for t in present]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)
    return ax


def agents_extent(scenario: Scenario, margin_m: float = ZOOM_MARGIN_M) -> tuple[float, float, float, float]:
    """``(x_min, x_max, y_min, y_max)`` [m] of all valid agent positions, widened by ``margin_m``."""
    a = scenario.agents
    x, y = a.x_m[a.valid], a.y_m[a.valid]
    return float(x.min()) - margin_m, float(x.max()) + margin_m, float(y.min()) - margin_m, float(y.max()) + margin_m


def save_scenario_png(scenario: Scenario, out_png: str | os.PathLike, zoom_to_agents: bool = True, rollouts=None,
                      dpi: int = 120) -> Path:
    """Plot ``scenario`` and write it as a PNG; with ``zoom_to_agents`` the view is the agents' extent."""
    plt = _pyplot()
    if zoom_to_agents and scenario.agents.valid.any():
        x0, x1, y0, y1 = agents_extent(scenario)
    else:
        x0, y0, x1, y1 = scenario.map.bounds()
    height_in = float(np.clip(10.0 * (y1 - y0) / max(x1 - x0, 1e-6), 3.0, 9.0)) + 1.0  # title and labels
    fig, ax = plt.subplots(figsize=(10, height_in))
    try:
        plot_scenario(scenario, ax=ax, rollouts=rollouts)
        if zoom_to_agents and scenario.agents.valid.any():
            ax.set_aspect("equal", adjustable="box")  # keep the zoomed limits, shrink the axes instead
            ax.set_xlim(x0, x1)
            ax.set_ylim(y0, y1)
        out = Path(out_png)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=dpi, bbox_inches="tight")
    finally:
        plt.close(fig)
    return out
