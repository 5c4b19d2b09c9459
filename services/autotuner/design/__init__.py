"""services.autotuner.design"""
