"""Subcommands of ``r1sim`` (see ``r1sim_sumo/cli.py`` for the module contract)."""
