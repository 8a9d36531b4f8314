"""r1sim_sumo.tokens"""
