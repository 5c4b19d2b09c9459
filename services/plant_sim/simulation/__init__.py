"""services.plant_sim.simulation"""
