"""Time-space pictures of a SUMO run: position along one route vs time, coloured by speed.

:class:`TimeSpaceRecorder` samples every vehicle once per second (edge, position on it [m], speed [m/s]) and
remembers each departed vehicle's route; :meth:`TimeSpaceRecorder.route` picks the route most vehicles drove
(or the one given). A point is drawn for every sample on an edge of that route, at the edge's offset along the
route plus the position on the edge, so queues show as horizontal bands that grow upstream (down the page)
and clear, or do not. :func:`plot_side_by_side` draws several runs (native, policy...) next to each other on the
same axes and colour scale.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

SAMPLE_EVERY_S = 1.0  # [s]


class TimeSpaceRecorder:
    """Per-second samples of every vehicle of a running SUMO (``conn``: libsumo or a TraCI connection)."""

    def __init__(self, conn, every_s: float = SAMPLE_EVERY_S):
        self.conn = conn
        self.every = max(1, int(round(every_s / float(conn.simulation.getDeltaT()))))
        self._n = 0
        self.rows: list[tuple[float, str, float, float]] = []  # (time [s], edge, position on edge [m], speed [m/s])
        self.routes: Counter = Counter()
        self.edge_length: dict[str, float] = {}

    def step(self) -> None:
        """Call after every ``simulationStep``."""
        c = self.conn
        for v in c.simulation.getDepartedIDList():
            self.routes[tuple(c.vehicle.getRoute(v))] += 1
        self._n += 1
        if self._n % self.every:
            return
        t = float(c.simulation.getTime())
        for v in c.vehicle.getIDList():
            e = c.vehicle.getRoadID(v)
            if not e or e.startswith(":"):  # on no edge this step (e.g. placed off every lane), or inside a junction
                continue
            if e not in self.edge_length:
                lane = c.vehicle.getLaneID(v)
                if not lane:
                    continue
                self.edge_length[e] = float(c.lane.getLength(lane))
            pos = float(c.vehicle.getLanePosition(v))
            if pos < -1.0:  # SUMO's invalid value (-2^30) for a vehicle not on a lane this step
                continue
            self.rows.append((t, e, pos, float(c.vehicle.getSpeed(v))))

    def route(self) -> tuple[str, ...]:
        """The route most departed vehicles drove (edges)."""
        return self.routes.most_common(1)[0][0] if self.routes else ()

    def data(self, keep_routes: int = 3) -> dict:
        """JSON-ready samples on the edges of the ``keep_routes`` routes most vehicles drove: ``route`` (the most
        driven), ``routes``, ``edge_length_m``, ``rows`` = ``[time s, edge, position on edge m, speed m/s]``."""
        routes = [list(r) for r, _ in self.routes.most_common(keep_routes)]
        edges = {e for r in routes for e in r}
        for e in edges:
            self.edge_length.setdefault(e, self._length(e))
        rows = [[t, e, round(p, 2), round(v, 2)] for t, e, p, v in self.rows if e in edges]
        return {"route": routes[0] if routes else [], "routes": routes,
                "edge_length_m": {e: self.edge_length[e] for e in edges}, "rows": rows}

    def _length(self, edge: str) -> float:
        try:
            return float(self.conn.lane.getLength(f"{edge}_0"))
        except Exception:  # noqa: BLE001 - unknown edge: zero length
            return 0.0

    def save(self, png: Path, title: str) -> str:
        """Write ``png`` and its samples (:func:`samples_path`); returns the picture's path."""
        data = self.data()
        data["title"] = title
        png = Path(png)
        png.parent.mkdir(parents=True, exist_ok=True)
        samples_path(png).write_text(json.dumps(data, separators=(",", ":")))
        plot_side_by_side([reproject(data, data["route"])], png)
        return str(png)


def samples_path(png: Path) -> Path:
    """Where the samples of the picture ``png`` are kept: ``<stem>.samples.json`` beside it."""
    png = Path(png)
    return png.with_name(png.stem + ".samples.json")


def reproject(data: dict, route) -> dict:
    """``{"title", "t_s", "pos_m", "speed_mps"}``: the samples of ``data`` (:meth:`TimeSpaceRecorder.data`) on the
    edges of ``route``, at their distance along it from the start of its first edge [m]."""
    offset, acc = {}, 0.0
    lengths = data.get("edge_length_m", {})
    for e in route:
        offset[e] = acc
        acc += float(lengths.get(e, 0.0))
    keep = [(t, offset[e] + p, v) for t, e, p, v in data["rows"] if e in offset]
    t, pos, v = (list(x) for x in zip(*keep, strict=True)) if keep else ([], [], [])
    return {"title": data.get("title", ""), "route_length_m": acc, "t_s": t, "pos_m": pos, "speed_mps": v}


def plot_side_by_side(runs: list[dict], png: Path, vmax_mps: float | None = None) -> None:
    """One panel per run (:func:`reproject` dicts), shared axes and speed colour scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vmax = vmax_mps or max([max(r["speed_mps"], default=0.0) for r in runs] + [1.0])
    tmax = max([max(r["t_s"], default=0.0) for r in runs] + [1.0])
    fig, axes = plt.subplots(1, len(runs), figsize=(5.0 * len(runs), 4.2), sharey=True, squeeze=False)
    sc = None
    for ax, r in zip(axes[0], runs, strict=True):
        sc = ax.scatter(r["t_s"], r["pos_m"], c=r["speed_mps"], s=1.5, cmap="RdYlGn", vmin=0.0, vmax=vmax,
                        linewidths=0, rasterized=True)
        ax.set_title(r.get("title", ""), fontsize=9)
        ax.set_xlabel("time [s]")
        ax.set_xlim(0, tmax)
    axes[0][0].set_ylabel("position along route [m]")
    fig.colorbar(sc, ax=axes[0].tolist(), label="speed [m/s]")
    fig.savefig(png, dpi=110, bbox_inches="tight")
    plt.close(fig)
