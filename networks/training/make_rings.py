"""Write the plain-XML sources of the training-only roundabouts (issue 19: the held-out ``roundabout`` is the
campaign's worst network; these give the policy other rings to learn circulating and yielding on).

Each ring is a single-lane, counter-clockwise roundabout with ``arms`` two-way 150 m arms (50 km/h, 3.5 m lanes),
ring lane 4-5 m wide at 30 km/h, entering traffic yields (``<roundabout>``). Radii and arm angles differ from the
held-out ``networks/roundabout`` (radius 20 m, 4 arms at 90 deg): ``ring_five`` has radius 30 m and 5 uneven arms,
``ring_three`` radius 15 m and 3 arms, so the held-out ring lies between them and is never trained on.

    python networks/training/make_rings.py        # then: python networks/build.py --only ring_five (and the others)

Metres, x east, y north; angles in degrees counter-clockwise from east.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

HERE = Path(__file__).resolve().parent
ARM_M = 150.0  # [m] arm length from the ring node
RINGS = {
    "ring_five": dict(radius_m=30.0, arm_deg=(10.0, 80.0, 150.0, 225.0, 295.0), veh_per_h_per_arm=420.0),
    "ring_three": dict(radius_m=15.0, arm_deg=(30.0, 150.0, 270.0), veh_per_h_per_arm=480.0),
    # session 10: more ring geometries (configs/dataset_rings2.yaml). None has the held-out ring's 20 m radius with
    # four arms at 90 deg; ring_four has four arms, but at uneven angles on a 25 m ring with a 5 m lane.
    "ring_four": dict(radius_m=25.0, arm_deg=(15.0, 110.0, 195.0, 280.0), veh_per_h_per_arm=400.0, ring_width_m=5.0),
    "ring_six": dict(radius_m=40.0, arm_deg=(0.0, 55.0, 120.0, 180.0, 245.0, 300.0), veh_per_h_per_arm=300.0),
    "ring_small": dict(radius_m=12.0, arm_deg=(0.0, 95.0, 180.0, 265.0), veh_per_h_per_arm=360.0, ring_width_m=4.0),
    # session 11: four more (configs/dataset_rings3.yaml), filling radii 17-33 m with 3-5 arms; the four-armed ones
    # have uneven arm angles, so the held-out ring (20 m, four arms at 90 deg) is still never seen.
    "ring_mid": dict(radius_m=17.0, arm_deg=(20.0, 105.0, 200.0, 290.0), veh_per_h_per_arm=420.0),
    "ring_wide": dict(radius_m=33.0, arm_deg=(0.0, 80.0, 170.0, 260.0), veh_per_h_per_arm=380.0),
    "ring_five_small": dict(radius_m=22.0, arm_deg=(0.0, 70.0, 145.0, 215.0, 290.0), veh_per_h_per_arm=340.0),
    "ring_three_large": dict(radius_m=28.0, arm_deg=(90.0, 200.0, 330.0), veh_per_h_per_arm=450.0, ring_width_m=5.0),
    # session 12: four more (configs/dataset_rings4.yaml), radii 14-24 m around the held-out 20 m; again no ring with
    # four arms at 90 deg.
    "ring_r19_three": dict(radius_m=19.0, arm_deg=(0.0, 115.0, 235.0), veh_per_h_per_arm=470.0),
    "ring_r21_five": dict(radius_m=21.0, arm_deg=(30.0, 100.0, 170.0, 250.0, 320.0), veh_per_h_per_arm=330.0,
                          ring_width_m=4.0),
    "ring_r24_four": dict(radius_m=24.0, arm_deg=(5.0, 75.0, 185.0, 255.0), veh_per_h_per_arm=400.0),
    "ring_r14_four": dict(radius_m=14.0, arm_deg=(10.0, 120.0, 190.0, 300.0), veh_per_h_per_arm=380.0),
}
VTYPES = (Path(__file__).resolve().parents[1] / "roundabout" / "roundabout.rou.xml").read_text()


def _vtypes() -> str:
    """The ``mixed`` vTypeDistribution of the bundled roundabout's demand (same fleet)."""
    a = VTYPES.index("    <vTypeDistribution")
    b = VTYPES.index("</vTypeDistribution>") + len("</vTypeDistribution>")
    return VTYPES[a:b]


def _arc(r: float, a0: float, a1: float, step_deg: float = 5.0) -> str:
    """Shape string of the counter-clockwise arc from ``a0`` to ``a1`` [deg] on the circle of radius ``r`` [m]."""
    if a1 <= a0:
        a1 += 360.0
    n = max(2, int(math.ceil((a1 - a0) / step_deg)) + 1)
    pts = [a0 + (a1 - a0) * i / (n - 1) for i in range(n)]
    return " ".join(f"{r * math.cos(math.radians(a)):.2f},{r * math.sin(math.radians(a)):.2f}" for a in pts)


def write_ring(name: str, radius_m: float, arm_deg: tuple[float, ...], veh_per_h_per_arm: float,
               ring_width_m: float = 4.5) -> None:
    """Write ``networks/training/<name>/``: ring of ``radius_m`` [m] (lane centre), arms at ``arm_deg`` [deg CCW from
    east], Poisson demand ``veh_per_h_per_arm``, ring lane ``ring_width_m`` [m] wide."""
    out = HERE / name
    out.mkdir(exist_ok=True)
    n = len(arm_deg)
    nodes, edges, routes, flows = [], [], [], []
    for i, a in enumerate(arm_deg):
        c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
        nodes.append(f'    <node id="ring{i}" x="{radius_m * c:.2f}" y="{radius_m * s:.2f}" type="priority"/>')
        nodes.append(f'    <node id="end{i}" x="{(radius_m + ARM_M) * c:.2f}" y="{(radius_m + ARM_M) * s:.2f}" type="priority"/>')
    for i in range(n):
        j = (i + 1) % n
        edges.append(f'    <edge id="ring{i}_{j}" from="ring{i}" to="ring{j}" priority="10" numLanes="1" speed="8.33" width="{ring_width_m:g}"\n'
                     f'          spreadType="center" shape="{_arc(radius_m, arm_deg[i], arm_deg[j])}"/>')
    for i in range(n):
        edges.append(f'    <edge id="arm{i}_in" from="end{i}" to="ring{i}" priority="5" numLanes="1" speed="13.89" width="3.5"/>')
        edges.append(f'    <edge id="arm{i}_out" from="ring{i}" to="end{i}" priority="5" numLanes="1" speed="13.89" width="3.5"/>')
    ring_nodes = " ".join(f"ring{i}" for i in range(n))
    ring_edges = " ".join(f"ring{i}_{(i + 1) % n}" for i in range(n))
    edges.append(f'    <roundabout nodes="{ring_nodes}" edges="{ring_edges}"/>')
    rate = veh_per_h_per_arm / 3600.0 / (n - 1)  # [veh/s] per (origin, exit): exits equally likely
    for i in range(n):
        for k in range(1, n):
            ring = " ".join(f"ring{(i + m) % n}_{(i + m + 1) % n}" for m in range(k))
            rid = f"a{i}_x{k}"
            routes.append(f'    <route id="{rid}" edges="arm{i}_in {ring} arm{(i + k) % n}_out"/>')
            flows.append(f'    <flow id="{rid}" type="mixed" route="{rid}" begin="0" end="900" period="exp({rate:.4f})"\n'
                         f'          departLane="best" departSpeed="max" departPos="base"/>')
    desc = (f"Training-only single-lane roundabout (radius {radius_m:g} m, ring 30 km/h, {ring_width_m:g} m ring lane) with {n} "
            f"two-way 150 m arms at {', '.join(f'{a:g}' for a in arm_deg)} deg; entering traffic yields.")
    (out / f"{name}.nod.xml").write_text(
        f'<?xml version="1.0" encoding="UTF-8"?>\n<!-- {name}: written by networks/training/make_rings.py. -->\n'
        "<nodes>\n" + "\n".join(nodes) + "\n</nodes>\n")
    (out / f"{name}.edg.xml").write_text(
        f'<?xml version="1.0" encoding="UTF-8"?>\n<!-- {name}: written by networks/training/make_rings.py. -->\n'
        "<edges>\n" + "\n".join(edges) + "\n</edges>\n")
    (out / f"{name}.rou.xml").write_text(
        f'<?xml version="1.0" encoding="UTF-8"?>\n<!-- Default demand for {name} (make_rings.py): Poisson arrivals, '
        f"{veh_per_h_per_arm:g} veh/h per arm, exits equally likely, 0-900 s. -->\n<routes>\n{_vtypes()}\n"
        + "\n".join(routes) + "\n" + "\n".join(flows) + "\n</routes>\n")
    (out / f"{name}.netccfg").write_text((HERE.parent / "roundabout" / "roundabout.netccfg").read_text()
                                         .replace("roundabout", name).replace(f"only {name}", f"only {name}"))
    (out / f"{name}.sumocfg").write_text((HERE.parent / "roundabout" / "roundabout.sumocfg").read_text().replace("roundabout", name))
    meta = {"name": name, "description": desc, "has_traffic_lights": False, "default_end_s": 900.0, "lane_width_m": 3.5,
            "speed_limit_mps": 13.89, "training_only": True}
    (out / "network.json").write_text(json.dumps(meta, indent=2) + "\n")


def main() -> None:
    for name, kw in RINGS.items():
        write_ring(name, **kw)
        print(f"wrote {HERE / name}")


if __name__ == "__main__":
    main()
