"""Zenoh router: zenoh-python's own session in ``router`` mode (no home-made broker)."""
