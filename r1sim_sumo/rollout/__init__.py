"""r1sim_sumo.rollout"""
