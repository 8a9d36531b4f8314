#!/usr/bin/env python3
"""The drop-in's map encoding in tiles against the whole map at once, per network (session 48).

    python scripts/diag_map_tiles.py [--networks motorway_merge lane_drop urban_intersection roundabout urban_grid]
        [--checkpoint CKPT]

For each network: its map tokens, the 250 m tiles (:data:`r1sim_sumo.sim.policy_driver.TILE_M`, forced even where the
drop-in now encodes the map whole), the wall time of both encodings [s], how many tokens' k-nearest map neighbours
differ between a tile and the whole map and whether every such difference is a swap between tokens at exactly the same
distance (a tie), and how many tokens' encoded features differ (> 1e-4) and by how much at most.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

BUNDLED = ("motorway_merge", "lane_drop", "urban_intersection", "roundabout", "urban_grid")


def _dist2(xy, g: int, others) -> list[float]:
    """Sorted squared distances [m^2] from token ``g`` to the tokens ``others`` (float32, as the search compares)."""
    return sorted(float(((xy[g] - xy[t]) ** 2).sum()) for t in others)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--networks", nargs="+", default=list(BUNDLED))
    ap.add_argument("--checkpoint", default=None, help="policy (default: the shipped r1sim-nano)")
    a = ap.parse_args(argv)

    import torch

    import r1sim_sumo.sim.policy_driver as pd
    from r1sim_sumo.adapters.sumo_map import read_sumo_map
    from r1sim_sumo.model.checkpoint import load_policy
    from r1sim_sumo.model.layers import knn
    from r1sim_sumo.resources import network_files

    torch.set_num_threads(1)
    pd.WHOLE_MAP_MAX_TOKENS = 0  # force tiles
    policy = load_policy(a.checkpoint) if a.checkpoint else load_policy()
    c = policy.model.config
    for net in a.networks:
        road = read_sumo_map(str(network_files(net)["net"])).polylines
        t0 = time.perf_counter()
        drv = pd.PolicyDriver(policy, road, map_cache_dir=None, lazy_map=False)
        t_tiles = time.perf_counter() - t0
        t0 = time.perf_counter()
        whole = drv._encode_tokens(np.arange(drv.map_tokens.num_tokens))
        t_whole = time.perf_counter() - t0
        diff = (drv._map_ctx.feat - whole.feat).abs().amax(-1)[0]  # [M]
        xy = torch.from_numpy(pd.token_centres(drv.map_tokens)).float()[None]
        M = xy.shape[1]
        iw, okw = knn(xy, xy, torch.ones(1, M, dtype=torch.bool), c.map_k, c.map_radius_m)
        n_diff = n_tie = 0
        for core, halo in drv._tiles:
            sub = xy[:, torch.from_numpy(halo)]
            it, okt = knn(sub, sub, torch.ones(1, len(halo), dtype=torch.bool), c.map_k, c.map_radius_m)
            row = {g: j for j, g in enumerate(halo.tolist())}
            for g in core.tolist():
                j = row[g]
                s_whole = set(iw[0, g][okw[0, g]].tolist())
                s_tile = set(halo[it[0, j][okt[0, j]].numpy()].tolist())
                if s_whole != s_tile:
                    n_diff += 1
                    n_tie += _dist2(xy[0], g, s_whole - s_tile) == _dist2(xy[0], g, s_tile - s_whole)
        print(f"{net}: {M} map tokens, {len(drv._tiles)} tiles; encoded in {t_tiles:.2f} s (tiles) / {t_whole:.2f} s "
              f"(whole); neighbour sets differ for {n_diff} tokens, {n_tie} of them only by equal-distance swaps; "
              f"features differ for {int((diff > 1e-4).sum())} tokens, by up to {float(diff.max()):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
