"""r1sim_sumo.data"""
