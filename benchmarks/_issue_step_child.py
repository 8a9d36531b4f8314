"""Child process of ``benchmarks/bench_training.py``: the training step of the code as it stood when the
training-throughput issue was filed, timed on the benchmark's own real batches.

Run with ``PYTHONPATH`` set to a checkout of that revision (``ISSUE_STEP_REV`` in ``bench_training.py``, the commit
of ``shared/studies/training-throughput.md``), so that ``import r1sim_sumo`` is the old code:

``python benchmarks/_issue_step_child.py BATCHES.pt THREADS PASSES [--flops]``

``BATCHES.pt`` (written by the parent with the current code) holds the reference batches as plain tensors by field
name, the vocabulary's token trajectories and sizes. The child builds the old ``SceneBatch`` from the fields the old
code knows, the old nano model (seed 0, ``configs/pretrain.yaml``'s neighbour counts) and AdamW, runs one warm-up
step on the first batch, then ``PASSES`` timed passes over all batches; a step is what the old ``r1sim pretrain``
did per batch: padded forward, ``model.loss`` (label smoothing 0.1), backward, gradient clip, AdamW (fp32, no
allocator setting: the old code had none). Prints one JSON line: ``file`` (where ``r1sim_sumo`` came from, so the
parent can check it is the old tree), ``times`` [s per pass], ``faults`` (minor page faults per step), ``flops``
(matmul FLOP per step, forward + backward, with ``--flops``) and ``losses``.
"""

from __future__ import annotations

import json
import resource
import sys
import time

import torch


def main() -> None:
    path, threads, passes = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    torch.set_num_threads(threads)
    import r1sim_sumo
    from r1sim_sumo.model import PolicyConfig, TrafficPolicy
    from r1sim_sumo.tokens.batch import SceneBatch

    blob = torch.load(path, weights_only=False)
    batches = [SceneBatch(**{f: d[f] for f in SceneBatch._fields}) for d in blob["batches"]]
    torch.manual_seed(0)
    cfg = PolicyConfig.preset("nano", vocab_sizes=tuple(blob["vocab_sizes"]), **blob["model_overrides"])
    model = TrafficPolicy(cfg, [torch.as_tensor(t) for t in blob["traj"]]).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    losses = []

    def step(b) -> None:
        loss, _ = model.loss(b, model(b), label_smoothing=0.1)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        losses.append(float(loss.detach()))

    flops = None
    if "--flops" in sys.argv:
        from torch.utils.flop_counter import FlopCounterMode

        total = 0
        for b in batches[:2]:
            with FlopCounterMode(display=False) as fc:
                model.loss(b, model(b))[0].backward()
            model.zero_grad(set_to_none=True)
            total += fc.get_total_flops()
        flops = total / min(2, len(batches))
    step(batches[0])  # warm-up
    times, faults = [], []
    for _ in range(passes):
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        t = time.perf_counter()
        for b in batches:
            step(b)
        times.append(time.perf_counter() - t)
        faults.append((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / len(batches))
    print(json.dumps({"file": r1sim_sumo.__file__, "times": times, "faults": faults, "flops": flops, "losses": losses}))


if __name__ == "__main__":
    main()
