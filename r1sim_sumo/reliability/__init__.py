"""Reliability checks: hostile inputs, fault injection, long (soak) runs and the report that lists them.

* :mod:`.cases` - the table of hostile inputs (each builds a bad file or object in a temp folder, feeds it to
  the module that owns that input and states the expected outcome: an error naming file and field, or a
  documented clean-up). ``tests/test_hostile_inputs.py`` and the report both iterate this one table.
* :mod:`.faults` - kill pretraining / fine-tuning subprocesses at random moments and resume; NaN logits in
  the samplers; a SUMO process killed during ``r1sim simulate --traci``.
* :mod:`.soak` - a long SUMO run with the learned controller: RSS over time, vehicle balance, stuck vehicles.
* :mod:`.report` - ``python -m r1sim_sumo.reliability report --out docs/reliability/``.

Command line: ``python -m r1sim_sumo.reliability {report,soak} --help``.
"""
