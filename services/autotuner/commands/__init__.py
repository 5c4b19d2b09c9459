"""services.autotuner.commands"""
