"""services.autotuner.identify"""
