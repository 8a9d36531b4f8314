"""r1sim_sumo.adapters"""
