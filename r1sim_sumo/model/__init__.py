"""r1sim_sumo.model"""
