"""r1sim_sumo.distributed"""
