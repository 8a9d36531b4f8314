"""r1sim_sumo.metrics"""
