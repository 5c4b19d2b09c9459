"""Code shared by the services: message models, key expressions, the wire codec, Zenoh sessions."""
