"""autotuner: experiments on a loop it does not own, identification and tuning rules.

Pure cores (``reaction_curve``, ``step_test``) are fed samples one at a time; ``loop_client``
drives a plant_sim loop over Zenoh.
"""
