"""Our realism metric against the official WOSAC code on golden fixtures (issue 16).

``tests/fixtures/wosac_golden/`` holds four scenes (straight motorway with a lane drop, merge, signalised junction,
roundabout), each with 32 policy rollouts (bundles of :mod:`r1sim_sumo.wosac_export`) and ``<id>.official.json``: the
official ``waymo-open-dataset-tf-2-12-0`` 1.6.7 metric on the same data, made by ``scripts/wosac_golden.py`` (see its
docstring for the two commands). Every per-feature likelihood and the 2024/2025 meta-metrics must match within
``TOL``, except the differences documented in :data:`KNOWN_DIFFERENCES` (each with its measured bound).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

pytest.importorskip("shapely")
pytest.importorskip("scipy")

from r1sim_sumo.metrics.realism import compute_realism  # noqa: E402
from r1sim_sumo.wosac_export import load_bundle  # noqa: E402

FIXTURES = Path(__file__).parent / "fixtures" / "wosac_golden"
SCENES = ("lane_drop", "motorway_merge", "urban_intersection", "roundabout")
TOL = 1e-3
# (scene, feature) -> (largest |ours - official| measured, why); see tests/fixtures/wosac_golden/README.md
_TL_RULE = ("red-light rule: ours flags a lane change into a red via-lane (map_features.red_light_violations), WOSAC a "
            "stop-line crossing; measured ours - official = -0.174")
_EDGE_SIGN = ("offroad: 95 of 40,960 (roundabout) simulated road-edge distances have opposite signs near the roundabout's "
              "entries (ours point-in-polygon, official sign of the nearest road-edge segment); cause not identified")
KNOWN_DIFFERENCES: dict[tuple[str, str], tuple[float, str]] = {
    ("urban_intersection", "traffic_light_violation"): (0.18, _TL_RULE),
    ("urban_intersection", "metametric_2025"): (0.008, _TL_RULE + "; weight 0.05 -> -0.0073"),
    ("urban_intersection", "offroad_indication"): (0.006, _EDGE_SIGN + "; measured +0.0057"),
    ("urban_intersection", "metametric_2024"): (0.0015, _EDGE_SIGN + "; weight 0.25 -> +0.0014"),
    ("roundabout", "offroad_indication"): (0.011, _EDGE_SIGN + "; measured -0.0109"),
    ("roundabout", "metametric_2024"): (0.003, _EDGE_SIGN + "; weight 0.25 -> -0.0027"),
    ("roundabout", "metametric_2025"): (0.003, _EDGE_SIGN + "; weight 0.25 -> -0.0027"),
}


def _load(sid: str):
    _, sc, sim = load_bundle(FIXTURES / f"{sid}.scenario.npz")
    official = json.loads((FIXTURES / f"{sid}.official.json").read_text())
    return sc, sim, official


@pytest.mark.parametrize("sid", SCENES)
def test_fixture_holds_the_cases_the_issue_asks_for(sid):
    _, sim, off = _load(sid)
    c = off["contents"]
    assert c["rollouts"] >= 32 and sim.num_rollouts == c["rollouts"]
    assert c["late_entering_agents"] >= 1


def test_fixtures_together_hold_collisions_offroad_and_agents_leaving():
    cs = [_load(s)[2]["contents"] for s in SCENES]
    assert sum(c["rollout_agent_pairs_with_collision"] for c in cs) > 0
    assert sum(c["rollout_agent_pairs_offroad"] for c in cs) > 0
    assert sum(c["agents_leaving_in_log"] for c in cs) > 0
    assert any(c["has_signals"] for c in cs)


@pytest.mark.parametrize("sid", SCENES)
def test_likelihoods_and_metametrics_match_the_official_code(sid):
    sc, sim, off = _load(sid)
    res = {w: compute_realism(sc, sim, weights=w) for w in ("2024", "2025")}
    bad = []
    for feat, want in off["likelihoods"].items():
        got = res["2024"].likelihoods.get(feat, math.nan)
        bound, _why = KNOWN_DIFFERENCES.get((sid, feat), (TOL, ""))
        if not abs(got - want) <= bound:
            bad.append(f"{feat}: ours {got:.6f} official {want:.6f} (allowed {bound:g})")
    for w in ("2024", "2025"):
        bound, _why = KNOWN_DIFFERENCES.get((sid, f"metametric_{w}"), (TOL, ""))
        if not abs(res[w].rmm - off[f"metametric_{w}"]) <= bound:
            bad.append(f"metametric {w}: ours {res[w].rmm:.6f} official {off[f'metametric_{w}']:.6f} (allowed {bound:g})")
    assert not bad, f"{sid}: " + "; ".join(bad)
