"""r1sim_sumo.train"""
