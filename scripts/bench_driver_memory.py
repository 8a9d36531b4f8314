"""Online planning cost, PolicyDriver stateless vs memory mode, on 90 token-chained agents (untrained nano).

Run: `python scripts/bench_driver_memory.py 1` (argument: torch threads).
"""
import sys, time, numpy as np, torch
sys.path.insert(0, "tests"); sys.path.insert(0, "benchmarks")
torch.set_num_threads(int(sys.argv[1]))
from r1sim_sumo.commands.simulate import untrained_policy
from r1sim_sumo.sim.policy_driver import PolicyDriver
import test_policy_driver as t
pol = untrained_policy(0)
A = 90
full = t._token_chained_history(pol, A=A, n_tok=12)
road = t._road()
res = {}
for mode in (False, True, False, True):
    d = PolicyDriver(pol, road, sampler="topk:5", seed=0, memory=mode)
    ts = []
    for k in range(0, 10):
        h = full.slice_steps(5*k, 5*k+11)
        t0 = time.perf_counter(); d.plan(h); ts.append(time.perf_counter()-t0)
    res.setdefault(mode, []).append(np.median(ts[2:]))
print({("memory" if k else "stateless"): [round(1000*v,1) for v in vals] for k, vals in res.items()}, "ms per plan,", A, "agents")
