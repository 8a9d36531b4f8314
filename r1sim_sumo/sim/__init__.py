"""r1sim_sumo.sim"""
