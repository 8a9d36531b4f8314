"""The bundled SUMO networks: metadata, up-to-date builds, demand definition and clean default runs.

Every network of ``r1sim_sumo.resources.list_networks()`` is run with the ``sumo`` binary in a subprocess on
its own ``.sumocfg`` for its full default horizon (all take a few seconds), reading ``--statistic-output``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from r1sim_sumo._sumo_env import ensure_sumo_home, sumo_binary
from r1sim_sumo.resources import (
    list_networks,
    list_training_networks,
    network_files,
    network_path,
    networks_dir,
)

pytestmark = pytest.mark.sumo

EXPECTED = ["lane_drop", "motorway_merge", "roundabout", "urban_grid", "urban_intersection"]
NETWORKS = list_networks()
TRAINING = ["training/ring_five", "training/ring_five_small", "training/ring_four", "training/ring_mid",
            "training/ring_r14_four", "training/ring_r19_three", "training/ring_r21_five", "training/ring_r24_four",
            "training/ring_six", "training/ring_small", "training/ring_three", "training/ring_three_large",
            "training/ring_wide"]  # networks/training: only for dataset recipes that name them
SIGNALISED = {"urban_intersection", "urban_grid"}


def _meta(name: str) -> dict:
    return json.loads((network_path(name) / "network.json").read_text())


def _sumocfg_value(cfg: Path, section: str, key: str) -> str:
    elem = ET.parse(cfg).getroot().find(f"{section}/{key}")
    assert elem is not None, f"{cfg}: missing <{section}><{key} value=.../>"
    return elem.get("value")


def test_expected_networks_are_bundled():
    assert NETWORKS == EXPECTED
    assert list_training_networks() == TRAINING


@pytest.mark.parametrize("name", TRAINING)
def test_training_networks_are_marked_and_kept_out_of_the_default_recipe(name):
    from r1sim_sumo.data.dataset import DatasetRecipe

    meta = _meta(name)
    assert meta["training_only"] is True and meta["name"] == name.split("/")[1]
    assert name not in DatasetRecipe().sumo_networks()
    jobs = DatasetRecipe(networks=(name,), heldout_networks=(), highway_envs=()).jobs()["train"]
    assert {j.network for j in jobs} == {name}
    with pytest.raises(ValueError, match="training/<name>"):
        DatasetRecipe(networks=("ring_nope",), heldout_networks=()).sumo_networks()


@pytest.mark.parametrize("name", NETWORKS)
def test_network_json_matches_config(name):
    meta = _meta(name)
    assert set(meta) == {
        "name",
        "description",
        "has_traffic_lights",
        "default_end_s",
        "lane_width_m",
        "speed_limit_mps",
    }
    assert meta["name"] == name
    assert meta["has_traffic_lights"] == (name in SIGNALISED)
    cfg = network_files(name)["sumocfg"]
    assert float(_sumocfg_value(cfg, "time", "step-length")) == pytest.approx(0.1)
    assert float(_sumocfg_value(cfg, "time", "end")) == pytest.approx(meta["default_end_s"])
    assert 2.5 <= meta["lane_width_m"] <= 4.0
    assert 8.0 <= meta["speed_limit_mps"] <= 36.2


def test_built_nets_are_up_to_date():
    """netconvert on the plain-XML sources reproduces every committed .net.xml (header comment ignored)."""
    env = dict(os.environ, SUMO_HOME=str(ensure_sumo_home()))
    proc = subprocess.run(
        [sys.executable, str(networks_dir() / "build.py"), "--check"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.count("up to date") == len(EXPECTED) + len(TRAINING), proc.stdout


@pytest.mark.parametrize("name", NETWORKS)
def test_net_loads_with_expected_geometry(name):
    import sumolib

    meta = _meta(name)
    net = sumolib.net.readNet(str(network_files(name)["net"]), withInternal=True)
    lanes = [lane for edge in net.getEdges(withInternal=False) for lane in edge.getLanes()]
    assert len(lanes) > 0
    assert any(e.isSpecial() for e in net.getEdges(withInternal=True)), "no internal (junction) lanes"
    assert (len(net.getTrafficLights()) > 0) == meta["has_traffic_lights"]
    if name == "urban_grid":
        assert len(net.getTrafficLights()) == 9
    widths = {round(lane.getWidth(), 2) for lane in lanes}
    speeds = [lane.getSpeed() for lane in lanes]
    assert meta["lane_width_m"] in widths
    assert max(speeds) == pytest.approx(meta["speed_limit_mps"], abs=0.01)
    # the plain-XML frame is kept: no netconvert offset, so net coordinates equal the source coordinates
    assert net.getLocationOffset() == pytest.approx((0.0, 0.0))


@pytest.mark.parametrize("name", NETWORKS + TRAINING)
def test_default_demand_fleet(name):
    """Flows draw from a vTypeDistribution mixing Krauss and IDM (sigma > 0) cars, trucks and buses, LC2013."""
    rou = network_path(name) / f"{Path(name).name}.rou.xml"
    root = ET.parse(rou).getroot()
    dists = root.findall("vTypeDistribution")
    assert len(dists) == 1, f"{rou}: expected one vTypeDistribution"
    vtypes = dists[0].findall("vType")
    assert {v.get("carFollowModel") for v in vtypes} == {"Krauss", "IDM"}
    assert {v.get("vClass") for v in vtypes} == {"passenger", "truck", "bus"}
    assert all(float(v.get("sigma")) > 0 for v in vtypes)
    assert all(v.get("lcModel") == "LC2013" for v in vtypes)
    assert sum(float(v.get("probability")) for v in vtypes) == pytest.approx(1.0)
    flows = root.findall("flow")
    assert flows and all(f.get("type") == dists[0].get("id") for f in flows)


def _run_default(name: str, out_dir: Path) -> tuple[subprocess.CompletedProcess, ET.Element]:
    cfg = network_files(name)["sumocfg"]
    stats_file = out_dir / f"{Path(name).name}.stats.xml"
    cmd = [
        sumo_binary("sumo"),
        "-c",
        str(cfg),
        "--duration-log.statistics",
        "--statistic-output",
        str(stats_file),
    ]
    env = dict(os.environ, SUMO_HOME=str(ensure_sumo_home()))
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert stats_file.is_file(), proc.stdout + proc.stderr
    return proc, ET.parse(stats_file).getroot()


@pytest.mark.parametrize("name", NETWORKS + TRAINING)
def test_default_demand_runs_without_teleports(name, tmp_path):
    proc, stats = _run_default(name, tmp_path)
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output
    assert "Error" not in output, output
    perf = stats.find("performance")
    assert float(perf.get("end")) == pytest.approx(_meta(name)["default_end_s"]), "the full horizon must run"
    assert int(stats.find("teleports").get("total")) == 0, output
    assert int(stats.find("safety").get("collisions")) == 0, output
    vehicles = stats.find("vehicles")
    # the training rings are run near the ring's capacity on purpose (queues that yield at the entries): a short backlog
    max_waiting = 30 if name in TRAINING else 5
    assert int(vehicles.get("waiting")) <= max_waiting, "insertion backlog: demand exceeds the entry capacity"
    arrived = int(stats.find("vehicleTripStatistics").get("count"))
    assert arrived > 200, f"only {arrived} vehicles arrived"
    assert int(vehicles.get("inserted")) >= arrived
