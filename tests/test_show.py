"""``r1sim show`` and the plotting helpers of ``r1sim_sumo.viz``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from r1sim_sumo.cli import main
from r1sim_sumo.data.logged import load_highd
from r1sim_sumo.scenario import write_dataset, write_shard

FIX = Path(__file__).resolve().parent / "fixtures"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def highd_scenarios():
    return load_highd(FIX / "highd", 1)


def _is_png(path: Path) -> bool:
    return path.exists() and path.stat().st_size > 5000 and path.read_bytes()[:8] == PNG_MAGIC


def test_show_shard_writes_png(tmp_path, highd_scenarios, capsys):
    shard = write_shard(tmp_path / "h.npz", highd_scenarios)
    out = tmp_path / "pics" / "h1.png"
    assert main(["show", str(shard), "--index", "1", "--out", str(out)]) == 0
    assert _is_png(out)
    assert f"{highd_scenarios[1].agents.num_agents} agents" in capsys.readouterr().out


def test_show_dataset_folder_and_full_map(tmp_path, highd_scenarios):
    root = write_dataset(tmp_path / "ds", highd_scenarios, shard_size=1)
    out = tmp_path / "d.png"
    assert main(["show", str(root), "--index", "-1", "--out", str(out), "--full-map"]) == 0
    assert _is_png(out)


def test_show_bad_inputs_return_error(tmp_path, highd_scenarios, capsys):
    shard = write_shard(tmp_path / "h.npz", highd_scenarios)
    assert main(["show", str(shard), "--index", "9", "--out", str(tmp_path / "x.png")]) == 2
    assert "outside" in capsys.readouterr().err
    assert main(["show", str(tmp_path / "missing.npz")]) == 2
    assert "missing.npz" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_plot_scenario_draws_lights_boxes_and_rollouts(highd_scenarios):
    from r1sim_sumo.viz import TL_COLOURS, plot_scenario

    sc = highd_scenarios[0]
    L, T = sc.map.num_polylines, sc.num_steps
    tl = np.zeros((L, T), np.int8)
    tl[0, :], tl[1, :] = 1, 3  # two signalled lanes: green and red at every step
    sc = type(sc)(agents=sc.agents, map=sc.map.with_tl_state(tl), metadata=sc.metadata)
    rollouts = np.stack([np.stack([sc.agents.x_m, sc.agents.y_m], -1)[:, 10:]] * 2)  # [R=2, A, 81, 2]
    ax = plot_scenario(sc, rollouts=rollouts)
    dots = [c for c in ax.collections if c.__class__.__name__ == "PathCollection"]
    assert len(dots) == 2  # one scatter per present light colour
    assert len(ax.patches) == sc.agents.num_agents  # one box per agent valid now
    assert ax.get_aspect() == 1.0
    assert "highd" in ax.get_title()
    assert set(TL_COLOURS) == {1, 2, 3}
    with pytest.raises(ValueError, match="rollouts"):
        plot_scenario(sc, rollouts=np.zeros((2, 99, 5, 2)))
    import matplotlib.pyplot as plt

    plt.close("all")
