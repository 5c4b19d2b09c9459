"""plant_sim: simulated process loops (process, measurement, the loop's PID block) over Zenoh.

The numeric core (``lti``, ``models``, ``physical``, ``pid``, ``loop``) has no Zenoh in it;
``service`` wires it to the bus.
"""
